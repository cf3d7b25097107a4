//! The section's table in memory: the header fields, one [`CloudLevel`] per level and one
//! [`CloudPlane`] (quad, texture size, texture range) per plane. Quads are in model space,
//! metres, Y up; textures have row 0 at the top (see the parent module's docs).

use glam::Vec3;

#[cfg(doc)]
use super::{CLOUD_FLAG_TEXTURE_DENSITY, CLOUD_FLAG_VIEW_LINE};
use super::{CLOUD_HEADER_LEN, CLOUD_LEVEL_ENTRY_LEN, CLOUD_PLANE_RECORD_LEN};
use crate::format::FormatError;

/// Tolerance of the plane-record consistency checks, relative to the record's scale.
const PLANE_TOLERANCE: f32 = 1e-3;

/// Image codec of the textures.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CloudCodec {
    /// PNG, RGBA8.
    Png,
}

/// A plane's quad in model space (metres): `p0 + s·edge_u + t·edge_v`, s, t ∈ [0, 1].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CloudQuad {
    /// Unit plane normal, `normalize(edge_u × edge_v)`.
    pub normal: Vec3,
    /// Plane offset: the plane is `normal · x = d`.
    pub d: f32,
    /// Corner at texture (left, bottom).
    pub origin: Vec3,
    /// Edge along the texture's x axis (to the right).
    pub edge_u: Vec3,
    /// Edge along the texture's y axis (up).
    pub edge_v: Vec3,
}

/// Texture coordinates of [`CloudQuad::corners`], in order, for a renderer whose `v = 0` is the
/// image's top row (the layout's row 0).
pub const CLOUD_QUAD_UVS: [[f32; 2]; 4] = [[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]];

impl CloudQuad {
    /// The four corners, counter-clockwise seen from the normal side: p0, p0 + u, p0 + u + v,
    /// p0 + v.
    pub fn corners(&self) -> [Vec3; 4] {
        let p = self.origin;
        [p, p + self.edge_u, p + self.edge_u + self.edge_v, p + self.edge_v]
    }

    /// Quad area, m².
    pub fn area(&self) -> f32 {
        self.edge_u.cross(self.edge_v).length()
    }

    /// Checks finiteness and that normal, d and edges agree within [`PLANE_TOLERANCE`].
    pub(super) fn validate(&self) -> Result<(), FormatError> {
        let all = [self.normal, self.origin, self.edge_u, self.edge_v];
        if !(all.iter().all(|v| v.is_finite()) && self.d.is_finite()) {
            return Err(FormatError::invalid("cloud plane", "non-finite geometry"));
        }
        let (lu, lv) = (self.edge_u.length(), self.edge_v.length());
        let scale = 1.0 + self.origin.length() + lu + lv;
        let ok = (self.normal.length() - 1.0).abs() <= PLANE_TOLERANCE
            && lu > 0.0
            && lv > 0.0
            && self.normal.dot(self.edge_u).abs() <= PLANE_TOLERANCE * lu
            && self.normal.dot(self.edge_v).abs() <= PLANE_TOLERANCE * lv
            && self.normal.dot(self.edge_u.cross(self.edge_v)) > 0.0
            && (self.normal.dot(self.origin) - self.d).abs() <= PLANE_TOLERANCE * scale;
        if ok {
            Ok(())
        } else {
            Err(FormatError::invalid(
                "cloud plane",
                "normal, offset and edges disagree (not a unit normal of the quad)",
            ))
        }
    }
}

/// Where a texture lies: byte range relative to the section start, and its CRC-32.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TextureRange {
    /// Offset from the section start.
    pub offset: u32,
    /// Length in bytes (> 0).
    pub length: u32,
    /// CRC-32 of the texture bytes.
    pub crc: u32,
}

impl TextureRange {
    /// `offset .. offset + length`, relative to the section start.
    pub fn range(&self) -> std::ops::Range<u64> {
        u64::from(self.offset)..u64::from(self.offset) + u64::from(self.length)
    }
}

/// One plane of the table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CloudPlane {
    /// The quad.
    pub quad: CloudQuad,
    /// Texture width, pixels.
    pub width: u16,
    /// Texture height, pixels.
    pub height: u16,
    /// Where the texture lies.
    pub texture: TextureRange,
}

/// One level of the table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CloudLevel {
    /// Index of the level's first plane in [`CloudTable::planes`].
    pub first_plane: u32,
    /// Planes in the level (≥ 1).
    pub plane_count: u32,
    /// Plane-distance threshold ε_i, metres: every primitive drawn on a plane was within ε_i of
    /// it (2ε_i for textures with [`CLOUD_FLAG_TEXTURE_DENSITY`]).
    pub epsilon: f32,
    /// Texture sampling step, metres per texel.
    pub texel: f32,
    /// All the level's textures, one contiguous range.
    pub textures: TextureRange,
}

impl CloudLevel {
    /// Distance from which ε_i subtends at most `pixel_error` pixels on a screen
    /// `screen_height` pixels high with vertical field of view `fov_y` (radians): the nearest
    /// distance at which this level's parallax error is below `pixel_error`
    /// (`σ_i = ε_i · L / (2 · tan(α/2) · τ)`). A client's LOD policy draws level i between
    /// `σ_i` and `σ_{i+1}` and blends adjacent levels near the switch.
    pub fn switch_distance(&self, pixel_error: f32, screen_height: f32, fov_y: f32) -> f32 {
        self.epsilon * screen_height / (2.0 * (0.5 * fov_y).tan() * pixel_error.max(1e-6))
    }
}

/// The section's table: everything but the textures.
#[derive(Debug, Clone, PartialEq)]
pub struct CloudTable {
    /// Texture codec.
    pub codec: CloudCodec,
    /// Header flags ([`CLOUD_FLAG_TEXTURE_DENSITY`], [`CLOUD_FLAG_VIEW_LINE`]).
    pub flags: u16,
    /// Bounding-sphere radius `r` the thresholds ε_i = scale · i · r were computed from.
    pub radius: f32,
    /// Bounding-sphere centre.
    pub center: Vec3,
    /// Flight height H of the view-line penalty (0: not used).
    pub view_line_height: f32,
    /// Levels, finest first.
    pub levels: Vec<CloudLevel>,
    /// Planes of every level, level-major.
    pub planes: Vec<CloudPlane>,
}

impl CloudTable {
    /// Bytes of a table with `levels` levels and `planes` planes: a client's first fetch.
    pub fn table_len(levels: usize, planes: usize) -> usize {
        CLOUD_HEADER_LEN + CLOUD_LEVEL_ENTRY_LEN * levels + CLOUD_PLANE_RECORD_LEN * planes + 4
    }

    /// An empty table (no levels): what an empty section decodes to.
    pub fn empty() -> Self {
        Self {
            codec: CloudCodec::Png,
            flags: 0,
            radius: 0.0,
            center: Vec3::ZERO,
            view_line_height: 0.0,
            levels: Vec::new(),
            planes: Vec::new(),
        }
    }

    /// The planes of level `level` (empty when out of range).
    pub fn level_planes(&self, level: usize) -> &[CloudPlane] {
        self.levels.get(level).map_or(&[], |l| {
            &self.planes[l.first_plane as usize..(l.first_plane + l.plane_count) as usize]
        })
    }

    /// Byte range (relative to the section start) of all of level `level`'s textures: one
    /// request fetches the whole level. `None` when out of range.
    pub fn level_range(&self, level: usize) -> Option<std::ops::Range<u64>> {
        self.levels.get(level).map(|l| l.textures.range())
    }
}
