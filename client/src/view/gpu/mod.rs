//! The viewer's wgpu renderer: pipelines, offscreen targets and read-back.
//!
//! Three pipelines share one bind group of globals (camera, lighting), per-frame tree transforms
//! and textures:
//! - **leaves**: one instance per drawn leaf (`LeafDraw`: leaf index into the model's leaf
//!   storage buffer, tree index, seed 004 enlargement), six vertices expanded in the shader,
//!   alpha-tested against the leaf mask, lit on both sides;
//! - **meshes**: bark tubes, crown hulls and the ground, per-vertex colour, one `MeshInstance`
//!   (transform and debug tint) per tree;
//! - **billboards**: one quad per instance blending up to three frames of a texture array
//!   (seed 001's hemi-octahedral blend; one frame for lat-long and crossed quads), unlit since
//!   the bake lit the images.
//!
//! Rendering goes to an offscreen colour texture (sRGB) with a depth buffer, used both by the
//! window (shown as an egui image) and by `--screenshot` (read back to a PNG), so the two paths
//! draw the same pixels.
//!
//! Code layout: the records the shaders read and the buffers that hold them are in `buffers`,
//! the offscreen targets and read-back in `target`, the pipelines and shared resources
//! ([`Renderer::new`]) in `pipelines`, and one frame's upload and render pass
//! ([`Renderer::render`]) in `frame`. The shaders are `shaders.wgsl`, beside this file.

mod buffers;
mod frame;
mod pipelines;
mod target;

pub use buffers::{
    BillboardInstance, Globals, GpuLeaf, GpuMesh, LeafDraw, LeafStore, MeshInstance, MeshVertex, TreeTransform,
};
pub use frame::{FrameCamera, FrameDraws};
pub use pipelines::Renderer;
pub use target::Target;

/// Colour target format (sRGB: shaders write linear colour).
pub const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8UnormSrgb;
/// Depth format.
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Side of one billboard texture slot, texels (images of other sizes are resampled).
pub const BILLBOARD_SLOT: u32 = 128;
/// Billboard texture slots (array layers); the least recently drawn is reused.
pub const BILLBOARD_LAYERS: u32 = 256;
/// Leaf draws per instance buffer (64 MiB: under every adapter's 256 MiB buffer limit; a
/// full-detail forest draws tens of millions of leaves).
pub const LEAF_DRAWS_PER_BUFFER: usize = 4 << 20;
/// Leaf mask side, texels (the shared rasterizer's procedural leaf).
pub const LEAF_MASK_SIDE: u32 = 32;
/// Alpha cutoff of leaves (the shared rasterizer's leaf materials).
pub const LEAF_ALPHA_CUTOFF: f32 = 0.5;
/// Alpha cutoff of blended billboards.
pub const BILLBOARD_ALPHA_CUTOFF: f32 = 0.5;

/// Why the GPU path failed.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter (no Vulkan or GL driver).
    #[error("no GPU adapter: {0}")]
    NoAdapter(String),
    /// The device could not be created.
    #[error("GPU device: {0}")]
    Device(String),
    /// Read-back failed.
    #[error("read-back: {0}")]
    Readback(String),
}

/// sRGB byte to linear.
pub fn srgb_to_linear(c: u8) -> f32 {
    let c = f32::from(c) / 255.0;
    if c <= 0.040_45 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Whether `adapter` can give a window its [`Target::ui_view`] (an `Rgba8Unorm` view of the
/// sRGB colour target).
pub fn supports_ui_view(adapter: &wgpu::Adapter) -> bool {
    adapter
        .get_downlevel_capabilities()
        .flags
        .contains(wgpu::DownlevelFlags::VIEW_FORMATS)
}

/// A headless device: the first adapter wgpu offers (Vulkan or GL), no surface.
pub fn headless_device() -> Result<(wgpu::Device, wgpu::Queue, String), GpuError> {
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions::default()))
        .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
    let info = adapter.get_info();
    let name = format!("{} ({:?}, {})", info.name, info.backend, info.driver);
    let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("canopy headless"),
        required_limits: wgpu::Limits::downlevel_defaults().using_resolution(adapter.limits()),
        ..wgpu::DeviceDescriptor::default()
    }))
    .map_err(|e| GpuError::Device(e.to_string()))?;
    Ok((device, queue, name))
}
