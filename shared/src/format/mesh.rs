//! The bark mesh section (spec: `docs/format.md#bark-mesh-kind-5`).

use glam::Vec3;

use super::FormatError;
use super::bytes::{Cursor, Writer};
use super::quant::{dequantize_point, pack_octahedral, quantize_point, unpack_octahedral};
use crate::model::TriangleMesh;

/// Encodes a mesh quantized over `[lo, hi]`. Missing normals encode as +Y.
pub fn encode_mesh(m: &TriangleMesh, lo: Vec3, hi: Vec3) -> Vec<u8> {
    let mut w = Writer::default();
    w.u32(m.positions.len() as u32);
    w.u32(m.indices.len() as u32);
    for (i, &p) in m.positions.iter().enumerate() {
        for q in quantize_point(p, lo, hi) {
            w.u16(q);
        }
        let n = m.normals.get(i).copied().unwrap_or(Vec3::Y);
        w.buf.extend_from_slice(&pack_octahedral(n));
    }
    for &i in &m.indices {
        w.u32(i);
    }
    w.buf
}

/// Decodes a mesh; checks counts, the index range and that the section is consumed exactly.
pub fn decode_mesh(bytes: &[u8], lo: Vec3, hi: Vec3) -> Result<TriangleMesh, FormatError> {
    let mut c = Cursor::new(bytes, "bark mesh");
    let nv = c.u32()? as usize;
    let ni = c.u32()? as usize;
    if !ni.is_multiple_of(3) {
        return Err(FormatError::invalid(
            "bark mesh",
            format!("{ni} indices is not a multiple of 3"),
        ));
    }
    let need = 8u64 + nv as u64 * 8 + ni as u64 * 4;
    if need != bytes.len() as u64 {
        return Err(FormatError::Truncated {
            what: "bark mesh",
            need,
            have: bytes.len() as u64,
        });
    }
    let mut m = TriangleMesh {
        positions: Vec::with_capacity(nv),
        normals: Vec::with_capacity(nv),
        indices: Vec::with_capacity(ni),
    };
    for _ in 0..nv {
        let q = [c.u16()?, c.u16()?, c.u16()?];
        m.positions.push(dequantize_point(q, lo, hi));
        m.normals.push(unpack_octahedral([c.u8()?, c.u8()?]));
    }
    for _ in 0..ni {
        let i = c.u32()?;
        if i as usize >= nv {
            return Err(FormatError::invalid(
                "bark mesh",
                format!("index {i} out of {nv} vertices"),
            ));
        }
        m.indices.push(i);
    }
    c.finish()?;
    Ok(m)
}
