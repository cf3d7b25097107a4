//! Billboard clouds (section kind 8): seed 002's stochastic billboard clouds, `L` levels of
//! textured quads, each level coarser than the one before (plane-distance threshold ε_i). The
//! section starts with a table (header, one entry per level, one record per plane, table CRC)
//! and then holds one encoded texture per plane, level-major. A client fetches the table, then
//! the textures of the level it wants: each plane's texture is its own byte range with its own
//! CRC-32, and the textures of one level are contiguous, so a whole level is also one range
//! ([`CloudTable::level_range`]). The byte layout is in `docs/format.md`, "Billboard clouds
//! (kind 8)"; the constants here are the ones named there.
//!
//! Layout (all little-endian, offsets relative to the section start):
//!
//! ```text
//! header (32 B):  u32 table length T | u8 codec (0 = PNG) | u8 levels L | u16 flags
//!                 | u32 planes P | f32 radius r | f32 view-line height H (0 = none)
//!                 | f32[3] bounding-sphere centre
//! level (24 B):   u32 first plane | u32 plane count | f32 ε (m) | f32 texel size (m)
//!                 | u32 offset | u32 length          (the level's textures, one range)
//! plane (68 B):   f32[3] normal n | f32 d (n·x = d) | f32[3] corner p0 | f32[3] edge u
//!                 | f32[3] edge v | u16 width px | u16 height px | u32 offset | u32 length
//!                 | u32 CRC-32 of the texture
//! u32 CRC-32 of the table bytes before it;  T = 36 + 24·L + 68·P
//! textures: plane order, tiling [T, section length) without gaps
//! ```
//!
//! The quad is `p0 + s·u + t·v`, s, t ∈ [0, 1]; `n = normalize(u × v)`. Texture pixel (x, y),
//! row 0 at the top, shows the quad point `s = (x + ½)/width`, `t = 1 − (y + ½)/height`: seen
//! from the side `n` points to, the image is upright and unmirrored (u to the right, v up).
//! Textures are RGBA8, straight alpha, transparent where the plane shows nothing.
//!
//! An empty section (length 0, as every file before format 1.2 has) decodes as a table with no
//! levels: "not baked".
//!
//! Code layout: the constants of the layout are here; [`CloudTable`] and its records are in
//! `table`, reading and validating a table in `decode`, fetching and checking textures (one
//! plane, one level, a whole section) in `textures`, and writing a section in `encode`. Errors
//! are the crate-wide [`FormatError`](crate::format::FormatError): the shared variants
//! (truncated, checksum mismatch, invalid field, trailing bytes) with a `what` naming the cloud
//! structure, and the cloud-specific ones (table length, counts, texture ranges, images).

mod decode;
mod encode;
mod table;
mod textures;

pub use encode::{CloudHeader, LevelTextures, PlaneTexture, encode_clouds};
pub use table::{CLOUD_QUAD_UVS, CloudCodec, CloudLevel, CloudPlane, CloudQuad, CloudTable, TextureRange};
pub use textures::decode_clouds;

/// Bytes of the fixed section header.
pub const CLOUD_HEADER_LEN: usize = 32;
/// Bytes of one level entry.
pub const CLOUD_LEVEL_ENTRY_LEN: usize = 24;
/// Bytes of one plane record.
pub const CLOUD_PLANE_RECORD_LEN: usize = 68;
/// Largest number of levels.
pub const MAX_CLOUD_LEVELS: usize = 16;
/// Largest number of planes in the whole section.
pub const MAX_CLOUD_PLANES: u32 = 1 << 16;
/// Largest texture side, pixels.
pub const MAX_CLOUD_TEXTURE: u16 = 2048;
/// Header flag: textures were baked with seed 002's texture-density option (2ε).
pub const CLOUD_FLAG_TEXTURE_DENSITY: u16 = 1;
/// Header flag: planes were chosen with seed 002's view-line penalty (height in the header).
pub const CLOUD_FLAG_VIEW_LINE: u16 = 2;

#[cfg(test)]
mod tests;
