//! One mesh primitive read into world space ([`Placed`]): positions transformed by the node's
//! world matrix, normals by its inverse transpose, strips and fans turned into triangle lists,
//! winding flipped under mirroring transforms; and bark primitives appended to the bark mesh
//! with unit normals (missing ones computed, area-weighted).

use std::collections::HashMap;

use canopy_shared::model::TriangleMesh;
use glam::{Mat3, Mat4, Vec2, Vec3};
use gltf::json;
use gltf::json::accessor::{ComponentType, Type};
use gltf::json::mesh::{Mode, Semantic};
use gltf::json::validation::Checked;

use super::accessors::oob;
use super::{ImportError, ImportStats, Importer};

/// One primitive, read and placed in world space.
pub(super) struct Placed {
    pub(super) positions: Vec<Vec3>,
    pub(super) normals: Option<Vec<Vec3>>,
    pub(super) uvs: Option<Vec<Vec2>>,
    pub(super) triangles: Vec<[u32; 3]>,
    pub(super) material: Option<usize>,
}

impl Importer<'_, '_> {
    /// Reads primitive `prim_index` of `mesh` placed by `world`; `None` (with a warning) for
    /// primitives without triangles or positions.
    pub(super) fn read_primitive(
        &mut self,
        mesh: usize,
        prim_index: usize,
        world: Mat4,
    ) -> Result<Option<Placed>, ImportError> {
        let root = self.root;
        let prim = &root.meshes[mesh].primitives[prim_index];
        let mode = match prim.mode {
            Checked::Valid(m) => m,
            Checked::Invalid => {
                self.warnings
                    .push(format!("mesh {mesh} primitive {prim_index}: invalid mode; skipped"));
                self.stats.skipped_primitives += 1;
                return Ok(None);
            }
        };
        if matches!(mode, Mode::Points | Mode::Lines | Mode::LineLoop | Mode::LineStrip) {
            self.warnings.push(format!(
                "mesh {mesh} primitive {prim_index}: mode {mode:?} has no triangles; skipped"
            ));
            self.stats.skipped_primitives += 1;
            return Ok(None);
        }
        let attr = |s: Semantic| prim.attributes.get(&Checked::Valid(s)).map(json::Index::value);
        let Some(pos_index) = attr(Semantic::Positions) else {
            self.warnings
                .push(format!("mesh {mesh} primitive {prim_index}: no POSITION; skipped"));
            self.stats.skipped_primitives += 1;
            return Ok(None);
        };
        let normal_index = attr(Semantic::Normals);
        let uv_index = attr(Semantic::TexCoords(0));
        let indices_index = prim.indices.map(|i| i.value());
        let material = prim.material.map(|m| m.value());

        let all_types = [
            ComponentType::F32,
            ComponentType::I8,
            ComponentType::U8,
            ComponentType::I16,
            ComponentType::U16,
        ];
        let local = self.read_accessor(pos_index, &[Type::Vec3], &all_types)?.vec3s();
        let vertex_count = local.len();
        let normals = match normal_index {
            Some(i) => {
                let n = self
                    .read_accessor(
                        i,
                        &[Type::Vec3],
                        &[ComponentType::F32, ComponentType::I8, ComponentType::I16],
                    )?
                    .vec3s();
                if n.len() == vertex_count {
                    Some(n)
                } else {
                    self.warnings.push(format!(
                        "mesh {mesh} primitive {prim_index}: {} normals for {vertex_count} vertices; recomputed",
                        n.len()
                    ));
                    None
                }
            }
            None => None,
        };
        let uvs = match uv_index {
            Some(i) => {
                let uv = self
                    .read_accessor(
                        i,
                        &[Type::Vec2],
                        &[
                            ComponentType::F32,
                            ComponentType::U8,
                            ComponentType::U16,
                            ComponentType::I8,
                            ComponentType::I16,
                        ],
                    )?
                    .vec2s();
                (uv.len() == vertex_count).then_some(uv)
            }
            None => None,
        };
        let order: Vec<u32> = if let Some(i) = indices_index {
            let raw = self.read_accessor(
                i,
                &[Type::Scalar],
                &[ComponentType::U8, ComponentType::U16, ComponentType::U32],
            )?;
            (0..raw.count).map(|k| raw.uint(k)).collect()
        } else {
            let Ok(n) = u32::try_from(vertex_count) else {
                return Err(oob(pos_index, "too many vertices"));
            };
            (0..n).collect()
        };
        if let Some(&bad_index) = order.iter().find(|&&k| k as usize >= vertex_count) {
            return Err(ImportError::IndexOutOfRange {
                mesh,
                primitive: prim_index,
                index: bad_index,
                vertex_count,
            });
        }
        let mut triangles = to_triangles(mode, &order);
        if mode == Mode::Triangles && !order.len().is_multiple_of(3) {
            self.warnings.push(format!(
                "mesh {mesh} primitive {prim_index}: {} indices is not a multiple of 3; tail ignored",
                order.len()
            ));
        }
        // World space. Mirroring transforms flip the winding.
        if world.determinant() < 0.0 {
            for t in &mut triangles {
                t.swap(1, 2);
            }
        }
        let positions: Vec<Vec3> = local.iter().map(|&p| world.transform_point3(p)).collect();
        let used_nonfinite = triangles.iter().flatten().any(|&k| !positions[k as usize].is_finite());
        if used_nonfinite {
            return Err(ImportError::NonFinitePosition {
                mesh,
                primitive: prim_index,
            });
        }
        let normal_matrix = Mat3::from_mat4(world).inverse().transpose();
        let normals = normals.map(|ns| {
            ns.iter()
                .map(|&n| {
                    let len = n.length();
                    if len.is_finite() && len > 1e-12 && (len - 1.0).abs() > 1e-3 {
                        self.stats.renormalized_normals += 1;
                    }
                    normal_matrix * n
                })
                .collect()
        });
        Ok(Some(Placed {
            positions,
            normals,
            uvs,
            triangles,
            material,
        }))
    }
}

/// Triangle list from an index sequence in `mode` (strips and fans are converted; degenerate
/// strip triangles, used as restarts, are dropped).
fn to_triangles(mode: Mode, order: &[u32]) -> Vec<[u32; 3]> {
    match mode {
        Mode::Triangles => order.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        Mode::TriangleStrip => order
            .windows(3)
            .enumerate()
            .map(|(i, w)| {
                if i % 2 == 0 {
                    [w[0], w[1], w[2]]
                } else {
                    [w[1], w[0], w[2]]
                }
            })
            .filter(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
            .collect(),
        Mode::TriangleFan => match order.split_first() {
            Some((&first, rest)) => rest.windows(2).map(|w| [first, w[0], w[1]]).collect(),
            None => Vec::new(),
        },
        _ => Vec::new(),
    }
}

/// Appends bark triangles (only the vertices they use), computing missing normals.
pub(super) fn append_bark(
    placed: &Placed,
    bark: &mut TriangleMesh,
    stats: &mut ImportStats,
) -> Result<(), ImportError> {
    let smooth = smooth_normals(&placed.positions, &placed.triangles);
    let mut remap: HashMap<u32, u32> = HashMap::new();
    for t in &placed.triangles {
        for &k in t {
            let next = u32::try_from(bark.positions.len()).map_err(|_| ImportError::AccessorOutOfBounds {
                accessor: 0,
                reason: "more than 2^32 bark vertices".into(),
            })?;
            let new = *remap.entry(k).or_insert_with(|| {
                let i = k as usize;
                bark.positions.push(placed.positions[i]);
                let given = placed.normals.as_ref().map(|n| n[i]);
                let n = given.and_then(Vec3::try_normalize).unwrap_or_else(|| {
                    stats.computed_normals += 1;
                    smooth[i]
                });
                bark.normals.push(n);
                next
            });
            bark.indices.push(new);
        }
    }
    Ok(())
}

/// Area-weighted vertex normals; `Vec3::Y` for vertices without a usable face.
fn smooth_normals(positions: &[Vec3], triangles: &[[u32; 3]]) -> Vec<Vec3> {
    let mut acc = vec![Vec3::ZERO; positions.len()];
    for t in triangles {
        let [a, b, c] = t.map(|k| positions[k as usize]);
        let n = (b - a).cross(c - a);
        if n.is_finite() {
            for &k in t {
                acc[k as usize] += n;
            }
        }
    }
    acc.into_iter().map(|n| n.try_normalize().unwrap_or(Vec3::Y)).collect()
}

// ---------------------------------------------------------------------------------------------

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strips_and_fans() {
        assert_eq!(
            to_triangles(Mode::TriangleStrip, &[0, 1, 2, 3]),
            vec![[0, 1, 2], [2, 1, 3]]
        );
        assert_eq!(
            to_triangles(Mode::TriangleFan, &[0, 1, 2, 3]),
            vec![[0, 1, 2], [0, 2, 3]]
        );
        assert!(to_triangles(Mode::TriangleFan, &[]).is_empty());
    }
}
