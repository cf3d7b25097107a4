//! Reading the table: [`CloudTable::peek_table_len`] (the first 4 bytes, so that a client knows
//! how much to fetch) and [`CloudTable::decode`], which checks everything the spec requires
//! before any texture is fetched: the table CRC, counts, level order, plane geometry, and that
//! the textures tile the rest of the section in plane order.

use glam::Vec3;

use super::table::{CloudCodec, CloudLevel, CloudPlane, CloudQuad, CloudTable, TextureRange};
use super::{CLOUD_FLAG_TEXTURE_DENSITY, CLOUD_FLAG_VIEW_LINE, MAX_CLOUD_LEVELS, MAX_CLOUD_PLANES, MAX_CLOUD_TEXTURE};
use crate::format::bytes::Cursor;
use crate::format::{FormatError, check_crc};

impl CloudTable {
    /// Reads the table length from the first 4 bytes of a non-empty section.
    pub fn peek_table_len(prefix: &[u8]) -> Result<u32, FormatError> {
        Cursor::new(prefix, "cloud header").u32()
    }

    /// Decodes and validates the table from the section's first bytes (`prefix` holds at least
    /// the table; more is ignored). `section_len` is the section's length from the directory;
    /// 0 gives [`CloudTable::empty`]. Textures must tile `[T, section_len)` in plane order: a
    /// range that starts early is a [`FormatError::TextureOverlap`], late a
    /// [`FormatError::TextureGap`], past the end [`FormatError::TextureOutOfRange`]; unused bytes
    /// at the end are [`FormatError::TrailingBytes`] of the "billboard-cloud section".
    pub fn decode(prefix: &[u8], section_len: u64) -> Result<Self, FormatError> {
        if section_len == 0 {
            return Ok(Self::empty());
        }
        let table_len = u64::from(Self::peek_table_len(prefix)?);
        let bad_len = |detail: String| FormatError::CloudTableLength { table_len, detail };
        if table_len < Self::table_len(0, 0) as u64 || table_len > section_len {
            return Err(bad_len(format!("section is {section_len} bytes")));
        }
        if table_len > prefix.len() as u64 {
            return Err(FormatError::Truncated {
                what: "cloud table",
                need: table_len,
                have: prefix.len() as u64,
            });
        }
        let t = table_len as usize;
        let stored = Cursor::new(&prefix[t - 4..t], "cloud table").u32()?;
        check_crc("cloud table", &prefix[..t - 4], stored)?;
        let mut c = Cursor::new(&prefix[..t - 4], "cloud table");
        c.u32()?;
        let codec = match c.u8()? {
            0 => CloudCodec::Png,
            k => return Err(FormatError::invalid("cloud codec", format!("unknown code {k}"))),
        };
        let nlevels = c.u8()? as usize;
        let flags = c.u16()?;
        if flags & !(CLOUD_FLAG_TEXTURE_DENSITY | CLOUD_FLAG_VIEW_LINE) != 0 {
            return Err(FormatError::invalid(
                "cloud flags",
                format!("{flags:#06x} has unknown bits"),
            ));
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
            return Err(FormatError::invalid(
                "cloud header",
                "radius, centre or view-line height out of range",
            ));
        }
        if nlevels > MAX_CLOUD_LEVELS || nplanes > MAX_CLOUD_PLANES {
            return Err(FormatError::CloudCounts(format!("{nlevels} levels, {nplanes} planes")));
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
                return Err(FormatError::CloudCounts(format!(
                    "level planes {first_plane}+{plane_count} where {next_plane}.. of {nplanes} remain"
                )));
            }
            let finer = levels.last().map_or(0.0, |l: &CloudLevel| l.epsilon);
            if !(epsilon.is_finite() && epsilon > finer && texel.is_finite() && texel > 0.0) {
                return Err(FormatError::invalid(
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
            return Err(FormatError::CloudCounts(format!(
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
                return Err(FormatError::invalid("cloud texture size", format!("{width}x{height}")));
            }
            let texture = TextureRange {
                offset: c.u32()?,
                length: c.u32()?,
                crc: c.u32()?,
            };
            let (offset, length) = (u64::from(texture.offset), u64::from(texture.length));
            if length == 0 {
                return Err(FormatError::invalid(
                    "cloud texture",
                    format!("plane {i} has no texture bytes"),
                ));
            }
            if offset + length > section_len {
                return Err(FormatError::TextureOutOfRange {
                    plane: i,
                    offset,
                    length,
                    section_len,
                });
            }
            if offset < cursor {
                return Err(FormatError::TextureOverlap {
                    plane: i,
                    offset,
                    expected: cursor,
                });
            }
            if offset > cursor {
                return Err(FormatError::TextureGap {
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
            return Err(FormatError::TrailingBytes {
                what: "billboard-cloud section",
                extra: section_len - cursor,
            });
        }
        for l in &levels {
            let ps = &planes[l.first_plane as usize..(l.first_plane + l.plane_count) as usize];
            let start = ps.first().map_or(0, |p| u64::from(p.texture.offset));
            let end = ps.last().map_or(0, |p| p.texture.range().end);
            if u64::from(l.textures.offset) != start || u64::from(l.textures.length) != end - start {
                return Err(FormatError::CloudCounts(format!(
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
}
