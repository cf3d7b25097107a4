//! Accessor reads: an accessor's elements copied out of its buffer view (stride removed), with
//! every offset, length and stride checked against the buffer, sparse substitutions applied,
//! and normalised integer components mapped to `[0, 1]` or `[-1, 1]` as glTF specifies.

use glam::{Vec2, Vec3};
use gltf::json;
use gltf::json::accessor::{ComponentType, Type};
use gltf::json::validation::Checked;

use super::{ImportError, Importer};

/// Largest element count accepted for an accessor that has no buffer view (all zeros plus sparse
/// values), so that a forged count cannot allocate unbounded memory.
pub const MAX_UNBACKED_ELEMENTS: u64 = 1 << 24;

/// An accessor's elements, tightly packed, in the file's component format.
pub(super) struct RawAccessor {
    pub(super) count: usize,
    comps: usize,
    ctype: ComponentType,
    normalized: bool,
    bytes: Vec<u8>,
}

impl RawAccessor {
    fn component(&self, i: usize) -> f32 {
        let size = self.ctype.size();
        let at = i * size;
        let Some(b) = self.bytes.get(at..at + size) else {
            return 0.0;
        };
        let n = self.normalized;
        match self.ctype {
            ComponentType::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
            ComponentType::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
            ComponentType::I8 => {
                let v = b[0] as i8 as f32;
                if n { (v / 127.0).max(-1.0) } else { v }
            }
            ComponentType::U8 => {
                let v = f32::from(b[0]);
                if n { v / 255.0 } else { v }
            }
            ComponentType::I16 => {
                let v = f32::from(i16::from_le_bytes([b[0], b[1]]));
                if n { (v / 32767.0).max(-1.0) } else { v }
            }
            ComponentType::U16 => {
                let v = f32::from(u16::from_le_bytes([b[0], b[1]]));
                if n { v / 65535.0 } else { v }
            }
        }
    }

    pub(super) fn uint(&self, i: usize) -> u32 {
        let size = self.ctype.size();
        let at = i * size;
        match self.bytes.get(at..at + size) {
            Some(&[a]) => u32::from(a),
            Some(&[a, b]) => u32::from(u16::from_le_bytes([a, b])),
            Some(&[a, b, c, d]) => u32::from_le_bytes([a, b, c, d]),
            _ => 0,
        }
    }

    pub(super) fn vec3s(&self) -> Vec<Vec3> {
        (0..self.count)
            .map(|k| {
                let b = k * self.comps;
                Vec3::new(self.component(b), self.component(b + 1), self.component(b + 2))
            })
            .collect()
    }

    pub(super) fn vec2s(&self) -> Vec<Vec2> {
        (0..self.count)
            .map(|k| {
                let b = k * self.comps;
                Vec2::new(self.component(b), self.component(b + 1))
            })
            .collect()
    }
}

pub(super) fn oob(accessor: usize, reason: impl Into<String>) -> ImportError {
    ImportError::AccessorOutOfBounds {
        accessor,
        reason: reason.into(),
    }
}

fn bad(accessor: usize, reason: impl Into<String>) -> ImportError {
    ImportError::BadAccessor {
        accessor,
        reason: reason.into(),
    }
}

impl Importer<'_, '_> {
    /// Bytes of buffer view `view` (bounds-checked), plus its stride.
    fn view_bytes(
        &self,
        view: json::Index<json::buffer::View>,
        accessor: usize,
    ) -> Result<(&[u8], Option<usize>), ImportError> {
        let v = self.root.get(view).ok_or(ImportError::InvalidReference {
            kind: "bufferView",
            index: view.value(),
            from: format!("accessor {accessor}"),
        })?;
        let buffer_index = v.buffer.value();
        let data = match self.buffers.get(buffer_index) {
            None => {
                return Err(ImportError::InvalidReference {
                    kind: "buffer",
                    index: buffer_index,
                    from: format!("bufferView {}", view.value()),
                });
            }
            Some(Err(reason)) => {
                return Err(ImportError::Buffer {
                    index: buffer_index,
                    reason: reason.clone(),
                });
            }
            Some(Ok(d)) => d,
        };
        let off = v.byte_offset.map_or(0, |o| o.0);
        let len = v.byte_length.0;
        let end = off
            .checked_add(len)
            .filter(|&e| e <= data.len() as u64)
            .ok_or_else(|| {
                oob(
                    accessor,
                    format!(
                        "bufferView {} spans {off}+{len} bytes of a {}-byte buffer",
                        view.value(),
                        data.len()
                    ),
                )
            })?;
        Ok((&data[off as usize..end as usize], v.byte_stride.map(|s| s.0)))
    }

    /// Reads accessor `index`, requiring one of `types` and one of `ctypes`.
    pub(super) fn read_accessor(
        &self,
        index: usize,
        types: &[Type],
        ctypes: &[ComponentType],
    ) -> Result<RawAccessor, ImportError> {
        let acc = self
            .root
            .accessors
            .get(index)
            .ok_or_else(|| ImportError::InvalidReference {
                kind: "accessor",
                index,
                from: "a mesh primitive".into(),
            })?;
        let Checked::Valid(ty) = acc.type_ else {
            return Err(bad(index, "invalid type"));
        };
        let Checked::Valid(json::accessor::GenericComponentType(ctype)) = acc.component_type else {
            return Err(bad(index, "invalid componentType"));
        };
        if !types.contains(&ty) {
            return Err(bad(index, format!("type {ty:?}, expected one of {types:?}")));
        }
        if !ctypes.contains(&ctype) {
            return Err(bad(
                index,
                format!("componentType {ctype:?}, expected one of {ctypes:?}"),
            ));
        }
        let comps = ty.multiplicity();
        let csize = ctype.size();
        let elem = comps * csize;
        let count64 = acc.count.0;
        let mut bytes = if let Some(view) = acc.buffer_view {
            let (data, stride) = self.view_bytes(view, index)?;
            let stride = match stride {
                None => elem,
                Some(s) if s >= elem && s % csize == 0 => s,
                Some(s) => {
                    return Err(bad(
                        index,
                        format!("byteStride {s} too small or misaligned for {elem}-byte elements"),
                    ));
                }
            };
            let off = acc.byte_offset.map_or(0, |o| o.0);
            if count64 > 0 {
                let need = (count64 - 1)
                    .checked_mul(stride as u64)
                    .and_then(|x| x.checked_add(elem as u64))
                    .and_then(|x| x.checked_add(off));
                match need {
                    Some(n) if n <= data.len() as u64 => {}
                    _ => {
                        return Err(oob(
                            index,
                            format!(
                                "{count64} elements of {elem} bytes (stride {stride}) at offset {off} exceed the {}-byte view",
                                data.len()
                            ),
                        ));
                    }
                }
            }
            let count = count64 as usize;
            let off = off as usize;
            let mut out = Vec::with_capacity(count * elem);
            for k in 0..count {
                let at = off + k * stride;
                out.extend_from_slice(&data[at..at + elem]);
            }
            out
        } else {
            if count64 > MAX_UNBACKED_ELEMENTS {
                return Err(oob(
                    index,
                    format!("{count64} elements without a bufferView is too many"),
                ));
            }
            vec![0u8; count64 as usize * elem]
        };
        let count = count64 as usize;
        if let Some(sparse) = &acc.sparse {
            self.apply_sparse(index, sparse, count, elem, &mut bytes)?;
        }
        Ok(RawAccessor {
            count,
            comps,
            ctype,
            normalized: acc.normalized,
            bytes,
        })
    }

    fn apply_sparse(
        &self,
        index: usize,
        sparse: &json::accessor::sparse::Sparse,
        count: usize,
        elem: usize,
        bytes: &mut [u8],
    ) -> Result<(), ImportError> {
        let n = sparse.count.0;
        if n > count as u64 {
            return Err(oob(index, format!("sparse count {n} exceeds count {count}")));
        }
        let n = n as usize;
        let Checked::Valid(json::accessor::IndexComponentType(ictype)) = sparse.indices.component_type else {
            return Err(bad(index, "invalid sparse index componentType"));
        };
        if !matches!(ictype, ComponentType::U8 | ComponentType::U16 | ComponentType::U32) {
            return Err(bad(index, "sparse indices must be unsigned"));
        }
        let isize = ictype.size();
        let (idata, _) = self.view_bytes(sparse.indices.buffer_view, index)?;
        let (vdata, _) = self.view_bytes(sparse.values.buffer_view, index)?;
        let ioff = usize::try_from(sparse.indices.byte_offset.0).unwrap_or(usize::MAX);
        let voff = usize::try_from(sparse.values.byte_offset.0).unwrap_or(usize::MAX);
        let ispan = ioff.checked_add(n * isize).filter(|&e| e <= idata.len());
        let vspan = voff.checked_add(n * elem).filter(|&e| e <= vdata.len());
        if ispan.is_none() || vspan.is_none() {
            return Err(oob(index, "sparse indices or values exceed their views"));
        }
        for k in 0..n {
            let at = ioff + k * isize;
            let target = match idata[at..at + isize] {
                [a] => u32::from(a),
                [a, b] => u32::from(u16::from_le_bytes([a, b])),
                [a, b, c, d] => u32::from_le_bytes([a, b, c, d]),
                _ => 0,
            } as usize;
            if target >= count {
                return Err(oob(index, format!("sparse index {target} not below count {count}")));
            }
            let src = voff + k * elem;
            bytes[target * elem..(target + 1) * elem].copy_from_slice(&vdata[src..src + elem]);
        }
        Ok(())
    }
}
