//! The client frame loop: from a camera to the bytes the LOD needs, fetched and checked.
//!
//! Every frame, for a scene opened from its manifest:
//!
//! 1. **Tiles.** Instance tiles within the view distance of the camera that are not yet loaded
//!    are fetched from the version's pack (one multi-range request) and checked (CRC-32 each).
//! 2. **Models.** A model used by a nearby instance is opened: one request for the header and
//!    directory (`FIRST_REQUEST_LEN`), then one for the node table, materials and the hull and
//!    atlas tables.
//! 3. **LOD.** Instance tiles are culled as a whole first (out of view: skipped; wholly in view:
//!    no per-instance test), then each instance by its bounding sphere; its representation comes
//!    from its projected height (seed 000's ladder, [`crate::lod::projection`]) or, with the
//!    flight policy, from seed 002's level ([`crate::lod::flight`]). A tree drawn as geometry gets
//!    per-leaf-node rates (seed 004, [`crate::lod::rate`] through switch control, a node
//!    evaluated only once the eye could have moved its rate past the switch threshold, see
//!    [`crate::lod::TreeLodState`]); culled nodes keep nothing. With
//!    [`StreamOptions::plan_on_pool`], once a frame has had four or more geometry trees, each
//!    geometry tree's update and node culling start on rayon's pool as soon as the instance loop
//!    meets the tree, while the loop goes on with the far trees (one job per tree; the result
//!    does not depend on it or on the thread count).
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

use std::borrow::Cow;
use std::collections::{BTreeMap, BTreeSet, HashSet};
use std::sync::Arc;
use std::time::Instant;

use bytes::Bytes;
use canopy_shared::format::atlas::{AtlasLayout, AtlasLayoutKind, AtlasTable, hemi_oct_blend, lat_long_nearest};
use canopy_shared::format::cloud::{CloudError, CloudTable};
use canopy_shared::format::directory::SectionKind;
use canopy_shared::format::hull::HullTable;
use canopy_shared::format::leaf::{BandLayout, LeafBlockRef, decode_block};
use canopy_shared::format::materials::decode_materials;
use canopy_shared::format::node::{NodeKind, decode_nodes};
use canopy_shared::format::tree::decode_index;
use canopy_shared::format::{
    Directory, FIRST_REQUEST_LEN, FormatError, HEADER_LEN, Header, NodeRecord, SectionEntry, check_crc,
};
use canopy_shared::pack::{PackInstance, decode_tile_records};
use futures_util::future::join_all;
use glam::{Mat4, Quat, Vec3, Vec4};
use serde::Serialize;

use crate::cache::{BlockCache, BlockKey, CacheStats, FrameTouches, ModelId};
use crate::lod::projection::{
    BillboardKind, DEFAULT_LADDER, LadderStep, Representation, SWITCH_BLEND_BAND, projected_height_tan, switch_blend,
};
use crate::lod::{
    DepthRange, FlightParams, FlightView, Frustum, LeafTable, LodParams, PixelBudget, TreeLodState, budget_keep,
    pixel_budget, projected_height, sphere_distance, visible_leaves_world,
};
use crate::net::{ByteRange, NetError, RangeSource};
use crate::plan::{MERGE_GAP_BYTES, plan_leaf_ranges};
use crate::scene::Manifest;

mod cached;
pub use cached::CachedModel;

/// Bytes asked for when opening a model: header and directory (the directory of the
/// 293,000-leaf linden is 660 bytes with the header).
pub const OPEN_REQUEST_LEN: u64 = 4096;

/// Bytes of the billboard-cloud section asked for when a model opens: the default bake's table
/// (3 levels, ≤ 20 planes, ≤ 1.5 KiB) fits; a bigger table costs one more request.
const CLOUD_TABLE_PREFIX: u64 = 2048;

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
    /// Cross-fade band between adjacent cloud rungs ([`switch_blend`]); 0: none.
    pub cloud_blend: f32,
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
    /// Plan a frame's geometry trees on rayon's pool (see [`PARALLEL_GEOMETRY_TREES`]). Off
    /// where many streamers already share the cores (`canopy load`): handing work to the pool
    /// and back then costs more than it saves.
    pub plan_on_pool: bool,
}

impl Default for StreamOptions {
    fn default() -> Self {
        Self {
            lod: LodParams::default(),
            ladder: DEFAULT_LADDER.to_vec(),
            cloud_blend: SWITCH_BLEND_BAND,
            flight: None,
            viewport: Viewport::default(),
            cache_budget: crate::cache::DEFAULT_BUDGET_BYTES,
            frame_byte_budget: None,
            lod_enabled: true,
            plan_on_pool: true,
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
    /// Trees drawn as billboard clouds.
    pub cloud_trees: usize,
    /// Cloud planes drawn (a tree inside a cross-fade band counts both levels' planes).
    pub cloud_planes: u64,
    /// Cloud trees drawn as two levels cross-fading.
    pub cloud_blends: usize,
    /// Visible trees with nothing cached to draw yet.
    pub pending_trees: usize,
    /// Leaves drawn.
    pub leaves: u64,
    /// Triangles drawn (leaves 2 each, bark, hulls, billboard quads, cloud planes).
    pub triangles: u64,
    /// Triangles the visible trees have at full detail.
    pub full_triangles: u64,
    /// Billboard quads drawn (crossed billboards count 2).
    pub billboard_quads: u64,
    /// Leaf nodes of geometry trees by drawn rate (1 − drawn/leaves), 10 bins of 0.1 (last bin
    /// includes 1.0; [`rate_bin`]).
    pub rate_histogram: [u64; 10],
    /// Leaf nodes whose rate switch control evaluated this frame (the others of the geometry
    /// trees were culled, or provably could not change): the planner's main per-frame work.
    pub nodes_evaluated: u64,
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
    /// Billboard-cloud table (`None`: no levels baked).
    cloud: Option<CloudTable>,
    /// Skeleton segments per iteration, once that iteration's bytes have been checked.
    skeleton_segments: Vec<Option<u64>>,
    /// Triangles of the imported bark mesh.
    bark_mesh_triangles: u64,
    height: f32,
    center: Vec3,
    radius: f32,
    /// Size of the model's largest leaf, `√(width_max · length_max)` (model units): the pixel
    /// budget's leaf size, an upper bound so that the budget errs towards more leaves.
    leaf_size: f32,
    /// Leaf-node data the rates read, shared by every instance.
    leaf_table: Arc<LeafTable>,
    /// Largest `|node centre − center| + node radius`: a sphere of this radius about `center`
    /// holds every node sphere (node spheres need not lie inside the tree's own sphere).
    node_reach: f32,
    /// Per node: radius about its centre holding its subtree's node spheres
    /// ([`crate::lod::tree::subtree_reach`]).
    subtree_reach: Vec<f32>,
    /// Per node, the leaf nodes before it ([`crate::lod::tree::leaves_before`]).
    leaves_before: Vec<u32>,
    /// Per node, its sphere (model frame): what node culling tests, shared by every instance.
    node_spheres: Vec<Vec4>,
    /// The byte ranges the opening requests read, sorted: a fetch does not merge over them.
    opened: Vec<ByteRange>,
    /// [`ModelIndex::other_units`], built once at open.
    other_units: Vec<Unit>,
}

impl ModelIndex {
    /// Whole leaf blocks inside the file's bytes `a..b` ([`BandLayout::blocks_within`]).
    fn leaf_blocks_within(&self, a: u64, b: u64) -> Vec<LeafBlockRef> {
        let lo = self.leaves_offset;
        if b <= lo {
            return Vec::new();
        }
        self.layout.blocks_within(a.max(lo) - lo..b - lo)
    }

    /// Skeleton bytes of iteration `k` alone.
    fn skeleton_unit(&self, k: usize) -> Option<Unit> {
        let sk = self.directory.section(SectionKind::Skeleton)?;
        let t = &self.directory.iteration_table;
        let start = if k == 0 {
            0
        } else {
            u64::from(t.get(k - 1)?.skeleton_bytes_end)
        };
        let e = t.get(k)?;
        Some(Unit {
            key: BlockKey::Skeleton { iteration: k as u8 },
            range: sk.offset + start..sk.offset + u64::from(e.skeleton_bytes_end),
            check: Check::Crc(e.skeleton_crc),
        })
    }

    /// The imported bark mesh section.
    fn bark_unit(&self) -> Option<Unit> {
        let b = self.directory.section(SectionKind::BarkMesh)?;
        Some(Unit {
            key: BlockKey::Section { kind: b.kind.code() },
            range: b.range(),
            check: Check::Crc(b.crc),
        })
    }

    /// Crown-hull level `level`.
    fn hull_unit(&self, level: usize) -> Option<Unit> {
        let sec = self.directory.section(SectionKind::Hulls)?;
        let e = self.hull.as_ref()?.levels.get(level)?;
        let a = sec.offset + u64::from(e.offset);
        Some(Unit {
            key: BlockKey::Hull { level: level as u16 },
            range: a..a + u64::from(e.length),
            check: Check::Crc(e.crc),
        })
    }

    /// Atlas image of `frame` at resolution `res`.
    fn atlas_unit(&self, frame: u32, res: u8) -> Option<Unit> {
        let sec = self.directory.section(SectionKind::BillboardAtlases)?;
        let e = self.atlas.as_ref()?.image(frame, usize::from(res))?;
        let a = sec.offset + u64::from(e.offset);
        Some(Unit {
            key: BlockKey::Atlas { frame, resolution: res },
            range: a..a + u64::from(e.length),
            check: Check::Crc(e.crc),
        })
    }

    /// Billboard-cloud level `level`.
    fn cloud_unit(&self, level: usize) -> Option<Unit> {
        let sec = self.directory.section(SectionKind::BillboardClouds)?;
        let r = self.cloud.as_ref()?.level_range(level)?;
        Some(Unit {
            key: BlockKey::Cloud { level: level as u8 },
            range: sec.offset + r.start..sec.offset + r.end,
            check: Check::CloudLevel(level as u8),
        })
    }

    /// Every unit other than leaf blocks (skeleton iterations, bark mesh, hull levels, atlas
    /// images, cloud levels), sorted by offset: built once at open.
    fn other_units(&self) -> Vec<Unit> {
        let mut units: Vec<Unit> = (0..self.directory.iteration_table.len())
            .filter_map(|k| self.skeleton_unit(k))
            .collect();
        units.extend(self.bark_unit());
        let hulls = self.hull.as_ref().map_or(0, |h| h.levels.len());
        units.extend((0..hulls).filter_map(|l| self.hull_unit(l)));
        if let Some(atlas) = &self.atlas {
            let nres = atlas.resolutions.len();
            for frame in 0..atlas.frames.len() as u32 {
                units.extend((0..nres).filter_map(|res| self.atlas_unit(frame, res as u8)));
            }
        }
        let clouds = self.cloud.as_ref().map_or(0, |c| c.levels.len());
        units.extend((0..clouds).filter_map(|l| self.cloud_unit(l)));
        units.retain(|u| u.range.end > u.range.start);
        units.sort_by_key(|u| u.range.start);
        units
    }

    /// Every unit the cache keys whose bytes lie wholly inside the file's bytes `a..b`.
    fn units_within(&self, a: u64, b: u64) -> Vec<Unit> {
        let mut units: Vec<Unit> = self
            .leaf_blocks_within(a, b)
            .into_iter()
            .map(|blk| {
                let start = self.leaves_offset + blk.offset;
                Unit {
                    key: BlockKey::Leaf {
                        band: blk.band,
                        leaf_node: blk.leaf_node,
                    },
                    range: start..start + blk.len,
                    check: Check::LeafBlock { count: blk.count },
                }
            })
            .collect();
        let from = self.other_units.partition_point(|u| u.range.start < a);
        units.extend(
            self.other_units[from..]
                .iter()
                .take_while(|u| u.range.start < b)
                .filter(|u| u.range.end <= b)
                .cloned(),
        );
        units
    }

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
    /// Manifest tile it came from.
    tile: u32,
    lod: Option<Box<TreeLodState>>,
    /// Frame (+ 1) in which the tree was last drawn as geometry.
    lod_frame: u64,
}

/// What culling and the ladder read of an instance, computed once its model is open (the same
/// expressions the frame used to evaluate per instance and frame).
#[derive(Debug, Clone, Copy)]
struct Placed {
    /// World centre of the tree's bounding sphere.
    c: Vec3,
    r: f32,
    /// Height (scaled).
    h: f32,
    model: u16,
    open: bool,
    /// Manifest tile it came from.
    tile: u32,
}

/// Bounds of a tile's placed instance spheres (world).
#[derive(Debug, Clone, Copy)]
struct TileBox {
    lo: Vec3,
    hi: Vec3,
}

/// A tile's relation to this frame's view volume (frustum and view distance).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum TileClass {
    /// No instance can be visible.
    Out,
    /// Every instance is inside: no per-instance test needed.
    In,
    /// Test each instance.
    Partial,
}

/// Up to three billboard frames `(frame, resolution index, weight)`, without allocating.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct FrameSet {
    len: u8,
    items: [(u32, u8, f32); 3],
}

impl FrameSet {
    fn as_slice(&self) -> &[(u32, u8, f32)] {
        &self.items[..usize::from(self.len)]
    }

    fn push(&mut self, x: (u32, u8, f32)) {
        if let Some(slot) = self.items.get_mut(usize::from(self.len)) {
            *slot = x;
            self.len += 1;
        }
    }
}

/// A piece of a model file the cache keys: where it is and how to check it.
#[derive(Debug, Clone)]
struct Unit {
    key: BlockKey,
    range: ByteRange,
    check: Check,
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
    LeafBlock {
        count: u32,
    },
    /// Every plane texture of a cloud level against its CRC.
    CloudLevel(u8),
}

/// Per-model needs gathered over the instances of one frame (buffers kept between frames).
#[derive(Debug, Default)]
struct Need {
    /// Some instance of the model is visible this frame.
    used: bool,
    geometry: bool,
    /// Most leaves any instance keeps of each leaf node (valid when `geometry`).
    keep: Vec<u32>,
    /// Summed gain per hull level; `None`: not needed.
    hull: Vec<Option<f64>>,
    /// Summed gain per atlas image (`frame × resolutions + resolution`); `None`: not needed.
    images: Vec<Option<f64>>,
    /// Summed gain per billboard-cloud level; `None`: not needed.
    clouds: Vec<Option<f64>>,
}

/// What a model gives the per-instance loop, gathered once per frame.
#[derive(Debug, Default)]
struct ModelFrame {
    open: bool,
    /// Representation of each ladder rung, moved down past what the model lacks.
    rungs: Vec<Representation>,
    hull_levels: usize,
    cloud_levels: usize,
    resolutions: usize,
    /// The atlas as the billboard choice reads it.
    atlas: AtlasFrame,
}

/// What [`billboard_frame_set`] reads of an atlas table, gathered once per model and frame.
#[derive(Debug, Default)]
struct AtlasFrame {
    /// Stored sides, finest first.
    sides: Vec<u16>,
    /// Layout of each billboard kind (hemi-oct, lat-long, crossed).
    layouts: [Option<AtlasLayout>; 3],
    /// Whether each frame has an image.
    present: Vec<bool>,
}

impl AtlasFrame {
    fn set(&mut self, a: Option<&AtlasTable>) {
        self.sides.clear();
        self.present.clear();
        self.layouts = [None, None, None];
        let Some(a) = a else { return };
        self.sides.extend_from_slice(&a.resolutions);
        self.present.extend(
            a.frames
                .iter()
                .map(canopy_shared::format::atlas::AtlasFrame::is_present),
        );
        for (k, kind) in [BillboardKind::HemiOct, BillboardKind::LatLong, BillboardKind::Crossed]
            .into_iter()
            .enumerate()
        {
            self.layouts[k] = a.layouts.iter().find(|l| layout_is(kind, &l.kind)).copied();
        }
    }

    /// [`billboard_frame_set`] from the gathered table (the same frames and weights).
    #[inline]
    fn frames(&self, kind: BillboardKind, dir_model: Vec3, px: f32) -> FrameSet {
        let res = self.sides.iter().rposition(|&s| f32::from(s) >= px).unwrap_or(0) as u8;
        let k = match kind {
            BillboardKind::HemiOct => 0,
            BillboardKind::LatLong => 1,
            BillboardKind::Crossed => 2,
        };
        let mut out = FrameSet::default();
        let Some(layout) = &self.layouts[k] else {
            return out;
        };
        let mut push = |f: u32, w: f32| {
            let f = layout.first_frame + f;
            if self.present.get(f as usize).copied().unwrap_or(false) {
                out.push((f, res, w));
            }
        };
        match kind {
            BillboardKind::HemiOct => {
                for (f, w) in hemi_oct_blend(dir_model, u32::from(layout.cols)) {
                    if w > 0.0 {
                        push(f, w);
                    }
                }
            }
            BillboardKind::LatLong => {
                if let Some(f) = lat_long_nearest(layout, dir_model) {
                    push(f, 1.0);
                }
            }
            BillboardKind::Crossed => {
                push(0, 0.5);
                push(1, 0.5);
            }
        }
        out
    }
}

/// Whether an atlas layout serves billboards of `kind`.
fn layout_is(kind: BillboardKind, k: &AtlasLayoutKind) -> bool {
    matches!(
        (kind, k),
        (BillboardKind::HemiOct, AtlasLayoutKind::HemiOctahedral)
            | (BillboardKind::LatLong, AtlasLayoutKind::LatLong { .. })
            | (BillboardKind::Crossed, AtlasLayoutKind::CrossedQuads)
    )
}

/// [`Draw::clouds`] of a draw that is not a cloud.
const NO_CLOUDS: [(u8, f32); 2] = [(0, 0.0); 2];

/// What an instance wants drawn this frame.
#[derive(Debug)]
struct Draw {
    /// Index into the streamer's instances.
    inst: u32,
    model: usize,
    rep: Representation,
    frames: FrameSet,
    /// Cloud levels and weights (clouds only): the rung's level, and the adjacent rung's level
    /// with weight > 0 inside a cross-fade band ([`switch_blend`]).
    clouds: [(u8, f32); 2],
    /// Index into the frame's geometry draws (geometry only).
    geo: u32,
}

/// Where a geometry draw's keep counts live.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum KeepOf {
    /// Every leaf (full detail).
    Full,
    /// The instance's switch-control state, every leaf node visible.
    State,
    /// The draw's own `culled_keep`: culled nodes at 0, every count lowered to the pixel budget
    /// when it limits the tree; `culled_vis` marks the visible nodes.
    Masked,
}

/// A tree drawn as geometry this frame.
#[derive(Debug, Clone)]
struct GeoDraw {
    inst: u32,
    model: usize,
    model_m: Mat4,
    scale: f32,
    keep: KeepOf,
    /// World centre of the tree's bounding sphere.
    center: Vec3,
    /// The eye in the model frame, when the switch-control state is to be updated.
    eye_model: Option<Vec3>,
    /// The pixel-scale leaf budget this frame ([`PixelBudget::NONE`] when off or at full detail).
    budget: PixelBudget,
    /// Keep counts with culled nodes at 0 (and lowered to the pixel budget when it limits the
    /// tree), and which leaf nodes are visible: this frame's only when `keep` is
    /// [`KeepOf::Masked`] (the buffers are reused from earlier frames).
    culled_keep: Vec<u32>,
    culled_vis: Vec<bool>,
}

/// Geometry trees per frame from which their updates run on the thread pool (with
/// [`StreamOptions::plan_on_pool`]): below it the pool's hand-off costs more than it saves.
/// The instance loop starts them on the pool as it meets them when the previous frame had this
/// many; otherwise they run after the loop.
pub const PARALLEL_GEOMETRY_TREES: usize = 4;

/// Geometry trees per job when the instance loop hands them to the pool as it goes: fewer
/// hand-offs (each may wake a sleeping worker) against a finer split of the work.
const GEOMETRY_BATCH: usize = 8;

/// The leaf bands the cache holds of one model, as of a cache generation.
#[derive(Debug, Clone)]
struct HeldBands {
    generation: u64,
    /// Band prefix held, per leaf node.
    bands: Vec<usize>,
    /// Leaves those bands hold, per leaf node (`leaves_in_bands`).
    present: Vec<u32>,
}

/// Buffers of one frame's LOD pass, reused between frames.
#[derive(Debug, Default)]
struct FrameScratch {
    draws: Vec<Draw>,
    geo: Vec<GeoDraw>,
    /// Culling buffers of earlier frames' geometry draws, reused.
    culled_pool: Vec<(Vec<u32>, Vec<bool>)>,
    needs: Vec<Need>,
    models: Vec<ModelFrame>,
    tile_class: Vec<TileClass>,
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
        /// Largest enlargement of the kept leaves the pixel-scale budget allows this frame
        /// (1: none; drawers also apply seed 004's capped enlargement when asked to).
        enlargement_cap: f32,
    },
    /// A crown hull level.
    Hull {
        /// Level index.
        level: u16,
    },
    /// Billboard-cloud levels with their weights (renormalised over the cached levels; two
    /// levels inside a cross-fade band, drawn with complementary coverage).
    Cloud {
        /// `(level, weight)`, heaviest first.
        levels: Vec<(u8, f32)>,
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
    /// Loaded instances in id order.
    instances: Vec<Instance>,
    /// Per instance (same order), valid unless `placed_stale`.
    placed: Vec<Placed>,
    /// Per instance: inverse of its placement (model → world).
    inverse: Vec<Mat4>,
    tile_boxes: Vec<Option<TileBox>>,
    placed_stale: bool,
    /// Instances whose LOD state was advanced last frame.
    lod_live: Vec<u32>,
    /// Per model: the cached band prefix of each leaf node, as of a cache generation.
    held_bands: Vec<Option<HeldBands>>,
    scratch: FrameScratch,
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
            instances: Vec::new(),
            placed: Vec::new(),
            inverse: Vec::new(),
            tile_boxes: Vec::new(),
            placed_stale: false,
            lod_live: Vec::new(),
            held_bands: Vec::new(),
            scratch: FrameScratch::default(),
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
                let mut added = Vec::new();
                for (&i, body) in want.iter().zip(bodies) {
                    let t = &self.manifest.tiles[i];
                    match decode_tile_records(&body, t.crc32, self.manifest.models.len()) {
                        Ok(list) => {
                            added.extend(list.into_iter().map(|inst| Instance {
                                inst,
                                tile: i as u32,
                                lod: None,
                                lod_frame: 0,
                            }));
                            self.tiles[i] = TileState::Loaded;
                        }
                        Err(_) => {
                            // Corrupt tile: try again next frame.
                            self.corrupt_total += 1;
                        }
                    }
                }
                self.add_instances(added);
            }
            Err(e) if !e.is_retryable() => {
                for &i in &want {
                    self.tiles[i] = TileState::Failed;
                }
            }
            Err(_) => {}
        }
    }

    /// Adds loaded instances (a later record of an id replaces the earlier one, with fresh
    /// state) and keeps them in id order.
    fn add_instances(&mut self, added: Vec<Instance>) {
        if added.is_empty() {
            return;
        }
        let mut all: BTreeMap<u32, Instance> = std::mem::take(&mut self.instances)
            .into_iter()
            .map(|i| (i.inst.id, i))
            .collect();
        for i in added {
            all.insert(i.inst.id, i);
        }
        self.instances = all.into_values().collect();
        self.placed_stale = true;
    }

    /// Recomputes what culling reads of each instance and the tiles' bounds, after instances
    /// were added or models opened.
    fn place_instances(&mut self) {
        self.placed.clear();
        self.inverse.clear();
        self.tile_boxes = vec![None; self.manifest.tiles.len()];
        for inst in &self.instances {
            let m = usize::from(inst.inst.model);
            let ModelState::Open(idx) = &self.models[m].state else {
                self.placed.push(Placed {
                    c: Vec3::ZERO,
                    r: 0.0,
                    h: 0.0,
                    model: inst.inst.model,
                    open: false,
                    tile: inst.tile,
                });
                self.inverse.push(Mat4::IDENTITY);
                continue;
            };
            let (model_m, scale) = placement(&inst.inst);
            let c = model_m.transform_point3(idx.center);
            let r = idx.radius * scale;
            self.placed.push(Placed {
                c,
                r,
                h: idx.height * scale,
                model: inst.inst.model,
                open: true,
                tile: inst.tile,
            });
            self.inverse.push(model_m.inverse());
            if let Some(b) = self.tile_boxes.get_mut(inst.tile as usize) {
                let (lo, hi) = (c - Vec3::splat(r.max(0.0)), c + Vec3::splat(r.max(0.0)));
                *b = Some(match *b {
                    Some(t) => TileBox {
                        lo: t.lo.min(lo),
                        hi: t.hi.max(hi),
                    },
                    None => TileBox { lo, hi },
                });
            }
        }
        self.lod_live = (0..self.instances.len() as u32)
            .filter(|&i| self.instances[i as usize].lod.is_some())
            .collect();
        self.placed_stale = false;
    }

    async fn open_models(&mut self, cam: &Camera) {
        if !self.models.iter().any(|m| matches!(m.state, ModelState::Closed)) {
            return;
        }
        let far = self.opts.viewport.far;
        let mut wanted = BTreeSet::new();
        for i in &self.instances {
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
            let mut opening = None;
            self.models[m].state = match r {
                Ok((idx, reads)) => {
                    self.placed_stale = true;
                    opening = Some(reads);
                    ModelState::Open(Box::new(idx))
                }
                Err(OpenError::Retry) => ModelState::Closed,
                Err(OpenError::Corrupt) => {
                    self.corrupt_total += 1;
                    ModelState::Closed
                }
                Err(OpenError::Fatal(e)) => ModelState::Failed(e),
            };
            if let Some((ranges, bodies)) = opening {
                self.keep_unasked_units(m, &ranges, &bodies, &HashSet::new());
            }
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
            Representation::CloudLevel(l) => match &idx.cloud {
                Some(c) => Representation::CloudLevel(l.min(u8::try_from(c.levels.len() - 1).unwrap_or(u8::MAX))),
                None => Self::supported(idx, Representation::Billboard(BillboardKind::HemiOct)),
            },
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
        if self.placed_stale {
            self.place_instances();
        }

        let t_plan = Instant::now();
        let vp = self.opts.viewport;
        let view_proj = vp.projection() * cam.view();
        let frustum = Frustum::from_view_proj(view_proj, DepthRange::ZeroToOne);
        let mut scratch = std::mem::take(&mut self.scratch);
        let visible = self.lod_pass(cam, &frustum, dt, &mut scratch);
        let nodes_evaluated: u64 = scratch
            .geo
            .iter()
            .filter(|g| g.eye_model.is_some())
            .filter_map(|g| self.instances.get(g.inst as usize)?.lod.as_ref())
            .map(|st| st.evaluated() as u64)
            .sum();
        let wants = self.plan(&scratch, cam);
        let plan_ms = t_plan.elapsed().as_secs_f64() * 1e3;

        self.fetch(wants).await;
        let mut report = self.draw_pass(&scratch);
        self.scratch = scratch;
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
        report.nodes_evaluated = nodes_evaluated;
        report.frame_ms = t_frame.elapsed().as_secs_f64() * 1e3;
        self.frame += 1;
        if self.frame.is_multiple_of(64) {
            self.cache.halve_uses();
        }
        report
    }

    /// Sorts every tile into out / in / partial for this frame's frustum and view distance.
    fn classify_tiles(&self, eye: Vec3, frustum: &Frustum, out: &mut Vec<TileClass>) {
        let far = self.opts.viewport.far;
        out.clear();
        out.extend(
            self.tile_boxes
                .iter()
                .map(|b| b.map_or(TileClass::Out, |b| classify_box(b, eye, far, frustum))),
        );
    }

    /// Per model, what the per-instance loop reads; resets the needs.
    fn prepare_models(&self, scratch: &mut FrameScratch) {
        let n = self.models.len();
        scratch.models.resize_with(n, ModelFrame::default);
        scratch.needs.resize_with(n, Need::default);
        for (m, (mf, need)) in scratch.models.iter_mut().zip(&mut scratch.needs).enumerate() {
            need.used = false;
            need.geometry = false;
            let Some(idx) = self.index(m) else {
                mf.open = false;
                continue;
            };
            mf.open = true;
            mf.rungs.clear();
            mf.rungs
                .extend(self.opts.ladder.iter().map(|s| Self::supported(idx, s.rep)));
            mf.hull_levels = idx.hull.as_ref().map_or(1, |h| h.levels.len().max(1));
            let (frames, res) = idx
                .atlas
                .as_ref()
                .map_or((0, 1), |a| (a.frames.len(), a.resolutions.len().max(1)));
            mf.resolutions = res;
            mf.atlas.set(idx.atlas.as_ref());
            need.hull.clear();
            need.hull.resize(mf.hull_levels, None);
            need.images.clear();
            need.images.resize(frames * res, None);
            mf.cloud_levels = idx.cloud.as_ref().map_or(0, |c| c.levels.len());
            need.clouds.clear();
            need.clouds.resize(mf.cloud_levels, None);
        }
    }

    /// LOD for every loaded instance (step 3): fills `scratch` with the frame's draws and needs;
    /// returns the number of visible instances. Instances are visited in id order, so every
    /// per-model sum is taken in the same order as before tiles were culled as a whole.
    fn lod_pass(&mut self, cam: &Camera, frustum: &Frustum, dt: f32, scratch: &mut FrameScratch) -> usize {
        let vp = self.opts.viewport;
        self.prepare_models(scratch);
        let mut tile_class = std::mem::take(&mut scratch.tile_class);
        self.classify_tiles(cam.eye, frustum, &mut tile_class);
        scratch.draws.clear();
        let previous_geometry_trees = scratch.geo.len();
        for g in scratch.geo.drain(..) {
            scratch.culled_pool.push((g.culled_keep, g.culled_vis));
        }
        let mut visible = 0usize;
        let mut geo_count = 0u32;
        let forward = cam.forward();
        let flight_view = FlightView {
            eye: cam.eye,
            forward,
            height: cam.eye.y,
            speed: 0.0,
        };
        let tan_half = (vp.fov_y * 0.5).tan();
        let screen = vp.height as f32;
        let frame = self.frame;
        let (models, opts, inverse) = (&self.models, &self.opts, &self.inverse);
        // With the pool and enough geometry trees last frame, each geometry tree's update and
        // culling starts on the pool as soon as the loop meets it, while the loop goes on.
        let pipelined = opts.plan_on_pool && previous_geometry_trees >= PARALLEL_GEOMETRY_TREES;
        let (done_tx, done_rx) = std::sync::mpsc::channel::<(u32, GeoDraw)>();
        // Instances are handed out in index order: `rest` holds those from `base` on.
        let (mut rest, mut base): (&mut [Instance], usize) = (&mut self.instances, 0);
        with_pool(pipelined, |pool| {
            // Geometry trees go to the pool a few at a time: each hand-off may wake a worker.
            let mut batch: Vec<(u32, &mut Instance, GeoDraw)> = Vec::new();
            let jobs = GeometryJobs {
                models,
                lod: &opts.lod,
                frustum,
                dt,
            };
            // The loop reads the compact `placed` records; the instance itself only for geometry.
            for (i, pl) in self.placed.iter().enumerate() {
                if !pl.open {
                    continue;
                }
                let class = tile_class.get(pl.tile as usize).copied().unwrap_or(TileClass::Partial);
                if class == TileClass::Out {
                    continue;
                }
                let (c, r) = (pl.c, pl.r);
                let centre_dist = c.distance(cam.eye);
                if class == TileClass::Partial && (centre_dist - r > vp.far || !frustum.intersects_sphere(c, r)) {
                    continue;
                }
                visible += 1;
                let m = usize::from(pl.model);
                let ModelState::Open(idx) = &models[m].state else {
                    continue;
                };
                let mf = &scratch.models[m];
                // `sphere_distance`, from the centre distance already at hand.
                let dist = {
                    let d = centre_dist - r.max(0.0);
                    if d.is_finite() { d.max(0.0) } else { 0.0 }
                };
                let px = projected_height_tan(pl.h, dist, screen, tan_half);
                let mut full_rate = false;
                let mut clouds = NO_CLOUDS;
                let rep = if !opts.lod_enabled {
                    full_rate = true;
                    Representation::Geometry
                } else if let Some(fp) = &opts.flight {
                    let pos = Vec3::from(rest[i - base].inst.position);
                    let level = crate::lod::flight::flight_level(fp, &flight_view, pos, pl.h, dist);
                    full_rate = level == 0;
                    let step = usize::from(level).min(opts.ladder.len().saturating_sub(1));
                    let rep = opts.ladder.get(step).map_or(Representation::Geometry, |s| s.rep);
                    Self::supported(idx, rep)
                } else {
                    // `choose_representation`, with the model's support folded into the rungs.
                    let x = if px.is_nan() { 0.0 } else { px };
                    let k = opts
                        .ladder
                        .iter()
                        .position(|s| x >= s.min_projected_px)
                        .unwrap_or(opts.ladder.len().saturating_sub(1));
                    let rep = mf.rungs.get(k).copied().unwrap_or(Representation::Geometry);
                    // Adjacent cloud levels cross-fade about their switch.
                    let other_cloud = |j: usize| match (rep, mf.rungs.get(j)) {
                        (Representation::CloudLevel(a), Some(&Representation::CloudLevel(b))) => a != b,
                        _ => false,
                    };
                    if let Representation::CloudLevel(a) = rep
                        && let Some((j, w)) = switch_blend(&opts.ladder, k, x, opts.cloud_blend, other_cloud)
                        && let Some(&Representation::CloudLevel(b)) = mf.rungs.get(j)
                    {
                        clouds = [(a, 1.0 - w), (b, w)];
                    }
                    rep
                };
                let need = &mut scratch.needs[m];
                need.used = true;
                let gain = f64::from(px.min(1e4)).powi(2);
                match rep {
                    Representation::Geometry => {
                        if !need.geometry {
                            need.geometry = true;
                            need.keep.clear();
                            need.keep.resize(idx.leaf_nodes.len(), 0);
                        }
                        let Some((inst, tail)) = std::mem::take(&mut rest)[i - base..].split_first_mut() else {
                            continue;
                        };
                        (rest, base) = (tail, i + 1);
                        let (model_m, scale) = placement(&inst.inst);
                        // The switch-control update and node culling run on the pool from here
                        // (`pool`), or after this loop.
                        let (keep, eye_model) = if full_rate {
                            inst.lod = None;
                            (KeepOf::Full, None)
                        } else {
                            inst.lod
                                .get_or_insert_with(|| Box::new(TreeLodState::with_table(Arc::clone(&idx.leaf_table))));
                            (KeepOf::State, Some(inverse[i].transform_point3(cam.eye)))
                        };
                        inst.lod_frame = frame + 1;
                        let budget = match opts.lod.leaf_pixels {
                            Some(target) if !full_rate => {
                                let b = pixel_budget(idx.leaf_size * scale, dist, screen, tan_half, target);
                                if opts.lod.leaf_pixels_enlarge {
                                    b
                                } else {
                                    PixelBudget {
                                        enlargement_cap: 1.0,
                                        ..b
                                    }
                                }
                            }
                            _ => PixelBudget::NONE,
                        };
                        let (culled_keep, culled_vis) = scratch.culled_pool.pop().unwrap_or_default();
                        let g = GeoDraw {
                            inst: i as u32,
                            model: m,
                            model_m,
                            scale,
                            keep,
                            center: c,
                            eye_model,
                            budget,
                            culled_keep,
                            culled_vis,
                        };
                        let gi = geo_count;
                        geo_count += 1;
                        if let Some(pool) = pool {
                            batch.push((gi, inst, g));
                            if batch.len() >= GEOMETRY_BATCH {
                                jobs.spawn(pool, std::mem::take(&mut batch), &done_tx);
                            }
                        } else {
                            scratch.geo.push(g);
                        }
                        scratch.draws.push(Draw {
                            inst: i as u32,
                            model: m,
                            rep,
                            frames: FrameSet::default(),
                            clouds: NO_CLOUDS,
                            geo: gi,
                        });
                    }
                    Representation::Hull { level } => {
                        let level = usize::from(level).min(mf.hull_levels - 1);
                        if let Some(g) = need.hull.get_mut(level) {
                            *g = Some(g.unwrap_or(0.0) + gain);
                        }
                        scratch.draws.push(Draw {
                            inst: i as u32,
                            model: m,
                            rep: Representation::Hull { level: level as u8 },
                            frames: FrameSet::default(),
                            clouds: NO_CLOUDS,
                            geo: u32::MAX,
                        });
                    }
                    Representation::CloudLevel(level) => {
                        if clouds[0].1 <= 0.0 {
                            clouds = [(level, 1.0), (level, 0.0)];
                        }
                        for &(l, w) in &clouds {
                            if w > 0.0
                                && let Some(g) = need.clouds.get_mut(usize::from(l))
                            {
                                // The partner level of a cross-fade is worth its weight.
                                *g = Some(g.unwrap_or(0.0) + gain * f64::from(w));
                            }
                        }
                        scratch.draws.push(Draw {
                            inst: i as u32,
                            model: m,
                            rep,
                            frames: FrameSet::default(),
                            clouds,
                            geo: u32::MAX,
                        });
                    }
                    Representation::Billboard(kind) => {
                        let frames = if idx.atlas.is_some() {
                            let dir = inverse[i].transform_vector3(cam.eye - c).normalize_or_zero();
                            mf.atlas.frames(kind, dir, px)
                        } else {
                            FrameSet::default()
                        };
                        for &(f, res, _) in frames.as_slice() {
                            let k = f as usize * mf.resolutions + usize::from(res);
                            if let Some(g) = need.images.get_mut(k) {
                                *g = Some(g.unwrap_or(0.0) + gain);
                            }
                        }
                        scratch.draws.push(Draw {
                            inst: i as u32,
                            model: m,
                            rep: Representation::Billboard(kind),
                            frames,
                            clouds: NO_CLOUDS,
                            geo: u32::MAX,
                        });
                    }
                }
            }
            if let Some(pool) = pool
                && !batch.is_empty()
            {
                jobs.spawn(pool, batch, &done_tx);
            }
        });
        drop(done_tx);
        if pipelined {
            // Back in draw order (the index each draw was given).
            let mut back: Vec<(u32, GeoDraw)> = done_rx.try_iter().collect();
            back.sort_unstable_by_key(|(gi, _)| *gi);
            debug_assert!(back.iter().enumerate().all(|(k, (gi, _))| *gi as usize == k));
            scratch.geo.extend(back.into_iter().map(|(_, g)| g));
        } else {
            self.geometry_pass(frustum, dt, scratch);
        }
        self.keep_maxima(scratch);
        // Trees that stopped being drawn as geometry lose their switch state.
        let mut live = std::mem::take(&mut self.lod_live);
        for &i in &live {
            if let Some(inst) = self.instances.get_mut(i as usize)
                && inst.lod_frame != frame + 1
            {
                inst.lod = None;
            }
        }
        live.clear();
        live.extend(scratch.geo.iter().map(|g| g.inst));
        self.lod_live = live;
        scratch.tile_class = tile_class;
        visible
    }

    /// The frame's geometry trees, after the instance loop ([`GeometryJobs::run`] each), when the
    /// loop did not start them on the pool already: with [`PARALLEL_GEOMETRY_TREES`] or more
    /// (and the pool allowed) they run on the thread pool; the result does not depend on it.
    fn geometry_pass(&mut self, frustum: &Frustum, dt: f32, scratch: &mut FrameScratch) {
        // The instances of the geometry draws, in draw order (ascending instance index).
        let draws = scratch.geo.len();
        let mut jobs: Vec<(&mut Instance, &mut GeoDraw)> = Vec::with_capacity(draws);
        // Split off each draw's instance in turn: O(draws), not a pass over every instance.
        let (mut rest, mut base): (&mut [Instance], usize) = (&mut self.instances, 0);
        for g in &mut scratch.geo {
            let i = g.inst as usize;
            let Some(k) = i.checked_sub(base).filter(|&k| k < rest.len()) else {
                continue;
            };
            let Some((inst, tail)) = std::mem::take(&mut rest)[k..].split_first_mut() else {
                break;
            };
            jobs.push((inst, g));
            (rest, base) = (tail, i + 1);
        }
        // One geometry draw per instance, pushed in instance order: every draw found its own.
        debug_assert_eq!(jobs.len(), draws, "geometry draws out of instance order");
        let ctx = GeometryJobs {
            models: &self.models,
            lod: &self.opts.lod,
            frustum,
            dt,
        };
        let work = |(inst, g): &mut (&mut Instance, &mut GeoDraw)| ctx.run(inst, g);
        if self.opts.plan_on_pool && jobs.len() >= PARALLEL_GEOMETRY_TREES {
            use rayon::prelude::*;
            jobs.par_iter_mut().for_each(work);
        } else {
            jobs.iter_mut().for_each(work);
        }
    }

    /// Each model's keep maxima over its geometry trees, in draw order (culled nodes keep 0,
    /// which leaves it alone).
    fn keep_maxima(&self, scratch: &mut FrameScratch) {
        for g in &scratch.geo {
            let Some(ModelState::Open(idx)) = self.models.get(g.model).map(|m| &m.state) else {
                continue;
            };
            let keep = Self::geo_keep_of(&self.instances, g, idx);
            for (n, &k) in scratch.needs[g.model].keep.iter_mut().zip(keep) {
                *n = (*n).max(k);
            }
        }
    }

    /// The band prefix the cache holds of each leaf node of model `m`, recomputed only when the
    /// cache changed.
    fn refresh_held_bands(&mut self, m: usize) {
        let generation = self.cache.generation();
        if self.held_bands.len() < self.models.len() {
            self.held_bands.resize_with(self.models.len(), || None);
        }
        let ModelState::Open(idx) = &self.models[m].state else {
            return;
        };
        if self.held_bands[m].as_ref().is_none_or(|h| h.generation != generation) {
            let bands: Vec<usize> = (0..idx.leaf_nodes.len())
                .map(|o| self.cache.held_leaf_bands(ModelId(m as u32), o as u32, &idx.layout))
                .collect();
            let present = idx
                .layout
                .leaf_counts()
                .iter()
                .zip(&bands)
                .map(|(&n, &b)| idx.layout.leaves_in_bands(n, b))
                .collect();
            self.held_bands[m] = Some(HeldBands {
                generation,
                bands,
                present,
            });
        }
    }

    /// Keep counts of a geometry draw, culled nodes at 0.
    fn geo_keep<'a>(&'a self, g: &'a GeoDraw, idx: &'a ModelIndex) -> &'a [u32] {
        Self::geo_keep_of(&self.instances, g, idx)
    }

    /// [`Self::geo_keep`] from the instances alone.
    fn geo_keep_of<'a>(instances: &'a [Instance], g: &'a GeoDraw, idx: &'a ModelIndex) -> &'a [u32] {
        match g.keep {
            KeepOf::Full => idx.layout.leaf_counts(),
            KeepOf::State => instances[g.inst as usize]
                .lod
                .as_ref()
                .map_or(idx.layout.leaf_counts(), |s| s.keep()),
            KeepOf::Masked => &g.culled_keep,
        }
    }

    /// Visual gain per leaf of the leaf nodes in `nodes` (the rest stay 0): the most any visible
    /// instance gives, `(projected node height)² / leaves`.
    fn leaf_gains(&self, m: usize, scratch: &FrameScratch, cam: &Camera, nodes: &[usize], out: &mut [f32]) {
        let Some(idx) = self.index(m) else { return };
        let vp = self.opts.viewport;
        for g in scratch.geo.iter().filter(|g| g.model == m) {
            let vis = (g.keep == KeepOf::Masked).then_some(&g.culled_vis);
            for &o in nodes {
                if vis.is_some_and(|v| !v[o]) {
                    continue;
                }
                let node = &idx.nodes[idx.leaf_nodes[o]];
                let nc = g.model_m.transform_point3(node.sphere_center);
                let nd = sphere_distance(cam.eye, nc, node.sphere_radius * g.scale);
                let npx = projected_height(2.0 * node.sphere_radius * g.scale, nd, vp.height as f32, vp.fov_y).min(1e4);
                let gain = npx * npx / node.leaf_count.max(1) as f32;
                out[o] = out[o].max(gain);
            }
        }
    }

    /// Turns the frame's needs into blocks to fetch, best gain per byte first, within the budget.
    fn plan(&mut self, scratch: &FrameScratch, cam: &Camera) -> Vec<(usize, Vec<Want>)> {
        let mut all: Vec<(usize, Want)> = Vec::new();
        for m in 0..scratch.needs.len() {
            let need = &scratch.needs[m];
            if !need.used || self.index(m).is_none() {
                continue;
            }
            // Leaf nodes with bands still to fetch, and their gains (only those are read).
            let mut leaf_plan = None;
            if need.geometry {
                self.refresh_held_bands(m);
                let nb = band_count(self.index(m));
                let (Some(Some(hb)), Some(idx)) = (self.held_bands.get(m), self.index(m)) else {
                    continue;
                };
                let held = &hb.bands;
                // A node needs more bands than it holds exactly when it keeps more leaves than
                // those bands hold (and not every band is held).
                let missing: Vec<usize> = need
                    .keep
                    .iter()
                    .zip(hb.bands.iter().zip(&hb.present))
                    .enumerate()
                    .filter(|(_, (k, (b, p)))| **k > **p && **b < nb)
                    .map(|(o, _)| o)
                    .collect();
                if !missing.is_empty() {
                    let mut gains = vec![0f32; idx.leaf_nodes.len()];
                    self.leaf_gains(m, scratch, cam, &missing, &mut gains);
                    leaf_plan = plan_leaf_ranges(&idx.layout, idx.leaves_offset, &need.keep, held, &gains).ok();
                }
            }
            let Some(idx) = self.index(m) else { continue };
            let id = ModelId(m as u32);
            let cache = &self.cache;
            let mut push = |unit: Option<Unit>, gain: f64| {
                let Some(Unit { key, range, check }) = unit else { return };
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
                for k in 0..idx.directory.iteration_table.len() {
                    push(idx.skeleton_unit(k), f64::MAX);
                }
                push(idx.bark_unit(), f64::MAX);
                if let Some(plan) = leaf_plan {
                    for r in plan.ranges {
                        let per_byte_gain = r.gain_per_byte();
                        for b in r.blocks {
                            let start = idx.leaves_offset + b.offset;
                            let unit = Unit {
                                key: BlockKey::Leaf {
                                    band: b.band,
                                    leaf_node: b.leaf_node,
                                },
                                range: start..start + b.len,
                                check: Check::LeafBlock { count: b.count },
                            };
                            push(Some(unit), per_byte_gain * b.len as f64);
                        }
                    }
                }
            }
            for (level, g) in need.hull.iter().enumerate() {
                if let Some(g) = *g {
                    push(idx.hull_unit(level), g);
                }
            }
            let nres = scratch.models[m].resolutions.max(1);
            for (k, g) in need.images.iter().enumerate() {
                if let Some(g) = *g {
                    push(idx.atlas_unit((k / nres) as u32, (k % nres) as u8), g);
                }
            }
            for (level, g) in need.clouds.iter().enumerate() {
                if let Some(g) = *g {
                    push(idx.cloud_unit(level), g);
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
        let planned: Vec<(usize, Vec<Want>, Vec<ByteRange>)> = wants
            .into_iter()
            .map(|(m, mut list)| {
                list.sort_by_key(|w| w.range.start);
                let ranges = merge_ranges_unless(list.iter().map(|w| w.range.clone()), |a, b| {
                    self.gap_holds_cached(m, a, b)
                });
                (m, list, ranges)
            })
            .collect();
        let jobs = planned.into_iter().map(|(m, list, ranges)| async move {
            let got = src.fetch(&models[m].url, &ranges).await;
            (m, list, ranges, got)
        });
        let results = join_all(jobs).await;
        for (m, list, ranges, got) in results {
            let Ok(bodies) = got else { continue };
            let wanted: HashSet<BlockKey> = list.iter().map(|w| w.key).collect();
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
                if self.unit_checks(m, w.check, bytes) {
                    self.accept_unit(m, w.key, bytes);
                } else {
                    self.corrupt_total += 1;
                }
            }
            self.keep_unasked_units(m, &ranges, &bodies, &wanted);
        }
    }

    /// Whether `bytes` pass `check` for a unit of model `m`.
    fn unit_checks(&self, m: usize, check: Check, bytes: &[u8]) -> bool {
        let Some(idx) = self.index(m) else { return false };
        match check {
            Check::Crc(crc) => check_crc("block", bytes, crc).is_ok(),
            Check::LeafBlock { count } => decode_block(bytes, count, idx.leaf_material_count).is_ok(),
            Check::CloudLevel(level) => idx
                .cloud
                .as_ref()
                .is_some_and(|c| c.verify_level(usize::from(level), bytes).is_ok()),
        }
    }

    /// Caches a checked unit of model `m` (a skeleton iteration also records its segments).
    fn accept_unit(&mut self, m: usize, key: BlockKey, bytes: &[u8]) {
        if let (BlockKey::Skeleton { iteration }, ModelState::Open(idx)) = (key, &mut self.models[m].state)
            && let Some(slot) = idx.skeleton_segments.get_mut(usize::from(iteration))
        {
            *slot = skeleton_segments(bytes);
        }
        self.cache_block(m, key, Arc::from(bytes));
    }

    /// Whether the bytes `a..b` of model `m` hold bytes the client already has, a unit the
    /// cache holds or bytes the opening requests read: such a gap is not merged over, or those
    /// bytes would cross the link again.
    fn gap_holds_cached(&self, m: usize, a: u64, b: u64) -> bool {
        let Some(idx) = self.index(m) else { return false };
        let id = ModelId(m as u32);
        idx.opened.iter().any(|r| r.start < b && a < r.end)
            || idx.units_within(a, b).iter().any(|u| self.cache.contains(id, u.key))
    }

    /// Whole units (leaf blocks, skeleton iterations, hull levels, atlas images, cloud levels)
    /// that arrived without being asked for: in the gaps merged between the `wanted` blocks
    /// ([`MERGE_GAP_BYTES`](crate::plan::MERGE_GAP_BYTES)), or in the requests that opened the
    /// model. Each is checked like a wanted one and cached, so that it does not cross the link
    /// again when it is needed. One is kept only while the cache has room for it without
    /// evicting (it must never push out a block this frame asked for); one that fails its
    /// check is dropped and counted as corrupt, like a wanted one. A leaf block may lie past a
    /// band the node does not hold yet: the cache's held prefix
    /// ([`BlockCache::held_leaf_bands`]) counts it once the bands before it arrive.
    fn keep_unasked_units(&mut self, m: usize, ranges: &[ByteRange], bodies: &[Bytes], wanted: &HashSet<BlockKey>) {
        let id = ModelId(m as u32);
        let Some(idx) = self.index(m) else { return };
        let (mut found, mut corrupt): (Vec<(BlockKey, &[u8])>, u64) = (Vec::new(), 0);
        // Reads may overlap (an opening read and a table read after it): one look per unit.
        let mut seen: HashSet<BlockKey> = HashSet::new();
        for (r, body) in ranges.iter().zip(bodies) {
            for u in idx.units_within(r.start, r.end) {
                if wanted.contains(&u.key) || self.cache.contains(id, u.key) || !seen.insert(u.key) {
                    continue;
                }
                let (Ok(a), Ok(b)) = (
                    usize::try_from(u.range.start - r.start),
                    usize::try_from(u.range.end - r.start),
                ) else {
                    continue;
                };
                let Some(bytes) = body.get(a..b) else { continue };
                if self.unit_checks(m, u.check, bytes) {
                    found.push((u.key, bytes));
                } else {
                    corrupt += 1;
                }
            }
        }
        self.corrupt_total += corrupt;
        for (key, data) in found {
            if self.cache.used_bytes() + data.len() as u64 > self.cache.budget() {
                break;
            }
            self.accept_unit(m, key, data);
        }
    }

    /// Inserts a checked block of model `m`, keeping the held band prefixes current.
    fn cache_block(&mut self, m: usize, key: BlockKey, data: Arc<[u8]>) {
        let (g0, ev0) = (self.cache.generation(), self.cache.stats().evictions);
        if self.cache.insert(ModelId(m as u32), key, data) && self.cache.stats().evictions == ev0 {
            self.note_insert(m, key, g0);
        }
    }

    /// Keeps the held band prefixes current after `key` of model `m` was inserted without
    /// evicting anything (the cache was at generation `g0` before): only that block changed.
    fn note_insert(&mut self, m: usize, key: BlockKey, g0: u64) {
        let g1 = self.cache.generation();
        for (k, slot) in self.held_bands.iter_mut().enumerate() {
            let Some(hb) = slot else { continue };
            if hb.generation != g0 {
                continue;
            }
            if let (true, BlockKey::Leaf { leaf_node, .. }, ModelState::Open(idx)) =
                (k == m, key, &self.models[k].state)
                && let Some(h) = hb.bands.get_mut(leaf_node as usize)
                && let Some(p) = hb.present.get_mut(leaf_node as usize)
            {
                *h = self.cache.held_leaf_bands(ModelId(k as u32), leaf_node, &idx.layout);
                *p = idx
                    .layout
                    .leaves_in_bands(idx.layout.leaf_counts()[leaf_node as usize], *h);
            }
            hb.generation = g1;
        }
    }

    fn draw_pass(&mut self, scratch: &FrameScratch) -> FrameReport {
        /// Per model, what every draw of it reads, looked up once per frame.
        struct ModelDraw {
            full_triangles: u64,
            bark_triangles: u64,
            has_geometry: bool,
            /// Triangles of each hull level held in the cache.
            hull_cached: Vec<Option<u32>>,
            /// Per atlas image (`frame × resolutions + resolution`): 0 not looked up, 1 held,
            /// 2 not held.
            image_cached: Vec<u8>,
            /// Planes of each cloud level held in the cache.
            cloud_cached: Vec<Option<u32>>,
            used_clouds: Vec<bool>,
            resolutions: usize,
            /// Most leaves any drawn instance keeps of each leaf node.
            max_keep: Vec<u32>,
            used_hull: Vec<bool>,
            used_images: Vec<bool>,
        }
        let mut rep = FrameReport::default();
        let mut drawn_list = Vec::with_capacity(scratch.draws.len());
        let mut per_model: Vec<Option<ModelDraw>> = (0..self.models.len()).map(|_| None).collect();
        // Held band prefixes of the models drawn as geometry (the cache changed while fetching).
        let geometry_models: Vec<usize> = (0..self.models.len())
            .filter(|&m| scratch.needs.get(m).is_some_and(|n| n.geometry))
            .collect();
        let mut held_by_model: Vec<Option<HeldBands>> = vec![None; self.models.len()];
        for m in geometry_models {
            self.refresh_held_bands(m);
            held_by_model[m] = self.held_bands.get(m).cloned().flatten();
        }
        for d in &scratch.draws {
            let Some(idx) = self.index(d.model) else { continue };
            let id = ModelId(d.model as u32);
            let cache = &self.cache;
            let md = per_model[d.model].get_or_insert_with(|| {
                let hull_cached: Vec<Option<u32>> = idx.hull.as_ref().map_or_else(Vec::new, |h| {
                    (0..h.levels.len())
                        .map(|l| {
                            cache
                                .contains(id, BlockKey::Hull { level: l as u16 })
                                .then_some(h.levels[l].triangles)
                        })
                        .collect()
                });
                let (frames, res) = idx
                    .atlas
                    .as_ref()
                    .map_or((0, 1), |a| (a.frames.len(), a.resolutions.len().max(1)));
                let cloud_cached: Vec<Option<u32>> = idx.cloud.as_ref().map_or_else(Vec::new, |c| {
                    c.levels
                        .iter()
                        .enumerate()
                        .map(|(l, e)| {
                            cache
                                .contains(id, BlockKey::Cloud { level: l as u8 })
                                .then_some(e.plane_count)
                        })
                        .collect()
                });
                ModelDraw {
                    used_clouds: vec![false; cloud_cached.len()],
                    cloud_cached,
                    full_triangles: 2 * u64::from(idx.directory.leaf_count) + idx.bark_triangles(),
                    bark_triangles: idx.bark_triangles(),
                    has_geometry: idx
                        .skeleton_iterations()
                        .all(|k| cache.contains(id, BlockKey::Skeleton { iteration: k })),
                    used_hull: vec![false; hull_cached.len()],
                    hull_cached,
                    image_cached: vec![0; frames * res],
                    used_images: vec![false; frames * res],
                    resolutions: res,
                    max_keep: vec![0; idx.leaf_nodes.len()],
                }
            });
            rep.full_triangles += md.full_triangles;
            // The wanted hull level if cached, else the finest cached one.
            let wanted_hull = match d.rep {
                Representation::Hull { level } => Some(usize::from(level)),
                _ => None,
            };
            let hull_any = wanted_hull
                .into_iter()
                .chain(0..md.hull_cached.len())
                .find_map(|l| md.hull_cached.get(l).copied().flatten().map(|t| (l, t)));
            let mut drew = None;
            match d.rep {
                Representation::Geometry if md.has_geometry => {
                    let Some(g) = scratch.geo.get(d.geo as usize) else {
                        continue;
                    };
                    let keep = self.geo_keep(g, idx);
                    let present: &[u32] = held_by_model[d.model].as_ref().map_or(&[], |h| &h.present);
                    let mut leaves = 0u64;
                    let mut per_node = vec![0u32; keep.len()];
                    let counts = idx.layout.leaf_counts();
                    for (o, &k) in keep.iter().enumerate() {
                        if k == 0 {
                            continue;
                        }
                        let n = counts[o];
                        md.max_keep[o] = md.max_keep[o].max(k);
                        let drawn = k.min(present.get(o).copied().unwrap_or(0));
                        per_node[o] = drawn;
                        leaves += u64::from(drawn);
                        rep.rate_histogram[rate_bin(drawn, n)] += 1;
                    }
                    rep.leaves += leaves;
                    rep.triangles += 2 * leaves + md.bark_triangles;
                    rep.geometry_trees += 1;
                    drew = Some(Drawn::Geometry {
                        leaves: per_node,
                        enlargement_cap: g.budget.enlargement_cap,
                    });
                }
                Representation::CloudLevel(want) => {
                    // The wanted levels that are held; else the held level nearest the first.
                    let mut levels: Vec<(u8, f32)> = d
                        .clouds
                        .iter()
                        .filter(|&&(l, w)| w > 0.0 && md.cloud_cached.get(usize::from(l)).copied().flatten().is_some())
                        .copied()
                        .collect();
                    if levels.is_empty()
                        && let Some(l) = (0..md.cloud_cached.len())
                            .filter(|&l| md.cloud_cached[l].is_some())
                            .min_by_key(|&l| l.abs_diff(usize::from(want)))
                    {
                        levels.push((l as u8, 1.0));
                    }
                    let total: f32 = levels.iter().map(|l| l.1).sum();
                    if total > 0.0 {
                        levels.sort_by(|a, b| b.1.total_cmp(&a.1));
                        let mut planes = 0u64;
                        for (l, w) in &mut levels {
                            *w /= total;
                            md.used_clouds[usize::from(*l)] = true;
                            planes += u64::from(md.cloud_cached[usize::from(*l)].unwrap_or(0));
                        }
                        rep.cloud_trees += 1;
                        rep.cloud_blends += usize::from(levels.len() > 1);
                        rep.cloud_planes += planes;
                        rep.triangles += 2 * planes;
                        drew = Some(Drawn::Cloud { levels });
                    }
                }
                Representation::Billboard(kind) => {
                    let mut held = FrameSet::default();
                    for &(f, r, w) in d.frames.as_slice() {
                        let k = f as usize * md.resolutions + usize::from(r);
                        let state = match md.image_cached.get(k) {
                            Some(0) => {
                                let s = if cache.contains(
                                    id,
                                    BlockKey::Atlas {
                                        frame: f,
                                        resolution: r,
                                    },
                                ) {
                                    1
                                } else {
                                    2
                                };
                                md.image_cached[k] = s;
                                s
                            }
                            Some(&s) => s,
                            None => 2,
                        };
                        if state == 1 {
                            held.push((f, r, w));
                            md.used_images[k] = true;
                        }
                    }
                    if held.len > 0 {
                        let quads = if kind == BillboardKind::Crossed {
                            2
                        } else {
                            u64::from(held.len)
                        };
                        rep.billboard_quads += quads;
                        rep.triangles += 2 * quads;
                        rep.billboard_trees += 1;
                        let total: f32 = held.as_slice().iter().map(|h| h.2).sum();
                        let frames = held
                            .as_slice()
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
                    md.used_hull[l] = true;
                    rep.hull_trees += 1;
                    rep.triangles += u64::from(tris);
                    drew = Some(Drawn::Hull { level: l as u16 });
                } else {
                    rep.pending_trees += 1;
                }
            }
            if let Some(what) = drew {
                drawn_list.push(DrawnTree {
                    instance: self.instances[d.inst as usize].inst.clone(),
                    what,
                });
            }
        }
        self.drawn = drawn_list;
        // Touch each block in use once per frame (the cache evicts the least used), in key
        // order: leaves (band, node), hull levels, cloud levels, atlas images.
        let mut touches = Vec::new();
        for (m, md) in per_model.into_iter().enumerate() {
            let Some(md) = md else { continue };
            // Bands drawn of each node: what the neediest instance keeps, as far as it is held
            // (bands needed grow with the keep count, so the maximum keep decides).
            let leaf_bands: Vec<usize> = match (self.index(m), &held_by_model[m]) {
                (Some(idx), Some(hb)) => md
                    .max_keep
                    .iter()
                    .zip(idx.layout.leaf_counts())
                    .zip(&hb.bands)
                    .map(|((&k, &n), &h)| h.min(idx.layout.bands_for_keep(n, k)))
                    .collect(),
                _ => Vec::new(),
            };
            let res = md.resolutions.max(1);
            let others = set_indices(&md.used_hull)
                .map(|l| BlockKey::Hull { level: l as u16 })
                .chain(set_indices(&md.used_clouds).map(|l| BlockKey::Cloud { level: l as u8 }))
                .chain(set_indices(&md.used_images).map(|k| BlockKey::Atlas {
                    frame: (k / res) as u32,
                    resolution: (k % res) as u8,
                }))
                .collect();
            touches.push(FrameTouches {
                model: ModelId(m as u32),
                leaf_bands,
                others,
            });
        }
        self.cache.touch_in_order(&touches);
        rep
    }
}

/// Where a box holding instance spheres lies against the view volume: `Out` only when every
/// sphere inside fails the per-instance test (beyond `far` or outside a plane), `In` only when
/// every sphere passes it.
fn classify_box(b: TileBox, eye: Vec3, far: f32, frustum: &Frustum) -> TileClass {
    // Margin (metres) that absorbs float rounding between the box and per-sphere tests.
    const EPS: f32 = 0.01;
    let (lo, hi) = (b.lo, b.hi);
    if !(lo.is_finite() && hi.is_finite() && eye.is_finite()) {
        return TileClass::Partial;
    }
    // Nearest and farthest points of the box from the eye.
    let near_pt = eye.clamp(lo, hi);
    let far_pt = Vec3::select(eye.cmplt((lo + hi) * 0.5), hi, lo);
    if near_pt.distance(eye) > far + EPS {
        return TileClass::Out;
    }
    let mut inside = far_pt.distance(eye) < far - EPS;
    for p in frustum.planes() {
        let n = p.truncate();
        // The corners with the largest and the smallest signed distance to the plane.
        let pos = Vec3::select(n.cmpge(Vec3::ZERO), hi, lo);
        let neg = Vec3::select(n.cmpge(Vec3::ZERO), lo, hi);
        if n.dot(pos) + p.w < -EPS {
            return TileClass::Out;
        }
        if n.dot(neg) + p.w < EPS {
            inside = false;
        }
    }
    if inside { TileClass::In } else { TileClass::Partial }
}

/// Leaf bands of an open model's layout (0 when closed).
fn band_count(idx: Option<&ModelIndex>) -> usize {
    idx.map_or(0, |i| i.layout.band_count())
}

/// An instance's placement (model → world) and its scale (1 when not finite and positive).
fn placement(inst: &PackInstance) -> (Mat4, f32) {
    let pos = Vec3::from(inst.position);
    let scale = if inst.scale.is_finite() && inst.scale > 0.0 {
        inst.scale
    } else {
        1.0
    };
    let rot = Quat::from_rotation_y(inst.rotation);
    (
        Mat4::from_scale_rotation_translation(Vec3::splat(scale), rot, pos),
        scale,
    )
}

/// Frames (and the resolution index) a billboard of `kind` needs for a view from `dir_model`
/// (unit, model frame, tree → eye), at `px` projected pixels.
#[cfg(test)]
fn billboard_frames(a: &AtlasTable, kind: BillboardKind, dir_model: Vec3, px: f32) -> Vec<(u32, u8, f32)> {
    let mut g = AtlasFrame::default();
    g.set(Some(a));
    g.frames(kind, dir_model, px).as_slice().to_vec()
}

/// The choice as first written (allocating, per tree), the reference for [`AtlasFrame::frames`].
#[cfg(test)]
fn reference_billboard_frames(a: &AtlasTable, kind: BillboardKind, dir_model: Vec3, px: f32) -> Vec<(u32, u8, f32)> {
    let res = a.resolutions.iter().rposition(|&s| f32::from(s) >= px).unwrap_or(0) as u8;
    let Some(layout) = a.layouts.iter().find(|l| layout_is(kind, &l.kind)) else {
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

/// The indices of the `true` flags.
fn set_indices(flags: &[bool]) -> impl Iterator<Item = usize> + '_ {
    flags.iter().enumerate().filter_map(|(k, &u)| u.then_some(k))
}

/// Runs `f` inside a rayon scope whose calling thread is this one (jobs spawned on it go to the
/// pool) when `on`, else with no pool.
fn with_pool<'s, R>(on: bool, f: impl FnOnce(Option<&rayon::Scope<'s>>) -> R) -> R {
    if on {
        rayon::in_place_scope(|s| f(Some(s)))
    } else {
        f(None)
    }
}

/// What every geometry job of a frame reads.
#[derive(Clone, Copy)]
struct GeometryJobs<'s> {
    models: &'s [Model],
    lod: &'s LodParams,
    frustum: &'s Frustum,
    dt: f32,
}

impl<'s> GeometryJobs<'s> {
    /// Runs [`Self::run`] for each tree of `batch` on the pool, in order, and sends each
    /// result back with its draw index.
    fn spawn(
        self,
        pool: &rayon::Scope<'s>,
        batch: Vec<(u32, &'s mut Instance, GeoDraw)>,
        done: &std::sync::mpsc::Sender<(u32, GeoDraw)>,
    ) {
        let done = done.clone();
        pool.spawn(move |_| {
            for (gi, inst, mut g) in batch {
                self.run(inst, &mut g);
                // The receiver lives until the scope has ended.
                let _ = done.send((gi, g));
            }
        });
    }

    /// One geometry tree's share of the frame: nodes culled where the tree crosses a frustum
    /// plane, then switch control advanced by `dt` for the visible nodes (when it has state;
    /// seed 004 culls first), keep counts lowered to the pixel budget where it limits the tree.
    /// Reads nothing another tree's job writes.
    fn run(self, inst: &mut Instance, g: &mut GeoDraw) {
        let ModelState::Open(idx) = &self.models[g.model].state else {
            return;
        };
        // Node culling only for trees that cross a frustum plane. Planes every node sphere
        // is inside of (with a margin for rounding) pass every node: test only the others.
        let crossing = self
            .frustum
            .crossing(g.center, idx.node_reach * g.scale * 1.0001 + 0.01);
        let culls = !crossing.planes().is_empty();
        g.culled_vis.clear();
        if culls {
            // The crossing planes taken into the model's frame, so that the walk reads the
            // model's node spheres (shared by its instances, and so mostly in cache) instead of
            // placed ones.
            visible_leaves_world(
                &crossing.in_frame_of(g.model_m),
                &idx.node_spheres,
                &idx.nodes,
                &idx.subtree_reach,
                &idx.leaves_before,
                1.0,
                &mut g.culled_vis,
            );
        }
        if let (Some(eye), Some(state)) = (g.eye_model, inst.lod.as_mut()) {
            let mut p = self.lod.clone();
            p.near /= g.scale;
            p.far /= g.scale;
            state.update_visible(&p, eye, self.dt, &g.culled_vis);
        }
        let counts = idx.layout.leaf_counts();
        let keep = match (g.keep, &inst.lod) {
            (KeepOf::State, Some(st)) => st.keep(),
            _ => counts,
        };
        if !culls && !g.budget.limits() {
            return;
        }
        g.culled_keep.clear();
        if !culls {
            g.culled_keep.extend_from_slice(keep);
            g.culled_vis.resize(keep.len(), true);
        } else if g.culled_vis.len() == keep.len() {
            // Branch-free, so that it vectorises: 0 where culled.
            g.culled_keep
                .extend(keep.iter().zip(&g.culled_vis).map(|(&k, &v)| k * u32::from(v)));
        } else {
            // Not one flag per leaf node (malformed tables): culled wherever there is none.
            let vis = &g.culled_vis;
            g.culled_keep.extend(
                keep.iter()
                    .enumerate()
                    .map(|(o, &k)| if vis.get(o) == Some(&true) { k } else { 0 }),
            );
        }
        if g.budget.limits() {
            let f = g.budget.keep_fraction;
            for (k, &n) in g.culled_keep.iter_mut().zip(counts) {
                *k = (*k).min(budget_keep(n, f));
            }
        }
        g.keep = KeepOf::Masked;
    }
}

/// The [`FrameReport::rate_histogram`] bin of a node that draws `drawn` of its `leaves`: bin `k`
/// holds rates `1 − drawn/leaves` in `[k/10, (k + 1)/10)`, 1.0 in the last. Exact (integers):
/// in floating point rates of exactly 0.1 or 0.2 (9 or 8 of 10 leaves drawn) came out just below and
/// fell one bin low. Malformed counts read as before: `drawn > leaves` as rate 0, and a node of no
/// leaves as one of one leaf.
pub fn rate_bin(drawn: u32, leaves: u32) -> usize {
    let n = leaves.max(1);
    let left_out = u64::from(n.saturating_sub(drawn));
    ((left_out * 10 / u64::from(n)) as usize).min(9)
}

/// Merges sorted ranges whose gap is under [`MERGE_GAP_BYTES`] (the plan's rule, applied to the
/// blocks of one model across kinds).
pub fn merge_ranges(sorted: impl Iterator<Item = ByteRange>) -> Vec<ByteRange> {
    merge_ranges_unless(sorted, |_, _| false)
}

/// [`merge_ranges`], except that a gap `end..start` for which `keep_apart(end, start)` holds is
/// never merged over (the fetcher passes "the gap holds a cached block").
pub fn merge_ranges_unless(
    sorted: impl Iterator<Item = ByteRange>,
    keep_apart: impl Fn(u64, u64) -> bool,
) -> Vec<ByteRange> {
    let mut out: Vec<ByteRange> = Vec::new();
    for r in sorted {
        if let Some(last) = out.last_mut()
            && r.start >= last.start
            && r.start.saturating_sub(last.end) < MERGE_GAP_BYTES
            && (r.start <= last.end || !keep_apart(last.end, r.start))
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

impl From<CloudError> for OpenError {
    fn from(_: CloudError) -> Self {
        // As for the rest of the index: maybe a corrupted transfer, so tried again.
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

/// The byte ranges a model's opening requests read, with their bodies: in a small file they
/// also hold leaf blocks, atlas images and the like, which are kept
/// ([`Streamer::keep_unasked_units`]) rather than fetched again.
type OpeningReads = (Vec<ByteRange>, Vec<Bytes>);

/// Opens a model: header and directory, then node table, materials and the hull and atlas tables
/// in one multi-range request.
async fn open_model<S: RangeSource>(src: &S, url: &str, size: u64) -> Result<(ModelIndex, OpeningReads), OpenError> {
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
    let cloud_e = sec(SectionKind::BillboardClouds);
    // Table prefixes: the hull table is ≤ 484 bytes, the atlas table ~10 KiB and the cloud
    // table ~1 KiB by default. Ask for enough to hold each in one go and fetch the rest of a
    // bigger table after.
    let hull_prefix = hull_e.map(|e| e.offset..e.offset + e.length.min(1024));
    let atlas_prefix = atlas_e.map(|e| e.offset..e.offset + e.length.min(16 * 1024));
    let cloud_prefix = cloud_e.map(|e| e.offset..e.offset + e.length.min(CLOUD_TABLE_PREFIX));
    let mut ranges = vec![nodes_e.range(), mats_e.range()];
    ranges.extend(hull_prefix.clone().filter(|r| r.end > r.start));
    ranges.extend(atlas_prefix.clone().filter(|r| r.end > r.start));
    ranges.extend(cloud_prefix.clone().filter(|r| r.end > r.start));
    // What the first request already holds (all of it, in a small file) is not asked again: a
    // table that starts inside it is asked from where it ends.
    let held = first.len() as u64;
    let mut sorted: Vec<ByteRange> = ranges
        .iter()
        .filter(|r| r.end > held)
        .map(|r| r.start.max(held)..r.end)
        .collect();
    sorted.sort_by_key(|r| r.start);
    let merged = merge_ranges(sorted.into_iter());
    let bodies = if merged.is_empty() {
        Vec::new()
    } else {
        src.fetch(url, &merged).await?
    };
    let first_read: ByteRange = 0..held;
    let mut reads: OpeningReads = (vec![first_read], vec![first.clone()]);
    let slice = |r: &ByteRange| -> Option<Cow<'_, [u8]>> {
        if r.end <= held {
            return first.get(r.start as usize..r.end as usize).map(Cow::Borrowed);
        }
        let rest = r.start.max(held)..r.end;
        let k = merged.iter().position(|m| m.start <= rest.start && rest.end <= m.end)?;
        let tail = bodies
            .get(k)?
            .get((rest.start - merged[k].start) as usize..(rest.end - merged[k].start) as usize)?;
        if r.start >= held {
            return Some(Cow::Borrowed(tail));
        }
        let mut joined = first.get(r.start as usize..)?.to_vec();
        joined.extend_from_slice(tail);
        Some(Cow::Owned(joined))
    };
    let table = slice(&nodes_e.range()).ok_or(OpenError::Retry)?;
    check_crc("node table", &table, nodes_e.crc)?;
    let nodes = decode_nodes(&table, directory.node_count, directory.branch_count)?;
    let mats = slice(&mats_e.range()).ok_or(OpenError::Retry)?;
    check_crc("materials", &mats, mats_e.crc)?;
    let materials = decode_materials(&mats)?;
    let hull = match (&hull_e, &hull_prefix) {
        (Some(e), Some(r)) if e.length > 0 => {
            let p = slice(r).ok_or(OpenError::Retry)?;
            let bytes = section_table(src, url, e, &p, HullTable::peek_table_len(&p)?).await?;
            Some(HullTable::decode(&bytes, e.length)?)
        }
        _ => None,
    };
    let atlas = match (&atlas_e, &atlas_prefix) {
        (Some(e), Some(r)) if e.length > 0 => {
            let p = slice(r).ok_or(OpenError::Retry)?;
            let bytes = section_table(src, url, e, &p, AtlasTable::peek_table_len(&p)?).await?;
            Some(AtlasTable::decode(&bytes, e.length)?)
        }
        _ => None,
    };
    let cloud = match (&cloud_e, &cloud_prefix) {
        (Some(e), Some(r)) if e.length > 0 => {
            // Clouds are optional: a table this client cannot use (malformed, or with flags from
            // a newer format) leaves the model without clouds rather than unopened. Only a CRC
            // mismatch, which a corrupted transfer gives, opens the model again.
            let p = slice(r).ok_or(OpenError::Retry)?;
            match CloudTable::peek_table_len(&p) {
                Ok(len) => {
                    let bytes = section_table(src, url, e, &p, len).await?;
                    match CloudTable::decode(&bytes, e.length) {
                        Ok(t) => Some(t).filter(|t| !t.levels.is_empty()),
                        Err(err @ CloudError::Checksum { .. }) => return Err(err.into()),
                        Err(_) => None,
                    }
                }
                Err(_) => None,
            }
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
    let (leaves_offset, leaves_len) = sec(SectionKind::Leaves).map_or((0, 0), |e| (e.offset, e.length));
    // Leaf blocks are located from the node table alone: a section of another length would put
    // them on other bytes.
    if leaves_len != layout.total_len() {
        return Err(OpenError::Fatal(format!(
            "the leaves section is {leaves_len} bytes, but the node table's leaf counts need {}",
            layout.total_len()
        )));
    }
    let bark_mesh_tris = sec(SectionKind::BarkMesh).map_or(0, |e| u64::from(e.item_count));
    let root = nodes
        .first()
        .ok_or_else(|| OpenError::Fatal("empty node table".into()))?;
    let (lo, hi) = (directory.bounds_min, directory.bounds_max);
    let center = root.sphere_center;
    let radius = root.sphere_radius.max((hi - lo).length() * 0.5);
    let node_reach = nodes
        .iter()
        .map(|n| n.sphere_center.distance(center) + n.sphere_radius.max(0.0))
        .fold(0f32, f32::max);
    reads.0.extend(merged.iter().cloned());
    reads.1.extend(bodies);
    let mut opened = reads.0.clone();
    opened.sort_by_key(|r| r.start);
    let mut index = ModelIndex {
        other_units: Vec::new(),
        opened,
        subtree_reach: crate::lod::tree::subtree_reach(&nodes),
        leaves_before: crate::lod::tree::leaves_before(&nodes),
        node_spheres: nodes.iter().map(|n| n.sphere_center.extend(n.sphere_radius)).collect(),
        leaf_table: Arc::new(LeafTable::new(&nodes)),
        node_reach: if node_reach.is_finite() {
            node_reach
        } else {
            f32::INFINITY
        },
        height: (hi.y - lo.y.min(0.0)).max(0.01),
        center,
        radius,
        leaf_size: (directory.leaf_width_max * directory.leaf_length_max).sqrt(),
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
        cloud,
    };
    index.other_units = index.other_units();
    Ok((index, reads))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A file whose leaves section has another length than its node table's leaf counts need
    /// (the directory and header CRCs recomputed, so only this check can catch it) is refused at
    /// open with a message; the same file unaltered opens.
    #[tokio::test]
    async fn a_leaves_section_that_disagrees_with_the_node_table_is_refused() {
        use canopy_shared::format::tree::decode_index;
        use canopy_shared::format::{HEADER_LEN, crc32};
        let good = crate::plan::tests::encoded_tree(&[64, 3, 200]);
        let (header, mut dir) = decode_index(&good, Some(good.len() as u64)).expect("index");
        let leaves = dir
            .sections
            .iter_mut()
            .find(|e| e.kind == SectionKind::Leaves)
            .expect("a leaves section");
        leaves.length -= 20;
        let dir_bytes = dir.encode();
        assert_eq!(dir_bytes.len(), header.directory_len as usize);
        let h = canopy_shared::format::header::Header {
            directory_crc: crc32(&dir_bytes),
            ..header
        };
        let mut bad = good.clone();
        bad[..HEADER_LEN].copy_from_slice(&h.encode());
        bad[HEADER_LEN..HEADER_LEN + dir_bytes.len()].copy_from_slice(&dir_bytes);

        let root = std::env::temp_dir().join(format!("canopy-leaves-len-{}", std::process::id()));
        std::fs::create_dir_all(root.join("assets")).expect("mkdir");
        std::fs::write(root.join("assets/good.ctree"), &good).expect("write");
        std::fs::write(root.join("assets/bad.ctree"), &bad).expect("write");
        let src = crate::net::file::FileSource::new(&root);
        let size = good.len() as u64;
        assert!(open_model(&src, "/assets/good.ctree", size).await.is_ok());
        let refused = match open_model(&src, "/assets/bad.ctree", size).await {
            Err(OpenError::Fatal(m)) => m,
            Err(_) => "another error".into(),
            Ok(_) => "opened".into(),
        };
        std::fs::remove_dir_all(&root).ok();
        assert!(refused.contains("leaves section"), "{refused}");
    }

    #[test]
    fn rate_bins_are_exact_tenths() {
        // 9 of 10 drawn is a rate of exactly 0.1: bin 1 (the float form gave 0.0999… → bin 0).
        assert_eq!(rate_bin(9, 10), 1);
        assert_eq!(rate_bin(10, 10), 0);
        assert_eq!(rate_bin(0, 10), 9);
        assert_eq!(rate_bin(1, 10), 9);
        assert_eq!(rate_bin(3, 10), 7);
        assert_eq!(rate_bin(7, 10), 3);
        assert_eq!(rate_bin(1, 3), 6); // 0.667
        assert_eq!(rate_bin(u32::MAX - 1, u32::MAX), 0);
        assert_eq!(rate_bin(0, u32::MAX), 9);
        // Malformed: more drawn than there are, or no leaves at all.
        assert_eq!(rate_bin(11, 10), 0);
        assert_eq!(rate_bin(0, 0), 9);
        assert_eq!(rate_bin(1, 0), 0);
        // Every tenth boundary lands in the bin it opens.
        for n in [10u32, 20, 50, 100, 1000, 4090] {
            for k in 0..10 {
                let drawn = n - n / 10 * k;
                assert_eq!(rate_bin(drawn, n), k as usize, "{drawn} of {n}");
            }
        }
    }

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
    fn merge_ranges_keeps_apart_gaps_it_is_told_to() {
        let apart = |a: u64, b: u64| a <= 15 && b >= 15;
        // The gap 10..20 holds byte 15: not merged; 30..40 does not: merged.
        assert_eq!(
            merge_ranges_unless([0..10, 20..30, 40..50].into_iter(), apart),
            vec![0..10, 20..50]
        );
        // Touching and overlapping ranges have no gap to keep apart.
        assert_eq!(
            merge_ranges_unless([0..15, 15..20, 18..25].into_iter(), apart),
            vec![0..25]
        );
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

    proptest::proptest! {
        /// Whole-tile decisions agree with the per-instance test for every sphere in the box.
        #[test]
        fn tile_classes_agree_with_the_instance_test(
            ex in -300.0f32..300.0, ey in 1.0f32..80.0, ez in -300.0f32..300.0, yaw in -3.2f32..3.2,
            pitch in -1.4f32..0.3, bx in -400.0f32..400.0, bz in -400.0f32..400.0, w in 1.0f32..120.0,
            spheres in proptest::collection::vec((0.0f32..1.0, 0.0f32..1.0, 0.0f32..1.0, 0.5f32..12.0), 1..12),
            far in 100.0f32..600.0,
        ) {
            let cam = Camera { eye: Vec3::new(ex, ey, ez), yaw, pitch };
            let vp = Viewport { far, ..Viewport::default() };
            let f = Frustum::from_view_proj(vp.projection() * cam.view(), DepthRange::ZeroToOne);
            let list: Vec<(Vec3, f32)> = spheres
                .iter()
                .map(|&(u, v, t, r)| (Vec3::new(bx + u * w, v * 25.0, bz + t * w), r))
                .collect();
            let lo = list.iter().fold(Vec3::splat(f32::INFINITY), |a, (c, r)| a.min(*c - Vec3::splat(*r)));
            let hi = list.iter().fold(Vec3::splat(f32::NEG_INFINITY), |a, (c, r)| a.max(*c + Vec3::splat(*r)));
            let class = classify_box(TileBox { lo, hi }, cam.eye, far, &f);
            for (c, r) in list {
                let passes = c.distance(cam.eye) - r <= far && f.intersects_sphere(c, r);
                match class {
                    TileClass::Out => proptest::prop_assert!(!passes),
                    TileClass::In => proptest::prop_assert!(passes),
                    TileClass::Partial => {}
                }
            }
        }
    }

    #[test]
    fn tiles_in_front_behind_and_beyond_the_view_distance() {
        let cam = Camera {
            eye: Vec3::new(0.0, 10.0, 0.0),
            yaw: 0.0,
            pitch: 0.0,
        };
        let vp = Viewport::default();
        let f = Frustum::from_view_proj(vp.projection() * cam.view(), DepthRange::ZeroToOne);
        let b = |z: f32| TileBox {
            lo: Vec3::new(-5.0, 0.0, z - 5.0),
            hi: Vec3::new(5.0, 20.0, z + 5.0),
        };
        assert_eq!(classify_box(b(-100.0), cam.eye, vp.far, &f), TileClass::In);
        assert_eq!(classify_box(b(100.0), cam.eye, vp.far, &f), TileClass::Out);
        assert_eq!(classify_box(b(-2000.0), cam.eye, vp.far, &f), TileClass::Out);
        assert_eq!(classify_box(b(-vp.far), cam.eye, vp.far, &f), TileClass::Partial);
        assert_eq!(classify_box(b(0.0), cam.eye, vp.far, &f), TileClass::Partial);
    }

    proptest::proptest! {
        /// The per-model billboard choice gives exactly the frames and weights of the reference.
        #[test]
        fn gathered_atlas_choice_matches_the_reference(
            x in -1.0f32..1.0, y in -1.0f32..1.0, z in -1.0f32..1.0, px in 0.0f32..300.0,
        ) {
            let dir = Vec3::new(x, y, z).normalize_or_zero();
            let a = atlas();
            let mut g = AtlasFrame::default();
            g.set(Some(&a));
            for kind in [BillboardKind::HemiOct, BillboardKind::LatLong, BillboardKind::Crossed] {
                let got = g.frames(kind, dir, px).as_slice().to_vec();
                proptest::prop_assert_eq!(got, reference_billboard_frames(&a, kind, dir, px));
            }
        }
    }
}
