//! The client frame loop: from a camera to the bytes the LOD needs, fetched and checked.
//!
//! Every frame, for a scene opened from its manifest:
//!
//! 1. **Tiles.** Instance tiles within the view distance of the camera that are not yet loaded
//!    are fetched from the version's pack (one multi-range request) and checked (CRC-32 each).
//! 2. **Models.** A model used by a nearby instance is opened: one request for the header and
//!    directory (`FIRST_REQUEST_LEN`), then one for the node table, materials and the hull and
//!    atlas tables.
//! 3. **LOD.** Each instance is frustum-culled by its bounding sphere; its representation comes
//!    from its projected height (seed 000's ladder, [`crate::lod::projection`]) or, with the
//!    flight policy, from seed 002's level ([`crate::lod::flight`]). A tree drawn as geometry gets
//!    per-leaf-node rates (seed 004, [`crate::lod::rate`] through switch control); culled nodes
//!    keep nothing.
//! 4. **Plan.** Per model, the needs of all its instances are merged (a leaf node needs the most
//!    leaves any instance draws of it), cached blocks are dropped, leaf blocks become merged
//!    ranges ([`crate::plan`]), and every other block (skeleton iterations, bark mesh, hull level,
//!    atlas image) is one range. All ranges are ordered by visual gain per byte and cut at the
//!    frame's byte budget, if any.
//! 5. **Fetch.** Each model's ranges go out as one multi-range request (or parallel singles, see
//!    [`crate::net::http`]); every block is checked against its CRC-32 before it enters the
//!    shared cache. A block that fails its check is dropped and counted, never drawn.
//! 6. **Draw.** What each instance can draw *from the cache* is counted: a tree whose geometry
//!    is not there yet falls back to a cached hull or billboard, so a slow or failing server
//!    degrades the picture, never corrupts it.
//!
//! The loop is deterministic for a given scene, camera path and options (instances are visited
//! in id order; fetches complete before the frame ends).

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Arc;
use std::time::Instant;

use bytes::Bytes;
use canopy_shared::format::atlas::{AtlasLayoutKind, AtlasTable, hemi_oct_blend, lat_long_nearest};
use canopy_shared::format::directory::SectionKind;
use canopy_shared::format::hull::HullTable;
use canopy_shared::format::leaf::{BandLayout, decode_block};
use canopy_shared::format::materials::decode_materials;
use canopy_shared::format::node::{NodeKind, decode_nodes};
use canopy_shared::format::tree::decode_index;
use canopy_shared::format::{
    Directory, FIRST_REQUEST_LEN, FormatError, HEADER_LEN, Header, NodeRecord, SectionEntry, check_crc,
};
use canopy_shared::pack::{PackInstance, decode_tile_records};
use futures_util::future::join_all;
use glam::{Mat4, Quat, Vec3};
use serde::Serialize;

use crate::cache::{BlockCache, BlockKey, CacheStats, ModelId};
use crate::lod::projection::{BillboardKind, DEFAULT_LADDER, LadderStep, Representation, choose_representation};
use crate::lod::{
    DepthRange, FlightParams, FlightView, Frustum, LodParams, TreeLodState, projected_height, sphere_distance,
    visible_nodes,
};
use crate::net::{ByteRange, NetError, RangeSource};
use crate::plan::{MERGE_GAP_BYTES, plan_leaf_ranges};
use crate::scene::Manifest;

mod cached;
pub use cached::CachedModel;

/// Bytes asked for when opening a model: header and directory (the directory of the
/// 293,000-leaf linden is 660 bytes with the header).
pub const OPEN_REQUEST_LEN: u64 = 4096;

/// Bark tube sides assumed when counting drawn bark triangles (the viewer's nearest tessellation).
pub const BARK_SIDES: u64 = 6;

/// A camera: eye and orientation. Yaw 0 looks along −Z, positive yaw turns towards +X; pitch is
/// positive upwards. Radians.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Eye position, metres.
    pub eye: Vec3,
    /// Heading, radians.
    pub yaw: f32,
    /// Elevation of the view direction, radians.
    pub pitch: f32,
}

impl Camera {
    /// Unit view direction.
    pub fn forward(&self) -> Vec3 {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        Vec3::new(sy * cp, sp, -cy * cp)
    }

    /// World → view matrix (right-handed, Y up).
    pub fn view(&self) -> Mat4 {
        let f = self.forward();
        let up = if f.cross(Vec3::Y).length_squared() < 1e-8 {
            Vec3::Z
        } else {
            Vec3::Y
        };
        Mat4::look_to_rh(self.eye, f, up)
    }
}

/// Viewport and projection.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Viewport {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels (seed 000's `L`).
    pub height: u32,
    /// Vertical field of view, radians (seed 000's `α`).
    pub fov_y: f32,
    /// Near plane, metres.
    pub near: f32,
    /// View distance: farther instances are neither loaded nor drawn, metres.
    pub far: f32,
}

impl Default for Viewport {
    fn default() -> Self {
        Self {
            width: 1280,
            height: 720,
            fov_y: 60f32.to_radians(),
            near: 0.1,
            far: 1500.0,
        }
    }
}

impl Viewport {
    /// Projection (depth 0..1).
    pub fn projection(&self) -> Mat4 {
        Mat4::perspective_rh(
            self.fov_y,
            self.width as f32 / self.height.max(1) as f32,
            self.near,
            self.far,
        )
    }
}

/// What the stream draws and fetches.
#[derive(Debug, Clone)]
pub struct StreamOptions {
    /// Seed 004 per-node rate parameters.
    pub lod: LodParams,
    /// Seed 000 representation ladder (finest first).
    pub ladder: Vec<LadderStep>,
    /// Seed 002 low-flight policy instead of the ladder, when set.
    pub flight: Option<FlightParams>,
    /// Viewport.
    pub viewport: Viewport,
    /// Cache budget, bytes.
    pub cache_budget: u64,
    /// Most bytes fetched per frame (best gain per byte first); `None`: everything needed.
    pub frame_byte_budget: Option<u64>,
    /// `false`: every visible tree as full geometry at rate 0 (the full-detail baseline).
    pub lod_enabled: bool,
}

impl Default for StreamOptions {
    fn default() -> Self {
        Self {
            lod: LodParams::default(),
            ladder: DEFAULT_LADDER.to_vec(),
            flight: None,
            viewport: Viewport::default(),
            cache_budget: crate::cache::DEFAULT_BUDGET_BYTES,
            frame_byte_budget: None,
            lod_enabled: true,
        }
    }
}

/// What one frame fetched and drew.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct FrameReport {
    /// Frame number from 0.
    pub frame: u64,
    /// Bytes received this frame (bodies, wasted gap bytes included).
    pub bytes: u64,
    /// Requests sent this frame (retries included).
    pub requests: u64,
    /// Retries this frame.
    pub retries: u64,
    /// Fetches that failed after retries this frame.
    pub failures: u64,
    /// Blocks that failed their CRC this frame (dropped).
    pub corrupt_blocks: u64,
    /// Cache payload bytes after the frame.
    pub cache_bytes: u64,
    /// Instances loaded so far (from tiles).
    pub instances_loaded: usize,
    /// Instances inside the view frustum and distance.
    pub visible: usize,
    /// Trees drawn as geometry.
    pub geometry_trees: usize,
    /// Trees drawn as crown hulls.
    pub hull_trees: usize,
    /// Trees drawn as billboards.
    pub billboard_trees: usize,
    /// Visible trees with nothing cached to draw yet.
    pub pending_trees: usize,
    /// Leaves drawn.
    pub leaves: u64,
    /// Triangles drawn (leaves 2 each, bark, hulls, billboard quads).
    pub triangles: u64,
    /// Triangles the visible trees have at full detail.
    pub full_triangles: u64,
    /// Billboard quads drawn (crossed billboards count 2).
    pub billboard_quads: u64,
    /// Leaf nodes of geometry trees by rate in force, 10 bins of 0.1 (last bin includes 1.0).
    pub rate_histogram: [u64; 10],
    /// Wall time of the frame's LOD and planning, milliseconds (fetch excluded).
    pub plan_ms: f64,
    /// Wall time of the whole frame, milliseconds.
    pub frame_ms: f64,
}

/// One opened model: what its first requests gave.
#[derive(Debug)]
struct ModelIndex {
    directory: Directory,
    nodes: Vec<NodeRecord>,
    layout: BandLayout,
    /// Node index of each leaf ordinal.
    leaf_nodes: Vec<usize>,
    leaves_offset: u64,
    leaf_material_count: usize,
    materials: canopy_shared::model::Materials,
    hull: Option<HullTable>,
    atlas: Option<AtlasTable>,
    /// Skeleton segments per iteration, once that iteration's bytes have been checked.
    skeleton_segments: Vec<Option<u64>>,
    /// Triangles of the imported bark mesh.
    bark_mesh_triangles: u64,
    height: f32,
    center: Vec3,
    radius: f32,
}

impl ModelIndex {
    /// Iterations whose skeleton bytes are not empty (each is one checked block).
    fn skeleton_iterations(&self) -> impl Iterator<Item = u8> + '_ {
        let t = &self.directory.iteration_table;
        (0..t.len()).filter_map(move |k| {
            let start = if k == 0 { 0 } else { t[k - 1].skeleton_bytes_end };
            (t[k].skeleton_bytes_end > start).then_some(k as u8)
        })
    }

    /// Bark triangles at full detail: skeleton tubes of [`BARK_SIDES`] sides plus the bark mesh.
    /// Until every skeleton iteration has arrived, 4 segments per branch are assumed.
    fn bark_triangles(&self) -> u64 {
        let complete = self
            .skeleton_iterations()
            .all(|k| self.skeleton_segments.get(usize::from(k)).is_some_and(Option::is_some));
        let segments = if complete {
            self.skeleton_segments.iter().flatten().sum()
        } else {
            u64::from(self.directory.branch_count) * 4
        };
        segments * 2 * BARK_SIDES + self.bark_mesh_triangles
    }
}

#[derive(Debug)]
enum ModelState {
    Closed,
    Open(Box<ModelIndex>),
    Failed(String),
}

#[derive(Debug)]
struct Model {
    url: String,
    size: u64,
    state: ModelState,
}

#[derive(Debug)]
struct Instance {
    inst: PackInstance,
    lod: Option<TreeLodState>,
}

/// A block to fetch: where it is and how to check it.
#[derive(Debug, Clone)]
struct Want {
    key: BlockKey,
    range: ByteRange,
    check: Check,
    gain: f64,
}

#[derive(Debug, Clone, Copy)]
enum Check {
    Crc(u32),
    LeafBlock { count: u32 },
}

/// Per-model needs gathered over the instances of one frame.
#[derive(Debug, Default)]
struct Need {
    keep: Vec<u32>,
    gain: Vec<f32>,
    geometry: bool,
    hull_levels: BTreeMap<u16, f64>,
    images: BTreeMap<(u32, u8), f64>,
}

/// What an instance wants drawn this frame.
#[derive(Debug)]
struct Draw {
    instance: PackInstance,
    model: usize,
    rep: Representation,
    keep: Vec<u32>,
    frames: Vec<(u32, u8, f32)>,
}

/// What one tree instance was drawn as in the last frame, from cached data only.
#[derive(Debug, Clone, PartialEq)]
pub struct DrawnTree {
    /// The instance (id, model index into the manifest, position, rotation, scale).
    pub instance: PackInstance,
    /// What was drawn.
    pub what: Drawn,
}

/// A drawn representation.
#[derive(Debug, Clone, PartialEq)]
pub enum Drawn {
    /// Geometry: the first `leaves[o]` leaves of each leaf node (ordinal `o`) and the bark.
    Geometry {
        /// Leaves drawn per leaf node.
        leaves: Vec<u32>,
    },
    /// A crown hull level.
    Hull {
        /// Level index.
        level: u16,
    },
    /// Billboard frames with their blend weights (renormalised over the cached frames).
    Billboard {
        /// Which kind.
        kind: BillboardKind,
        /// `(frame, resolution index, weight)`.
        frames: Vec<(u32, u8, f32)>,
    },
}

/// The streaming client for one scene.
#[derive(Debug)]
pub struct Streamer<S: RangeSource> {
    src: Arc<S>,
    manifest: Manifest,
    opts: StreamOptions,
    models: Vec<Model>,
    tiles: Vec<TileState>,
    instances: BTreeMap<u32, Instance>,
    cache: BlockCache,
    frame: u64,
    corrupt_total: u64,
    drawn: Vec<DrawnTree>,
}

#[derive(Debug, Clone, PartialEq)]
enum TileState {
    Absent,
    Loaded,
    Failed,
}

/// Bytes of one skeleton branch record header (parent u32, level u8, iteration u8, points u16).
const BRANCH_HEADER_LEN: usize = 8;
/// Bytes per skeleton point.
const BRANCH_POINT_LEN: usize = 8;

/// Segments (points − 1, summed) of skeleton bytes; `None` if the bytes do not parse.
fn skeleton_segments(bytes: &[u8]) -> Option<u64> {
    let mut o = 0usize;
    let mut segs = 0u64;
    while o < bytes.len() {
        let h = bytes.get(o..o + BRANCH_HEADER_LEN)?;
        let p = usize::from(u16::from_le_bytes([h[6], h[7]]));
        o = o.checked_add(BRANCH_HEADER_LEN + p * BRANCH_POINT_LEN)?;
        segs += p.saturating_sub(1) as u64;
    }
    (o == bytes.len()).then_some(segs)
}

impl<S: RangeSource> Streamer<S> {
    /// A streamer for an already fetched manifest.
    pub fn with_manifest(src: Arc<S>, manifest: Manifest, opts: StreamOptions) -> Self {
        let models = manifest
            .models
            .iter()
            .map(|m| Model {
                url: m.url.clone(),
                size: m.size,
                state: ModelState::Closed,
            })
            .collect();
        let tiles = vec![TileState::Absent; manifest.tiles.len()];
        let cache = BlockCache::new(opts.cache_budget);
        Self {
            src,
            manifest,
            opts,
            models,
            tiles,
            instances: BTreeMap::new(),
            cache,
            frame: 0,
            corrupt_total: 0,
            drawn: Vec::new(),
        }
    }

    /// The manifest.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// Cache counters.
    pub fn cache_stats(&self) -> CacheStats {
        self.cache.stats()
    }

    /// The source.
    pub fn source(&self) -> &S {
        &self.src
    }

    /// Models that could not be opened (name, reason): bad files or missing ones. Their
    /// instances are not drawn.
    pub fn failed_models(&self) -> Vec<(String, String)> {
        self.models
            .iter()
            .zip(&self.manifest.models)
            .filter_map(|(m, mm)| match &m.state {
                ModelState::Failed(e) => Some((mm.name.clone(), e.clone())),
                _ => None,
            })
            .collect()
    }

    /// Blocks that failed their CRC since the start.
    pub fn corrupt_blocks(&self) -> u64 {
        self.corrupt_total
    }

    /// What each visible tree was drawn as in the last frame (instances in id order).
    pub fn drawn(&self) -> &[DrawnTree] {
        &self.drawn
    }

    async fn load_tiles(&mut self, cam: &Camera) {
        let want: Vec<usize> = self
            .manifest
            .tiles_near(cam.eye.x, cam.eye.z, self.opts.viewport.far)
            .into_iter()
            .filter(|&i| self.tiles[i] == TileState::Absent)
            .collect();
        if want.is_empty() {
            return;
        }
        let ranges: Vec<ByteRange> = want
            .iter()
            .map(|&i| {
                let t = &self.manifest.tiles[i];
                t.offset..t.offset + t.length
            })
            .collect();
        let url = self.manifest.pack.url.clone();
        match self.src.fetch(&url, &ranges).await {
            Ok(bodies) => {
                for (&i, body) in want.iter().zip(bodies) {
                    let t = &self.manifest.tiles[i];
                    match decode_tile_records(&body, t.crc32, self.manifest.models.len()) {
                        Ok(list) => {
                            for inst in list {
                                self.instances.insert(inst.id, Instance { inst, lod: None });
                            }
                            self.tiles[i] = TileState::Loaded;
                        }
                        Err(_) => {
                            // Corrupt tile: try again next frame.
                            self.corrupt_total += 1;
                        }
                    }
                }
            }
            Err(e) if !e.is_retryable() => {
                for &i in &want {
                    self.tiles[i] = TileState::Failed;
                }
            }
            Err(_) => {}
        }
    }

    async fn open_models(&mut self, cam: &Camera) {
        let far = self.opts.viewport.far;
        let mut wanted = BTreeSet::new();
        for i in self.instances.values() {
            let p = Vec3::from(i.inst.position);
            if p.distance(cam.eye) <= far + 100.0 {
                wanted.insert(usize::from(i.inst.model));
            }
        }
        let todo: Vec<usize> = wanted
            .into_iter()
            .filter(|&m| matches!(self.models[m].state, ModelState::Closed))
            .collect();
        let src = &self.src;
        let results = join_all(
            todo.iter()
                .map(|&m| open_model(src.as_ref(), &self.models[m].url, self.models[m].size)),
        )
        .await;
        for (m, r) in todo.into_iter().zip(results) {
            self.models[m].state = match r {
                Ok(idx) => ModelState::Open(Box::new(idx)),
                Err(OpenError::Retry) => ModelState::Closed,
                Err(OpenError::Corrupt) => {
                    self.corrupt_total += 1;
                    ModelState::Closed
                }
                Err(OpenError::Fatal(e)) => ModelState::Failed(e),
            };
        }
    }

    fn index(&self, m: usize) -> Option<&ModelIndex> {
        match &self.models[m].state {
            ModelState::Open(i) => Some(i),
            _ => None,
        }
    }

    /// Representation of a tree, moved down the ladder past what the model lacks.
    fn supported(idx: &ModelIndex, rep: Representation) -> Representation {
        let has_hull = idx.hull.as_ref().is_some_and(|h| !h.levels.is_empty());
        let has_atlas = idx.atlas.as_ref().is_some_and(|a| !a.frames.is_empty());
        match rep {
            Representation::Hull { .. } if !has_hull => {
                if has_atlas {
                    Representation::Billboard(BillboardKind::HemiOct)
                } else {
                    Representation::Geometry
                }
            }
            Representation::Billboard(_) if !has_atlas => {
                if has_hull {
                    Representation::Hull { level: 255 }
                } else {
                    Representation::Geometry
                }
            }
            Representation::CloudLevel(_) => Self::supported(idx, Representation::Billboard(BillboardKind::HemiOct)),
            r => r,
        }
    }

    /// Runs one frame with the camera at `cam`, `dt` seconds after the previous one.
    pub async fn frame(&mut self, cam: &Camera, dt: f32) -> FrameReport {
        let t_frame = Instant::now();
        let net0 = self.src.stats().snapshot();
        let corrupt0 = self.corrupt_total;
        self.load_tiles(cam).await;
        self.open_models(cam).await;

        let t_plan = Instant::now();
        let vp = self.opts.viewport;
        let view_proj = vp.projection() * cam.view();
        let frustum = Frustum::from_view_proj(view_proj, DepthRange::ZeroToOne);
        let (draws, needs, visible) = self.lod_pass(cam, &frustum, dt);
        let wants = self.plan(&needs);
        let plan_ms = t_plan.elapsed().as_secs_f64() * 1e3;

        self.fetch(wants).await;
        let mut report = self.draw_pass(&draws);
        let net1 = self.src.stats().snapshot();
        report.frame = self.frame;
        report.bytes = net1.bytes - net0.bytes;
        report.requests = net1.requests - net0.requests;
        report.retries = net1.retries - net0.retries;
        report.failures = net1.failures - net0.failures;
        report.corrupt_blocks = self.corrupt_total - corrupt0;
        report.cache_bytes = self.cache.used_bytes();
        report.instances_loaded = self.instances.len();
        report.visible = visible;
        report.plan_ms = plan_ms;
        report.frame_ms = t_frame.elapsed().as_secs_f64() * 1e3;
        self.frame += 1;
        if self.frame.is_multiple_of(64) {
            self.cache.halve_uses();
        }
        report
    }

    fn lod_pass(&mut self, cam: &Camera, frustum: &Frustum, dt: f32) -> (Vec<Draw>, HashMap<usize, Need>, usize) {
        let vp = self.opts.viewport;
        let mut draws = Vec::new();
        let mut needs: HashMap<usize, Need> = HashMap::new();
        let mut visible = 0usize;
        let forward = cam.forward();
        let flight_view = FlightView {
            eye: cam.eye,
            forward,
            height: cam.eye.y,
            speed: 0.0,
        };
        let models = &self.models;
        for inst in self.instances.values_mut() {
            let m = usize::from(inst.inst.model);
            let ModelState::Open(idx) = &models[m].state else {
                continue;
            };
            let pos = Vec3::from(inst.inst.position);
            let scale = if inst.inst.scale.is_finite() && inst.inst.scale > 0.0 {
                inst.inst.scale
            } else {
                1.0
            };
            let rot = Quat::from_rotation_y(inst.inst.rotation);
            let model_m = Mat4::from_scale_rotation_translation(Vec3::splat(scale), rot, pos);
            let c = model_m.transform_point3(idx.center);
            let r = idx.radius * scale;
            if c.distance(cam.eye) - r > vp.far || !frustum.intersects_sphere(c, r) {
                inst.lod = None;
                continue;
            }
            visible += 1;
            let dist = sphere_distance(cam.eye, c, r);
            let px = projected_height(idx.height * scale, dist, vp.height as f32, vp.fov_y);
            let mut full_rate = false;
            let rep = if !self.opts.lod_enabled {
                full_rate = true;
                Representation::Geometry
            } else if let Some(fp) = &self.opts.flight {
                let level = crate::lod::flight::flight_level(fp, &flight_view, pos, idx.height * scale, dist);
                full_rate = level == 0;
                let step = usize::from(level).min(self.opts.ladder.len().saturating_sub(1));
                self.opts.ladder.get(step).map_or(Representation::Geometry, |s| s.rep)
            } else {
                choose_representation(&self.opts.ladder, px).unwrap_or(Representation::Geometry)
            };
            let rep = Self::supported(idx, rep);
            let need = needs.entry(m).or_insert_with(|| Need {
                keep: vec![0; idx.leaf_nodes.len()],
                gain: vec![0.0; idx.leaf_nodes.len()],
                ..Need::default()
            });
            let gain = f64::from(px.min(1e4)).powi(2);
            let inv = model_m.inverse();
            match rep {
                Representation::Geometry => {
                    need.geometry = true;
                    let keep = if full_rate {
                        inst.lod = None;
                        idx.layout.leaf_counts().to_vec()
                    } else {
                        let eye_m = inv.transform_point3(cam.eye);
                        let mut p = self.opts.lod.clone();
                        p.near /= scale;
                        p.far /= scale;
                        let state = inst.lod.get_or_insert_with(|| TreeLodState::new(&idx.nodes));
                        state.update(&p, &idx.nodes, eye_m, dt)
                    };
                    let vis = visible_nodes(frustum, model_m, &idx.nodes);
                    let mut keep = keep;
                    for (o, &ni) in idx.leaf_nodes.iter().enumerate() {
                        if !vis[ni] {
                            keep[o] = 0;
                            continue;
                        }
                        need.keep[o] = need.keep[o].max(keep[o]);
                        let node = &idx.nodes[ni];
                        let nc = model_m.transform_point3(node.sphere_center);
                        let nd = sphere_distance(cam.eye, nc, node.sphere_radius * scale);
                        let npx =
                            projected_height(2.0 * node.sphere_radius * scale, nd, vp.height as f32, vp.fov_y).min(1e4);
                        let g = npx * npx / node.leaf_count.max(1) as f32;
                        need.gain[o] = need.gain[o].max(g);
                    }
                    draws.push(Draw {
                        instance: inst.inst.clone(),
                        model: m,
                        rep,
                        keep,
                        frames: Vec::new(),
                    });
                }
                Representation::Hull { level } => {
                    inst.lod = None;
                    let levels = idx.hull.as_ref().map_or(1, |h| h.levels.len().max(1));
                    let level = usize::from(level).min(levels - 1) as u16;
                    *need.hull_levels.entry(level).or_default() += gain;
                    draws.push(Draw {
                        instance: inst.inst.clone(),
                        model: m,
                        rep: Representation::Hull { level: level as u8 },
                        keep: Vec::new(),
                        frames: Vec::new(),
                    });
                }
                Representation::Billboard(_) | Representation::CloudLevel(_) => {
                    inst.lod = None;
                    let kind = match rep {
                        Representation::Billboard(k) => k,
                        _ => BillboardKind::HemiOct,
                    };
                    let frames = idx
                        .atlas
                        .as_ref()
                        .map(|a| billboard_frames(a, kind, inv.transform_vector3(cam.eye - c).normalize_or_zero(), px))
                        .unwrap_or_default();
                    for &(f, r, _) in &frames {
                        *need.images.entry((f, r)).or_default() += gain;
                    }
                    draws.push(Draw {
                        instance: inst.inst.clone(),
                        model: m,
                        rep: Representation::Billboard(kind),
                        keep: Vec::new(),
                        frames,
                    });
                }
            }
        }
        (draws, needs, visible)
    }

    /// Turns the frame's needs into blocks to fetch, best gain per byte first, within the budget.
    fn plan(&mut self, needs: &HashMap<usize, Need>) -> Vec<(usize, Vec<Want>)> {
        let mut all: Vec<(usize, Want)> = Vec::new();
        let mut models: Vec<usize> = needs.keys().copied().collect();
        models.sort_unstable();
        for m in models {
            let Some(idx) = self.index(m) else { continue };
            let need = &needs[&m];
            let id = ModelId(m as u32);
            let dir = &idx.directory;
            let cache = &self.cache;
            let mut push = |key: BlockKey, range: ByteRange, check: Check, gain: f64| {
                if !cache.contains(id, key) && range.end > range.start {
                    all.push((
                        m,
                        Want {
                            key,
                            range,
                            check,
                            gain,
                        },
                    ));
                }
            };
            if need.geometry {
                // Skeleton by iteration, bark mesh and materials: small, needed before any leaf.
                if let Some(sk) = dir.section(SectionKind::Skeleton) {
                    let mut start = 0u64;
                    for (k, e) in dir.iteration_table.iter().enumerate() {
                        let end = u64::from(e.skeleton_bytes_end);
                        push(
                            BlockKey::Skeleton { iteration: k as u8 },
                            sk.offset + start..sk.offset + end,
                            Check::Crc(e.skeleton_crc),
                            f64::MAX,
                        );
                        start = end;
                    }
                }
                if let Some(b) = dir.section(SectionKind::BarkMesh) {
                    push(
                        BlockKey::Section { kind: b.kind.code() },
                        b.range(),
                        Check::Crc(b.crc),
                        f64::MAX,
                    );
                }
                let held: Vec<usize> = (0..idx.leaf_nodes.len())
                    .map(|o| self.cache.held_leaf_bands(id, o as u32, &idx.layout))
                    .collect();
                if let Ok(plan) = plan_leaf_ranges(&idx.layout, idx.leaves_offset, &need.keep, &held, &need.gain) {
                    for r in plan.ranges {
                        let per_byte_gain = r.gain_per_byte();
                        for b in r.blocks {
                            let start = idx.leaves_offset + b.offset;
                            push(
                                BlockKey::Leaf {
                                    band: b.band,
                                    leaf_node: b.leaf_node,
                                },
                                start..start + b.len,
                                Check::LeafBlock { count: b.count },
                                per_byte_gain * b.len as f64,
                            );
                        }
                    }
                }
            }
            if let (Some(h), Some(sec)) = (&idx.hull, dir.section(SectionKind::Hulls)) {
                for (&level, &g) in &need.hull_levels {
                    if let Some(e) = h.levels.get(usize::from(level)) {
                        let a = sec.offset + u64::from(e.offset);
                        push(
                            BlockKey::Hull { level },
                            a..a + u64::from(e.length),
                            Check::Crc(e.crc),
                            g,
                        );
                    }
                }
            }
            if let (Some(a), Some(sec)) = (&idx.atlas, dir.section(SectionKind::BillboardAtlases)) {
                for (&(frame, res), &g) in &need.images {
                    if let Some(e) = a.image(frame, usize::from(res)) {
                        let s = sec.offset + u64::from(e.offset);
                        push(
                            BlockKey::Atlas { frame, resolution: res },
                            s..s + u64::from(e.length),
                            Check::Crc(e.crc),
                            g,
                        );
                    }
                }
            }
        }
        // Best gain per byte first; cut at the budget (always at least one block, so a frame
        // with a tiny budget still makes progress).
        all.sort_by(|(ma, a), (mb, b)| {
            let ga = a.gain / (a.range.end - a.range.start) as f64;
            let gb = b.gain / (b.range.end - b.range.start) as f64;
            gb.total_cmp(&ga)
                .then(ma.cmp(mb))
                .then(a.range.start.cmp(&b.range.start))
        });
        self.cache.record_misses(all.len() as u64);
        if let Some(budget) = self.opts.frame_byte_budget {
            let mut spent = 0u64;
            let mut keep = 0usize;
            for (_, w) in &all {
                let len = w.range.end - w.range.start;
                if keep > 0 && spent + len > budget {
                    break;
                }
                spent += len;
                keep += 1;
            }
            all.truncate(keep);
        }
        let mut by_model: BTreeMap<usize, Vec<Want>> = BTreeMap::new();
        for (m, w) in all {
            by_model.entry(m).or_default().push(w);
        }
        by_model.into_iter().collect()
    }

    async fn fetch(&mut self, wants: Vec<(usize, Vec<Want>)>) {
        let src = &self.src;
        let models = &self.models;
        let jobs = wants.into_iter().map(|(m, mut list)| async move {
            list.sort_by_key(|w| w.range.start);
            let ranges = merge_ranges(list.iter().map(|w| w.range.clone()));
            let got = src.fetch(&models[m].url, &ranges).await;
            (m, list, ranges, got)
        });
        let results = join_all(jobs).await;
        for (m, list, ranges, got) in results {
            let Ok(bodies) = got else { continue };
            let material_count = self.index(m).map_or(1, |i| i.leaf_material_count);
            let id = ModelId(m as u32);
            // Both `list` and the merged `ranges` are sorted by start: walk them together.
            let mut k = 0;
            for w in list {
                while k < ranges.len() && ranges[k].end < w.range.end {
                    k += 1;
                }
                let Some(r) = ranges.get(k).filter(|r| r.start <= w.range.start) else {
                    continue;
                };
                let body = &bodies[k];
                let a = (w.range.start - r.start) as usize;
                let b = (w.range.end - r.start) as usize;
                let Some(bytes) = body.get(a..b) else {
                    self.corrupt_total += 1;
                    continue;
                };
                let ok = match w.check {
                    Check::Crc(crc) => check_crc("block", bytes, crc).is_ok(),
                    Check::LeafBlock { count } => decode_block(bytes, count, material_count).is_ok(),
                };
                if ok {
                    if let (BlockKey::Skeleton { iteration }, ModelState::Open(idx)) =
                        (w.key, &mut self.models[m].state)
                        && let Some(slot) = idx.skeleton_segments.get_mut(usize::from(iteration))
                    {
                        *slot = skeleton_segments(bytes);
                    }
                    self.cache.insert(id, w.key, Arc::from(bytes));
                } else {
                    self.corrupt_total += 1;
                }
            }
        }
    }

    fn draw_pass(&mut self, draws: &[Draw]) -> FrameReport {
        let mut rep = FrameReport::default();
        let mut drawn_list = Vec::with_capacity(draws.len());
        // Touch each block in use once per frame (the cache evicts the least used).
        let mut touched: Vec<(usize, BlockKey)> = Vec::new();
        // Per model: cached band prefix of each leaf node (computed once per frame) and the most
        // bands any instance drew of it (touched once after the loop).
        let mut held_by_model: HashMap<usize, (Vec<usize>, Vec<usize>)> = HashMap::new();
        for d in draws {
            let Some(idx) = self.index(d.model) else { continue };
            let id = ModelId(d.model as u32);
            let full_leaves = u64::from(idx.directory.leaf_count);
            rep.full_triangles += 2 * full_leaves + idx.bark_triangles();
            let has_geometry = idx
                .skeleton_iterations()
                .all(|k| self.cache.contains(id, BlockKey::Skeleton { iteration: k }));
            // The wanted hull level if cached, else the finest cached one.
            let wanted_hull = match d.rep {
                Representation::Hull { level } => Some(usize::from(level)),
                _ => None,
            };
            let hull_any = idx.hull.as_ref().and_then(|h| {
                wanted_hull
                    .into_iter()
                    .chain(0..h.levels.len())
                    .find(|&l| l < h.levels.len() && self.cache.contains(id, BlockKey::Hull { level: l as u16 }))
                    .map(|l| (l, h.levels[l].triangles))
            });
            let mut drew = None;
            match d.rep {
                Representation::Geometry if has_geometry => {
                    let mut leaves = 0u64;
                    let mut per_node = vec![0u32; d.keep.len()];
                    let cache = &self.cache;
                    let (held_bands, used_bands) = held_by_model.entry(d.model).or_insert_with(|| {
                        let held = (0..idx.leaf_nodes.len())
                            .map(|o| cache.held_leaf_bands(id, o as u32, &idx.layout))
                            .collect();
                        (held, vec![0; idx.leaf_nodes.len()])
                    });
                    for (o, &k) in d.keep.iter().enumerate() {
                        if k == 0 {
                            continue;
                        }
                        let n = idx.layout.leaf_counts()[o];
                        let held = held_bands[o];
                        used_bands[o] = used_bands[o].max(held.min(idx.layout.bands_for_keep(n, k)));
                        let drawn = k.min(idx.layout.leaves_in_bands(n, held));
                        per_node[o] = drawn;
                        leaves += u64::from(drawn);
                        let rate = 1.0 - f64::from(drawn) / f64::from(n.max(1));
                        rep.rate_histogram[((rate * 10.0) as usize).min(9)] += 1;
                    }
                    rep.leaves += leaves;
                    rep.triangles += 2 * leaves + idx.bark_triangles();
                    rep.geometry_trees += 1;
                    drew = Some(Drawn::Geometry { leaves: per_node });
                }
                Representation::Billboard(kind) => {
                    let held: Vec<(u32, u8, f32)> = d
                        .frames
                        .iter()
                        .copied()
                        .filter(|&(f, r, _)| {
                            self.cache.contains(
                                id,
                                BlockKey::Atlas {
                                    frame: f,
                                    resolution: r,
                                },
                            )
                        })
                        .collect();
                    if !held.is_empty() {
                        let quads = if kind == BillboardKind::Crossed {
                            2
                        } else {
                            held.len() as u64
                        };
                        for &(f, r, _) in &held {
                            touched.push((
                                d.model,
                                BlockKey::Atlas {
                                    frame: f,
                                    resolution: r,
                                },
                            ));
                        }
                        rep.billboard_quads += quads;
                        rep.triangles += 2 * quads;
                        rep.billboard_trees += 1;
                        let total: f32 = held.iter().map(|h| h.2).sum();
                        let frames = held
                            .iter()
                            .map(|&(f, r, w)| (f, r, if total > 0.0 { w / total } else { 0.0 }))
                            .collect();
                        drew = Some(Drawn::Billboard { kind, frames });
                    }
                }
                _ => {}
            }
            if drew.is_none() {
                // Wanted a hull, or a fallback because what was wanted is not cached yet.
                if let Some((l, tris)) = hull_any {
                    touched.push((d.model, BlockKey::Hull { level: l as u16 }));
                    rep.hull_trees += 1;
                    rep.triangles += u64::from(tris);
                    drew = Some(Drawn::Hull { level: l as u16 });
                } else {
                    rep.pending_trees += 1;
                }
            }
            if let Some(what) = drew {
                drawn_list.push(DrawnTree {
                    instance: d.instance.clone(),
                    what,
                });
            }
        }
        self.drawn = drawn_list;
        for (m, (_, used)) in held_by_model {
            for (o, &bands) in used.iter().enumerate() {
                for b in 0..bands {
                    touched.push((
                        m,
                        BlockKey::Leaf {
                            band: b as u8,
                            leaf_node: o as u32,
                        },
                    ));
                }
            }
        }
        touched.sort_unstable();
        touched.dedup();
        for (m, k) in touched {
            let _ = self.cache.get(ModelId(m as u32), k);
        }
        rep
    }
}

/// Frames (and the resolution index) a billboard of `kind` needs for a view from `dir_model`
/// (unit, model frame, tree → eye), at `px` projected pixels.
fn billboard_frames(a: &AtlasTable, kind: BillboardKind, dir_model: Vec3, px: f32) -> Vec<(u32, u8, f32)> {
    // Smallest stored side at least the projected size; the largest when none is.
    let res = a.resolutions.iter().rposition(|&s| f32::from(s) >= px).unwrap_or(0) as u8;
    let want_kind = |k: &AtlasLayoutKind| {
        matches!(
            (kind, k),
            (BillboardKind::HemiOct, AtlasLayoutKind::HemiOctahedral)
                | (BillboardKind::LatLong, AtlasLayoutKind::LatLong { .. })
                | (BillboardKind::Crossed, AtlasLayoutKind::CrossedQuads)
        )
    };
    let Some(layout) = a.layouts.iter().find(|l| want_kind(&l.kind)) else {
        return Vec::new();
    };
    let local: Vec<(u32, f32)> = match kind {
        BillboardKind::HemiOct => hemi_oct_blend(dir_model, u32::from(layout.cols))
            .into_iter()
            .filter(|(_, w)| *w > 0.0)
            .collect(),
        BillboardKind::LatLong => lat_long_nearest(layout, dir_model)
            .map(|f| (f, 1.0))
            .into_iter()
            .collect(),
        BillboardKind::Crossed => vec![(0, 0.5), (1, 0.5)],
    };
    local
        .into_iter()
        .map(|(f, w)| (layout.first_frame + f, w))
        .filter(|&(f, _)| {
            a.frames
                .get(f as usize)
                .is_some_and(canopy_shared::format::atlas::AtlasFrame::is_present)
        })
        .map(|(f, w)| (f, res, w))
        .collect()
}

/// Merges sorted ranges whose gap is under [`MERGE_GAP_BYTES`] (the plan's rule, applied to the
/// blocks of one model across kinds).
pub fn merge_ranges(sorted: impl Iterator<Item = ByteRange>) -> Vec<ByteRange> {
    let mut out: Vec<ByteRange> = Vec::new();
    for r in sorted {
        if let Some(last) = out.last_mut()
            && r.start >= last.start
            && r.start.saturating_sub(last.end) < MERGE_GAP_BYTES
        {
            last.end = last.end.max(r.end);
            continue;
        }
        out.push(r);
    }
    out
}

enum OpenError {
    Retry,
    /// Bytes that failed a check (CRC or structure): counted as corrupt, retried next frame.
    Corrupt,
    Fatal(String),
}

impl From<NetError> for OpenError {
    fn from(e: NetError) -> Self {
        if e.is_retryable() {
            Self::Retry
        } else {
            Self::Fatal(e.to_string())
        }
    }
}

impl From<FormatError> for OpenError {
    fn from(e: FormatError) -> Self {
        // A corrupt index may be a corrupted transfer: count it, try again next frame.
        let _ = e;
        Self::Corrupt
    }
}

/// One range of `url`.
async fn fetch_one<S: RangeSource>(src: &S, url: &str, r: ByteRange) -> Result<Bytes, OpenError> {
    src.fetch(url, std::slice::from_ref(&r))
        .await?
        .pop()
        .ok_or(OpenError::Retry)
}

/// The first `table_len` bytes of section `e` (a hull or atlas table): from `prefix`, the
/// section's first bytes already fetched, when it holds them, else one more request.
async fn section_table<S: RangeSource>(
    src: &S,
    url: &str,
    e: &SectionEntry,
    prefix: &[u8],
    table_len: u32,
) -> Result<Bytes, OpenError> {
    let t = u64::from(table_len);
    if t <= prefix.len() as u64 {
        Ok(Bytes::copy_from_slice(&prefix[..t as usize]))
    } else {
        fetch_one(src, url, e.offset..e.offset + t.min(e.length)).await
    }
}

/// Opens a model: header and directory, then node table, materials and the hull and atlas tables
/// in one multi-range request.
async fn open_model<S: RangeSource>(src: &S, url: &str, size: u64) -> Result<ModelIndex, OpenError> {
    // The header and directory of every baked tree fit in a few hundred bytes: ask for
    // OPEN_REQUEST_LEN and fetch the rest of a longer directory (up to FIRST_REQUEST_LEN, the
    // format's bound) only when the header says so.
    let first_len = size.min(OPEN_REQUEST_LEN);
    let mut first = fetch_one(src, url, 0..first_len).await?;
    if first.len() >= HEADER_LEN {
        let header = Header::decode(&first[..HEADER_LEN])?;
        let need = (header.directory_offset + u64::from(header.directory_len)).min(size.min(FIRST_REQUEST_LEN));
        if need > first.len() as u64 {
            first = fetch_one(src, url, 0..need).await?;
        }
    }
    let (_, directory) = decode_index(&first, Some(size))?;
    let sec = |k: SectionKind| directory.section(k).copied();
    let nodes_e = sec(SectionKind::NodeTable).ok_or_else(|| OpenError::Fatal("no node table".into()))?;
    let mats_e = sec(SectionKind::Materials).ok_or_else(|| OpenError::Fatal("no materials".into()))?;
    let hull_e = sec(SectionKind::Hulls);
    let atlas_e = sec(SectionKind::BillboardAtlases);
    // Table prefixes: the hull table is ≤ 484 bytes; the atlas table ~10 KiB by default. Ask for
    // enough to hold both in one go and fetch the rest of a bigger atlas table after.
    let hull_prefix = hull_e.map(|e| e.offset..e.offset + e.length.min(1024));
    let atlas_prefix = atlas_e.map(|e| e.offset..e.offset + e.length.min(16 * 1024));
    let mut ranges = vec![nodes_e.range(), mats_e.range()];
    ranges.extend(hull_prefix.clone().filter(|r| r.end > r.start));
    ranges.extend(atlas_prefix.clone().filter(|r| r.end > r.start));
    let mut sorted = ranges.clone();
    sorted.sort_by_key(|r| r.start);
    let merged = merge_ranges(sorted.into_iter());
    let bodies = src.fetch(url, &merged).await?;
    let slice = |r: &ByteRange| -> Option<&[u8]> {
        let k = merged.iter().position(|m| m.start <= r.start && r.end <= m.end)?;
        bodies[k].get((r.start - merged[k].start) as usize..(r.end - merged[k].start) as usize)
    };
    let table = slice(&nodes_e.range()).ok_or(OpenError::Retry)?;
    check_crc("node table", table, nodes_e.crc)?;
    let nodes = decode_nodes(table, directory.node_count, directory.branch_count)?;
    let mats = slice(&mats_e.range()).ok_or(OpenError::Retry)?;
    check_crc("materials", mats, mats_e.crc)?;
    let materials = decode_materials(mats)?;
    let hull = match (&hull_e, &hull_prefix) {
        (Some(e), Some(r)) if e.length > 0 => {
            let p = slice(r).ok_or(OpenError::Retry)?;
            let bytes = section_table(src, url, e, p, HullTable::peek_table_len(p)?).await?;
            Some(HullTable::decode(&bytes, e.length)?)
        }
        _ => None,
    };
    let atlas = match (&atlas_e, &atlas_prefix) {
        (Some(e), Some(r)) if e.length > 0 => {
            let p = slice(r).ok_or(OpenError::Retry)?;
            let bytes = section_table(src, url, e, p, AtlasTable::peek_table_len(p)?).await?;
            Some(AtlasTable::decode(&bytes, e.length)?)
        }
        _ => None,
    };
    let leaf_nodes: Vec<usize> = nodes
        .iter()
        .enumerate()
        .filter(|(_, n)| n.kind == NodeKind::Leaf)
        .map(|(i, _)| i)
        .collect();
    let counts: Vec<u32> = leaf_nodes.iter().map(|&i| nodes[i].leaf_count).collect();
    let layout = BandLayout::new(&directory.band_edges, &counts);
    let leaves_offset = sec(SectionKind::Leaves).map_or(0, |e| e.offset);
    let bark_mesh_tris = sec(SectionKind::BarkMesh).map_or(0, |e| u64::from(e.item_count));
    let root = nodes
        .first()
        .ok_or_else(|| OpenError::Fatal("empty node table".into()))?;
    let (lo, hi) = (directory.bounds_min, directory.bounds_max);
    let center = root.sphere_center;
    let radius = root.sphere_radius.max((hi - lo).length() * 0.5);
    Ok(ModelIndex {
        height: (hi.y - lo.y.min(0.0)).max(0.01),
        center,
        radius,
        leaf_material_count: materials.leaf.len(),
        materials,
        skeleton_segments: vec![None; directory.iteration_table.len()],
        bark_mesh_triangles: bark_mesh_tris,
        directory,
        layout,
        leaf_nodes,
        leaves_offset,
        nodes,
        hull,
        atlas,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn merge_ranges_uses_the_gap_constant() {
        let g = MERGE_GAP_BYTES;
        assert_eq!(merge_ranges([0..10, 10 + g - 1..20 + g].into_iter()), vec![0..20 + g]);
        assert_eq!(
            merge_ranges([0..10, 10 + g..20 + g].into_iter()),
            vec![0..10, 10 + g..20 + g]
        );
        assert_eq!(merge_ranges([0..10, 5..8].into_iter()), vec![0..10]);
    }

    #[test]
    fn skeleton_segment_count() {
        let mut b = Vec::new();
        for p in [3u16, 1] {
            b.extend_from_slice(&[0, 0, 0, 0, 1, 0]);
            b.extend_from_slice(&p.to_le_bytes());
            b.extend(std::iter::repeat_n(0u8, usize::from(p) * BRANCH_POINT_LEN));
        }
        assert_eq!(skeleton_segments(&b), Some(2));
        assert_eq!(skeleton_segments(&b[..b.len() - 1]), None);
    }

    #[test]
    fn camera_axes() {
        let c = Camera {
            eye: Vec3::ZERO,
            yaw: 0.0,
            pitch: 0.0,
        };
        assert!((c.forward() - Vec3::NEG_Z).length() < 1e-6);
        let c = Camera {
            yaw: std::f32::consts::FRAC_PI_2,
            ..c
        };
        assert!((c.forward() - Vec3::X).length() < 1e-6);
        let c = Camera {
            pitch: -std::f32::consts::FRAC_PI_2 + 1e-4,
            ..c
        };
        assert!(c.forward().y < -0.99);
        // Looking straight down still gives a valid view matrix.
        assert!(c.view().is_finite());
    }

    /// A table with all three layouts (lat-long 12 × 4 from 0° in 20° steps, hemi-oct 4 × 4,
    /// crossed), every frame present at two resolutions.
    fn atlas() -> AtlasTable {
        use canopy_shared::format::atlas::{AtlasCodec, AtlasFrame, AtlasLayout, ImageEntry};
        let layouts = vec![
            AtlasLayout {
                kind: AtlasLayoutKind::LatLong {
                    elevation_min: 0.0,
                    elevation_step: 20f32.to_radians(),
                    azimuth_step: 30f32.to_radians(),
                },
                cols: 12,
                rows: 4,
                first_frame: 0,
            },
            AtlasLayout {
                kind: AtlasLayoutKind::HemiOctahedral,
                cols: 4,
                rows: 4,
                first_frame: 48,
            },
            AtlasLayout {
                kind: AtlasLayoutKind::CrossedQuads,
                cols: 2,
                rows: 1,
                first_frame: 64,
            },
        ];
        let image = ImageEntry {
            offset: 1,
            length: 1,
            crc: 0,
        };
        AtlasTable {
            codec: AtlasCodec::Png,
            center: Vec3::ZERO,
            radius: 1.0,
            resolutions: vec![128, 64],
            layouts,
            frames: vec![
                AtlasFrame {
                    root_u: 0.5,
                    root_v: 0.0,
                    images: vec![image; 2],
                };
                66
            ],
        }
    }

    #[test]
    fn billboards_seen_from_straight_above_and_the_side() {
        let a = atlas();
        let up = Vec3::Y;
        // Hemi-oct covers the zenith: weights sum to 1 over frames of its own layout.
        let h = billboard_frames(&a, BillboardKind::HemiOct, up, 10.0);
        assert!(!h.is_empty() && h.iter().all(|&(f, _, _)| (48..64).contains(&f)));
        assert!((h.iter().map(|x| x.2).sum::<f32>() - 1.0).abs() < 1e-4, "{h:?}");
        // Lat-long has no frame above 60°: straight above clamps to the top row (the failure
        // case of seed 001's grid, measured in BENCHMARKS.md).
        let l = billboard_frames(&a, BillboardKind::LatLong, up, 10.0);
        assert_eq!(l.len(), 1);
        assert!((36..48).contains(&l[0].0), "{l:?}");
        // Crossed quads are two vertical images whatever the view.
        let c = billboard_frames(&a, BillboardKind::Crossed, up, 10.0);
        assert_eq!(c.iter().map(|x| x.0).collect::<Vec<_>>(), vec![64, 65]);
        // Resolution: the smallest side at least the projected size, else the largest.
        assert_eq!(billboard_frames(&a, BillboardKind::Crossed, Vec3::X, 50.0)[0].1, 1);
        assert_eq!(billboard_frames(&a, BillboardKind::Crossed, Vec3::X, 100.0)[0].1, 0);
        assert_eq!(billboard_frames(&a, BillboardKind::Crossed, Vec3::X, 1000.0)[0].1, 0);
        // A degenerate direction (eye at the centre) never panics.
        let _ = billboard_frames(&a, BillboardKind::HemiOct, Vec3::ZERO, 10.0);
        let _ = billboard_frames(&a, BillboardKind::LatLong, Vec3::ZERO, 10.0);
    }
}
