//! Evaluation: render what a client draws with the shared CPU rasterizer and compare it with the
//! full-detail scene (SSIM, coverage precision/recall, popping).
//!
//! What is drawn for each tree comes from a [`crate::stream::DrawnTree`] list (the streamer's
//! record of what it drew from its cache). The geometry itself is taken from the model files
//! decoded whole: a drawn prefix of `k` leaves is the first `k` leaves of the node in the file,
//! byte for byte what the client's cached, CRC-checked blocks hold. Leaf textures are the bake's
//! procedural leaf mask, so billboards (baked with it) and geometry look alike.
//!
//! Rendering: one lit pass for geometry and hulls, one unlit pass for billboards (their images
//! already carry the bake's lighting), composited by depth. The rasterizer does not blend:
//! billboards draw the frame of largest weight (the GPU viewer blends up to three), and two
//! cross-fading cloud levels split the pixels with complementary 4 × 4 screen-door ranges (the
//! rasterizer's [`RasterMaterial::coverage`]), exactly as the viewer does.

use std::collections::HashMap;
use std::sync::OnceLock;

use canopy_shared::format::atlas::{AtlasLayoutKind, AtlasTable, decode_png_frame};
use canopy_shared::format::cloud::{CLOUD_QUAD_UVS, CloudQuad, CloudTable, decode_clouds};
use canopy_shared::format::directory::SectionKind;
use canopy_shared::format::hull::decode_hulls;
use canopy_shared::format::tree::{DecodedTree, section_bytes};
use canopy_shared::lsystem::rng::SplitMix64;
use canopy_shared::metrics::{coverage, ssim_rgba};
use canopy_shared::model::{Leaf, TreeModel};
use canopy_shared::raster::{
    Camera as RasterCamera, FULL_COVERAGE, Filter, Frame, Instance, ItemMap, Projection, QuadBatch, RasterMaterial,
    RasterMesh, RenderOptions, Scene, Texture, TextureId, TreeMeshOptions, Wrap, render, render_in_passes,
    tree_materials,
};
use canopy_shared::tessellate::{TubeOptions, branch_tubes_thicker_than};
use glam::{Mat4, Quat, Vec3};

use crate::lod::leaf_enlargement;
use crate::lod::projection::BillboardKind;
use crate::stream::{Camera, Drawn, DrawnTree, Viewport};

/// Background the images are composited over for SSIM and popping (a pale sky).
pub const BACKGROUND: [u8; 3] = [200, 220, 240];
/// Bark variants: branches whose radius never reaches this many metres are left out. Every
/// rendering (reference included) uses, per tree, the coarsest variant whose dropped twigs are
/// all thinner than [`BARK_MIN_PIXELS`] of a pixel, as the bake's atlases do: tubes of a
/// hundredth of a pixel cost most of a forest's triangles and change nothing visible.
pub const BARK_MIN_RADII: [f32; 5] = [0.0, 0.003, 0.01, 0.03, 0.1];
/// Radius in pixels below which a twig may be left out of a rendering.
pub const BARK_MIN_PIXELS: f32 = 0.1;
/// Cap of the seed 004 leaf enlargement when drawing simplified nodes.
pub const ENLARGEMENT_CAP: f32 = 2.0;

/// Largest enlargement of a geometry tree's kept leaves: the pixel-scale budget's cap
/// ([`Drawn::Geometry`]'s `enlargement_cap`, 1 when off), raised to [`ENLARGEMENT_CAP`] when
/// seed 004's enlargement is asked for everywhere (`enlarge`).
pub fn enlargement_cap(enlarge: bool, budget_cap: f32) -> f32 {
    let budget_cap = if budget_cap.is_finite() {
        budget_cap.max(1.0)
    } else {
        1.0
    };
    if enlarge {
        budget_cap.max(ENLARGEMENT_CAP)
    } else {
        budget_cap
    }
}

/// Why evaluation failed.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// A model file did not decode.
    #[error("model {0}: {1}")]
    Model(String, canopy_shared::format::FormatError),
    /// Rendering failed.
    #[error(transparent)]
    Raster(#[from] canopy_shared::raster::RasterError),
    /// A metric failed.
    #[error(transparent)]
    Metrics(#[from] canopy_shared::metrics::MetricsError),
}

/// How a method picks the leaves of a simplified node.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LeafChoice {
    /// The first `k` in the file's order (VMI for a default bake).
    Prefix,
    /// `k` leaves chosen at random (seeded by instance and node): what a file in random order
    /// would give for the same bytes.
    Random,
}

/// One model decoded for rendering.
#[derive(Debug)]
pub struct EvalModel {
    tree: DecodedTree,
    /// Bark meshes without twigs thinner than [`BARK_MIN_RADII`]`[i]` metres.
    bark: Vec<RasterMesh>,
    mat_offset: u16,
    hulls: Vec<RasterMesh>,
    atlas: Option<(AtlasTable, Vec<u8>)>,
    /// Billboard-cloud table and section bytes (`None`: no levels baked).
    clouds: Option<(CloudTable, Vec<u8>)>,
    /// Triangles at full detail (bark + 2 per leaf).
    pub full_triangles: u64,
    /// Every leaf, in file order: the mesh all full-detail instances share (built on first use).
    full_leaves: OnceLock<RasterMesh>,
}

/// Every model of a scene, decoded, with the shared material table.
#[derive(Debug, Default)]
pub struct EvalScene {
    models: Vec<Option<EvalModel>>,
    materials: Vec<RasterMaterial>,
    textures: Vec<Texture>,
    billboard_textures: HashMap<(usize, u32, u8), Texture>,
    /// Cloud plane textures by (model, plane).
    cloud_textures: HashMap<(usize, u32), Texture>,
}

fn empty_model(tree: &DecodedTree) -> TreeModel {
    TreeModel {
        name: tree.directory.name.clone(),
        branches: tree.branches.clone(),
        leaves: Vec::new(),
        bark_mesh: tree.bark_mesh.clone(),
        materials: tree.materials.clone(),
        iterations: tree.directory.iterations,
        source: tree.directory.source,
    }
}

impl EvalScene {
    /// An empty scene with room for `models` models.
    pub fn new(models: usize) -> Self {
        Self {
            models: (0..models).map(|_| None).collect(),
            materials: Vec::new(),
            textures: vec![Texture::procedural_leaf(32)],
            billboard_textures: HashMap::new(),
            cloud_textures: HashMap::new(),
        }
    }

    /// Whether model `m` is loaded.
    pub fn has(&self, m: usize) -> bool {
        self.models.get(m).is_some_and(Option::is_some)
    }

    /// Decodes model `m` from its whole file.
    pub fn load(&mut self, m: usize, name: &str, bytes: &[u8]) -> Result<(), EvalError> {
        let tree = DecodedTree::decode(bytes).map_err(|e| EvalError::Model(name.into(), e))?;
        let model = empty_model(&tree);
        let mat_offset = self.materials.len() as u16;
        let mats = tree_materials(&model, &vec![Some(0); model.materials.leaf.len()]);
        let crown = {
            let n = tree.materials.leaf.len().max(1) as f32;
            let mut c = [0.0f32; 4];
            for l in &tree.materials.leaf {
                for (a, b) in c.iter_mut().zip(l.color) {
                    *a += b / n;
                }
            }
            RasterMaterial {
                color: [c[0], c[1], c[2], 1.0],
                texture: None,
                alpha_cutoff: 0.0,
                double_sided: false,
                coverage: FULL_COVERAGE,
            }
        };
        let crown_index = mat_offset + mats.len() as u16;
        self.materials.extend(mats);
        self.materials.push(crown);
        let bark: Vec<RasterMesh> = BARK_MIN_RADII
            .iter()
            .map(|&min_radius| {
                let tubes = branch_tubes_thicker_than(&model, TubeOptions { sides: 6, caps: false }, min_radius);
                RasterMesh::from_bark(&[&tubes, &model.bark_mesh], mat_offset)
            })
            .collect();
        let section = |k: SectionKind| {
            tree.directory
                .section(k)
                .and_then(|e| section_bytes(bytes, e).ok())
                .filter(|b| !b.is_empty())
        };
        let hulls = section(SectionKind::Hulls)
            .and_then(|b| decode_hulls(b).ok())
            .map(|(_, levels)| {
                levels
                    .into_iter()
                    .map(|h| RasterMesh {
                        item_of_triangle: vec![0; h.indices.len() / 3],
                        material_of_triangle: vec![crown_index; h.indices.len() / 3],
                        positions: h.positions,
                        indices: h.indices,
                        ..RasterMesh::default()
                    })
                    .collect()
            })
            .unwrap_or_default();
        let atlas = section(SectionKind::BillboardAtlases)
            .and_then(|b| AtlasTable::decode(b, b.len() as u64).ok().map(|t| (t, b.to_vec())));
        let clouds = section(SectionKind::BillboardClouds)
            .and_then(|b| decode_clouds(b).ok().map(|t| (t, b.to_vec())))
            .filter(|(t, _)| !t.levels.is_empty());
        let full_triangles = bark[0].triangle_count() as u64 + 2 * u64::from(tree.directory.leaf_count);
        self.models[m] = Some(EvalModel {
            tree,
            bark,
            mat_offset,
            hulls,
            atlas,
            clouds,
            full_triangles,
            full_leaves: OnceLock::new(),
        });
        Ok(())
    }

    /// Loads billboard frame `frame` at resolution `res` of model `m` into the texture cache and
    /// returns its root anchor `(u, v)`, the atlas's centre and radius, and the frame's direction.
    fn billboard_texture(&mut self, m: usize, frame: u32, res: u8) -> Option<(f32, f32, Vec3, f32, Vec3)> {
        let model = self.models.get(m)?.as_ref()?;
        let (table, section) = model.atlas.as_ref()?;
        let side = *table.resolutions.get(usize::from(res))?;
        let dir = table.frame_direction(frame)?;
        let f = table.frames.get(frame as usize)?;
        let (ru, rv) = (f.root_u, f.root_v);
        let (center, radius) = (table.center, table.radius);
        if let std::collections::hash_map::Entry::Vacant(slot) = self.billboard_textures.entry((m, frame, res)) {
            let bytes = table.image_bytes(section, frame, usize::from(res)).ok()??;
            let img = decode_png_frame(bytes, side).ok()?;
            slot.insert(Texture::from_image(&img).ok()?);
        }
        Some((ru, rv, center, radius, dir))
    }

    /// The planes of cloud level `level` of model `m` (section-wide index and quad) whose
    /// textures (bilinear, clamped) are in the texture cache.
    fn cloud_level(&mut self, m: usize, level: u8) -> Vec<(u32, CloudQuad)> {
        let Some(Some(model)) = self.models.get(m) else {
            return Vec::new();
        };
        let Some((table, section)) = &model.clouds else {
            return Vec::new();
        };
        let Some(l) = table.levels.get(usize::from(level)) else {
            return Vec::new();
        };
        let mut out = Vec::with_capacity(l.plane_count as usize);
        for p in l.first_plane..l.first_plane + l.plane_count {
            let plane = table.planes[p as usize];
            if let std::collections::hash_map::Entry::Vacant(v) = self.cloud_textures.entry((m, p)) {
                let Some(t) = cloud_texture(table, section, p) else {
                    continue;
                };
                v.insert(t);
            }
            out.push((p, plane.quad));
        }
        out
    }

    /// Full triangles of the drawn trees at full detail.
    pub fn full_triangles(&self, trees: &[DrawnTree]) -> u64 {
        trees
            .iter()
            .filter_map(|t| self.models.get(usize::from(t.instance.model))?.as_ref())
            .map(|m| m.full_triangles)
            .sum()
    }
}

/// A stand-in texture of the scene's caches.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum TextureKey {
    /// Model, atlas frame, resolution index.
    Atlas(usize, u32, u8),
    /// Model, cloud plane.
    Cloud(usize, u32),
}

/// The id in `bb` of the cached texture `key`, added to the batch on its first use in a view
/// (so a texture drawn by many trees is copied once per view, not once per tree).
fn batch_texture(
    bb: &mut QuadBatch,
    ids: &mut HashMap<TextureKey, TextureId>,
    key: TextureKey,
    scene: &EvalScene,
) -> Option<TextureId> {
    if let Some(&id) = ids.get(&key) {
        return Some(id);
    }
    let tex = match key {
        TextureKey::Atlas(m, f, r) => scene.billboard_textures.get(&(m, f, r)),
        TextureKey::Cloud(m, p) => scene.cloud_textures.get(&(m, p)),
    }?;
    let id = bb.add_texture(tex.clone());
    ids.insert(key, id);
    Some(id)
}

/// Plane `p`'s texture (bilinear, clamped), `None` when it fails its check.
fn cloud_texture(table: &CloudTable, section: &[u8], p: u32) -> Option<Texture> {
    let plane = table.planes.get(p as usize)?;
    let bytes = table.texture_bytes(section, p as usize).ok()?;
    let img = CloudTable::decode_texture(plane, bytes).ok()?;
    let mut t = Texture::from_image(&img).ok()?;
    t.filter = Filter::Bilinear;
    t.wrap = Wrap::Clamp;
    Some(t)
}

/// A billboard frame's quad for tree `t`: world centre and half extents `(right, up)`.
///
/// The frame was baked looking along `−dir` (model space) with the tree's root at image position
/// `root = (u, v)` (seed 001's anchor), over a square of side `2·radius`; the quad faces `dir`,
/// turned with the instance and scaled by it, and is placed so that the root lands on the
/// instance's position.
pub fn billboard_quad(t: &DrawnTree, dir: Vec3, radius: f32, root: (f32, f32)) -> (Vec3, Vec3, Vec3) {
    let s = t.instance.placement().1;
    let rot = Quat::from_rotation_y(t.instance.rotation);
    let fwd = -dir;
    let up_hint = if dir.cross(Vec3::Y).length_squared() < 1e-6 {
        Vec3::Z
    } else {
        Vec3::Y
    };
    let right = fwd.cross(up_hint).normalize_or_zero();
    let up = right.cross(fwd);
    let (right, up) = (rot * right, rot * up);
    let r = radius * s;
    let base = Vec3::from(t.instance.position);
    let center = base + right * ((0.5 - root.0) * 2.0 * r) + up * ((0.5 - root.1) * 2.0 * r);
    (center, right * r, up * r)
}

/// What to render for each tree.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RenderMode {
    /// Every tree at full detail, whatever the list says.
    Full,
    /// What the list says, leaves chosen by `choice`, with seed 004 enlargement when `enlarge`.
    AsDrawn {
        /// Leaf choice.
        choice: LeafChoice,
        /// Enlarge kept leaves.
        enlarge: bool,
    },
}

/// Whether `keep` keeps every leaf of every node of `model` (a missing entry keeps 0, as in
/// [`leaves_mesh`]).
fn keeps_every_leaf(model: &EvalModel, keep: &[u32]) -> bool {
    model
        .tree
        .node_leaves
        .iter()
        .enumerate()
        .all(|(o, leaves)| keep.get(o).copied().unwrap_or(0) as usize >= leaves.len())
}

/// The kept leaves of every node (all when `keep` is `None`), each node's enlarged by seed 004's
/// `s = √(1/(1 − R))` up to `max_scale` (1: none).
fn leaves_mesh(model: &EvalModel, keep: Option<&[u32]>, choice: LeafChoice, max_scale: f32, seed: u64) -> RasterMesh {
    let mut chosen: Vec<Leaf> = Vec::new();
    for (o, leaves) in model.tree.node_leaves.iter().enumerate() {
        let n = leaves.len() as u32;
        let k = keep.map_or(n, |k| k.get(o).copied().unwrap_or(0).min(n));
        if k == 0 {
            continue;
        }
        let s = if max_scale > 1.0 && k < n {
            leaf_enlargement(0.0, 1.0 - k as f32 / n as f32, max_scale)
        } else {
            1.0
        };
        let mut push = |l: &Leaf| {
            chosen.push(Leaf {
                width: l.width * s,
                length: l.length * s,
                ..*l
            });
        };
        if choice == LeafChoice::Random && k < n {
            // Partial Fisher–Yates: k distinct leaves, seeded per instance and node.
            let mut idx: Vec<u32> = (0..n).collect();
            let mut rng = SplitMix64::new(seed ^ (o as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
            for i in 0..k as usize {
                let j = i + rng.below(u64::from(n) - i as u64) as usize;
                idx.swap(i, j);
                push(&leaves[idx[i] as usize]);
            }
        } else {
            leaves[..k as usize].iter().for_each(&mut push);
        }
    }
    let holder = TreeModel {
        leaves: chosen,
        ..empty_model_light(&model.tree)
    };
    let mut mesh = RasterMesh::from_tree(
        &holder,
        &TreeMeshOptions {
            bark: false,
            ..TreeMeshOptions::default()
        },
    );
    for mt in &mut mesh.material_of_triangle {
        *mt += model.mat_offset;
    }
    mesh
}

/// A model shell without branches (leaf meshes need only the materials).
fn empty_model_light(tree: &DecodedTree) -> TreeModel {
    TreeModel {
        name: String::new(),
        branches: Vec::new(),
        leaves: Vec::new(),
        bark_mesh: canopy_shared::model::TriangleMesh::default(),
        materials: tree.materials.clone(),
        iterations: tree.directory.iterations,
        source: tree.directory.source,
    }
}

/// A rendered view: composited colour (sRGB RGBA, straight alpha) and coverage.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
    /// Colour.
    pub color: Vec<[u8; 4]>,
    /// Covered pixels.
    pub covered: Vec<bool>,
    /// Triangles rendered.
    pub triangles: u64,
}

fn raster_camera(cam: &Camera, vp: &Viewport) -> RasterCamera {
    RasterCamera::look_at(
        cam.eye,
        cam.eye + cam.forward(),
        if cam.forward().cross(Vec3::Y).length_squared() < 1e-8 {
            Vec3::Z
        } else {
            Vec3::Y
        },
        Projection::Perspective {
            fov_y: vp.fov_y,
            near: vp.near.max(0.05),
            far: vp.far,
        },
    )
}

/// Most triangles the rasterizer prepares at once; larger scenes (a forest at full detail) render
/// in several passes merged by depth, with the same result (`render_in_passes`). About 0.5 GB of
/// prepared triangles.
pub const RENDER_PASS_TRIANGLES: usize = 4_000_000;

/// Renders `trees` as `mode` says, from `cam`, at `width × height`.
pub fn render_view(
    scene: &mut EvalScene,
    trees: &[DrawnTree],
    mode: RenderMode,
    cam: &Camera,
    vp: &Viewport,
    width: u32,
    height: u32,
) -> Result<View, EvalError> {
    let rcam = raster_camera(cam, vp);
    // Billboard quads first (they need &mut scene for textures), then geometry.
    let mut bb = QuadBatch::default();
    let mut bb_ids: HashMap<TextureKey, TextureId> = HashMap::new();
    let mut leaf_meshes: Vec<(usize, Mat4, RasterMesh)> = Vec::new();
    // Every leaf (full detail, or a tree drawn whole): all such instances of a model share one
    // mesh, so a forest at full detail holds one copy per model, not per tree.
    let mut full_leaf_instances: Vec<(usize, Mat4)> = Vec::new();
    let mut hulls: Vec<(usize, Mat4, usize)> = Vec::new();
    let mut bark: Vec<(usize, Mat4, usize)> = Vec::new();
    // Metres per pixel at distance 1.
    let pixel_per_metre = 2.0 * (vp.fov_y * 0.5).tan() / height.max(1) as f32;
    for t in trees {
        let m = usize::from(t.instance.model);
        if !scene.has(m) {
            continue;
        }
        let xf = t.instance.placement().0;
        let what = match mode {
            RenderMode::Full => Drawn::Geometry {
                leaves: Vec::new(),
                enlargement_cap: 1.0,
            },
            RenderMode::AsDrawn { .. } => t.what.clone(),
        };
        match what {
            Drawn::Geometry {
                leaves,
                enlargement_cap: budget_cap,
            } => {
                let Some(model) = scene.models[m].as_ref() else {
                    continue;
                };
                match mode {
                    RenderMode::AsDrawn { choice, enlarge } if !keeps_every_leaf(model, &leaves) => leaf_meshes.push((
                        m,
                        xf,
                        leaves_mesh(
                            model,
                            Some(leaves.as_slice()),
                            choice,
                            enlargement_cap(enlarge, budget_cap),
                            u64::from(t.instance.id),
                        ),
                    )),
                    // Every leaf: the same mesh whatever the choice (and no enlargement).
                    _ => full_leaf_instances.push((m, xf)),
                }
                let s = xf.to_scale_rotation_translation().0.x;
                let dir = &model.tree.directory;
                let c = xf.transform_point3(0.5 * (dir.bounds_min + dir.bounds_max));
                let r = 0.5 * (dir.bounds_max - dir.bounds_min).length() * s;
                let d = crate::lod::sphere_distance(cam.eye, c, r);
                let allowed = BARK_MIN_PIXELS * pixel_per_metre * d / s;
                let variant = BARK_MIN_RADII.iter().rposition(|&t| t <= allowed).unwrap_or(0);
                bark.push((m, xf, variant));
            }
            Drawn::Hull { level } => {
                let Some(model) = scene.models[m].as_ref() else {
                    continue;
                };
                if usize::from(level) < model.hulls.len() {
                    hulls.push((m, xf, usize::from(level)));
                }
            }
            Drawn::Cloud { levels } => {
                // Cross-fading levels take complementary screen-door ranges, as on the GPU.
                let mut lo = 0.0f32;
                for (k, &(level, w)) in levels.iter().enumerate() {
                    let hi = if k + 1 == levels.len() { 1.0 } else { (lo + w).min(1.0) };
                    for (p, q) in scene.cloud_level(m, level) {
                        let Some(tex) = batch_texture(&mut bb, &mut bb_ids, TextureKey::Cloud(m, p), scene) else {
                            continue;
                        };
                        let n = xf.transform_vector3(q.normal).normalize_or_zero();
                        let corners = q.corners().map(|p| xf.transform_point3(p));
                        bb.push(tex, corners, CLOUD_QUAD_UVS, n, [lo, hi]);
                    }
                    lo = hi;
                }
            }
            Drawn::Billboard { kind, frames } => {
                // Crossed: both quads. Else the frame of largest weight: the GPU blends up to
                // three, and splitting the pixels between them here (screen-door) scored lower
                // against the GPU's blend than the heaviest frame alone (SSIM 0.869 against 0.886
                // from straight above).
                let picks: Vec<(u32, u8)> = if kind == BillboardKind::Crossed {
                    frames.iter().map(|&(f, r, _)| (f, r)).collect()
                } else {
                    frames
                        .iter()
                        .max_by(|a, b| a.2.total_cmp(&b.2))
                        .map(|&(f, r, _)| (f, r))
                        .into_iter()
                        .collect()
                };
                for (frame, res) in picks {
                    let Some((ru, rv, _center, radius, dir)) = scene.billboard_texture(m, frame, res) else {
                        continue;
                    };
                    let Some(tex) = batch_texture(&mut bb, &mut bb_ids, TextureKey::Atlas(m, frame, res), scene) else {
                        continue;
                    };
                    let (center, right, up) = billboard_quad(t, dir, radius, (ru, rv));
                    let fwd = up.cross(right).normalize_or_zero();
                    let (right, up) = (right.normalize_or_zero(), up.normalize_or_zero());
                    let r = radius * xf.to_scale_rotation_translation().0.x;
                    // Top-left, bottom-left, bottom-right, top-right; uv row 0 at the top.
                    bb.push(
                        tex,
                        [
                            center - right * r + up * r,
                            center - right * r - up * r,
                            center + right * r - up * r,
                            center + right * r + up * r,
                        ],
                        [[0.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, 0.0]],
                        -fwd,
                        FULL_COVERAGE,
                    );
                }
            }
        }
    }
    let mut instances: Vec<Instance<'_>> = Vec::new();
    for &(m, xf, variant) in &bark {
        if let Some(model) = scene.models[m].as_ref() {
            instances.push(Instance {
                mesh: &model.bark[variant],
                transform: xf,
                items: ItemMap::Keep,
            });
        }
    }
    for (_, xf, mesh) in &leaf_meshes {
        instances.push(Instance {
            mesh,
            transform: *xf,
            items: ItemMap::Keep,
        });
    }
    for &(m, xf) in &full_leaf_instances {
        if let Some(model) = scene.models[m].as_ref() {
            instances.push(Instance {
                mesh: model
                    .full_leaves
                    .get_or_init(|| leaves_mesh(model, None, LeafChoice::Prefix, 1.0, 0)),
                transform: xf,
                items: ItemMap::Keep,
            });
        }
    }
    for &(m, xf, level) in &hulls {
        if let Some(model) = scene.models[m].as_ref() {
            instances.push(Instance {
                mesh: &model.hulls[level],
                transform: xf,
                items: ItemMap::Keep,
            });
        }
    }
    let geo_scene = Scene {
        instances,
        materials: &scene.materials,
        textures: &scene.textures,
    };
    let triangles = geo_scene.triangle_count() as u64 + bb.mesh.triangle_count() as u64;
    let lit = RenderOptions::default();
    let geo = render_in_passes(&geo_scene, &rcam, width, height, &lit, RENDER_PASS_TRIANGLES)?;
    let mut out = View {
        width,
        height,
        color: geo.color.clone(),
        covered: geo.depth.iter().map(|d| d.is_finite()).collect(),
        triangles,
    };
    if !bb.mesh.indices.is_empty() {
        let bb: Frame = render(&bb.scene(), &rcam, width, height, &RenderOptions::unlit())?;
        for i in 0..out.color.len() {
            if bb.depth[i] < geo.depth[i] {
                out.color[i] = bb.color[i];
                out.covered[i] = true;
            }
        }
    }
    Ok(out)
}

/// Quality of one view against the reference.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Quality {
    /// Colour SSIM (min over R, G, B) over [`BACKGROUND`].
    pub ssim: f64,
    /// Coverage precision.
    pub precision: f64,
    /// Coverage recall.
    pub recall: f64,
}

/// SSIM and coverage of `view` against `reference`.
pub fn quality(reference: &View, view: &View) -> Result<Quality, EvalError> {
    let ssim = ssim_rgba(&reference.color, &view.color, view.width, view.height, BACKGROUND)?;
    let c = coverage(&reference.covered, &view.covered)?;
    Ok(Quality {
        ssim,
        precision: c.precision,
        recall: c.recall,
    })
}

fn luminance(p: [u8; 4]) -> f32 {
    let a = f32::from(p[3]) / 255.0;
    let c = |i: usize| (f32::from(p[i]) * a + f32::from(BACKGROUND[i]) * (1.0 - a)) / 255.0;
    0.2126 * c(0) + 0.7152 * c(1) + 0.0722 * c(2)
}

/// Temporal popping: the mean over pixels of the frame-to-frame luminance change of the method
/// beyond the reference's own change, `max(0, |M_t − M_{t−1}| − |R_t − R_{t−1}|)`, in [0, 1].
/// Camera motion changes both alike and cancels; what is left is the method's own flicker.
pub fn popping(ref_prev: &View, ref_now: &View, prev: &View, now: &View) -> f64 {
    let n = now
        .color
        .len()
        .min(prev.color.len())
        .min(ref_now.color.len())
        .min(ref_prev.color.len());
    if n == 0 {
        return 0.0;
    }
    let mut sum = 0.0f64;
    for i in 0..n {
        let dm = (luminance(now.color[i]) - luminance(prev.color[i])).abs();
        let dr = (luminance(ref_now.color[i]) - luminance(ref_prev.color[i])).abs();
        sum += f64::from((dm - dr).max(0.0));
    }
    sum / n as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view(c: [u8; 4], cov: bool) -> View {
        View {
            width: 8,
            height: 8,
            color: vec![c; 64],
            covered: vec![cov; 64],
            triangles: 0,
        }
    }

    #[test]
    fn popping_cancels_the_reference_change() {
        let a = view([0, 0, 0, 255], true);
        let b = view([255, 255, 255, 255], true);
        // The reference changes as much as the method: no popping.
        assert_eq!(popping(&a, &b, &a, &b), 0.0);
        // Reference still, method flips black to white: full popping.
        assert!((popping(&a, &a, &a, &b) - 1.0).abs() < 1e-6);
        // Method still while the reference moves: not popping (clamped at 0).
        assert_eq!(popping(&a, &b, &a, &a), 0.0);
    }

    #[test]
    fn identical_views_have_perfect_quality() {
        let a = view([10, 120, 30, 255], true);
        let q = quality(&a, &a).expect("quality");
        assert!((q.ssim - 1.0).abs() < 1e-9 && q.precision == 1.0 && q.recall == 1.0);
    }
}

/// The usual alternative to progressive streaming: a few discrete LOD files per model, each
/// downloaded whole the first time a tree needs it, then kept (no eviction, which favours it).
///
/// Levels (rates are seed 004 simplification rates, leaves chosen in the file's order):
///
/// | level | content | used while the tree's projected height is |
/// |---|---|---|
/// | 0 | every leaf | ≥ 4·g px |
/// | 1 | rate 0.75 (a quarter of the leaves) | ≥ 2·g px |
/// | 2 | rate 0.9375 | ≥ g px |
/// | 3 | crossed-quad billboard (seed 000), top resolution | below |
///
/// `g` is the projected height down to which Canopy's ladder draws geometry (150 px by
/// default), so both methods switch to images at the same size.
///
/// A geometry level's file size is what it must hold in Canopy's own compact encoding (index,
/// node table, materials, skeleton, bark mesh, and the leaves of that rate: the band-major
/// prefix), so the comparison measures granularity and whole-file download, not encoding.
#[derive(Debug, Default)]
pub struct DiscreteLod {
    fetched: std::collections::BTreeSet<(usize, u8)>,
    thresholds: [f32; 3],
    /// Bytes downloaded so far.
    pub bytes: u64,
}

/// Simplification rate of discrete geometry levels 0, 1, 2.
pub const DISCRETE_RATES: [f32; 3] = [0.0, 0.75, 0.9375];
/// Projected-height thresholds of discrete levels 0, 1, 2 as multiples of `g`.
pub const DISCRETE_PX_FACTORS: [f32; 3] = [4.0, 2.0, 1.0];

impl DiscreteLod {
    /// Discrete LOD switching to billboards below `geometry_px` pixels.
    pub fn new(geometry_px: f32) -> Self {
        Self {
            thresholds: DISCRETE_PX_FACTORS.map(|f| f * geometry_px.max(0.0)),
            ..Self::default()
        }
    }

    /// Bytes of model `m`'s level file.
    fn level_bytes(model: &EvalModel, level: u8) -> u64 {
        let dir = &model.tree.directory;
        let sec = |k: SectionKind| dir.section(k).map_or(0, |e| e.length);
        if let Some(&rate) = DISCRETE_RATES.get(usize::from(level)) {
            let counts: Vec<u32> = model.tree.node_leaves.iter().map(|v| v.len() as u32).collect();
            let layout = canopy_shared::format::leaf::BandLayout::new(&dir.band_edges, &counts);
            let leaves = crate::plan::uniform_range(&layout, 0, rate).map_or(0, |r| r.end - r.start);
            let index = dir.section(SectionKind::NodeTable).map_or(0, |e| e.offset);
            index
                + sec(SectionKind::NodeTable)
                + sec(SectionKind::Materials)
                + sec(SectionKind::Skeleton)
                + sec(SectionKind::BarkMesh)
                + leaves
        } else {
            model.atlas.as_ref().map_or(0, |(t, _)| {
                t.layouts
                    .iter()
                    .filter(|l| l.kind == AtlasLayoutKind::CrossedQuads)
                    .flat_map(|l| l.first_frame..l.first_frame + l.frame_count())
                    .filter_map(|f| t.image(f, 0))
                    .map(|e| u64::from(e.length))
                    .sum::<u64>()
                    + 64
            })
        }
    }

    /// Chooses each tree's level from its projected height, downloads level files not yet held
    /// and returns what this method draws. `trees` is the list of visible trees (any
    /// representation; only the instances are used).
    pub fn update(&mut self, scene: &EvalScene, trees: &[DrawnTree], cam: &Camera, vp: &Viewport) -> Vec<DrawnTree> {
        let mut out = Vec::with_capacity(trees.len());
        for t in trees {
            let m = usize::from(t.instance.model);
            let Some(model) = scene.models.get(m).and_then(Option::as_ref) else {
                continue;
            };
            let xf = t.instance.placement().0;
            let s = xf.to_scale_rotation_translation().0.x;
            let dir = &model.tree.directory;
            let (lo, hi) = (dir.bounds_min, dir.bounds_max);
            let c = xf.transform_point3(0.5 * (lo + hi));
            let r = 0.5 * (hi - lo).length() * s;
            let d = crate::lod::sphere_distance(cam.eye, c, r);
            let px = crate::lod::projected_height((hi.y - lo.y.min(0.0)) * s, d, vp.height as f32, vp.fov_y);
            let level = self.thresholds.iter().position(|&p| px >= p).unwrap_or(3) as u8;
            if self.fetched.insert((m, level)) {
                self.bytes += Self::level_bytes(model, level);
            }
            let what = if let Some(&rate) = DISCRETE_RATES.get(usize::from(level)) {
                Drawn::Geometry {
                    leaves: model
                        .tree
                        .node_leaves
                        .iter()
                        .map(|v| canopy_shared::format::leaf::keep_count(v.len() as u32, rate))
                        .collect(),
                    enlargement_cap: 1.0,
                }
            } else {
                let frames = model
                    .atlas
                    .as_ref()
                    .and_then(|(t, _)| t.layouts.iter().find(|l| l.kind == AtlasLayoutKind::CrossedQuads))
                    .map(|l| {
                        (l.first_frame..l.first_frame + l.frame_count())
                            .map(|f| (f, 0u8, 0.5))
                            .collect()
                    })
                    .unwrap_or_default();
                Drawn::Billboard {
                    kind: BillboardKind::Crossed,
                    frames,
                }
            };
            out.push(DrawnTree {
                instance: t.instance.clone(),
                what,
            });
        }
        out
    }
}
