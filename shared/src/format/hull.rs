//! Crown hulls (section kind 6): closed triangle meshes around the crown (seed 004's crown
//! contour hull) at several triangle budgets, each level a quantized mesh with its own CRC-32,
//! located by a small table at the start of the section. The byte layout is in
//! `docs/format.md`, "Crown hulls (kind 6)".

use glam::Vec3;

use super::bytes::{Cursor, Writer};
use super::quant::{dequantize_point, quantize_point};
use super::{FormatError, check_crc, crc32};

/// Bytes of the fixed section header.
pub const HULL_HEADER_LEN: usize = 32;
/// Bytes of one level entry of the table.
pub const HULL_LEVEL_ENTRY_LEN: usize = 28;
/// Largest number of levels.
pub const MAX_HULL_LEVELS: usize = 16;
/// Largest vertex count of one level.
pub const MAX_HULL_VERTICES: u32 = 1 << 20;
/// Largest triangle count of one level.
pub const MAX_HULL_TRIANGLES: u32 = 1 << 21;

/// How a hull level was made.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum HullMethod {
    /// Seed 004's method: feature points, implicit-surface reconstruction, simplification.
    Reconstruction,
    /// Convex hull of the feature points (fallback).
    ConvexHull,
    /// Axis-aligned box of the points (last-resort fallback for degenerate input).
    BoundingBox,
}

impl HullMethod {
    /// Byte code in the level table.
    pub fn code(self) -> u8 {
        match self {
            Self::Reconstruction => 0,
            Self::ConvexHull => 1,
            Self::BoundingBox => 2,
        }
    }

    /// Inverse of [`HullMethod::code`].
    pub fn from_code(c: u8) -> Option<Self> {
        Some(match c {
            0 => Self::Reconstruction,
            1 => Self::ConvexHull,
            2 => Self::BoundingBox,
            _ => return None,
        })
    }

    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Reconstruction => "reconstruction",
            Self::ConvexHull => "convex_hull",
            Self::BoundingBox => "bounding_box",
        }
    }
}

/// One hull level in memory: a triangle mesh, counter-clockwise seen from outside.
#[derive(Debug, Clone, PartialEq)]
pub struct HullMesh {
    /// How it was made.
    pub method: HullMethod,
    /// Silhouette IoU against the full tree measured at bake time (informative; NaN unknown).
    pub iou: f32,
    /// Vertex positions, tree space (metres).
    pub positions: Vec<Vec3>,
    /// Three indices per triangle.
    pub indices: Vec<u32>,
}

impl HullMesh {
    /// Triangles.
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }
}

/// Table entry of one level.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HullLevelEntry {
    /// Offset of the level's bytes from the section start.
    pub offset: u32,
    /// Length in bytes.
    pub length: u32,
    /// CRC-32 of the level's bytes.
    pub crc: u32,
    /// Triangles.
    pub triangles: u32,
    /// Vertices.
    pub vertices: u32,
    /// Method.
    pub method: HullMethod,
    /// Bytes per index: 2 (vertices ≤ 65,536) or 4.
    pub index_size: u8,
    /// Bake-time silhouette IoU (informative).
    pub iou: f32,
}

impl HullLevelEntry {
    fn body_len(vertices: u32, triangles: u32, index_size: u8) -> u64 {
        8 + 6 * u64::from(vertices) + 3 * u64::from(triangles) * u64::from(index_size)
    }
}

/// The hull table: quantization box and level entries, finest level first.
#[derive(Debug, Clone, PartialEq)]
pub struct HullTable {
    /// Quantization box min (every level's vertices lie inside).
    pub lo: Vec3,
    /// Quantization box max.
    pub hi: Vec3,
    /// Levels, by decreasing triangle count.
    pub levels: Vec<HullLevelEntry>,
}

impl HullTable {
    /// Bytes of the table for `levels` levels (header, entries, table CRC).
    pub fn table_len(levels: usize) -> usize {
        HULL_HEADER_LEN + HULL_LEVEL_ENTRY_LEN * levels + 4
    }

    /// Reads the table length from the first 4 bytes of the section.
    pub fn peek_table_len(prefix: &[u8]) -> Result<u32, FormatError> {
        Cursor::new(prefix, "hull header").u32()
    }

    /// Decodes and validates the table from the section's first bytes (at least the table).
    /// `section_len` is the section's length from the directory: levels must tile
    /// `[table_len, section_len)` in order, and each level's length must match its counts.
    pub fn decode(prefix: &[u8], section_len: u64) -> Result<Self, FormatError> {
        let table_len = Self::peek_table_len(prefix)? as usize;
        if table_len > prefix.len() {
            return Err(FormatError::Truncated {
                what: "hull table",
                need: table_len as u64,
                have: prefix.len() as u64,
            });
        }
        if table_len < Self::table_len(0) || table_len as u64 > section_len {
            return Err(FormatError::invalid(
                "hull table length",
                format!("{table_len} for a {section_len}-byte section"),
            ));
        }
        let stored = Cursor::new(&prefix[table_len - 4..table_len], "hull table").u32()?;
        check_crc("hull table", &prefix[..table_len - 4], stored)?;
        let mut c = Cursor::new(&prefix[..table_len - 4], "hull table");
        c.u32()?;
        let n = c.u16()? as usize;
        c.u16()?;
        let mut b = [0f32; 6];
        for v in &mut b {
            *v = c.finite_f32("hull bounds")?;
        }
        let (lo, hi) = (Vec3::new(b[0], b[1], b[2]), Vec3::new(b[3], b[4], b[5]));
        if n > MAX_HULL_LEVELS || Self::table_len(n) != table_len || lo.cmpgt(hi).any() {
            return Err(FormatError::invalid("hull table", "level count, length or bounds"));
        }
        let mut levels = Vec::with_capacity(n);
        let mut cursor = table_len as u64;
        for _ in 0..n {
            let offset = c.u32()?;
            let length = c.u32()?;
            let crc = c.u32()?;
            let triangles = c.u32()?;
            let vertices = c.u32()?;
            let method =
                HullMethod::from_code(c.u8()?).ok_or_else(|| FormatError::invalid("hull method", "unknown code"))?;
            let index_size = c.u8()?;
            c.u16()?;
            let iou = c.f32()?;
            let size_ok = match index_size {
                2 => vertices <= 1 << 16,
                4 => true,
                _ => false,
            };
            if !size_ok
                || vertices > MAX_HULL_VERTICES
                || triangles > MAX_HULL_TRIANGLES
                || u64::from(offset) != cursor
                || u64::from(length) != HullLevelEntry::body_len(vertices, triangles, index_size)
            {
                return Err(FormatError::invalid("hull level entry", "counts, index size or range"));
            }
            cursor += u64::from(length);
            levels.push(HullLevelEntry {
                offset,
                length,
                crc,
                triangles,
                vertices,
                method,
                index_size,
                iou,
            });
        }
        c.finish()?;
        if cursor != section_len {
            return Err(FormatError::invalid(
                "hull levels",
                format!("end at {cursor}, section is {section_len} bytes"),
            ));
        }
        Ok(Self { lo, hi, levels })
    }

    /// Decodes level `k` from its own bytes (as fetched by range): checks length, CRC, counts
    /// and indices.
    pub fn decode_level(&self, k: usize, bytes: &[u8]) -> Result<HullMesh, FormatError> {
        let e = self
            .levels
            .get(k)
            .ok_or_else(|| FormatError::invalid("hull level", format!("{k} out of range")))?;
        if bytes.len() != e.length as usize {
            return Err(FormatError::Truncated {
                what: "hull level",
                need: u64::from(e.length),
                have: bytes.len() as u64,
            });
        }
        check_crc("hull level", bytes, e.crc)?;
        let mut c = Cursor::new(bytes, "hull level");
        if c.u32()? != e.vertices || c.u32()? != e.triangles {
            return Err(FormatError::invalid("hull level", "counts disagree with the table"));
        }
        let mut positions = Vec::with_capacity(e.vertices as usize);
        for _ in 0..e.vertices {
            let q = [c.u16()?, c.u16()?, c.u16()?];
            positions.push(dequantize_point(q, self.lo, self.hi));
        }
        let mut indices = Vec::with_capacity(3 * e.triangles as usize);
        for _ in 0..3 * e.triangles {
            let i = if e.index_size == 2 {
                u32::from(c.u16()?)
            } else {
                c.u32()?
            };
            if i >= e.vertices {
                return Err(FormatError::invalid(
                    "hull index",
                    format!("{i} ≥ {} vertices", e.vertices),
                ));
            }
            indices.push(i);
        }
        c.finish()?;
        Ok(HullMesh {
            method: e.method,
            iou: e.iou,
            positions,
            indices,
        })
    }

    /// Decodes level `k` out of the whole section.
    pub fn level_from_section(&self, section: &[u8], k: usize) -> Result<HullMesh, FormatError> {
        let e = self
            .levels
            .get(k)
            .ok_or_else(|| FormatError::invalid("hull level", format!("{k} out of range")))?;
        let start = e.offset as usize;
        let end = start.saturating_add(e.length as usize);
        let bytes = section.get(start..end).ok_or(FormatError::Truncated {
            what: "hull level",
            need: end as u64,
            have: section.len() as u64,
        })?;
        self.decode_level(k, bytes)
    }
}

/// Decodes every level of a whole hull section.
pub fn decode_hulls(section: &[u8]) -> Result<(HullTable, Vec<HullMesh>), FormatError> {
    let t = HullTable::decode(section, section.len() as u64)?;
    let meshes = (0..t.levels.len())
        .map(|k| t.level_from_section(section, k))
        .collect::<Result<Vec<_>, _>>()?;
    Ok((t, meshes))
}

/// Encodes a hull section. Levels should be finest first; the quantization box is the bounds of
/// all their vertices. Errors on out-of-range indices, non-finite positions or too many levels.
pub fn encode_hulls(levels: &[HullMesh]) -> Result<Vec<u8>, FormatError> {
    if levels.len() > MAX_HULL_LEVELS {
        return Err(FormatError::invalid("hull", "too many levels"));
    }
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for m in levels {
        if m.positions.len() > MAX_HULL_VERTICES as usize
            || m.triangle_count() > MAX_HULL_TRIANGLES as usize
            || !m.indices.len().is_multiple_of(3)
            || m.indices.iter().any(|&i| i as usize >= m.positions.len())
            || m.positions.iter().any(|p| !p.is_finite())
        {
            return Err(FormatError::invalid("hull level", "bad indices, counts or positions"));
        }
        for &p in &m.positions {
            lo = lo.min(p);
            hi = hi.max(p);
        }
    }
    if lo.cmpgt(hi).any() {
        (lo, hi) = (Vec3::ZERO, Vec3::ZERO);
    }
    let bodies: Vec<Vec<u8>> = levels
        .iter()
        .map(|m| {
            let mut w = Writer::default();
            w.u32(m.positions.len() as u32);
            w.u32(m.triangle_count() as u32);
            for &p in &m.positions {
                for q in quantize_point(p, lo, hi) {
                    w.u16(q);
                }
            }
            let short = m.positions.len() <= 1 << 16;
            for &i in &m.indices {
                if short {
                    w.u16(i as u16);
                } else {
                    w.u32(i);
                }
            }
            w.buf
        })
        .collect();
    let table_len = HullTable::table_len(levels.len());
    let mut w = Writer::default();
    w.u32(table_len as u32);
    w.u16(levels.len() as u16);
    w.u16(0);
    for v in lo.to_array().into_iter().chain(hi.to_array()) {
        w.f32(v);
    }
    let mut offset = table_len as u64;
    for (m, b) in levels.iter().zip(&bodies) {
        let off = u32::try_from(offset).map_err(|_| FormatError::invalid("hull", "over 4 GiB"))?;
        w.u32(off);
        w.u32(b.len() as u32);
        w.u32(crc32(b));
        w.u32(m.triangle_count() as u32);
        w.u32(m.positions.len() as u32);
        w.u8(m.method.code());
        w.u8(if m.positions.len() <= 1 << 16 { 2 } else { 4 });
        w.u16(0);
        w.f32(m.iou);
        offset += b.len() as u64;
    }
    let crc = crc32(&w.buf);
    w.u32(crc);
    for b in bodies {
        w.buf.extend_from_slice(&b);
    }
    Ok(w.buf)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn tetra(scale: f32, method: HullMethod) -> HullMesh {
        HullMesh {
            method,
            iou: 0.75,
            positions: vec![
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(scale, 0.0, 0.0),
                Vec3::new(0.0, scale, 0.0),
                Vec3::new(0.0, 0.0, scale),
            ],
            indices: vec![0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3],
        }
    }

    #[test]
    fn round_trip() {
        let levels = vec![
            tetra(2.0, HullMethod::Reconstruction),
            tetra(1.0, HullMethod::ConvexHull),
        ];
        let bytes = encode_hulls(&levels).unwrap();
        let (t, meshes) = decode_hulls(&bytes).unwrap();
        assert_eq!(t.levels.len(), 2);
        assert_eq!(t.levels[1].method, HullMethod::ConvexHull);
        for (a, b) in levels.iter().zip(&meshes) {
            assert_eq!(a.indices, b.indices);
            assert_eq!(a.method, b.method);
            for (p, q) in a.positions.iter().zip(&b.positions) {
                assert!(p.distance(*q) < 1e-4);
            }
        }
        // A client: table from a prefix, then one level by range.
        let tl = HullTable::peek_table_len(&bytes).unwrap() as usize;
        let t2 = HullTable::decode(&bytes[..tl], bytes.len() as u64).unwrap();
        let e = t2.levels[1];
        let one = &bytes[e.offset as usize..(e.offset + e.length) as usize];
        assert_eq!(t2.decode_level(1, one).unwrap().indices, levels[1].indices);
        let empty = encode_hulls(&[]).unwrap();
        assert!(decode_hulls(&empty).unwrap().1.is_empty());
    }

    #[test]
    fn corrupt_sections_are_rejected() {
        let bytes = encode_hulls(&[tetra(2.0, HullMethod::BoundingBox)]).unwrap();
        for n in 0..bytes.len() {
            assert!(decode_hulls(&bytes[..n]).is_err(), "prefix {n}");
        }
        for i in 0..bytes.len() {
            for bit in [0u8, 4, 7] {
                let mut b = bytes.clone();
                b[i] ^= 1 << bit;
                assert!(decode_hulls(&b).is_err(), "flip at {i}");
            }
        }
        let mut long = bytes.clone();
        long.push(0);
        assert!(decode_hulls(&long).is_err());
        let mut bad = tetra(1.0, HullMethod::ConvexHull);
        bad.indices[0] = 9;
        assert!(encode_hulls(&[bad]).is_err());
    }
}
