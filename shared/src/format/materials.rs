//! The materials section (spec: `docs/format.md#materials-kind-4`).

use super::FormatError;
use super::bytes::{Cursor, Writer};
use crate::model::{LeafMaterial, Materials};

fn color(c: &mut Cursor) -> Result<[f32; 4], FormatError> {
    let mut out = [0.0; 4];
    for v in &mut out {
        *v = c.finite_f32("colour")?;
    }
    Ok(out)
}

fn texture(c: &mut Cursor) -> Result<Option<String>, FormatError> {
    let s = c.string("texture name")?;
    Ok((!s.is_empty()).then_some(s))
}

/// Encodes materials. At most 255 leaf materials are written.
pub fn encode_materials(m: &Materials) -> Vec<u8> {
    let mut w = Writer::default();
    for v in m.bark_color {
        w.f32(v);
    }
    w.string(m.bark_texture.as_deref().unwrap_or(""));
    let n = m.leaf.len().min(255);
    w.u8(n as u8);
    for l in &m.leaf[..n] {
        for v in l.color {
            w.f32(v);
        }
        w.string(l.texture.as_deref().unwrap_or(""));
    }
    w.buf
}

/// Decodes materials; the section must be consumed exactly and hold at least one leaf material.
pub fn decode_materials(bytes: &[u8]) -> Result<Materials, FormatError> {
    let mut c = Cursor::new(bytes, "materials");
    let bark_color = color(&mut c)?;
    let bark_texture = texture(&mut c)?;
    let n = c.u8()?;
    if n == 0 {
        return Err(FormatError::invalid("materials", "no leaf material"));
    }
    let mut leaf = Vec::with_capacity(n as usize);
    for _ in 0..n {
        leaf.push(LeafMaterial {
            color: color(&mut c)?,
            texture: texture(&mut c)?,
        });
    }
    c.finish()?;
    Ok(Materials {
        bark_color,
        bark_texture,
        leaf,
    })
}
