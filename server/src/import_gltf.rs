//! glTF 2.0 import (`.glb` and `.gltf`) into a [`TreeModel`].
//!
//! Real tree assets carry no branch skeleton, so the importer splits geometry into bark and
//! leaves and turns leaf geometry into [`Leaf`] records (see `docs/import.md`):
//!
//! - **Leaf detection, per primitive**, first rule that applies wins:
//!   1. the material name contains a leaf word (`leaf`, `leaves`, `foliage`, `needle`,
//!      `canopy`, `crown`, `frond`, `blossom`, `petal`) → leaf;
//!   2. the material name contains a bark word (`bark`, `trunk`, `wood`, `stem`, `branch`,
//!      `twig`) → bark;
//!   3. the material's `alphaMode` is `MASK` or `BLEND` → leaf;
//!   4. the mesh or node name contains a leaf word → leaf, a bark word → bark;
//!   5. shape: at least [`SHAPE_MIN_QUADS`] connected components and at least 80 % of the
//!      triangles in small (under 1/8 of the primitive's diagonal) quads → leaf;
//!   6. otherwise bark.
//! - **Leaf records**: a leaf primitive is split into connected components, joining
//!   triangles that share a vertex index or a vertex position (welding bit-equal positions).
//!   A component of two triangles over four distinct positions, folded by at most ~75 degrees
//!   (real leaf cards are folded), is one leaf quad: centre of its bounding rectangle, normal
//!   from the winding, axis along the uv `v` direction when uvs exist (else the longest side),
//!   width and length its extents. Other
//!   components are first split back by shared vertex index only, and a quad in there that
//!   shares at most one edge with the rest stays a leaf (leaves that merely touch); everything
//!   else (low-poly blobs like Kenney's) becomes **one leaf per triangle**:
//!   centre at the centroid, the face normal, axis along the longest edge, length = that edge,
//!   width = the triangle's height over it. That rectangle has twice the triangle's area; it is
//!   an approximation for low-poly leaf blobs, which have no individual leaves.
//! - **Bark**: every other triangle goes to [`TreeModel::bark_mesh`] in world space, with unit
//!   normals (missing normals are computed, non-unit ones renormalised).
//! - **Transforms**: nodes are walked from the chosen scene's nodes (default scene, else the
//!   first scene, else every root node); each node is visited once even if a scene lists a node
//!   that is not a root (Kenney files do), and its world transform is the product along its
//!   parent chain (matrix or TRS).
//! - **Placement**: the model is translated so that the centre of the bark's xz bounds at the
//!   bark's lowest y (or of all geometry, without bark) is the origin. glTF is Y up, metres.
//!
//! Nothing here panics on malformed input: every index, offset and length read from the file is
//! checked, and errors are typed ([`ImportError`]).

use std::borrow::Cow;
use std::collections::HashMap;
use std::path::{Component, Path, PathBuf};

use canopy_shared::model::{Leaf, LeafMaterial, Materials, ModelSource, TreeModel, TriangleMesh};
use glam::{Mat3, Mat4, Quat, Vec2, Vec3};
use gltf::json;
use gltf::json::accessor::{ComponentType, Type};
use gltf::json::material::AlphaMode;
use gltf::json::mesh::{Mode, Semantic};
use gltf::json::validation::Checked;

/// Cosine of the largest fold between the two triangles of a leaf quad (about 75 degrees).
pub const QUAD_MIN_FOLD_COS: f32 = 0.25;

/// Minimum number of leaf-like quads for the shape rule to call a primitive foliage.
pub const SHAPE_MIN_QUADS: usize = 16;

/// Largest element count accepted for an accessor that has no buffer view (all zeros plus sparse
/// values), so that a forged count cannot allocate unbounded memory.
pub const MAX_UNBACKED_ELEMENTS: u64 = 1 << 24;

/// Words that mark leaf geometry in material, mesh or node names (lower case, substring match).
pub const LEAF_WORDS: &[&str] = &[
    "leaf", "leaves", "foliage", "needle", "canopy", "crown", "frond", "blossom", "petal",
];

/// Words that mark bark geometry in material, mesh or node names (lower case, substring match).
pub const BARK_WORDS: &[&str] = &["bark", "trunk", "wood", "stem", "branch", "twig"];

/// Why an import failed.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The bytes are neither a GLB container nor glTF JSON.
    #[error("not glTF: {0}")]
    NotGltf(String),
    /// The GLB container ends before its header, a chunk, or its declared length.
    #[error("truncated GLB: {0}")]
    TruncatedGlb(String),
    /// The GLB container is structurally invalid (bad version, chunk order, lengths).
    #[error("malformed GLB: {0}")]
    MalformedGlb(String),
    /// The JSON part does not parse as a glTF 2.0 document.
    #[error("invalid glTF JSON: {0}")]
    Json(String),
    /// The asset requires something this importer cannot read (glTF 1.0, Draco, meshopt).
    #[error("unsupported glTF: {0}")]
    Unsupported(String),
    /// A JSON index points at an object that does not exist.
    #[error("{from} refers to {kind} {index}, which does not exist")]
    InvalidReference {
        /// Kind of the missing object (`"accessor"`, `"bufferView"`, ...).
        kind: &'static str,
        /// The dangling index.
        index: usize,
        /// Where the reference was found.
        from: String,
    },
    /// A buffer's bytes are unavailable (missing BIN chunk, bad data URI, missing file).
    #[error("buffer {index}: {reason}")]
    Buffer {
        /// Buffer index.
        index: usize,
        /// What went wrong.
        reason: String,
    },
    /// An accessor or buffer view reaches outside its buffer, or is otherwise unreadable.
    #[error("accessor {accessor} out of bounds: {reason}")]
    AccessorOutOfBounds {
        /// Accessor index.
        accessor: usize,
        /// What went wrong.
        reason: String,
    },
    /// An accessor has a type or component type that does not fit its use.
    #[error("accessor {accessor} has the wrong type: {reason}")]
    BadAccessor {
        /// Accessor index.
        accessor: usize,
        /// What went wrong.
        reason: String,
    },
    /// A vertex index is not below the primitive's vertex count.
    #[error("mesh {mesh} primitive {primitive}: index {index} out of range for {vertex_count} vertices")]
    IndexOutOfRange {
        /// Mesh index.
        mesh: usize,
        /// Primitive index within the mesh.
        primitive: usize,
        /// The offending vertex index.
        index: u32,
        /// Number of vertices of the primitive.
        vertex_count: usize,
    },
    /// A vertex position is NaN or infinite (in the file, or after the node transforms).
    #[error("mesh {mesh} primitive {primitive}: non-finite vertex position")]
    NonFinitePosition {
        /// Mesh index.
        mesh: usize,
        /// Primitive index within the mesh.
        primitive: usize,
    },
    /// The file holds no triangles at all in the imported scene.
    #[error("no triangle geometry in the scene")]
    NoGeometry,
}

/// Counters describing what an import found.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ImportStats {
    /// Primitives imported as bark.
    pub bark_primitives: usize,
    /// Primitives imported as leaves.
    pub leaf_primitives: usize,
    /// Primitives skipped (points, lines, no POSITION).
    pub skipped_primitives: usize,
    /// Leaves made from quads (two triangles, four corners).
    pub leaf_quads: usize,
    /// Leaves made from single triangles (the per-triangle approximation).
    pub leaf_triangles: usize,
    /// Degenerate leaf triangles dropped.
    pub degenerate_leaf_triangles: usize,
    /// Bark normals that were renormalised because they were not unit length.
    pub renormalized_normals: usize,
    /// Bark normals computed because they were missing, zero or non-finite.
    pub computed_normals: usize,
}

/// Result of [`import_gltf_report`]: the model plus diagnostics.
#[derive(Debug, Clone)]
pub struct ImportReport {
    /// The imported model.
    pub model: TreeModel,
    /// Non-fatal problems (skipped primitives, fallbacks taken), human readable.
    pub warnings: Vec<String>,
    /// Counters.
    pub stats: ImportStats,
}

/// Imports a `.glb` or `.gltf` file. External buffers are resolved relative to the file's
/// folder. The model is named after the file stem.
///
/// Contract: see the module docs. Returns a model with `source = ModelSource::Gltf`,
/// `iterations = 0`, no branches, every leaf with `branch = None` and `iteration = 0`, at least
/// one leaf material, and bark normals one per bark position. Never panics.
pub fn import_gltf(path: &Path) -> Result<TreeModel, ImportError> {
    let bytes = std::fs::read(path).map_err(|source| ImportError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let name = path
        .file_stem()
        .map_or_else(|| "tree".to_owned(), |s| s.to_string_lossy().into_owned());
    import_gltf_slice(&bytes, &name, path.parent())
}

/// Imports glTF from memory (GLB container or JSON). `base_dir` resolves external buffer URIs;
/// without it, a file that needs an external buffer fails with [`ImportError::Buffer`].
///
/// Contract as for [`import_gltf`].
pub fn import_gltf_slice(bytes: &[u8], name: &str, base_dir: Option<&Path>) -> Result<TreeModel, ImportError> {
    import_gltf_report(bytes, name, base_dir).map(|r| r.model)
}

/// Like [`import_gltf_slice`], also returning warnings and counters.
pub fn import_gltf_report(bytes: &[u8], name: &str, base_dir: Option<&Path>) -> Result<ImportReport, ImportError> {
    let (json_bytes, bin) = split_container(bytes)?;
    let root = json::Root::from_slice(json_bytes).map_err(|e| ImportError::Json(e.to_string()))?;
    let mut importer = Importer {
        root: &root,
        buffers: load_buffers(&root, bin, base_dir),
        warnings: Vec::new(),
        stats: ImportStats::default(),
    };
    importer.check_asset()?;
    let model = importer.run(name)?;
    Ok(ImportReport {
        model,
        warnings: importer.warnings,
        stats: importer.stats,
    })
}

// ---------------------------------------------------------------------------------------------
// Container

/// Splits the input into the JSON bytes and the GLB BIN chunk (if any).
fn split_container(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>), ImportError> {
    if bytes.starts_with(b"glTF") {
        return split_glb(bytes);
    }
    let first = bytes
        .iter()
        .copied()
        .find(|b| !b.is_ascii_whitespace() && *b != 0xEF && *b != 0xBB && *b != 0xBF);
    match first {
        Some(b'{') => Ok((bytes, None)),
        Some(_) => Err(ImportError::NotGltf("neither GLB magic nor a JSON object".into())),
        None => Err(ImportError::NotGltf("empty input".into())),
    }
}

fn read_u32(bytes: &[u8], at: usize) -> Option<u32> {
    let b = bytes.get(at..at.checked_add(4)?)?;
    Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
}

fn split_glb(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>), ImportError> {
    let (Some(version), Some(declared)) = (read_u32(bytes, 4), read_u32(bytes, 8)) else {
        return Err(ImportError::TruncatedGlb(format!(
            "{} bytes, header needs 12",
            bytes.len()
        )));
    };
    if version != 2 {
        return Err(ImportError::MalformedGlb(format!("GLB version {version}, expected 2")));
    }
    let declared = declared as usize;
    if declared > bytes.len() {
        return Err(ImportError::TruncatedGlb(format!(
            "header declares {declared} bytes, only {} present",
            bytes.len()
        )));
    }
    if declared < 20 {
        return Err(ImportError::MalformedGlb(format!(
            "declared length {declared} leaves no room for a JSON chunk"
        )));
    }
    let data = &bytes[..declared];
    let mut at = 12usize;
    let mut json_chunk: Option<&[u8]> = None;
    let mut bin_chunk: Option<&[u8]> = None;
    while at < data.len() {
        let (Some(len), Some(kind)) = (read_u32(data, at), read_u32(data, at + 4)) else {
            return Err(ImportError::TruncatedGlb(format!(
                "chunk header at byte {at} is cut off"
            )));
        };
        let start = at + 8;
        let end = start
            .checked_add(len as usize)
            .filter(|&e| e <= data.len())
            .ok_or_else(|| {
                ImportError::TruncatedGlb(format!(
                    "chunk at byte {at} declares {len} bytes, only {} left",
                    data.len() - start
                ))
            })?;
        let body = &data[start..end];
        match &kind.to_le_bytes() {
            b"JSON" if json_chunk.is_none() && at == 12 => json_chunk = Some(body),
            b"JSON" => {
                return Err(ImportError::MalformedGlb("JSON chunk is not the first chunk".into()));
            }
            b"BIN\0" if json_chunk.is_some() && bin_chunk.is_none() => bin_chunk = Some(body),
            b"BIN\0" => {
                return Err(ImportError::MalformedGlb("unexpected BIN chunk".into()));
            }
            _ if json_chunk.is_none() => {
                return Err(ImportError::MalformedGlb("first chunk is not JSON".into()));
            }
            _ => {} // Unknown chunks are ignored, as the spec says.
        }
        // Chunks are 4-byte aligned; tolerate writers that did not pad the last chunk.
        at = end.checked_add(3).map_or(usize::MAX, |e| e & !3);
    }
    let json_chunk = json_chunk.ok_or_else(|| ImportError::MalformedGlb("no JSON chunk".into()))?;
    Ok((json_chunk, bin_chunk))
}

// ---------------------------------------------------------------------------------------------
// Buffers

fn load_buffers<'a>(
    root: &json::Root,
    bin: Option<&'a [u8]>,
    base_dir: Option<&Path>,
) -> Vec<Result<Cow<'a, [u8]>, String>> {
    root.buffers
        .iter()
        .enumerate()
        .map(|(i, buffer)| {
            let data: Cow<'a, [u8]> = match &buffer.uri {
                None => match bin {
                    Some(b) if i == 0 => Cow::Borrowed(b),
                    Some(_) => return Err("only buffer 0 may use the GLB BIN chunk".into()),
                    None => return Err("no uri and no GLB BIN chunk".into()),
                },
                Some(uri) if uri.starts_with("data:") => Cow::Owned(decode_data_uri(uri)?),
                Some(uri) => Cow::Owned(read_external(uri, base_dir)?),
            };
            let want = usize::try_from(buffer.byte_length.0).unwrap_or(usize::MAX);
            if data.len() < want {
                return Err(format!(
                    "byteLength is {want} but only {} bytes are present",
                    data.len()
                ));
            }
            // Views must lie within byteLength; cut padding off.
            Ok(match data {
                Cow::Borrowed(b) => Cow::Borrowed(&b[..want]),
                Cow::Owned(mut v) => {
                    v.truncate(want);
                    Cow::Owned(v)
                }
            })
        })
        .collect()
}

/// Decodes a `data:[<mime>];base64,<payload>` URI.
fn decode_data_uri(uri: &str) -> Result<Vec<u8>, String> {
    let Some((head, payload)) = uri.split_once(',') else {
        return Err("data URI without a comma".into());
    };
    if !head.ends_with(";base64") {
        return Err("only base64 data URIs are supported".into());
    }
    base64_decode(payload)
}

/// Standard base64 (RFC 4648 alphabet, URL-safe characters also accepted), padding optional,
/// ASCII whitespace ignored.
pub fn base64_decode(text: &str) -> Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(text.len() / 4 * 3);
    let mut acc = 0u32;
    let mut bits = 0u32;
    let mut padding = false;
    for (pos, c) in text.bytes().enumerate() {
        let v = match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' | b'-' => 62,
            b'/' | b'_' => 63,
            b'=' => {
                padding = true;
                continue;
            }
            c if c.is_ascii_whitespace() => continue,
            _ => return Err(format!("invalid base64 character at {pos}")),
        };
        if padding {
            return Err(format!("base64 data after padding at {pos}"));
        }
        acc = (acc << 6) | u32::from(v);
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    if bits >= 6 {
        return Err("base64 data ends mid-byte".into());
    }
    Ok(out)
}

/// Reads an external buffer relative to `base_dir`. Absolute paths, URI schemes and `..`
/// components are refused so that a file cannot make the importer read outside its folder.
fn read_external(uri: &str, base_dir: Option<&Path>) -> Result<Vec<u8>, String> {
    let Some(base) = base_dir else {
        return Err(format!("external buffer {uri:?} but no base folder was given"));
    };
    if uri.contains("://") || uri.contains(':') {
        return Err(format!("unsupported URI {uri:?}"));
    }
    let decoded = percent_decode(uri);
    let rel = Path::new(&decoded);
    if rel
        .components()
        .any(|c| !matches!(c, Component::Normal(_) | Component::CurDir))
    {
        return Err(format!("refusing URI {uri:?} outside the model folder"));
    }
    let path = base.join(rel);
    std::fs::read(&path).map_err(|e| format!("cannot read {}: {e}", path.display()))
}

fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' && i + 2 < b.len() {
            let hex = std::str::from_utf8(&b[i + 1..i + 3])
                .ok()
                .and_then(|h| u8::from_str_radix(h, 16).ok());
            if let Some(v) = hex {
                out.push(v);
                i += 3;
                continue;
            }
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

// ---------------------------------------------------------------------------------------------
// Accessors

/// An accessor's elements, tightly packed, in the file's component format.
struct RawAccessor {
    count: usize,
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

    fn uint(&self, i: usize) -> u32 {
        let size = self.ctype.size();
        let at = i * size;
        match self.bytes.get(at..at + size) {
            Some(&[a]) => u32::from(a),
            Some(&[a, b]) => u32::from(u16::from_le_bytes([a, b])),
            Some(&[a, b, c, d]) => u32::from_le_bytes([a, b, c, d]),
            _ => 0,
        }
    }

    fn vec3s(&self) -> Vec<Vec3> {
        (0..self.count)
            .map(|k| {
                let b = k * self.comps;
                Vec3::new(self.component(b), self.component(b + 1), self.component(b + 2))
            })
            .collect()
    }

    fn vec2s(&self) -> Vec<Vec2> {
        (0..self.count)
            .map(|k| {
                let b = k * self.comps;
                Vec2::new(self.component(b), self.component(b + 1))
            })
            .collect()
    }
}

fn oob(accessor: usize, reason: impl Into<String>) -> ImportError {
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

struct Importer<'r, 'b> {
    root: &'r json::Root,
    buffers: Vec<Result<Cow<'b, [u8]>, String>>,
    warnings: Vec<String>,
    stats: ImportStats,
}

/// One primitive, read and placed in world space.
struct Placed {
    positions: Vec<Vec3>,
    normals: Option<Vec<Vec3>>,
    uvs: Option<Vec<Vec2>>,
    triangles: Vec<[u32; 3]>,
    material: Option<usize>,
}

impl Importer<'_, '_> {
    fn check_asset(&mut self) -> Result<(), ImportError> {
        let version = &self.root.asset.version;
        if !version.starts_with('2') {
            return Err(ImportError::Unsupported(format!("glTF version {version}")));
        }
        for ext in &self.root.extensions_required {
            match ext.as_str() {
                "KHR_draco_mesh_compression" | "EXT_meshopt_compression" => {
                    return Err(ImportError::Unsupported(format!("required extension {ext}")));
                }
                "KHR_mesh_quantization" | "KHR_texture_transform" | "KHR_materials_unlit" => {}
                _ => self.warnings.push(format!("required extension {ext} ignored")),
            }
        }
        Ok(())
    }

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
    fn read_accessor(
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

    // -----------------------------------------------------------------------------------------
    // Scene graph

    /// Meshes to import with their world transforms: `(node, mesh, world)`.
    fn instances(&mut self) -> Vec<(Option<usize>, usize, Mat4)> {
        let root = self.root;
        let nodes = &root.nodes;
        let n = nodes.len();
        let mut parent: Vec<Option<usize>> = vec![None; n];
        for (i, node) in nodes.iter().enumerate() {
            for c in node.children.iter().flatten() {
                let c = c.value();
                if c >= n || c == i {
                    self.warnings
                        .push(format!("node {i} has an invalid child {c}; ignored"));
                } else if parent[c].is_none() {
                    parent[c] = Some(i);
                } else {
                    self.warnings
                        .push(format!("node {c} has more than one parent; using the first"));
                }
            }
        }
        let scene_nodes: Vec<usize> = match self.root.scene.map(|s| s.value()) {
            Some(s) if s < self.root.scenes.len() => self.root.scenes[s].nodes.iter().map(json::Index::value).collect(),
            other => {
                if let Some(s) = other {
                    self.warnings.push(format!("default scene {s} does not exist"));
                }
                if let Some(first) = self.root.scenes.first() {
                    if other.is_none() {
                        self.warnings.push("no default scene; using scene 0".into());
                    }
                    first.nodes.iter().map(json::Index::value).collect()
                } else {
                    self.warnings.push("no scenes; using every root node".into());
                    (0..n).filter(|&i| parent[i].is_none()).collect()
                }
            }
        };
        let mut out = Vec::new();
        let mut visited = vec![false; n];
        let mut cache: Vec<Option<Mat4>> = vec![None; n];
        let mut stack: Vec<usize> = Vec::new();
        for &s in scene_nodes.iter().rev() {
            if s < n {
                if parent[s].is_some() {
                    self.warnings
                        .push(format!("scene lists node {s}, which is not a root node; imported once"));
                }
                stack.push(s);
            } else {
                self.warnings
                    .push(format!("scene lists node {s}, which does not exist"));
            }
        }
        while let Some(i) = stack.pop() {
            if std::mem::replace(&mut visited[i], true) {
                continue;
            }
            let node = &nodes[i];
            if let Some(mesh) = node.mesh {
                if mesh.value() < self.root.meshes.len() {
                    let world = self.world_transform(i, &parent, &mut cache);
                    out.push((Some(i), mesh.value(), world));
                } else {
                    self.warnings.push(format!(
                        "node {i} refers to mesh {}, which does not exist; skipped",
                        mesh.value()
                    ));
                }
            }
            for c in node.children.iter().flatten().rev() {
                if c.value() < n && !visited[c.value()] {
                    stack.push(c.value());
                }
            }
        }
        if out.is_empty() && n == 0 && !self.root.meshes.is_empty() {
            self.warnings
                .push("no nodes; importing every mesh untransformed".into());
            out.extend((0..self.root.meshes.len()).map(|m| (None, m, Mat4::IDENTITY)));
        }
        out
    }

    fn local_transform(&mut self, i: usize) -> Mat4 {
        let root = self.root;
        let node = &root.nodes[i];
        if let Some(m) = node.matrix {
            return Mat4::from_cols_array(&m);
        }
        let t = node.translation.map_or(Vec3::ZERO, Vec3::from_array);
        let s = node.scale.map_or(Vec3::ONE, Vec3::from_array);
        let r = match node.rotation {
            None => Quat::IDENTITY,
            Some(json::scene::UnitQuaternion(q)) => {
                let q = Quat::from_array(q);
                let len = q.length();
                if len.is_finite() && len > 1e-6 {
                    q / len
                } else {
                    self.warnings
                        .push(format!("node {i} has a degenerate rotation; ignored"));
                    Quat::IDENTITY
                }
            }
        };
        Mat4::from_scale_rotation_translation(s, r, t)
    }

    /// World transform of node `i`: the product of the local transforms along its parent
    /// chain. Memoised in `cache` so that a whole hierarchy costs linear time; a cycle (invalid
    /// file) is cut after `parent.len()` steps.
    fn world_transform(&mut self, i: usize, parent: &[Option<usize>], cache: &mut [Option<Mat4>]) -> Mat4 {
        let mut chain = Vec::new();
        let mut cur = Some(i);
        let mut world = Mat4::IDENTITY;
        while let Some(c) = cur {
            if let Some(m) = cache[c] {
                world = m;
                break;
            }
            if chain.len() > parent.len() {
                self.warnings.push(format!("node hierarchy above node {i} has a cycle"));
                break;
            }
            chain.push(c);
            cur = parent[c];
        }
        for &k in chain.iter().rev() {
            world *= self.local_transform(k);
            cache[k] = Some(world);
        }
        world
    }

    // -----------------------------------------------------------------------------------------
    // Primitives

    fn read_primitive(&mut self, mesh: usize, prim_index: usize, world: Mat4) -> Result<Option<Placed>, ImportError> {
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

    fn material(&self, m: Option<usize>) -> Option<&json::Material> {
        m.and_then(|m| self.root.materials.get(m))
    }

    fn texture_name(&self, m: Option<usize>) -> Option<String> {
        let info = self.material(m)?.pbr_metallic_roughness.base_color_texture.as_ref()?;
        let texture = self.root.get(info.index)?;
        let image = self.root.get(texture.source)?;
        if let Some(uri) = image.uri.as_deref().filter(|u| !u.starts_with("data:")) {
            let decoded = percent_decode(uri);
            let file = decoded.rsplit(['/', '\\']).next().unwrap_or(&decoded);
            if !file.is_empty() {
                return Some(file.to_owned());
            }
        }
        image.name.clone().or_else(|| texture.name.clone())
    }

    fn base_color(&self, m: Option<usize>) -> Option<[f32; 4]> {
        let c = self.material(m)?.pbr_metallic_roughness.base_color_factor.0;
        c.iter().all(|v| v.is_finite()).then_some(c)
    }

    /// Decides whether a primitive is foliage (the rules in the module docs).
    fn is_leaf(&self, mesh: usize, node: Option<usize>, placed: &Placed) -> bool {
        let has = |name: Option<&str>, words: &[&str]| {
            name.is_some_and(|n| {
                let n = n.to_lowercase();
                words.iter().any(|w| n.contains(w))
            })
        };
        let mat = self.material(placed.material);
        let mat_name = mat.and_then(|m| m.name.as_deref());
        if has(mat_name, LEAF_WORDS) {
            return true;
        }
        if has(mat_name, BARK_WORDS) {
            return false;
        }
        if mat.is_some_and(|m| matches!(m.alpha_mode, Checked::Valid(AlphaMode::Mask | AlphaMode::Blend))) {
            return true;
        }
        let mesh_name = self.root.meshes[mesh].name.as_deref();
        let node_name = node.and_then(|n| self.root.nodes[n].name.as_deref());
        for name in [mesh_name, node_name] {
            if has(name, LEAF_WORDS) {
                return true;
            }
            if has(name, BARK_WORDS) {
                return false;
            }
        }
        looks_like_foliage(&placed.positions, &placed.triangles)
    }

    fn run(&mut self, name: &str) -> Result<TreeModel, ImportError> {
        let root = self.root;
        let instances = self.instances();
        let mut bark = TriangleMesh::default();
        let mut bark_by_material: Vec<(Option<usize>, usize)> = Vec::new();
        let mut leaf_materials: Vec<Option<usize>> = Vec::new();
        let mut leaves: Vec<Leaf> = Vec::new();
        for (node, mesh, world) in instances {
            for p in 0..root.meshes[mesh].primitives.len() {
                let Some(placed) = self.read_primitive(mesh, p, world)? else {
                    continue;
                };
                if placed.triangles.is_empty() {
                    continue;
                }
                if self.is_leaf(mesh, node, &placed) {
                    self.stats.leaf_primitives += 1;
                    let slot = if let Some(k) = leaf_materials.iter().position(|&m| m == placed.material) {
                        k
                    } else if leaf_materials.len() < 256 {
                        leaf_materials.push(placed.material);
                        leaf_materials.len() - 1
                    } else {
                        self.warnings
                            .push("more than 256 leaf materials; extra ones merged".into());
                        255
                    };
                    let before = leaves.len();
                    leaves_from_primitive(&placed, slot as u8, &mut leaves, &mut self.stats);
                    if leaves.len() == before {
                        self.warnings
                            .push(format!("mesh {mesh} primitive {p}: leaf primitive yielded no leaves"));
                    }
                } else {
                    self.stats.bark_primitives += 1;
                    let tris = placed.triangles.len();
                    match bark_by_material.iter_mut().find(|(m, _)| *m == placed.material) {
                        Some(entry) => entry.1 += tris,
                        None => bark_by_material.push((placed.material, tris)),
                    }
                    append_bark(&placed, &mut bark, &mut self.stats)?;
                }
            }
        }
        if bark.indices.is_empty() && leaves.is_empty() {
            return Err(ImportError::NoGeometry);
        }

        // Materials.
        let defaults = Materials::default();
        let bark_material = bark_by_material.iter().max_by_key(|(_, n)| *n).and_then(|(m, _)| *m);
        let leaf = if leaf_materials.is_empty() {
            defaults.leaf.clone()
        } else {
            leaf_materials
                .iter()
                .map(|&m| LeafMaterial {
                    color: self.base_color(m).unwrap_or(defaults.leaf[0].color),
                    texture: self.texture_name(m),
                })
                .collect()
        };
        let materials = Materials {
            bark_color: self.base_color(bark_material).unwrap_or(defaults.bark_color),
            bark_texture: self.texture_name(bark_material),
            leaf,
        };

        // Re-centre: base of the bark (or of everything) at the origin.
        let mut model = TreeModel {
            name: name.to_owned(),
            branches: Vec::new(),
            leaves,
            bark_mesh: bark,
            materials,
            iterations: 0,
            source: ModelSource::Gltf,
        };
        let bounds = if model.bark_mesh.positions.is_empty() {
            model.bounds()
        } else {
            let lo = model
                .bark_mesh
                .positions
                .iter()
                .fold(Vec3::splat(f32::INFINITY), |a, &p| a.min(p));
            let hi = model
                .bark_mesh
                .positions
                .iter()
                .fold(Vec3::splat(f32::NEG_INFINITY), |a, &p| a.max(p));
            Some((lo, hi))
        };
        if let Some((lo, hi)) = bounds {
            let origin = Vec3::new(0.5 * (lo.x + hi.x), lo.y, 0.5 * (lo.z + hi.z));
            if origin.is_finite() {
                for p in &mut model.bark_mesh.positions {
                    *p -= origin;
                }
                for l in &mut model.leaves {
                    l.center -= origin;
                }
            }
        }
        if model
            .bounds()
            .is_some_and(|(lo, hi)| !(lo.is_finite() && hi.is_finite()))
        {
            return Err(ImportError::NonFinitePosition { mesh: 0, primitive: 0 });
        }
        Ok(model)
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
fn append_bark(placed: &Placed, bark: &mut TriangleMesh, stats: &mut ImportStats) -> Result<(), ImportError> {
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
// Leaves

struct UnionFind(Vec<u32>);

impl UnionFind {
    fn new(n: usize) -> Self {
        Self((0..n as u32).collect())
    }
    fn find(&mut self, mut x: u32) -> u32 {
        while self.0[x as usize] != x {
            let p = self.0[x as usize];
            self.0[x as usize] = self.0[p as usize];
            x = p;
        }
        x
    }
    fn union(&mut self, a: u32, b: u32) {
        let (a, b) = (self.find(a), self.find(b));
        if a != b {
            self.0[a.max(b) as usize] = a.min(b);
        }
    }
}

fn position_key(p: Vec3) -> [u32; 3] {
    // +0.0 for -0.0 so that both weld.
    (p + Vec3::ZERO)
        .to_array()
        .map(|c| if c == 0.0 { 0 } else { c.to_bits() })
}

/// For every vertex, the first vertex with a bit-equal position.
fn weld(positions: &[Vec3]) -> Vec<u32> {
    let mut first: HashMap<[u32; 3], u32> = HashMap::with_capacity(positions.len());
    positions
        .iter()
        .enumerate()
        .map(|(i, &p)| *first.entry(position_key(p)).or_insert(i as u32))
        .collect()
}

/// Groups triangles into connected components (by shared index and, with `welded`, by shared
/// position). Components are ordered by their first triangle.
fn components(
    vertex_count: usize,
    triangles: &[[u32; 3]],
    tri_ids: &[usize],
    welded: Option<&[u32]>,
) -> Vec<Vec<usize>> {
    let mut uf = UnionFind::new(vertex_count);
    let map = |k: u32| welded.map_or(k, |w| w[k as usize]);
    for &t in tri_ids {
        let [a, b, c] = triangles[t].map(map);
        uf.union(a, b);
        uf.union(a, c);
    }
    let mut slot: HashMap<u32, usize> = HashMap::new();
    let mut out: Vec<Vec<usize>> = Vec::new();
    for &t in tri_ids {
        let r = uf.find(map(triangles[t][0]));
        let k = *slot.entry(r).or_insert_with(|| {
            out.push(Vec::new());
            out.len() - 1
        });
        out[k].push(t);
    }
    out
}

/// The four corners of a two-triangle component, in outline order, if it is a planar quad.
fn quad_outline(placed: &Placed, welded: &[u32], tris: &[usize]) -> Option<[u32; 4]> {
    let [t0, t1] = *tris else { return None };
    let a = placed.triangles[t0];
    let b = placed.triangles[t1];
    let wa = a.map(|k| welded[k as usize]);
    let wb = b.map(|k| welded[k as usize]);
    if wa[0] == wa[1] || wa[1] == wa[2] || wa[0] == wa[2] {
        return None;
    }
    let shared: Vec<usize> = (0..3).filter(|&i| wb.contains(&wa[i])).collect();
    if shared.len() != 2 {
        return None;
    }
    let lone_a = (0..3).find(|i| !shared.contains(i))?;
    let lone_b = (0..3).find(|&i| !wa.contains(&wb[i]))?;
    if wb[lone_b] == wa[lone_a] {
        return None;
    }
    // Nearly planar: real leaf cards are often folded along a diagonal (tfs_detailedTree's by
    // exactly 60 degrees), so accept folds up to ~75 degrees.
    let p = |k: u32| placed.positions[k as usize];
    let na = (p(a[1]) - p(a[0])).cross(p(a[2]) - p(a[0]));
    let nb = (p(b[1]) - p(b[0])).cross(p(b[2]) - p(b[0]));
    let (Some(na), Some(nb)) = (na.try_normalize(), nb.try_normalize()) else {
        return None;
    };
    if na.dot(nb).abs() < QUAD_MIN_FOLD_COS {
        return None;
    }
    // Outline: lone_a, next shared, lone_b, other shared.
    let s1 = a[(lone_a + 1) % 3];
    let s2 = a[(lone_a + 2) % 3];
    Some([a[lone_a], s1, b[lone_b], s2])
}

/// Unit 3-D direction of increasing uv `v` over the given vertices: the `v` column of the
/// least-squares affine map from uv to position. `None` without uvs or with degenerate uvs.
fn uv_v_direction(placed: &Placed, verts: &[u32]) -> Option<Vec3> {
    let uvs = placed.uvs.as_ref()?;
    let k = verts.len() as f32;
    let p_mean = verts.iter().map(|&i| placed.positions[i as usize]).sum::<Vec3>() / k;
    let q_mean = verts.iter().map(|&i| uvs[i as usize]).sum::<Vec2>() / k;
    let (mut suu, mut svv, mut suv) = (0.0f32, 0.0f32, 0.0f32);
    let (mut sup, mut svp) = (Vec3::ZERO, Vec3::ZERO);
    for &i in verts {
        let d = uvs[i as usize] - q_mean;
        let p = placed.positions[i as usize] - p_mean;
        suu += d.x * d.x;
        svv += d.y * d.y;
        suv += d.x * d.y;
        sup += p * d.x;
        svp += p * d.y;
    }
    let det = suu * svv - suv * suv;
    if !det.is_finite() || det.abs() <= 1e-12 * (suu * svv).max(f32::MIN_POSITIVE) {
        return None;
    }
    ((svp * suu - sup * suv) / det).try_normalize()
}

/// Builds a leaf from a plane frame and the points to cover.
fn leaf_from_points(points: &[Vec3], normal: Vec3, axis: Vec3, material: u8) -> Option<Leaf> {
    let axis = (axis - normal * axis.dot(normal)).try_normalize()?;
    let side = axis.cross(normal);
    let mean = points.iter().copied().sum::<Vec3>() / points.len() as f32;
    let (mut a_lo, mut a_hi, mut s_lo, mut s_hi) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
    for &p in points {
        let d = p - mean;
        a_lo = a_lo.min(d.dot(axis));
        a_hi = a_hi.max(d.dot(axis));
        s_lo = s_lo.min(d.dot(side));
        s_hi = s_hi.max(d.dot(side));
    }
    let (length, width) = (a_hi - a_lo, s_hi - s_lo);
    if !(length > 0.0 && width > 0.0 && length.is_finite() && width.is_finite()) {
        return None;
    }
    Some(Leaf {
        center: mean + axis * (0.5 * (a_lo + a_hi)) + side * (0.5 * (s_lo + s_hi)),
        normal,
        axis,
        width,
        length,
        branch: None,
        iteration: 0,
        material,
    })
}

/// Orients a face normal like the vertex normals, when the primitive has them.
fn orient(placed: &Placed, face: Vec3, verts: &[u32]) -> Vec3 {
    let Some(ns) = &placed.normals else {
        return face;
    };
    let sum: Vec3 = verts.iter().map(|&k| ns[k as usize]).sum();
    if sum.dot(face) < 0.0 { -face } else { face }
}

fn quad_leaf(placed: &Placed, tris: &[usize], outline: [u32; 4], material: u8) -> Option<Leaf> {
    let p = |k: u32| placed.positions[k as usize];
    let corners = outline.map(p);
    let mut normal = Vec3::ZERO;
    for &t in tris {
        let [a, b, c] = placed.triangles[t].map(p);
        normal += (b - a).cross(c - a);
    }
    let normal = orient(placed, normal.try_normalize()?, &outline);
    let uv_axis = uv_v_direction(placed, &outline).filter(|d| d.dot(normal).abs() < 0.9);
    let axis = uv_axis.unwrap_or_else(|| {
        let mut best = Vec3::ZERO;
        for i in 0..4 {
            let e = corners[(i + 1) % 4] - corners[i];
            if e.length_squared() > best.length_squared() {
                best = e;
            }
        }
        best
    });
    leaf_from_points(&corners, normal, axis, material)
}

fn triangle_leaf(placed: &Placed, t: [u32; 3], material: u8) -> Option<Leaf> {
    let [a, b, c] = t.map(|k| placed.positions[k as usize]);
    let face = (b - a).cross(c - a).try_normalize()?;
    let normal = orient(placed, face, &t);
    let edges = [b - a, c - b, a - c];
    let longest = edges
        .into_iter()
        .max_by(|x, y| x.length_squared().total_cmp(&y.length_squared()))?;
    let mut leaf = leaf_from_points(&[a, b, c], normal, longest, material)?;
    leaf.center = (a + b + c) / 3.0;
    Some(leaf)
}

/// Turns a leaf primitive into leaves (see the module docs).
fn leaves_from_primitive(placed: &Placed, material: u8, out: &mut Vec<Leaf>, stats: &mut ImportStats) {
    let welded = weld(&placed.positions);
    let all: Vec<usize> = (0..placed.triangles.len()).collect();
    let n = placed.positions.len();
    let per_triangle = |tris: &[usize], out: &mut Vec<Leaf>, stats: &mut ImportStats| {
        for &t in tris {
            match triangle_leaf(placed, placed.triangles[t], material) {
                Some(leaf) => {
                    out.push(leaf);
                    stats.leaf_triangles += 1;
                }
                None => stats.degenerate_leaf_triangles += 1,
            }
        }
    };
    for comp in components(n, &placed.triangles, &all, Some(&welded)) {
        if comp.len() == 2 {
            if let Some(leaf) =
                quad_outline(placed, &welded, &comp).and_then(|outline| quad_leaf(placed, &comp, outline, material))
            {
                out.push(leaf);
                stats.leaf_quads += 1;
            } else {
                per_triangle(&comp, out, stats);
            }
            continue;
        }
        // Split back by shared vertex index. A quad in there stays a leaf if it touches the
        // rest along at most one edge (leaves that merely touch); quads of a flat-shaded blob
        // share most of their edges with neighbouring faces and go per triangle.
        let subs = components(n, &placed.triangles, &comp, None);
        let outlines: Vec<Option<[u32; 4]>> = subs.iter().map(|sub| quad_outline(placed, &welded, sub)).collect();
        let corner_sets: Vec<Option<[u32; 4]>> = outlines
            .iter()
            .map(|o| {
                o.map(|o| {
                    let mut w = o.map(|k| welded[k as usize]);
                    w.sort_unstable();
                    w
                })
            })
            .collect();
        let mut edge_owners: HashMap<(u32, u32), Vec<usize>> = HashMap::new();
        for (si, sub) in subs.iter().enumerate() {
            for &t in sub {
                let w = placed.triangles[t].map(|k| welded[k as usize]);
                for (a, b) in [(w[0], w[1]), (w[1], w[2]), (w[2], w[0])] {
                    let owners = edge_owners.entry((a.min(b), a.max(b))).or_default();
                    if owners.last() != Some(&si) {
                        owners.push(si);
                    }
                }
            }
        }
        for (si, sub) in subs.iter().enumerate() {
            if let Some(outline) = outlines[si] {
                let w = outline.map(|k| welded[k as usize]);
                let shared = (0..4)
                    .filter(|&e| {
                        let (a, b) = (w[e], w[(e + 1) % 4]);
                        edge_owners
                            .get(&(a.min(b), a.max(b)))
                            .is_some_and(|owners| owners.iter().any(|&o| o != si && corner_sets[o] != corner_sets[si]))
                    })
                    .count();
                if shared <= 1
                    && let Some(leaf) = quad_leaf(placed, sub, outline, material)
                {
                    out.push(leaf);
                    stats.leaf_quads += 1;
                    continue;
                }
            }
            per_triangle(sub, out, stats);
        }
    }
}

/// The shape rule: many small, disconnected, planar quads.
fn looks_like_foliage(positions: &[Vec3], triangles: &[[u32; 3]]) -> bool {
    if triangles.len() < 2 * SHAPE_MIN_QUADS {
        return false;
    }
    let (lo, hi) = triangles.iter().flatten().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), &k| (lo.min(positions[k as usize]), hi.max(positions[k as usize])),
    );
    let diag = (hi - lo).length();
    if !(diag > 0.0 && diag.is_finite()) {
        return false;
    }
    let placed = Placed {
        positions: positions.to_vec(),
        normals: None,
        uvs: None,
        triangles: triangles.to_vec(),
        material: None,
    };
    let welded = weld(positions);
    let all: Vec<usize> = (0..triangles.len()).collect();
    let mut quad_tris = 0usize;
    let mut quads = 0usize;
    for comp in components(positions.len(), triangles, &all, Some(&welded)) {
        if let Some(outline) = quad_outline(&placed, &welded, &comp) {
            let c = outline.map(|k| positions[k as usize]);
            let size = c[0].distance(c[2]).max(c[1].distance(c[3]));
            if size < diag / 8.0 {
                quads += 1;
                quad_tris += 2;
            }
        }
    }
    quads >= SHAPE_MIN_QUADS && quad_tris * 5 >= triangles.len() * 4
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn base64_round_trip() {
        assert_eq!(base64_decode("aGVsbG8=").unwrap(), b"hello");
        assert_eq!(base64_decode("aGVsbG8").unwrap(), b"hello");
        assert_eq!(base64_decode("AAEC\n/w==").unwrap(), &[0, 1, 2, 255]);
        assert!(base64_decode("a$==").is_err());
        assert!(base64_decode("a").is_err());
    }

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

    #[test]
    fn glb_header_checks() {
        assert!(matches!(split_container(b"glTF"), Err(ImportError::TruncatedGlb(_))));
        let mut v = b"glTF".to_vec();
        v.extend_from_slice(&2u32.to_le_bytes());
        v.extend_from_slice(&4u32.to_le_bytes());
        assert!(matches!(split_container(&v), Err(ImportError::MalformedGlb(_))));
        assert!(matches!(split_container(b"\x00\x01"), Err(ImportError::NotGltf(_))));
    }

    #[test]
    fn percent_decoding() {
        assert_eq!(percent_decode("a%20b.bin"), "a b.bin");
        assert_eq!(percent_decode("a%2"), "a%2");
        assert_eq!(percent_decode("%"), "%");
    }
}
