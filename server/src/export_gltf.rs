//! glTF 2.0 binary (`.glb`) export of a [`TreeModel`].
//!
//! The file holds one scene with one node (named after the model) carrying one mesh:
//!
//! - primitive 0, material `bark`: the skeleton tubes ([`tessellate::branch_tubes`] with
//!   [`TUBE_SIDES`] sides) followed by [`TreeModel::bark_mesh`] (omitted when both are empty);
//! - then one primitive per leaf material that has leaves, material `leaf_<i>`: the leaf quads
//!   ([`tessellate::leaf_quads_scaled`] with the requested leaf scale), `alphaMode` `MASK`,
//!   double sided, base colour = the leaf colour. A leaf texture name, if any, is recorded in the
//!   material's `extras.canopy_texture` (the image itself is not embedded).
//!
//! Every primitive has `POSITION` (with `min`/`max`), unit `NORMAL` and `u32` indices; leaf
//! primitives also `TEXCOORD_0`. Buffer views are tightly packed, 4-byte aligned. The output
//! passes `gltf::Gltf::from_slice` validation and re-imports with
//! [`crate::import_gltf::import_gltf_slice`] into the same number of leaves.

use std::path::Path;

use canopy_shared::model::{Materials, TreeModel, TriangleMesh};
use canopy_shared::tessellate;
use glam::Vec3;
use serde_json::{Value, json};

/// Sides of the branch tubes written for skeleton models.
pub const TUBE_SIDES: u32 = 8;

const ARRAY_BUFFER: u32 = 34_962;
const ELEMENT_ARRAY_BUFFER: u32 = 34_963;
const FLOAT: u32 = 5126;
const UNSIGNED_INT: u32 = 5125;

/// Why an export failed.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// A position, normal or leaf parameter is NaN or infinite.
    #[error("non-finite geometry: {0}")]
    NonFinite(String),
    /// The bark mesh is inconsistent (index out of range, normals count mismatch).
    #[error("invalid bark mesh: {0}")]
    InvalidMesh(String),
    /// The binary payload would exceed the 4 GiB GLB limit.
    #[error("model too large for GLB: {0} bytes")]
    TooLarge(u64),
    /// JSON serialisation failed.
    #[error("JSON serialisation failed: {0}")]
    Json(#[from] serde_json::Error),
    /// Writing the file failed.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
}

/// Builds the BIN chunk and the JSON arrays describing it.
#[derive(Default)]
struct Builder {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Builder {
    fn view(&mut self, bytes: &[u8], target: u32) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.views.push(json!({
            "buffer": 0,
            "byteOffset": offset,
            "byteLength": bytes.len(),
            "target": target,
        }));
        self.views.len() - 1
    }

    fn vec3(&mut self, data: &[Vec3], with_bounds: bool) -> usize {
        let bytes: Vec<u8> = data
            .iter()
            .flat_map(Vec3::to_array)
            .flat_map(f32::to_le_bytes)
            .collect();
        let view = self.view(&bytes, ARRAY_BUFFER);
        let mut acc = json!({
            "bufferView": view,
            "componentType": FLOAT,
            "count": data.len(),
            "type": "VEC3",
        });
        if with_bounds {
            let lo = data.iter().fold(Vec3::splat(f32::INFINITY), |a, &p| a.min(p));
            let hi = data.iter().fold(Vec3::splat(f32::NEG_INFINITY), |a, &p| a.max(p));
            acc["min"] = json!(lo.to_array());
            acc["max"] = json!(hi.to_array());
        }
        self.accessors.push(acc);
        self.accessors.len() - 1
    }

    fn vec2(&mut self, data: &[[f32; 2]]) -> usize {
        let bytes: Vec<u8> = data.iter().flatten().flat_map(|c| c.to_le_bytes()).collect();
        let view = self.view(&bytes, ARRAY_BUFFER);
        self.accessors.push(json!({
            "bufferView": view,
            "componentType": FLOAT,
            "count": data.len(),
            "type": "VEC2",
        }));
        self.accessors.len() - 1
    }

    fn indices(&mut self, data: &[u32]) -> usize {
        let bytes: Vec<u8> = data.iter().flat_map(|i| i.to_le_bytes()).collect();
        let view = self.view(&bytes, ELEMENT_ARRAY_BUFFER);
        self.accessors.push(json!({
            "bufferView": view,
            "componentType": UNSIGNED_INT,
            "count": data.len(),
            "type": "SCALAR",
        }));
        self.accessors.len() - 1
    }
}

pub(crate) fn unit_or_y(n: Vec3) -> Vec3 {
    n.try_normalize().unwrap_or(Vec3::Y)
}

pub(crate) fn color(c: [f32; 4]) -> [f32; 4] {
    c.map(|v| if v.is_finite() { v.clamp(0.0, 1.0) } else { 1.0 })
}

/// The `bark` material of `model` (both writers).
pub(crate) fn bark_material_json(model: &TreeModel) -> Value {
    json!({
        "name": "bark",
        "pbrMetallicRoughness": {
            "baseColorFactor": color(model.materials.bark_color),
            "metallicFactor": 0.0,
            "roughnessFactor": 1.0,
        },
        "extras": { "canopy_texture": model.materials.bark_texture },
    })
}

/// The material `leaf_<m>` (both writers).
pub(crate) fn leaf_material_json(m: usize, mat: &canopy_shared::model::LeafMaterial) -> Value {
    json!({
        "name": format!("leaf_{m}"),
        "alphaMode": "MASK",
        "alphaCutoff": 0.5,
        "doubleSided": true,
        "pbrMetallicRoughness": {
            "baseColorFactor": color(mat.color),
            "metallicFactor": 0.0,
            "roughnessFactor": 1.0,
        },
        "extras": { "canopy_texture": mat.texture },
    })
}

/// The leaves of material `m` of `count`; leaves naming a missing material go with the last one.
pub(crate) fn leaves_of_material(model: &TreeModel, m: usize, count: usize) -> Vec<canopy_shared::model::Leaf> {
    let last = m + 1 == count;
    model
        .leaves
        .iter()
        .filter(|l| l.material as usize == m || (last && l.material as usize > m))
        .copied()
        .collect()
}

/// Skeleton tubes plus the bark mesh, with unit normals.
pub(crate) fn bark_geometry(model: &TreeModel) -> Result<TriangleMesh, ExportError> {
    bark_geometry_with(model, TUBE_SIDES, 0.0)
}

/// [`bark_geometry`] with `sides`-sided tubes and without the branches whose radius never
/// reaches `min_radius` metres (a coarser level's bark).
pub(crate) fn bark_geometry_with(model: &TreeModel, sides: u32, min_radius: f32) -> Result<TriangleMesh, ExportError> {
    let options = tessellate::TubeOptions { sides, caps: false };
    let mut mesh = tessellate::branch_tubes_thicker_than(model, options, min_radius);
    let bark = &model.bark_mesh;
    let n = bark.positions.len();
    if let Some(&i) = bark.indices.iter().find(|&&i| i as usize >= n) {
        return Err(ExportError::InvalidMesh(format!(
            "index {i} out of range for {n} positions"
        )));
    }
    if !bark.normals.is_empty() && bark.normals.len() != n {
        return Err(ExportError::InvalidMesh(format!(
            "{} normals for {n} positions",
            bark.normals.len()
        )));
    }
    if !bark.indices.len().is_multiple_of(3) {
        return Err(ExportError::InvalidMesh(format!(
            "{} indices is not a multiple of 3",
            bark.indices.len()
        )));
    }
    let base = u32::try_from(mesh.positions.len()).map_err(|_| ExportError::TooLarge(mesh.positions.len() as u64))?;
    let normals = if bark.normals.is_empty() {
        let mut acc = vec![Vec3::ZERO; n];
        for t in bark.indices.chunks_exact(3) {
            let [a, b, c] = [0, 1, 2].map(|k| bark.positions[t[k] as usize]);
            let fn_ = (b - a).cross(c - a);
            for &k in t {
                acc[k as usize] += fn_;
            }
        }
        acc
    } else {
        bark.normals.clone()
    };
    mesh.positions.extend_from_slice(&bark.positions);
    mesh.normals.extend(normals);
    for n in &mut mesh.normals {
        *n = unit_or_y(*n);
    }
    for &i in &bark.indices {
        mesh.indices
            .push(base.checked_add(i).ok_or(ExportError::TooLarge(u64::from(u32::MAX)))?);
    }
    if let Some(p) = mesh.positions.iter().find(|p| !p.is_finite()) {
        return Err(ExportError::NonFinite(format!("bark position {p}")));
    }
    Ok(mesh)
}

/// Writes `model` as a `.glb` (see the module docs), leaves enlarged by `leaf_scale` about their
/// centres (pass 1.0 for their true size).
///
/// Contract: the result starts with the 12-byte GLB header (`glTF`, version 2, total length),
/// then the JSON chunk (padded with spaces to 4 bytes) and, when there is geometry, the BIN
/// chunk (padded with zeros). A model with no geometry gives a valid file whose node has no
/// mesh. Errors: non-finite geometry or `leaf_scale`, an inconsistent bark mesh, more than
/// 4 GiB of data.
pub fn export_glb(model: &TreeModel, leaf_scale: f32) -> Result<Vec<u8>, ExportError> {
    if !leaf_scale.is_finite() {
        return Err(ExportError::NonFinite(format!("leaf scale {leaf_scale}")));
    }
    let defaults = Materials::default();
    let leaf_materials = if model.materials.leaf.is_empty() {
        &defaults.leaf
    } else {
        &model.materials.leaf
    };
    let mut builder = Builder::default();
    let mut primitives: Vec<Value> = Vec::new();
    let mut materials: Vec<Value> = Vec::new();

    let bark = bark_geometry(model)?;
    materials.push(bark_material_json(model));
    if !bark.indices.is_empty() {
        let pos = builder.vec3(&bark.positions, true);
        let nrm = builder.vec3(&bark.normals, false);
        let idx = builder.indices(&bark.indices);
        primitives.push(json!({
            "attributes": { "POSITION": pos, "NORMAL": nrm },
            "indices": idx,
            "material": 0,
            "mode": 4,
        }));
    }

    for (m, mat) in leaf_materials.iter().enumerate() {
        let leaves = leaves_of_material(model, m, leaf_materials.len());
        let material_index = materials.len();
        materials.push(leaf_material_json(m, mat));
        if leaves.is_empty() {
            continue;
        }
        let (positions, normals, uvs, indices) = tessellate::leaf_quads_scaled(&leaves, leaf_scale);
        if let Some(p) = positions.iter().find(|p| !p.is_finite()) {
            return Err(ExportError::NonFinite(format!("leaf corner {p}")));
        }
        let normals: Vec<Vec3> = normals.into_iter().map(unit_or_y).collect();
        let pos = builder.vec3(&positions, true);
        let nrm = builder.vec3(&normals, false);
        let uv = builder.vec2(&uvs);
        let idx = builder.indices(&indices);
        primitives.push(json!({
            "attributes": { "POSITION": pos, "NORMAL": nrm, "TEXCOORD_0": uv },
            "indices": idx,
            "material": material_index,
            "mode": 4,
        }));
    }

    let mut node = json!({ "name": model.name });
    let mut doc = json!({
        "asset": { "version": "2.0", "generator": "canopy-server export_gltf" },
        "scene": 0,
        "scenes": [{ "nodes": [0] }],
        "materials": materials,
    });
    if !primitives.is_empty() {
        node["mesh"] = json!(0);
        doc["meshes"] = json!([{ "name": model.name, "primitives": primitives }]);
        doc["accessors"] = Value::Array(builder.accessors);
        doc["bufferViews"] = Value::Array(builder.views);
        doc["buffers"] = json!([{ "byteLength": builder.bin.len() }]);
    }
    doc["nodes"] = json!([node]);
    let bin = if primitives.is_empty() { Vec::new() } else { builder.bin };
    write_glb(&serde_json::to_vec(&doc)?, &bin)
}

/// Assembles the GLB container.
pub(crate) fn write_glb(json_bytes: &[u8], bin: &[u8]) -> Result<Vec<u8>, ExportError> {
    let pad4 = |n: usize| (n + 3) & !3;
    let json_len = pad4(json_bytes.len());
    let bin_len = pad4(bin.len());
    let total = 12 + 8 + json_len + if bin.is_empty() { 0 } else { 8 + bin_len };
    let total32 = u32::try_from(total).map_err(|_| ExportError::TooLarge(total as u64))?;
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&total32.to_le_bytes());
    out.extend_from_slice(&(json_len as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(json_bytes);
    out.resize(20 + json_len, b' ');
    if !bin.is_empty() {
        out.extend_from_slice(&(bin_len as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(bin);
        out.resize(total, 0);
    }
    Ok(out)
}

/// [`export_glb`] written to `path` (created or truncated).
pub fn export_glb_to(path: &Path, model: &TreeModel, leaf_scale: f32) -> Result<(), ExportError> {
    let bytes = export_glb(model, leaf_scale)?;
    std::fs::write(path, bytes).map_err(|source| ExportError::Io {
        path: path.to_path_buf(),
        source,
    })
}
