//! Deterministic CPU rasterizer for offline bakes and evaluation.
//!
//! - [`camera`]: perspective and orthographic cameras, [`fibonacci_sphere`] viewpoints.
//! - [`texture`]: RGBA8 textures, nearest/bilinear sampling, alpha test.
//! - [`scene`]: the input: [`RasterMesh`] triangle soups, [`Instance`]s with transforms,
//!   [`RasterMaterial`]s, and [`RasterMesh::from_tree`] for a [`TreeModel`](crate::TreeModel).
//! - [`pipeline`]: [`render`] to colour + depth + item buffers ([`Frame`]).
//! - [`abuffer`]: [`ABuffer`], per-pixel depth-sorted fragment lists with an item → pixels
//!   index, and [`FrontTracker`] to re-resolve visibility as items are removed (VMI bake).
//!
//! # Conventions
//!
//! - **World**: Y up, right-handed, metres (as [`crate::model`]).
//! - **Camera / view space**: right-handed, the camera looks down −Z with +Y up (OpenGL/glam
//!   `look_at_rh`). Projections are glam's `perspective_rh` / `orthographic_rh`: clip-space depth
//!   `z/w` runs from 0 at the near plane to 1 at the far plane. Depth buffers hold that NDC depth
//!   (smaller is closer); the clear value is `f32::INFINITY`.
//! - **Image**: pixel `(x, y)` is at index `y * width + x`, row 0 is the **top** row, x grows to
//!   the right. NDC (−1, +1) is the top-left image corner, (+1, −1) the bottom-right. Pixel
//!   `(x, y)` has its centre at `(x + 0.5, y + 0.5)` in pixel units; a pixel is covered by a
//!   triangle when its centre is.
//! - **Fill rule**: top-left, evaluated exactly in 24.8 fixed point (vertices are snapped to
//!   1/256 pixel): a centre exactly on an edge belongs to the triangle only if that edge is a
//!   top or a left edge, so two triangles sharing an edge never both cover a pixel and never
//!   leave a gap.
//! - **Faces**: triangles are counter-clockwise seen from the front (the side their normals point
//!   to). Materials are double-sided by default (leaves); a back-facing triangle of a
//!   double-sided material is lit with its normal flipped towards the viewer; single-sided
//!   materials cull back faces.
//! - **Items**: every triangle carries a `u32` item id (a leaf index, an instance, …).
//!   [`EMPTY_ITEM`] (`u32::MAX`) marks an empty pixel, [`BARK_ITEM`] (`u32::MAX - 1`) is the item
//!   of bark built by [`RasterMesh::from_tree`].
//! - **Depth ties**: a fragment replaces the stored one if its depth is smaller, or equal with a
//!   smaller item id; remaining ties keep the earlier triangle in submission order. The A-buffer
//!   sorts each pixel by `(depth, item)`, so its front equals the item buffer.
//! - **Colour**: textures hold sRGB-encoded colour and linear alpha; material colours and
//!   lighting are linear; the output colour is sRGB-encoded RGBA8 with straight alpha (255 where
//!   covered, `clear_color` elsewhere).
//! - **Determinism**: triangles are binned to horizontal bands of [`BAND_ROWS`] rows in
//!   submission order and each band is rasterized by one task; per-pixel arithmetic depends only
//!   on the triangle and the pixel. Output is bit-identical whatever the rayon thread count.
//! - **Clipping**: triangles are clipped in homogeneous space against the near and far planes
//!   and a guard band of ±[`GUARD_BAND`] × the viewport, so images up to [`MAX_IMAGE_SIZE`]
//!   pixels a side stay inside 24.8 fixed point.

pub mod abuffer;
pub mod camera;
pub mod pipeline;
pub mod scene;
pub mod texture;

pub use abuffer::{ABuffer, BitSet, Fragment, FrontTracker};
pub use camera::{Camera, Projection, fibonacci_hemisphere, fibonacci_sphere};
pub use pipeline::{Frame, Lighting, RenderOptions, render, render_in_passes};
pub use scene::{
    FULL_COVERAGE, Instance, ItemMap, QuadBatch, RasterMaterial, RasterMesh, Scene, TreeMeshOptions, dither_threshold,
    tree_materials,
};
pub use texture::{Filter, Texture, TextureId, Wrap};

/// Item id of an empty pixel.
pub const EMPTY_ITEM: u32 = u32::MAX;
/// Item id of bark triangles built by [`RasterMesh::from_tree`].
pub const BARK_ITEM: u32 = u32::MAX - 1;
/// Rows per band: the unit of binning and of parallel work.
pub const BAND_ROWS: u32 = 16;
/// Largest image width or height accepted.
pub const MAX_IMAGE_SIZE: u32 = 8192;
/// Guard band, in multiples of the viewport half-size, beyond which triangles are clipped.
pub const GUARD_BAND: f32 = 4.0;

/// Errors of the rasterizer.
#[derive(Debug, thiserror::Error)]
pub enum RasterError {
    /// Width or height is zero or above [`MAX_IMAGE_SIZE`].
    #[error("image size {width}x{height} is outside 1..={MAX_IMAGE_SIZE}")]
    InvalidSize {
        /// Requested width.
        width: u32,
        /// Requested height.
        height: u32,
    },
    /// A mesh's arrays disagree (lengths, indices out of range, missing materials).
    #[error("invalid mesh: {0}")]
    InvalidMesh(String),
    /// A material names a texture that the scene does not have.
    #[error("material {material} names missing texture {texture}")]
    MissingTexture {
        /// Material index.
        material: usize,
        /// Texture index.
        texture: u32,
    },
    /// A texture's pixel array does not match its size.
    #[error("invalid texture: {0}")]
    InvalidTexture(String),
    /// Camera parameters are not usable (non-finite, near ≥ far, eye = target, …).
    #[error("invalid camera: {0}")]
    InvalidCamera(String),
    /// Reading or writing an image file failed.
    #[error("image i/o: {0}")]
    Image(#[from] image::ImageError),
    /// More fragments than an A-buffer can index (u32 offsets).
    #[error("A-buffer overflow: {0} fragments")]
    TooManyFragments(usize),
}

#[cfg(test)]
mod tests;
