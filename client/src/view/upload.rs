//! GPU copies of what the streamer cached, and one frame's draws from its drawn list.
//!
//! Uploads follow the cache, never the files: a leaf node's leaves go up as its bands arrive
//! (each model has one storage buffer, node after node, so a node's drawn prefix is a
//! contiguous run), bark is tessellated from the cached skeleton per distance variant (fewer
//! tube sides and no thin twigs as distance grows, as the CPU evaluation does), hull levels and
//! billboard frames are uploaded when first drawn. Billboard frames share a texture array whose
//! least recently drawn slot is reused.

use std::collections::HashMap;

use canopy_shared::model::Leaf;
use canopy_shared::tessellate::{TubeOptions, branch_tubes_thicker_than};
use glam::{Mat4, Vec3};

use super::gpu::{
    BILLBOARD_LAYERS, BILLBOARD_SLOT, BillboardInstance, FrameCamera, FrameDraws, GpuLeaf, GpuMesh, LeafDraw,
    LeafStore, MeshInstance, MeshVertex, Renderer, TreeTransform,
};
use crate::eval::{BACKGROUND, BARK_MIN_RADII, billboard_quad, enlargement_cap};
use crate::lod::projection::BillboardKind;
use crate::lod::{leaf_enlargement, sphere_distance};
use crate::net::RangeSource;
use crate::stream::{CachedModel, Camera, Drawn, Streamer, Viewport};

pub use crate::lod::bark::BARK_VARIANT_SIDES;
/// Half side of the ground square, metres.
pub const GROUND_HALF_SIDE: f32 = 5000.0;
/// Ground colour (linear).
pub const GROUND_COLOR: [f32; 4] = [0.16, 0.22, 0.08, 1.0];

/// What the viewer draws beyond the streamer's choices.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewOptions {
    /// Seed 004 leaf enlargement of simplified nodes.
    pub enlarge: bool,
    /// Colour trees by representation (debug view).
    pub color_by_lod: bool,
    /// Draw the ground plane.
    pub ground: bool,
}

impl Default for ViewOptions {
    fn default() -> Self {
        Self {
            enlarge: false,
            color_by_lod: false,
            ground: true,
        }
    }
}

/// Figures of one prepared frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct DrawStats {
    /// Trees drawn as geometry.
    pub geometry_trees: u64,
    /// Trees drawn as hulls.
    pub hull_trees: u64,
    /// Trees drawn as billboards.
    pub billboard_trees: u64,
    /// Trees drawn as billboard clouds.
    pub cloud_trees: u64,
    /// Leaves drawn.
    pub leaves: u64,
    /// Triangles drawn (leaves 2 each, meshes, billboard quads 2 each, ground excluded).
    pub triangles: u64,
    /// Instances submitted (leaves, mesh instances, billboard quads).
    pub instances: u64,
    /// Bytes uploaded to the GPU this frame (leaves, meshes, billboard frames).
    pub upload_bytes: u64,
    /// Billboard frames and cloud levels that found no free texture slot this frame (not drawn).
    pub billboard_slots_full: u64,
}

#[derive(Debug)]
struct GpuModel {
    leaves: LeafStore,
    node_base: Vec<u32>,
    uploaded: Vec<u32>,
    colors: Vec<u32>,
    bark: Vec<Option<GpuMesh>>,
    hulls: Vec<Option<GpuMesh>>,
    crown_color: [f32; 4],
}

/// The viewer's GPU scene.
#[derive(Debug)]
pub struct GpuScene {
    models: Vec<Option<GpuModel>>,
    /// Texture-array layer and last frame drawn of each uploaded image.
    slots: HashMap<SlotKey, (u32, u64)>,
    free_slots: Vec<u32>,
    frame: u64,
    ground: GpuMesh,
    /// The terrain's tiles uploaded so far, and the terrain generation they are of.
    terrain: Vec<Option<GpuMesh>>,
    terrain_generation: u64,
}

/// An image in the billboard texture array.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum SlotKey {
    /// Model, atlas frame, resolution index.
    Atlas(usize, u32, u8),
    /// Model, cloud plane (section-wide index).
    CloudPlane(usize, u32),
}

fn pack_color(c: [f32; 4]) -> u32 {
    let b = |x: f32| (x.clamp(0.0, 1.0) * 255.0).round() as u32;
    b(c[0]) | (b(c[1]) << 8) | (b(c[2]) << 16) | (b(c[3]) << 24)
}

fn gpu_leaf(l: &Leaf, colors: &[u32]) -> GpuLeaf {
    let side = l.side() * (0.5 * l.width);
    let axis = l.axis * (0.5 * l.length);
    let color = colors.get(usize::from(l.material)).copied().unwrap_or(0xff00_ff00);
    GpuLeaf {
        center: [l.center.x, l.center.y, l.center.z, f32::from_bits(color)],
        side: [side.x, side.y, side.z, 0.0],
        axis: [axis.x, axis.y, axis.z, 0.0],
    }
}

fn mesh_vertices(positions: &[Vec3], normals: &[Vec3], color: [f32; 4]) -> Vec<MeshVertex> {
    positions
        .iter()
        .enumerate()
        .map(|(i, p)| MeshVertex {
            pos: p.to_array(),
            normal: normals.get(i).copied().unwrap_or(Vec3::Y).to_array(),
            color,
        })
        .collect()
}

/// Debug colours of the representations (linear RGB, tint strength in alpha), in the order
/// geometry, hull, cloud, hemi-oct, lat-long and crossed billboard: what "colour by LOD" paints.
pub const LOD_COLORS: [(&str, [f32; 4]); 7] = [
    ("geometry", [0.1, 0.85, 0.1, 0.8]),
    ("hull", [0.15, 0.35, 1.0, 0.8]),
    ("cloud", [0.1, 0.9, 0.9, 0.8]),
    ("hemi-oct billboard", [1.0, 0.2, 0.2, 0.8]),
    ("lat-long billboard", [1.0, 0.6, 0.1, 0.8]),
    ("crossed billboard", [0.75, 0.2, 1.0, 0.8]),
    ("views billboard", [1.0, 0.95, 0.2, 0.8]),
];

/// Debug colour of a representation.
fn lod_tint(what: &Drawn, on: bool) -> [f32; 4] {
    if !on {
        return [0.0; 4];
    }
    let k = match what {
        Drawn::Geometry { .. } => 0,
        Drawn::Hull { .. } => 1,
        Drawn::Cloud { .. } => 2,
        Drawn::Billboard { kind, .. } => match kind {
            BillboardKind::HemiOct => 3,
            BillboardKind::LatLong => 4,
            BillboardKind::Crossed => 5,
            BillboardKind::Views => 6,
        },
    };
    LOD_COLORS[k].1
}

impl GpuScene {
    /// An empty scene for a manifest of `models` models.
    pub fn new(device: &wgpu::Device, models: usize) -> Self {
        let h = GROUND_HALF_SIDE;
        let ground = GpuMesh::new(
            device,
            &mesh_vertices(
                &[
                    Vec3::new(-h, 0.0, -h),
                    Vec3::new(h, 0.0, -h),
                    Vec3::new(h, 0.0, h),
                    Vec3::new(-h, 0.0, h),
                ],
                &[Vec3::Y; 4],
                GROUND_COLOR,
            ),
            &[0, 2, 1, 0, 3, 2],
        );
        Self {
            models: (0..models).map(|_| None).collect(),
            slots: HashMap::new(),
            free_slots: (0..BILLBOARD_LAYERS).rev().collect(),
            frame: 0,
            ground,
            terrain: Vec::new(),
            terrain_generation: 0,
        }
    }

    fn model_mut(
        &mut self,
        device: &wgpu::Device,
        renderer: &Renderer,
        m: usize,
        cm: &CachedModel<'_>,
    ) -> Option<&mut GpuModel> {
        let slot = self.models.get_mut(m)?;
        // A model first drawn as a stand-in was uploaded before its geometry part (node table,
        // materials) arrived: made again once it has, with room for every node's leaves.
        let stale = slot
            .as_ref()
            .is_some_and(|g| g.node_base.len() != cm.leaf_counts().len());
        if slot.is_none() || stale {
            let counts = cm.leaf_counts();
            let mut node_base = Vec::with_capacity(counts.len());
            let mut total = 0u32;
            for &c in counts {
                node_base.push(total);
                total = total.saturating_add(c);
            }
            let mats = cm.materials();
            let colors: Vec<u32> = mats.leaf.iter().map(|l| pack_color(l.color)).collect();
            let n = mats.leaf.len().max(1) as f32;
            let mut crown = [0.0f32, 0.0, 0.0, 1.0];
            for l in &mats.leaf {
                for (a, b) in crown.iter_mut().zip(l.color).take(3) {
                    *a += b / n;
                }
            }
            *slot = Some(GpuModel {
                // A model with more leaves than one storage binding holds draws the first ones.
                leaves: renderer.leaf_store(
                    device,
                    total.min((device.limits().max_storage_buffer_binding_size / size_of::<GpuLeaf>() as u64) as u32),
                ),
                uploaded: vec![0; counts.len()],
                node_base,
                colors,
                bark: (0..BARK_MIN_RADII.len()).map(|_| None).collect(),
                hulls: (0..cm.hull_levels()).map(|_| None).collect(),
                crown_color: crown,
            });
        }
        slot.as_mut()
    }

    /// Uploads what the streamer's last drawn list needs and returns the frame's plan (`cam` is
    /// the camera the streamer chose the LOD for: it picks the bark variants).
    #[allow(clippy::too_many_arguments)]
    pub fn prepare<S: RangeSource>(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        renderer: &Renderer,
        streamer: &Streamer<S>,
        cam: &Camera,
        vp: &Viewport,
        opts: &ViewOptions,
    ) -> (FramePlan, DrawStats) {
        self.frame += 1;
        let frame = self.frame;
        let mut stats = DrawStats::default();
        // The terrain's tiles that arrived since the last upload.
        if let Some(t) = streamer.terrain()
            && t.generation != self.terrain_generation
        {
            self.terrain.resize_with(t.records.len(), || None);
            for (k, samples) in t.held_tiles() {
                if self.terrain[k].is_none() {
                    let mesh = crate::terrain::tile_mesh(&t.grid, samples);
                    let v = mesh_vertices(&mesh.positions, &mesh.normals, GROUND_COLOR);
                    self.terrain[k] = Some(GpuMesh::new(device, &v, &mesh.indices));
                }
            }
            self.terrain_generation = t.generation;
        }
        let pixel_per_metre = 2.0 * (vp.fov_y * 0.5).tan() / vp.height.max(1) as f32;
        // Pass 1: uploads, and what each tree will draw.
        let mut plan: Vec<(usize, Mat4, [f32; 4], PlannedTree)> = Vec::new();
        for t in streamer.drawn() {
            let m = usize::from(t.instance.model);
            let Some(cm) = streamer.cached_model(m) else { continue };
            let xf = t.instance.placement().0;
            let tint = lod_tint(&t.what, opts.color_by_lod);
            match &t.what {
                Drawn::Geometry {
                    leaves,
                    enlargement_cap: budget_cap,
                    iterations,
                } => {
                    let cap = enlargement_cap(opts.enlarge, *budget_cap);
                    let Some(gm) = self.model_mut(device, renderer, m, &cm) else {
                        continue;
                    };
                    let mut nodes = Vec::with_capacity(leaves.len());
                    for (o, &k) in leaves.iter().enumerate() {
                        let Some(&base) = gm.node_base.get(o) else { break };
                        let have = gm.uploaded.get(o).copied().unwrap_or(0);
                        if k > have
                            && let Ok(Some(new)) = cm.leaves(o, have, k)
                        {
                            let g: Vec<GpuLeaf> = new.iter().map(|l| gpu_leaf(l, &gm.colors)).collect();
                            gm.leaves.write(queue, base + have, &g);
                            stats.upload_bytes += (g.len() * size_of::<GpuLeaf>()) as u64;
                            gm.uploaded[o] = k;
                        }
                        let room = gm.leaves.capacity().saturating_sub(base);
                        let drawn = k.min(gm.uploaded.get(o).copied().unwrap_or(0)).min(room);
                        if drawn > 0 {
                            let n = cm.leaf_counts()[o];
                            let scale = if cap > 1.0 && drawn < n {
                                leaf_enlargement(0.0, 1.0 - drawn as f32 / n as f32, cap)
                            } else {
                                1.0
                            };
                            nodes.push((base, drawn, scale));
                        }
                    }
                    // Bark variant by distance, as the CPU evaluation picks it.
                    let s = xf.to_scale_rotation_translation().0.x;
                    let (lo, hi) = cm.bounds();
                    let c = xf.transform_point3(0.5 * (lo + hi));
                    let r = 0.5 * (hi - lo).length() * s;
                    let d = sphere_distance(cam.eye, c, r);
                    let thin = crate::lod::bark::bark_variant(pixel_per_metre, d, s);
                    // One bark mesh per (iterations left out, variant).
                    let dropped = usize::from(cm.last_iteration().saturating_sub(*iterations));
                    let variant = dropped * BARK_MIN_RADII.len() + thin;
                    if gm.bark.len() <= variant {
                        gm.bark.resize_with(variant + 1, || None);
                    }
                    if gm.bark[variant].is_none()
                        && let Ok(Some(model)) = cm.bark_model_through(*iterations)
                    {
                        let tubes = branch_tubes_thicker_than(
                            &model,
                            TubeOptions {
                                sides: BARK_VARIANT_SIDES[thin],
                                caps: false,
                            },
                            BARK_MIN_RADII[thin],
                        );
                        let mut pos = tubes.positions.clone();
                        let mut nrm = tubes.normals.clone();
                        nrm.resize(pos.len(), Vec3::Y);
                        let mut idx = tubes.indices.clone();
                        let base = pos.len() as u32;
                        pos.extend_from_slice(&model.bark_mesh.positions);
                        let mut bn = model.bark_mesh.normals.clone();
                        bn.resize(model.bark_mesh.positions.len(), Vec3::Y);
                        nrm.extend_from_slice(&bn);
                        idx.extend(model.bark_mesh.indices.iter().map(|&i| i + base));
                        let verts = mesh_vertices(&pos, &nrm, model.materials.bark_color);
                        stats.upload_bytes += (verts.len() * size_of::<MeshVertex>() + idx.len() * 4) as u64;
                        gm.bark[variant] = Some(GpuMesh::new(device, &verts, &idx));
                    }
                    plan.push((m, xf, tint, PlannedTree::Geometry { nodes, variant }));
                }
                Drawn::Hull { level } => {
                    let Some(gm) = self.model_mut(device, renderer, m, &cm) else {
                        continue;
                    };
                    let l = usize::from(*level);
                    if l < gm.hulls.len()
                        && gm.hulls[l].is_none()
                        && let Ok(Some(h)) = cm.hull(*level)
                    {
                        let normals = vertex_normals(&h.positions, &h.indices);
                        let verts = mesh_vertices(&h.positions, &normals, gm.crown_color);
                        stats.upload_bytes += (verts.len() * size_of::<MeshVertex>() + h.indices.len() * 4) as u64;
                        gm.hulls[l] = Some(GpuMesh::new(device, &verts, &h.indices));
                    }
                    plan.push((m, xf, tint, PlannedTree::Hull(l)));
                }
                Drawn::Billboard { kind, frames } => {
                    let Some(table) = cm.atlas() else { continue };
                    let mut quads: Vec<BillboardInstance> = Vec::new();
                    // Crossed: each frame its own quad. Else one quad facing the heaviest
                    // frame's direction, blending all (up to three).
                    let groups: Vec<Vec<(u32, u8, f32)>> = if *kind == BillboardKind::Crossed {
                        frames.iter().map(|&(f, r, _)| vec![(f, r, 1.0)]).collect()
                    } else {
                        let mut fs = frames.clone();
                        fs.sort_by(|a, b| b.2.total_cmp(&a.2));
                        fs.truncate(3);
                        vec![fs]
                    };
                    for group in groups {
                        let mut layers = [0u32; 3];
                        let mut weights = [0f32; 3];
                        for (i, &(f, r, w)) in group.iter().enumerate() {
                            match self.billboard_slot(queue, renderer, &cm, m, f, r, frame, &mut stats) {
                                Some(layer) => {
                                    layers[i] = layer;
                                    weights[i] = w.max(0.0);
                                }
                                None => stats.billboard_slots_full += 1,
                            }
                        }
                        let sum: f32 = weights.iter().sum();
                        let Some(&(f0, _, _)) = group.first() else { continue };
                        if sum <= 0.0 {
                            continue;
                        }
                        for w in &mut weights {
                            *w /= sum;
                        }
                        let (Some(dir), Some(fr)) = (table.frame_direction(f0), table.frames.get(f0 as usize)) else {
                            continue;
                        };
                        let (center, right, up) = billboard_quad(t, dir, table.radius, (fr.root_u, fr.root_v));
                        quads.push(BillboardInstance {
                            center: center.to_array(),
                            right: right.to_array(),
                            up: up.to_array(),
                            layers,
                            weights,
                            tint,
                            coverage: 1.0,
                        });
                    }
                    plan.push((m, xf, tint, PlannedTree::Billboard(quads)));
                }
                Drawn::Cloud { levels } => {
                    let Some(table) = cm.cloud() else { continue };
                    // The levels whose planes have texture layers this frame.
                    let mut ready: Vec<(std::ops::Range<u32>, Vec<u32>, f32)> = Vec::with_capacity(2);
                    for &(level, w) in levels {
                        let Some(l) = table.levels.get(usize::from(level)) else {
                            continue;
                        };
                        let planes = l.first_plane..l.first_plane + l.plane_count;
                        if let Some(layers) =
                            self.cloud_slots(queue, renderer, &cm, m, level, planes.clone(), frame, &mut stats)
                        {
                            ready.push((planes, layers, w));
                        }
                    }
                    // Two levels cross-fade with complementary screen-door patterns (the first
                    // keeps the dither thresholds below w, the second the rest); a level alone
                    // covers everything.
                    let w0 = ready.first().map_or(1.0, |r| r.2);
                    let mut quads: Vec<BillboardInstance> = Vec::new();
                    for (k, (planes, layers, _)) in ready.iter().enumerate() {
                        let coverage = match (ready.len(), k) {
                            (1, _) => 1.0,
                            (_, 0) => w0,
                            _ => -(1.0 - w0),
                        };
                        for (p, &layer) in planes.clone().zip(layers) {
                            let q = table.planes[p as usize].quad;
                            let (u, v) = (q.edge_u * 0.5, q.edge_v * 0.5);
                            quads.push(BillboardInstance {
                                center: xf.transform_point3(q.origin + u + v).to_array(),
                                right: xf.transform_vector3(u).to_array(),
                                up: xf.transform_vector3(v).to_array(),
                                layers: [layer, 0, 0],
                                weights: [1.0, 0.0, 0.0],
                                tint,
                                coverage,
                            });
                        }
                    }
                    plan.push((m, xf, tint, PlannedTree::Cloud(quads)));
                }
            }
        }
        // Pass 2: the draws, by resource key.
        let mut draws = FramePlan {
            generation: frame,
            ..FramePlan::default()
        };
        let mut leaf_draws: HashMap<usize, Vec<LeafDraw>> = HashMap::new();
        let mut mesh_draws: HashMap<(usize, u8, usize), Vec<MeshInstance>> = HashMap::new();
        for (m, xf, tint, p) in plan {
            let inst = MeshInstance {
                model: xf.to_cols_array_2d(),
                tint,
            };
            match p {
                PlannedTree::Geometry { nodes, variant } => {
                    let Some(gm) = self.models[m].as_ref() else { continue };
                    let tree = draws.trees.len() as u32;
                    draws.trees.push(TreeTransform {
                        model: xf.to_cols_array_2d(),
                        tint,
                    });
                    let list = leaf_draws.entry(m).or_default();
                    for (base, k, scale) in nodes {
                        list.extend((base..base + k).map(|leaf| LeafDraw {
                            leaf,
                            tree,
                            scale,
                            pad: 0,
                        }));
                        stats.leaves += u64::from(k);
                    }
                    if let Some(b) = &gm.bark[variant] {
                        stats.triangles += b.triangles();
                        mesh_draws.entry((m, 0, variant)).or_default().push(inst);
                    }
                    stats.geometry_trees += 1;
                }
                PlannedTree::Hull(l) => {
                    let Some(gm) = self.models[m].as_ref() else { continue };
                    if let Some(Some(h)) = gm.hulls.get(l) {
                        stats.triangles += h.triangles();
                        stats.hull_trees += 1;
                        mesh_draws.entry((m, 1, l)).or_default().push(inst);
                    }
                }
                PlannedTree::Cloud(quads) => {
                    if !quads.is_empty() {
                        stats.cloud_trees += 1;
                    }
                    stats.triangles += 2 * quads.len() as u64;
                    draws.billboards.extend(quads);
                }
                PlannedTree::Billboard(quads) => {
                    if !quads.is_empty() {
                        stats.billboard_trees += 1;
                    }
                    stats.triangles += 2 * quads.len() as u64;
                    draws.billboards.extend(quads);
                }
            }
        }
        stats.triangles += 2 * stats.leaves;
        stats.instances = stats.leaves + draws.billboards.len() as u64;
        let mut leaf_keys: Vec<usize> = leaf_draws.keys().copied().collect();
        leaf_keys.sort_unstable();
        for m in leaf_keys {
            if let Some(list) = leaf_draws.remove(&m) {
                draws.leaves.push((m, list));
            }
        }
        let mut mesh_keys: Vec<(usize, u8, usize)> = mesh_draws.keys().copied().collect();
        mesh_keys.sort_unstable();
        for key in mesh_keys {
            if let Some(list) = mesh_draws.remove(&key) {
                stats.instances += list.len() as u64;
                draws.meshes.push((MeshKey::Model(key.0, key.1, key.2), list));
            }
        }
        let flat = streamer.terrain().is_none();
        for k in (0..self.terrain.len()).filter(|&k| opts.ground && self.terrain[k].is_some()) {
            draws.meshes.push((
                MeshKey::Terrain(k),
                vec![MeshInstance {
                    model: Mat4::IDENTITY.to_cols_array_2d(),
                    tint: [0.0; 4],
                }],
            ));
        }
        if opts.ground && flat {
            draws.meshes.push((
                MeshKey::Ground,
                vec![MeshInstance {
                    model: Mat4::IDENTITY.to_cols_array_2d(),
                    tint: [0.0; 4],
                }],
            ));
        }
        (draws, stats)
    }

    /// The GPU resources of `plan` (keys whose resource is gone are skipped).
    pub fn draws<'a>(&'a self, plan: &'a FramePlan) -> FrameDraws<'a> {
        let mut out = FrameDraws {
            generation: plan.generation,
            trees: &plan.trees,
            billboards: &plan.billboards,
            ..FrameDraws::default()
        };
        for (m, list) in &plan.leaves {
            if let Some(Some(gm)) = self.models.get(*m) {
                out.leaves.push((&gm.leaves, list));
            }
        }
        for (key, list) in &plan.meshes {
            let mesh =
                match *key {
                    MeshKey::Ground => Some(&self.ground),
                    MeshKey::Terrain(k) => self.terrain.get(k).and_then(Option::as_ref),
                    MeshKey::Model(m, kind, i) => self.models.get(m).and_then(Option::as_ref).and_then(|gm| {
                        if kind == 0 { gm.bark.get(i) } else { gm.hulls.get(i) }.and_then(Option::as_ref)
                    }),
                };
            if let Some(mesh) = mesh {
                out.meshes.push((mesh, list));
            }
        }
        out
    }

    #[allow(clippy::too_many_arguments)]
    fn billboard_slot(
        &mut self,
        queue: &wgpu::Queue,
        renderer: &Renderer,
        cm: &CachedModel<'_>,
        m: usize,
        frame_id: u32,
        res: u8,
        frame: u64,
        stats: &mut DrawStats,
    ) -> Option<u32> {
        let key = SlotKey::Atlas(m, frame_id, res);
        if let Some(e) = self.slots.get_mut(&key) {
            e.1 = frame;
            return Some(e.0);
        }
        let img = cm.atlas_image(frame_id, res).ok()??;
        let layer = self.take_slot(frame)?;
        self.fill_slot(queue, renderer, key, layer, &img, frame, stats);
        Some(layer)
    }

    /// The layers of every plane of cloud level `level` (`planes`, section-wide), uploading the
    /// level when a plane lacks one; `None` (nothing drawn) while the level is not cached or the
    /// array has no room for all its planes this frame.
    #[allow(clippy::too_many_arguments)]
    fn cloud_slots(
        &mut self,
        queue: &wgpu::Queue,
        renderer: &Renderer,
        cm: &CachedModel<'_>,
        m: usize,
        level: u8,
        planes: std::ops::Range<u32>,
        frame: u64,
        stats: &mut DrawStats,
    ) -> Option<Vec<u32>> {
        if planes.len() > BILLBOARD_LAYERS as usize {
            // Can never fit: not drawn, and no slot is given up for it.
            stats.billboard_slots_full += 1;
            return None;
        }
        let held: Option<Vec<u32>> = planes
            .clone()
            .map(|p| self.slots.get(&SlotKey::CloudPlane(m, p)).map(|e| e.0))
            .collect();
        if let Some(layers) = held {
            for p in planes {
                if let Some(e) = self.slots.get_mut(&SlotKey::CloudPlane(m, p)) {
                    e.1 = frame;
                }
            }
            return Some(layers);
        }
        let images = cm.cloud_level(level).ok()??;
        let mut layers = Vec::with_capacity(images.len());
        for (p, img) in planes.zip(&images) {
            let key = SlotKey::CloudPlane(m, p);
            let layer = if let Some(e) = self.slots.get_mut(&key) {
                e.1 = frame;
                e.0
            } else {
                let Some(layer) = self.take_slot(frame) else {
                    stats.billboard_slots_full += 1;
                    return None;
                };
                self.fill_slot(queue, renderer, key, layer, img, frame, stats);
                layer
            };
            layers.push(layer);
        }
        Some(layers)
    }

    /// A free layer, or the least recently drawn one (never one drawn this frame).
    fn take_slot(&mut self, frame: u64) -> Option<u32> {
        if let Some(l) = self.free_slots.pop() {
            return Some(l);
        }
        let (&old, &(layer, last)) = self.slots.iter().min_by_key(|(_, (_, last))| *last)?;
        if last == frame {
            return None;
        }
        self.slots.remove(&old);
        Some(layer)
    }

    /// Uploads `img` (resampled to the slot size) into `layer` and records it under `key`.
    #[allow(clippy::too_many_arguments)]
    fn fill_slot(
        &mut self,
        queue: &wgpu::Queue,
        renderer: &Renderer,
        key: SlotKey,
        layer: u32,
        img: &image::RgbaImage,
        frame: u64,
        stats: &mut DrawStats,
    ) {
        let resized;
        let img = if img.width() == BILLBOARD_SLOT && img.height() == BILLBOARD_SLOT {
            img
        } else {
            resized = image::imageops::resize(
                img,
                BILLBOARD_SLOT,
                BILLBOARD_SLOT,
                image::imageops::FilterType::Triangle,
            );
            &resized
        };
        renderer.write_billboard(queue, layer, img.as_raw());
        stats.upload_bytes += img.as_raw().len() as u64;
        self.slots.insert(key, (layer, frame));
    }
}

/// Which uploaded mesh a list of instances draws.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshKey {
    /// The ground plane.
    Ground,
    /// Terrain tile `0` (index into the manifest's terrain tiles).
    Terrain(usize),
    /// Model `0`: bark variant (kind 0) or hull level (kind 1) `2`.
    Model(usize, u8, usize),
}

/// One frame's draws by resource key: kept across UI frames and drawn from any camera.
#[derive(Debug, Clone, Default)]
pub struct FramePlan {
    /// Distinct per prepared plan (see [`FrameDraws::generation`]).
    pub generation: u64,
    /// Tree transforms.
    pub trees: Vec<TreeTransform>,
    /// Leaf draws per model.
    pub leaves: Vec<(usize, Vec<LeafDraw>)>,
    /// Mesh instances per mesh.
    pub meshes: Vec<(MeshKey, Vec<MeshInstance>)>,
    /// Billboard quads.
    pub billboards: Vec<BillboardInstance>,
}

#[derive(Debug)]
enum PlannedTree {
    Geometry {
        nodes: Vec<(u32, u32, f32)>,
        variant: usize,
    },
    Hull(usize),
    Billboard(Vec<BillboardInstance>),
    Cloud(Vec<BillboardInstance>),
}

/// Area-weighted vertex normals of a triangle mesh (hull levels carry none).
pub fn vertex_normals(positions: &[Vec3], indices: &[u32]) -> Vec<Vec3> {
    let mut n = vec![Vec3::ZERO; positions.len()];
    for t in indices.chunks_exact(3) {
        let (a, b, c) = (t[0] as usize, t[1] as usize, t[2] as usize);
        let (Some(&pa), Some(&pb), Some(&pc)) = (positions.get(a), positions.get(b), positions.get(c)) else {
            continue;
        };
        let f = (pb - pa).cross(pc - pa);
        n[a] += f;
        n[b] += f;
        n[c] += f;
    }
    n.iter().map(|v| v.normalize_or(Vec3::Y)).collect()
}

/// Camera and lighting of the viewer (the CPU rasterizer's default lighting, [`BACKGROUND`] sky).
pub fn frame_camera(cam: &Camera, vp: &Viewport) -> FrameCamera {
    let l = canopy_shared::raster::Lighting::default();
    let vp = Viewport {
        near: vp.near.max(0.05),
        ..*vp
    };
    FrameCamera {
        view_proj: vp.projection() * cam.view(),
        sun_direction: l.sun_direction,
        sun: l.sun,
        ambient: l.ambient,
        clear: BACKGROUND,
    }
}
