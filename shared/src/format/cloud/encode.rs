//! Writing a section: [`encode_clouds`] lays out the table and the textures (level-major, no
//! gaps) and refuses anything [`CloudTable::decode`] would reject.

use glam::Vec3;

use super::table::{CloudQuad, CloudTable};
use super::{CLOUD_FLAG_TEXTURE_DENSITY, CLOUD_FLAG_VIEW_LINE, MAX_CLOUD_LEVELS, MAX_CLOUD_PLANES, MAX_CLOUD_TEXTURE};
use crate::format::bytes::Writer;
use crate::format::{FormatError, crc32};

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
pub fn encode_clouds(header: &CloudHeader, levels: &[LevelTextures]) -> Result<Vec<u8>, FormatError> {
    if levels.is_empty() {
        return Ok(Vec::new());
    }
    let nplanes: usize = levels.iter().map(|l| l.planes.len()).sum();
    if levels.len() > MAX_CLOUD_LEVELS || nplanes > MAX_CLOUD_PLANES as usize {
        return Err(FormatError::CloudCounts(format!(
            "{} levels, {nplanes} planes",
            levels.len()
        )));
    }
    let h = header.view_line_height.unwrap_or(0.0);
    if !(header.radius > 0.0 && header.radius.is_finite() && header.center.is_finite() && h >= 0.0 && h.is_finite())
        || header.view_line_height.is_some_and(|h| h <= 0.0)
    {
        return Err(FormatError::invalid(
            "cloud header",
            "radius, centre or height out of range",
        ));
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
            return Err(FormatError::invalid(
                "cloud level",
                "no planes, or ε not increasing, or bad texel",
            ));
        }
        prev_eps = l.epsilon;
        let len: u64 = l.planes.iter().map(|p| p.bytes.len() as u64).sum();
        let (off, len) = (
            u32::try_from(offset).map_err(|_| FormatError::invalid("cloud section", "over 4 GiB"))?,
            u32::try_from(len).map_err(|_| FormatError::invalid("cloud section", "over 4 GiB"))?,
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
            return Err(FormatError::invalid(
                "cloud plane",
                "empty texture or size out of range",
            ));
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
        w.u32(u32::try_from(offset).map_err(|_| FormatError::invalid("cloud section", "over 4 GiB"))?);
        w.u32(p.bytes.len() as u32);
        w.u32(crc32(&p.bytes));
        offset += p.bytes.len() as u64;
    }
    let crc = crc32(&w.buf);
    w.u32(crc);
    if w.buf.len() != table_len {
        return Err(FormatError::invalid("cloud table", "length mismatch (encoder bug)"));
    }
    for p in levels.iter().flat_map(|l| &l.planes) {
        w.buf.extend_from_slice(&p.bytes);
    }
    Ok(w.buf)
}
