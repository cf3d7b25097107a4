//! Rendering one view for evaluation: what each tree is drawn as, gathered representation by
//! representation (geometry leaves and bark, crown hulls, billboard-cloud planes, billboard
//! quads), then one lit pass for geometry and hulls and one unlit pass for the textured quads,
//! composited by depth.
//!
//! Conventions: world axes as the streamer's (Y up, metres, radians); an instance's placement is
//! [`canopy_shared::pack::PackInstance::placement`]; images are sRGB RGBA.

use std::collections::HashMap;

use canopy_shared::format::cloud::CLOUD_QUAD_UVS;
use canopy_shared::format::tree::DecodedTree;
use canopy_shared::model::{Leaf, TreeModel};
use canopy_shared::raster::{
    Camera as RasterCamera, FULL_COVERAGE, Frame, Instance, ItemMap, Projection, QuadBatch, RasterMesh, RenderOptions,
    Scene, TextureId, TreeMeshOptions, render, render_in_passes,
};
use canopy_shared::rng::SplitMix64;
use glam::{Mat4, Quat, Vec3};

use super::{EvalError, EvalModel, EvalScene, LeafChoice, TERRAIN_ITEM, enlargement_cap};
use crate::lod::leaf_enlargement;
use crate::lod::projection::BillboardKind;
use crate::stream::{Camera, Drawn, DrawnTree, Viewport};

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
    render_view_with_trees(scene, trees, mode, cam, vp, width, height).map(|(v, _)| v)
}

/// [`render_view`], with the tree seen at each pixel: the instance id
/// ([`canopy_shared::pack::PackInstance::id`]) of the front-most surface, or
/// [`canopy_shared::raster::EMPTY_ITEM`] where no tree is. The rasterizer's item buffer carries
/// it (every triangle of a tree gets its instance id as item), so it costs nothing extra.
pub fn render_view_with_trees(
    scene: &mut EvalScene,
    trees: &[DrawnTree],
    mode: RenderMode,
    cam: &Camera,
    vp: &Viewport,
    width: u32,
    height: u32,
) -> Result<(View, Vec<u32>), EvalError> {
    let rcam = raster_camera(cam, vp);
    let mut lists = DrawLists {
        // Metres per pixel at distance 1.
        pixel_per_metre: 2.0 * (vp.fov_y * 0.5).tan() / height.max(1) as f32,
        ..DrawLists::default()
    };
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
                iterations: u8::MAX,
            },
            RenderMode::AsDrawn { .. } => t.what.clone(),
        };
        match what {
            Drawn::Geometry {
                leaves,
                enlargement_cap: budget_cap,
                iterations,
            } => lists.geometry(scene, t, xf, (&leaves, iterations), budget_cap, mode, cam),
            Drawn::Hull { level } => lists.hull(scene, m, xf, level, t.instance.id),
            Drawn::Cloud { levels } => lists.cloud(scene, m, xf, &levels, t.instance.id),
            Drawn::Billboard { kind, frames } => lists.billboard(scene, t, xf, kind, &frames),
        }
    }
    lists.render(scene, &rcam, width, height)
}

/// One view's draws, gathered tree by tree, per representation.
#[derive(Default)]
struct DrawLists {
    /// Metres per pixel at distance 1 (the bark variant's choice).
    pixel_per_metre: f32,
    /// Textured quads (billboards and cloud planes), drawn unlit.
    bb: QuadBatch,
    bb_ids: HashMap<TextureKey, TextureId>,
    /// Trees drawn with some of their leaves: a mesh each, with the instance id.
    leaf_meshes: Vec<(usize, Mat4, RasterMesh, u32)>,
    /// Every leaf (full detail, or a tree drawn whole): all such instances of a model share one
    /// mesh, so a forest at full detail holds one copy per model, not per tree.
    full_leaf_instances: Vec<(usize, Mat4, u32)>,
    /// `(model, placement, hull level, instance id)`.
    hulls: Vec<(usize, Mat4, usize, u32)>,
    /// `(model, placement, bark variant, skeleton iterations drawn, instance id)`.
    bark: Vec<(usize, Mat4, usize, u8, u32)>,
}

impl DrawLists {
    /// A tree drawn as geometry: its kept leaves (seed 004's enlargement up to the cap) and the
    /// coarsest bark variant whose dropped twigs stay under [`BARK_MIN_PIXELS`](crate::lod::bark::BARK_MIN_PIXELS).
    #[allow(clippy::too_many_arguments)] // One tree's draw: each argument is read once.
    fn geometry(
        &mut self,
        scene: &EvalScene,
        t: &DrawnTree,
        xf: Mat4,
        (leaves, iterations): (&[u32], u8),
        budget_cap: f32,
        mode: RenderMode,
        cam: &Camera,
    ) {
        let m = usize::from(t.instance.model);
        let id = t.instance.id;
        let Some(model) = scene.models[m].as_ref() else {
            return;
        };
        match mode {
            RenderMode::AsDrawn { choice, enlarge } if !keeps_every_leaf(model, leaves) => self.leaf_meshes.push((
                m,
                xf,
                leaves_mesh(
                    model,
                    Some(leaves),
                    choice,
                    enlargement_cap(enlarge, budget_cap),
                    u64::from(id),
                ),
                id,
            )),
            // Every leaf: the same mesh whatever the choice (and no enlargement).
            _ => self.full_leaf_instances.push((m, xf, id)),
        }
        let s = xf.to_scale_rotation_translation().0.x;
        let dir = &model.tree.directory;
        let c = xf.transform_point3(0.5 * (dir.bounds_min + dir.bounds_max));
        let r = 0.5 * (dir.bounds_max - dir.bounds_min).length() * s;
        let d = crate::lod::sphere_distance(cam.eye, c, r);
        let variant = crate::lod::bark::bark_variant(self.pixel_per_metre, d, s);
        self.bark.push((m, xf, variant, iterations, id));
    }

    /// A tree drawn as a crown hull level (when the model has it).
    fn hull(&mut self, scene: &EvalScene, m: usize, xf: Mat4, level: u16, id: u32) {
        let Some(model) = scene.models[m].as_ref() else {
            return;
        };
        if usize::from(level) < model.hulls.len() {
            self.hulls.push((m, xf, usize::from(level), id));
        }
    }

    /// Adds a textured quad of tree `id` to the billboard batch.
    fn push_quad(&mut self, id: u32, tex: TextureId, corners: [Vec3; 4], uvs: [[f32; 2]; 4], n: Vec3, cov: [f32; 2]) {
        if self.bb.push(tex, corners, uvs, n, cov) {
            let items = &mut self.bb.mesh.item_of_triangle;
            let k = items.len() - 2;
            items[k..].fill(id);
        }
    }

    /// A tree drawn as billboard-cloud levels: cross-fading levels take complementary
    /// screen-door ranges, as on the GPU.
    fn cloud(&mut self, scene: &mut EvalScene, m: usize, xf: Mat4, levels: &[(u8, f32)], id: u32) {
        let mut lo = 0.0f32;
        for (k, &(level, w)) in levels.iter().enumerate() {
            let hi = if k + 1 == levels.len() { 1.0 } else { (lo + w).min(1.0) };
            for (p, q) in scene.cloud_level(m, level) {
                let Some(tex) = batch_texture(&mut self.bb, &mut self.bb_ids, TextureKey::Cloud(m, p), scene) else {
                    continue;
                };
                let n = xf.transform_vector3(q.normal).normalize_or_zero();
                let corners = q.corners().map(|p| xf.transform_point3(p));
                self.push_quad(id, tex, corners, CLOUD_QUAD_UVS, n, [lo, hi]);
            }
            lo = hi;
        }
    }

    /// A tree drawn as a billboard. Crossed: both quads. Else the frame of largest weight: the
    /// GPU blends up to three, and splitting the pixels between them here (screen-door) scored
    /// lower against the GPU's blend than the heaviest frame alone (SSIM 0.869 against 0.886
    /// from straight above).
    fn billboard(
        &mut self,
        scene: &mut EvalScene,
        t: &DrawnTree,
        xf: Mat4,
        kind: BillboardKind,
        frames: &[(u32, u8, f32)],
    ) {
        let m = usize::from(t.instance.model);
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
            let Some(tex) = batch_texture(&mut self.bb, &mut self.bb_ids, TextureKey::Atlas(m, frame, res), scene)
            else {
                continue;
            };
            let (center, right, up) = billboard_quad(t, dir, radius, (ru, rv));
            let fwd = up.cross(right).normalize_or_zero();
            let (right, up) = (right.normalize_or_zero(), up.normalize_or_zero());
            let r = radius * xf.to_scale_rotation_translation().0.x;
            // Top-left, bottom-left, bottom-right, top-right; uv row 0 at the top.
            self.push_quad(
                t.instance.id,
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

    /// Renders the gathered draws: bark, partial leaves, full leaves and hulls lit in one pass,
    /// the textured quads unlit in another, composited by depth.
    fn render(
        self,
        scene: &EvalScene,
        rcam: &RasterCamera,
        width: u32,
        height: u32,
    ) -> Result<(View, Vec<u32>), EvalError> {
        let mut instances: Vec<Instance<'_>> = Vec::new();
        for &(m, xf, variant, iterations, id) in &self.bark {
            if let Some(model) = scene.models[m].as_ref() {
                instances.push(Instance {
                    mesh: if iterations >= model.last_iteration() {
                        &model.bark[variant]
                    } else {
                        model.bark_through(iterations, variant)
                    },
                    transform: xf,
                    items: ItemMap::Constant(id),
                });
            }
        }
        for (_, xf, mesh, id) in &self.leaf_meshes {
            instances.push(Instance {
                mesh,
                transform: *xf,
                items: ItemMap::Constant(*id),
            });
        }
        for &(m, xf, id) in &self.full_leaf_instances {
            if let Some(model) = scene.models[m].as_ref() {
                instances.push(Instance {
                    mesh: model
                        .full_leaves
                        .get_or_init(|| leaves_mesh(model, None, LeafChoice::Prefix, 1.0, 0)),
                    transform: xf,
                    items: ItemMap::Constant(id),
                });
            }
        }
        for &(m, xf, level, id) in &self.hulls {
            if let Some(model) = scene.models[m].as_ref() {
                instances.push(Instance {
                    mesh: &model.hulls[level],
                    transform: xf,
                    items: ItemMap::Constant(id),
                });
            }
        }
        if let Some(mesh) = scene.terrain() {
            instances.push(Instance {
                mesh,
                transform: Mat4::IDENTITY,
                items: ItemMap::Keep,
            });
        }
        let geo_scene = Scene {
            instances,
            materials: &scene.materials,
            textures: &scene.textures,
        };
        // The trees' triangles (the terrain's left out).
        let triangles = geo_scene.triangle_count() as u64 + self.bb.mesh.triangle_count() as u64
            - scene.terrain().map_or(0, |m| m.triangle_count() as u64);
        let lit = RenderOptions::default();
        let geo = render_in_passes(&geo_scene, rcam, width, height, &lit, RENDER_PASS_TRIANGLES)?;
        let mut out = View {
            width,
            height,
            color: geo.color.clone(),
            // Tree pixels: the terrain's are not.
            covered: geo
                .depth
                .iter()
                .zip(&geo.item)
                .map(|(d, &item)| d.is_finite() && item != TERRAIN_ITEM)
                .collect(),
            triangles,
        };
        let mut trees = geo.item;
        for t in trees.iter_mut().filter(|t| **t == TERRAIN_ITEM) {
            *t = canopy_shared::raster::EMPTY_ITEM;
        }
        if !self.bb.mesh.indices.is_empty() {
            let bb: Frame = render(&self.bb.scene(), rcam, width, height, &RenderOptions::unlit())?;
            for (i, tree) in trees.iter_mut().enumerate() {
                if bb.depth[i] < geo.depth[i] {
                    out.color[i] = bb.color[i];
                    out.covered[i] = true;
                    *tree = bb.item[i];
                }
            }
        }
        Ok((out, trees))
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
