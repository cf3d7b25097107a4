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

use glam::Vec3;

use super::FormatError;
use super::bytes::{Cursor, Writer};
use super::crc32;

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
/// Tolerance of the plane-record consistency checks, relative to the record's scale.
const PLANE_TOLERANCE: f32 = 1e-3;

/// Why a billboard-cloud section (or one of its textures) was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CloudError {
    /// Fewer bytes than the structure needs.
    #[error("truncated {what}: need {need} bytes, have {have}")]
    Truncated {
        /// Which structure.
        what: &'static str,
        /// Bytes needed.
        need: u64,
        /// Bytes available.
        have: u64,
    },
    /// The table length disagrees with the counts or does not fit the section.
    #[error("bad cloud table length {table_len} ({detail})")]
    TableLength {
        /// Table length read from the header.
        table_len: u64,
        /// What it disagrees with.
        detail: String,
    },
    /// A count out of range or inconsistent (levels, planes, planes per level).
    #[error("bad cloud counts: {0}")]
    Counts(String),
    /// A texture range that ends past the section.
    #[error("texture of plane {plane} at {offset}+{length} lies outside the {section_len}-byte section")]
    OffsetOutOfRange {
        /// Plane index (section-wide).
        plane: u32,
        /// Offset from the section start.
        offset: u64,
        /// Length.
        length: u64,
        /// Section length.
        section_len: u64,
    },
    /// A texture range that starts before the previous one ends (or inside the table).
    #[error("texture of plane {plane} at {offset} overlaps the bytes before it (ending at {expected})")]
    Overlap {
        /// Plane index.
        plane: u32,
        /// Its offset.
        offset: u64,
        /// Where the previous range ended.
        expected: u64,
    },
    /// A texture range that leaves unused bytes before it.
    #[error("texture of plane {plane} at {offset} leaves a gap after {expected}")]
    Gap {
        /// Plane index.
        plane: u32,
        /// Its offset.
        offset: u64,
        /// Where the previous range ended.
        expected: u64,
    },
    /// A CRC-32 mismatch (table or texture).
    #[error("checksum mismatch in {what}: stored {stored:#010x}, computed {computed:#010x}")]
    Checksum {
        /// Which structure.
        what: &'static str,
        /// Stored CRC.
        stored: u32,
        /// CRC of the bytes.
        computed: u32,
    },
    /// A field the spec forbids (non-finite or inconsistent geometry, unknown codec or flags).
    #[error("invalid {what}: {detail}")]
    Invalid {
        /// Which field.
        what: &'static str,
        /// What is wrong.
        detail: String,
    },
    /// Bytes after the last texture.
    #[error("billboard-cloud section has {0} bytes after its last texture")]
    TrailingBytes(u64),
    /// A texture that is not a PNG of the recorded size.
    #[error("cloud texture: {0}")]
    Image(String),
}

impl From<FormatError> for CloudError {
    fn from(e: FormatError) -> Self {
        match e {
            FormatError::Truncated { what, need, have } => Self::Truncated { what, need, have },
            other => Self::Invalid {
                what: "cloud table",
                detail: other.to_string(),
            },
        }
    }
}

fn invalid(what: &'static str, detail: impl Into<String>) -> CloudError {
    CloudError::Invalid {
        what,
        detail: detail.into(),
    }
}

fn check(what: &'static str, bytes: &[u8], stored: u32) -> Result<(), CloudError> {
    let computed = crc32(bytes);
    if computed == stored {
        Ok(())
    } else {
        Err(CloudError::Checksum { what, stored, computed })
    }
}

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
    fn validate(&self) -> Result<(), CloudError> {
        let all = [self.normal, self.origin, self.edge_u, self.edge_v];
        if !(all.iter().all(|v| v.is_finite()) && self.d.is_finite()) {
            return Err(invalid("cloud plane", "non-finite geometry"));
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
            Err(invalid(
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

    /// Reads the table length from the first 4 bytes of a non-empty section.
    pub fn peek_table_len(prefix: &[u8]) -> Result<u32, CloudError> {
        Ok(Cursor::new(prefix, "cloud header").u32()?)
    }

    /// Decodes and validates the table from the section's first bytes (`prefix` holds at least
    /// the table; more is ignored). `section_len` is the section's length from the directory;
    /// 0 gives [`CloudTable::empty`]. Textures must tile `[T, section_len)` in plane order: a
    /// range that starts early is an [`CloudError::Overlap`], late a [`CloudError::Gap`], past
    /// the end [`CloudError::OffsetOutOfRange`]; unused bytes at the end are
    /// [`CloudError::TrailingBytes`].
    pub fn decode(prefix: &[u8], section_len: u64) -> Result<Self, CloudError> {
        if section_len == 0 {
            return Ok(Self::empty());
        }
        let table_len = u64::from(Self::peek_table_len(prefix)?);
        let bad_len = |detail: String| CloudError::TableLength { table_len, detail };
        if table_len < Self::table_len(0, 0) as u64 || table_len > section_len {
            return Err(bad_len(format!("section is {section_len} bytes")));
        }
        if table_len > prefix.len() as u64 {
            return Err(CloudError::Truncated {
                what: "cloud table",
                need: table_len,
                have: prefix.len() as u64,
            });
        }
        let t = table_len as usize;
        let stored = Cursor::new(&prefix[t - 4..t], "cloud table").u32()?;
        check("cloud table", &prefix[..t - 4], stored)?;
        let mut c = Cursor::new(&prefix[..t - 4], "cloud table");
        c.u32()?;
        let codec = match c.u8()? {
            0 => CloudCodec::Png,
            k => return Err(invalid("cloud codec", format!("unknown code {k}"))),
        };
        let nlevels = c.u8()? as usize;
        let flags = c.u16()?;
        if flags & !(CLOUD_FLAG_TEXTURE_DENSITY | CLOUD_FLAG_VIEW_LINE) != 0 {
            return Err(invalid("cloud flags", format!("{flags:#06x} has unknown bits")));
        }
        let nplanes = c.u32()?;
        let radius = c.f32()?;
        let view_line_height = c.f32()?;
        let center = Vec3::new(c.f32()?, c.f32()?, c.f32()?);
        if !(radius > 0.0
            && radius.is_finite()
            && center.is_finite()
            && view_line_height >= 0.0
            && view_line_height.is_finite())
            || ((flags & CLOUD_FLAG_VIEW_LINE != 0) != (view_line_height > 0.0))
        {
            return Err(invalid(
                "cloud header",
                "radius, centre or view-line height out of range",
            ));
        }
        if nlevels > MAX_CLOUD_LEVELS || nplanes > MAX_CLOUD_PLANES {
            return Err(CloudError::Counts(format!("{nlevels} levels, {nplanes} planes")));
        }
        if Self::table_len(nlevels, nplanes as usize) as u64 != table_len {
            return Err(bad_len(format!(
                "{nlevels} levels and {nplanes} planes need {}",
                Self::table_len(nlevels, nplanes as usize)
            )));
        }
        let mut levels = Vec::with_capacity(nlevels);
        let mut next_plane = 0u32;
        for _ in 0..nlevels {
            let first_plane = c.u32()?;
            let plane_count = c.u32()?;
            let epsilon = c.f32()?;
            let texel = c.f32()?;
            let textures = TextureRange {
                offset: c.u32()?,
                length: c.u32()?,
                crc: 0,
            };
            if first_plane != next_plane || plane_count == 0 || plane_count > nplanes - next_plane {
                return Err(CloudError::Counts(format!(
                    "level planes {first_plane}+{plane_count} where {next_plane}.. of {nplanes} remain"
                )));
            }
            let finer = levels.last().map_or(0.0, |l: &CloudLevel| l.epsilon);
            if !(epsilon.is_finite() && epsilon > finer && texel.is_finite() && texel > 0.0) {
                return Err(invalid(
                    "cloud level",
                    "ε must be finite and increase level by level, texel size positive",
                ));
            }
            next_plane += plane_count;
            levels.push(CloudLevel {
                first_plane,
                plane_count,
                epsilon,
                texel,
                textures,
            });
        }
        if next_plane != nplanes {
            return Err(CloudError::Counts(format!(
                "levels hold {next_plane} of {nplanes} planes"
            )));
        }
        let mut planes = Vec::with_capacity(nplanes as usize);
        let mut cursor = table_len;
        for i in 0..nplanes {
            let normal = Vec3::new(c.f32()?, c.f32()?, c.f32()?);
            let d = c.f32()?;
            let origin = Vec3::new(c.f32()?, c.f32()?, c.f32()?);
            let edge_u = Vec3::new(c.f32()?, c.f32()?, c.f32()?);
            let edge_v = Vec3::new(c.f32()?, c.f32()?, c.f32()?);
            let quad = CloudQuad {
                normal,
                d,
                origin,
                edge_u,
                edge_v,
            };
            quad.validate()?;
            let width = c.u16()?;
            let height = c.u16()?;
            if !(1..=MAX_CLOUD_TEXTURE).contains(&width) || !(1..=MAX_CLOUD_TEXTURE).contains(&height) {
                return Err(invalid("cloud texture size", format!("{width}x{height}")));
            }
            let texture = TextureRange {
                offset: c.u32()?,
                length: c.u32()?,
                crc: c.u32()?,
            };
            let (offset, length) = (u64::from(texture.offset), u64::from(texture.length));
            if length == 0 {
                return Err(invalid("cloud texture", format!("plane {i} has no texture bytes")));
            }
            if offset + length > section_len {
                return Err(CloudError::OffsetOutOfRange {
                    plane: i,
                    offset,
                    length,
                    section_len,
                });
            }
            if offset < cursor {
                return Err(CloudError::Overlap {
                    plane: i,
                    offset,
                    expected: cursor,
                });
            }
            if offset > cursor {
                return Err(CloudError::Gap {
                    plane: i,
                    offset,
                    expected: cursor,
                });
            }
            cursor += length;
            planes.push(CloudPlane {
                quad,
                width,
                height,
                texture,
            });
        }
        c.finish()?;
        if cursor != section_len {
            return Err(CloudError::TrailingBytes(section_len - cursor));
        }
        for l in &levels {
            let ps = &planes[l.first_plane as usize..(l.first_plane + l.plane_count) as usize];
            let start = ps.first().map_or(0, |p| u64::from(p.texture.offset));
            let end = ps.last().map_or(0, |p| p.texture.range().end);
            if u64::from(l.textures.offset) != start || u64::from(l.textures.length) != end - start {
                return Err(CloudError::Counts(format!(
                    "level range {}+{} disagrees with its planes' {start}..{end}",
                    l.textures.offset, l.textures.length
                )));
            }
        }
        Ok(Self {
            codec,
            flags,
            radius,
            center,
            view_line_height,
            levels,
            planes,
        })
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

    /// Checks fetched texture bytes against the plane's entry (length, CRC) and returns them.
    pub fn verify_texture<'a>(plane: &CloudPlane, bytes: &'a [u8]) -> Result<&'a [u8], CloudError> {
        if bytes.len() as u64 != u64::from(plane.texture.length) {
            return Err(CloudError::Truncated {
                what: "cloud texture",
                need: u64::from(plane.texture.length),
                have: bytes.len() as u64,
            });
        }
        check("cloud texture", bytes, plane.texture.crc)?;
        Ok(bytes)
    }

    /// Verifies and decodes one plane's texture to RGBA8 of the recorded size.
    pub fn decode_texture(plane: &CloudPlane, bytes: &[u8]) -> Result<image::RgbaImage, CloudError> {
        let bytes = Self::verify_texture(plane, bytes)?;
        let img = image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
            .map_err(|e| CloudError::Image(e.to_string()))?
            .to_rgba8();
        if img.width() != u32::from(plane.width) || img.height() != u32::from(plane.height) {
            return Err(CloudError::Image(format!(
                "{}x{} where {}x{} was recorded",
                img.width(),
                img.height(),
                plane.width,
                plane.height
            )));
        }
        Ok(img)
    }

    /// Checks the bytes of [`CloudTable::level_range`] (fetched in one request) against every
    /// plane's length and CRC-32, without decoding the PNGs: what a client checks before it
    /// caches a level.
    pub fn verify_level(&self, level: usize, level_bytes: &[u8]) -> Result<(), CloudError> {
        self.level_textures(level, level_bytes)?
            .try_for_each(|(p, b)| Self::verify_texture(p, b).map(|_| ()))
    }

    /// Each plane of level `level` with its texture bytes cut from the level's bytes (length
    /// checked; CRCs not).
    fn level_textures<'s, 'b>(
        &'s self,
        level: usize,
        level_bytes: &'b [u8],
    ) -> Result<impl Iterator<Item = (&'s CloudPlane, &'b [u8])> + use<'s, 'b>, CloudError> {
        let l = self
            .levels
            .get(level)
            .ok_or_else(|| CloudError::Counts(format!("level {level} of {}", self.levels.len())))?;
        if level_bytes.len() as u64 != u64::from(l.textures.length) {
            return Err(CloudError::Truncated {
                what: "cloud level",
                need: u64::from(l.textures.length),
                have: level_bytes.len() as u64,
            });
        }
        let base = u64::from(l.textures.offset);
        Ok(self.level_planes(level).iter().map(move |p| {
            let r = p.texture.range();
            // In bounds: decode checked that the planes tile the level's range.
            (p, &level_bytes[(r.start - base) as usize..(r.end - base) as usize])
        }))
    }

    /// Decodes every texture of level `level` from the bytes of [`CloudTable::level_range`]
    /// (fetched in one request): one image per plane, in plane order.
    pub fn decode_level(&self, level: usize, level_bytes: &[u8]) -> Result<Vec<image::RgbaImage>, CloudError> {
        self.level_textures(level, level_bytes)?
            .map(|(p, b)| Self::decode_texture(p, b))
            .collect()
    }

    /// The verified texture bytes of section-wide plane `plane` out of the whole section.
    pub fn texture_bytes<'a>(&self, section: &'a [u8], plane: usize) -> Result<&'a [u8], CloudError> {
        let p = self
            .planes
            .get(plane)
            .ok_or_else(|| CloudError::Counts(format!("plane {plane} of {}", self.planes.len())))?;
        let r = p.texture.range();
        let bytes = section
            .get(r.start as usize..r.end as usize)
            .ok_or(CloudError::Truncated {
                what: "cloud texture",
                need: r.end,
                have: section.len() as u64,
            })?;
        Self::verify_texture(p, bytes)
    }
}

/// Decodes a whole section: the table and every texture's CRC (not the PNGs).
pub fn decode_clouds(section: &[u8]) -> Result<CloudTable, CloudError> {
    let t = CloudTable::decode(section, section.len() as u64)?;
    for i in 0..t.planes.len() {
        t.texture_bytes(section, i)?;
    }
    Ok(t)
}

/// One plane to encode: its quad and its encoded texture (PNG of `width × height`).
#[derive(Debug, Clone, PartialEq)]
pub struct PlaneTexture {
    /// The quad.
    pub quad: CloudQuad,
    /// Texture width, pixels.
    pub width: u16,
    /// Texture height, pixels.
    pub height: u16,
    /// Encoded texture.
    pub bytes: Vec<u8>,
}

/// One level to encode.
#[derive(Debug, Clone, PartialEq)]
pub struct LevelTextures {
    /// ε_i, metres.
    pub epsilon: f32,
    /// Metres per texel.
    pub texel: f32,
    /// Planes (≥ 1).
    pub planes: Vec<PlaneTexture>,
}

/// What the header records besides the levels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CloudHeader {
    /// Bounding-sphere centre.
    pub center: Vec3,
    /// Bounding-sphere radius (> 0).
    pub radius: f32,
    /// Texture-density option used.
    pub texture_density: bool,
    /// View-line penalty height H (> 0), if used.
    pub view_line_height: Option<f32>,
}

/// Encodes a billboard-cloud section. Every check [`CloudTable::decode`] makes is made here
/// first, so the encoder errors rather than write a section a reader would reject. No levels
/// gives an empty section (length 0).
pub fn encode_clouds(header: &CloudHeader, levels: &[LevelTextures]) -> Result<Vec<u8>, CloudError> {
    if levels.is_empty() {
        return Ok(Vec::new());
    }
    let nplanes: usize = levels.iter().map(|l| l.planes.len()).sum();
    if levels.len() > MAX_CLOUD_LEVELS || nplanes > MAX_CLOUD_PLANES as usize {
        return Err(CloudError::Counts(format!("{} levels, {nplanes} planes", levels.len())));
    }
    let h = header.view_line_height.unwrap_or(0.0);
    if !(header.radius > 0.0 && header.radius.is_finite() && header.center.is_finite() && h >= 0.0 && h.is_finite())
        || header.view_line_height.is_some_and(|h| h <= 0.0)
    {
        return Err(invalid("cloud header", "radius, centre or height out of range"));
    }
    let mut flags = 0;
    if header.texture_density {
        flags |= CLOUD_FLAG_TEXTURE_DENSITY;
    }
    if header.view_line_height.is_some() {
        flags |= CLOUD_FLAG_VIEW_LINE;
    }
    let table_len = CloudTable::table_len(levels.len(), nplanes);
    let mut w = Writer::default();
    w.u32(table_len as u32);
    w.u8(0);
    w.u8(levels.len() as u8);
    w.u16(flags);
    w.u32(nplanes as u32);
    w.f32(header.radius);
    w.f32(h);
    for v in header.center.to_array() {
        w.f32(v);
    }
    let mut offset = table_len as u64;
    let mut first = 0u32;
    let mut prev_eps = 0.0;
    for l in levels {
        if l.planes.is_empty()
            || !(l.epsilon.is_finite() && l.epsilon > prev_eps && l.texel > 0.0 && l.texel.is_finite())
        {
            return Err(invalid("cloud level", "no planes, or ε not increasing, or bad texel"));
        }
        prev_eps = l.epsilon;
        let len: u64 = l.planes.iter().map(|p| p.bytes.len() as u64).sum();
        let (off, len) = (
            u32::try_from(offset).map_err(|_| invalid("cloud section", "over 4 GiB"))?,
            u32::try_from(len).map_err(|_| invalid("cloud section", "over 4 GiB"))?,
        );
        w.u32(first);
        w.u32(l.planes.len() as u32);
        w.f32(l.epsilon);
        w.f32(l.texel);
        w.u32(off);
        w.u32(len);
        first += l.planes.len() as u32;
        offset += u64::from(len);
    }
    let mut offset = table_len as u64;
    for p in levels.iter().flat_map(|l| &l.planes) {
        p.quad.validate()?;
        if p.bytes.is_empty()
            || !(1..=MAX_CLOUD_TEXTURE).contains(&p.width)
            || !(1..=MAX_CLOUD_TEXTURE).contains(&p.height)
        {
            return Err(invalid("cloud plane", "empty texture or size out of range"));
        }
        let q = &p.quad;
        let mut fields = q.normal.to_array().to_vec();
        fields.push(q.d);
        for v in [q.origin, q.edge_u, q.edge_v] {
            fields.extend(v.to_array());
        }
        for v in fields {
            w.f32(v);
        }
        w.u16(p.width);
        w.u16(p.height);
        w.u32(u32::try_from(offset).map_err(|_| invalid("cloud section", "over 4 GiB"))?);
        w.u32(p.bytes.len() as u32);
        w.u32(crc32(&p.bytes));
        offset += p.bytes.len() as u64;
    }
    let crc = crc32(&w.buf);
    w.u32(crc);
    if w.buf.len() != table_len {
        return Err(invalid("cloud table", "length mismatch (encoder bug)"));
    }
    for p in levels.iter().flat_map(|l| &l.planes) {
        w.buf.extend_from_slice(&p.bytes);
    }
    Ok(w.buf)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn quad(z: f32, size: f32) -> CloudQuad {
        CloudQuad {
            normal: Vec3::Z,
            d: z,
            origin: Vec3::new(-size / 2.0, 0.0, z),
            edge_u: Vec3::X * size,
            edge_v: Vec3::Y * size,
        }
    }

    fn png(w: u32, h: u32, seed: u8) -> Vec<u8> {
        let img = image::RgbaImage::from_fn(w, h, |x, y| {
            image::Rgba([seed, x as u8, y as u8, 255 * ((x + y) % 2) as u8])
        });
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png).unwrap();
        out.into_inner()
    }

    fn sample() -> (CloudHeader, Vec<LevelTextures>) {
        let header = CloudHeader {
            center: Vec3::new(0.0, 2.0, 0.0),
            radius: 3.0,
            texture_density: true,
            view_line_height: Some(20.0),
        };
        let levels = vec![
            LevelTextures {
                epsilon: 0.3,
                texel: 0.05,
                planes: (0..3)
                    .map(|i| PlaneTexture {
                        quad: quad(i as f32 - 1.0, 2.0),
                        width: 4 + i,
                        height: 3,
                        bytes: png(u32::from(4 + i), 3, i as u8),
                    })
                    .collect(),
            },
            LevelTextures {
                epsilon: 0.6,
                texel: 0.1,
                planes: vec![PlaneTexture {
                    quad: quad(0.0, 4.0),
                    width: 2,
                    height: 2,
                    bytes: png(2, 2, 9),
                }],
            },
        ];
        (header, levels)
    }

    #[test]
    fn round_trip_and_client_fetch() {
        let (header, levels) = sample();
        let bytes = encode_clouds(&header, &levels).unwrap();
        // A client: 4 bytes, then the table, then one level by one range.
        let tl = CloudTable::peek_table_len(&bytes[..4]).unwrap() as usize;
        assert_eq!(tl, CloudTable::table_len(2, 4));
        let t = CloudTable::decode(&bytes[..tl], bytes.len() as u64).unwrap();
        assert_eq!(t.flags, CLOUD_FLAG_TEXTURE_DENSITY | CLOUD_FLAG_VIEW_LINE);
        assert_eq!(t.view_line_height, 20.0);
        assert_eq!(t.levels.len(), 2);
        assert_eq!(t.level_planes(0).len(), 3);
        assert_eq!(t.level_planes(1)[0].quad, levels[1].planes[0].quad);
        let r = t.level_range(0).unwrap();
        let imgs = t.decode_level(0, &bytes[r.start as usize..r.end as usize]).unwrap();
        assert_eq!(imgs.len(), 3);
        assert_eq!((imgs[2].width(), imgs[2].height()), (6, 3));
        assert_eq!(imgs[1].get_pixel(2, 1).0, [1, 2, 1, 255]);
        // A client checks a fetched level's CRCs before caching it: one flipped byte in any
        // plane's texture, or a short body, is rejected.
        let mut level = bytes[r.start as usize..r.end as usize].to_vec();
        t.verify_level(0, &level).unwrap();
        assert!(matches!(
            t.verify_level(0, &level[1..]),
            Err(CloudError::Truncated { .. })
        ));
        let last = level.len() - 1;
        level[last] ^= 1;
        assert!(matches!(t.verify_level(0, &level), Err(CloudError::Checksum { .. })));
        assert!(matches!(t.verify_level(9, &level), Err(CloudError::Counts(_))));
        // One plane alone, by its own range.
        let p = t.planes[3];
        let r = p.texture.range();
        let img = CloudTable::decode_texture(&p, &bytes[r.start as usize..r.end as usize]).unwrap();
        assert_eq!(img.width(), 2);
        assert_eq!(decode_clouds(&bytes).unwrap(), t);
        // Levels switch farther out as ε grows.
        let d0 = t.levels[0].switch_distance(1.0, 1080.0, 1.0);
        assert!(t.levels[1].switch_distance(1.0, 1080.0, 1.0) > d0 && d0 > 0.0);
        assert_eq!(t.planes[0].quad.corners()[2], Vec3::new(1.0, 2.0, -1.0));
    }

    #[test]
    fn empty_section_is_not_baked() {
        let (header, _) = sample();
        assert!(encode_clouds(&header, &[]).unwrap().is_empty());
        let t = decode_clouds(&[]).unwrap();
        assert!(t.levels.is_empty() && t.planes.is_empty());
        assert_eq!(t.level_range(0), None);
        assert!(t.level_planes(0).is_empty());
    }

    /// Rewrites a table field and fixes the table CRC, so the check under test is the one that
    /// fires (not the CRC).
    fn patch(bytes: &[u8], at: usize, v: &[u8]) -> Vec<u8> {
        let mut b = bytes.to_vec();
        b[at..at + v.len()].copy_from_slice(v);
        let tl = CloudTable::peek_table_len(&b).unwrap() as usize;
        let crc = crc32(&b[..tl - 4]);
        b[tl - 4..tl].copy_from_slice(&crc.to_le_bytes());
        b
    }

    fn plane_at(level_count: usize, i: usize) -> usize {
        CLOUD_HEADER_LEN + CLOUD_LEVEL_ENTRY_LEN * level_count + CLOUD_PLANE_RECORD_LEN * i
    }

    #[test]
    fn each_kind_of_bad_input_gives_its_error() {
        let (header, levels) = sample();
        let bytes = encode_clouds(&header, &levels).unwrap();
        let n = bytes.len() as u64;
        let dec = |b: &[u8]| CloudTable::decode(b, b.len() as u64);
        // Truncated: a prefix shorter than the table.
        assert!(matches!(
            CloudTable::decode(&bytes[..40], n),
            Err(CloudError::Truncated { .. })
        ));
        assert!(matches!(
            CloudTable::decode(&bytes[..2], n),
            Err(CloudError::Truncated { .. })
        ));
        // Table length larger than the section, or disagreeing with the counts.
        assert!(matches!(
            CloudTable::decode(&bytes, 50),
            Err(CloudError::TableLength { .. })
        ));
        let b = patch(&bytes, 8, &5u32.to_le_bytes());
        assert!(matches!(dec(&b), Err(CloudError::TableLength { .. })));
        // Bad counts: a level that claims more planes than there are.
        let b = patch(&bytes, CLOUD_HEADER_LEN + 4, &9u32.to_le_bytes());
        assert!(matches!(dec(&b), Err(CloudError::Counts(_))), "{:?}", dec(&b));
        let b = patch(&bytes, CLOUD_HEADER_LEN + 4, &0u32.to_le_bytes());
        assert!(matches!(dec(&b), Err(CloudError::Counts(_))));
        // Bad CRC of the table.
        let mut b = bytes.clone();
        b[13] ^= 0x40;
        assert!(matches!(
            dec(&b),
            Err(CloudError::Checksum {
                what: "cloud table",
                ..
            })
        ));
        // Texture offsets: out of range, overlapping, leaving a gap.
        let off = plane_at(2, 1) + 56;
        let first = u32::from_le_bytes(bytes[off..off + 4].try_into().unwrap());
        let b = patch(&bytes, off, &(n as u32 + 5).to_le_bytes());
        assert!(matches!(dec(&b), Err(CloudError::OffsetOutOfRange { plane: 1, .. })));
        let b = patch(&bytes, off, &(first - 1).to_le_bytes());
        assert!(matches!(dec(&b), Err(CloudError::Overlap { plane: 1, .. })));
        let b = patch(&bytes, off, &(first + 1).to_le_bytes());
        assert!(matches!(dec(&b), Err(CloudError::Gap { plane: 1, .. })));
        let b = patch(&bytes, plane_at(2, 0) + 56, &8u32.to_le_bytes());
        assert!(matches!(dec(&b), Err(CloudError::Overlap { plane: 0, .. })));
        // Trailing bytes after the last texture.
        let mut b = bytes.clone();
        b.push(0);
        assert!(matches!(dec(&b), Err(CloudError::TrailingBytes(1))));
        // A level range that disagrees with its planes.
        let b = patch(&bytes, CLOUD_HEADER_LEN + 20, &1u32.to_le_bytes());
        assert!(matches!(dec(&b), Err(CloudError::Counts(_))));
        // Geometry: a non-unit normal, a NaN, a plane offset that disagrees with the corner.
        let b = patch(&bytes, plane_at(2, 2), &2f32.to_le_bytes());
        assert!(matches!(
            dec(&b),
            Err(CloudError::Invalid {
                what: "cloud plane",
                ..
            })
        ));
        let b = patch(&bytes, plane_at(2, 2) + 20, &f32::NAN.to_le_bytes());
        assert!(matches!(
            dec(&b),
            Err(CloudError::Invalid {
                what: "cloud plane",
                ..
            })
        ));
        let b = patch(&bytes, plane_at(2, 2) + 12, &7f32.to_le_bytes());
        assert!(matches!(
            dec(&b),
            Err(CloudError::Invalid {
                what: "cloud plane",
                ..
            })
        ));
        // Unknown codec and flag bits; ε not increasing.
        let b = patch(&bytes, 4, &[3]);
        assert!(matches!(
            dec(&b),
            Err(CloudError::Invalid {
                what: "cloud codec",
                ..
            })
        ));
        let b = patch(&bytes, 6, &8u16.to_le_bytes());
        assert!(matches!(
            dec(&b),
            Err(CloudError::Invalid {
                what: "cloud flags",
                ..
            })
        ));
        let b = patch(
            &bytes,
            CLOUD_HEADER_LEN + CLOUD_LEVEL_ENTRY_LEN + 8,
            &0.1f32.to_le_bytes(),
        );
        assert!(matches!(
            dec(&b),
            Err(CloudError::Invalid {
                what: "cloud level",
                ..
            })
        ));
        // Texture bytes: a flipped bit fails that plane's CRC only; a short fetch is truncated.
        let t = dec(&bytes).unwrap();
        let mut b = bytes.clone();
        let last = b.len() - 1;
        b[last] ^= 1;
        assert!(matches!(
            t.texture_bytes(&b, 3),
            Err(CloudError::Checksum {
                what: "cloud texture",
                ..
            })
        ));
        assert!(t.texture_bytes(&b, 0).is_ok());
        assert!(matches!(decode_clouds(&b), Err(CloudError::Checksum { .. })));
        let p = t.planes[3];
        let r = p.texture.range();
        assert!(matches!(
            CloudTable::verify_texture(&p, &bytes[r.start as usize..r.end as usize - 1]),
            Err(CloudError::Truncated { .. })
        ));
        // A PNG whose size disagrees with the record (CRC fixed so the size check fires).
        let mut q = p;
        q.width = 3;
        assert!(matches!(
            CloudTable::decode_texture(&q, &bytes[r.start as usize..r.end as usize]),
            Err(CloudError::Image(_))
        ));
        // Converts into the crate-wide error.
        let e: FormatError = CloudError::TrailingBytes(1).into();
        assert!(matches!(e, FormatError::Cloud(_)));
    }

    #[test]
    fn every_prefix_and_bit_flip_is_rejected_without_panic() {
        let (header, levels) = sample();
        let bytes = encode_clouds(&header, &levels).unwrap();
        for n in 1..bytes.len() {
            assert!(decode_clouds(&bytes[..n]).is_err(), "prefix {n}");
        }
        for i in 0..bytes.len() {
            for bit in [0u8, 5, 7] {
                let mut b = bytes.clone();
                b[i] ^= 1 << bit;
                assert!(decode_clouds(&b).is_err(), "flip at {i}");
            }
        }
    }

    #[test]
    fn encoder_rejects_what_the_decoder_would() {
        let (header, levels) = sample();
        let mut l = levels.clone();
        l[1].epsilon = 0.2;
        assert!(encode_clouds(&header, &l).is_err());
        let mut l = levels.clone();
        l[0].planes[0].quad.normal = Vec3::X;
        assert!(encode_clouds(&header, &l).is_err());
        let mut l = levels.clone();
        l[1].planes.clear();
        assert!(encode_clouds(&header, &l).is_err());
        let mut l = levels.clone();
        l[0].planes[1].width = 0;
        assert!(encode_clouds(&header, &l).is_err());
        let h = CloudHeader { radius: 0.0, ..header };
        assert!(encode_clouds(&h, &levels).is_err());
        let h = CloudHeader {
            view_line_height: Some(0.0),
            ..header
        };
        assert!(encode_clouds(&h, &levels).is_err());
    }
}
