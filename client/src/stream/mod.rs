//! The client frame loop: from a camera to the bytes the LOD needs, fetched, checked and drawn
//! from what is held. A frame is a list of stages with plain types between them; each stage is
//! one module with one job, and none writes another's state:
//!
//! | stage | module | reads → gives |
//! |---|---|---|
//! | view | [`view`] | camera, viewport → frustum |
//! | instances | [`instances`] | manifest, eye → loaded instance tiles, their placement |
//! | models | [`model`] ([`model::open`], [`model::index`]) | nearby instances → opened model indexes (immutable) |
//! | select | [`select`] | instances, indexes, frustum → draws per instance, needs per model |
//! | geometry | [`geometry`] | geometry draws → per-node keep counts; owns per-tree LOD state |
//! | needs | [`needs`] | geometry draws → each model's keep maxima, leaf-node gains |
//! | schedule | [`schedule`] | needs, residency → requests: units ordered once, ranges merged once |
//! | fetch | [`fetch`] | requests → bodies (network only) |
//! | residency | [`residency`] | bodies → units checked by `canopy_shared::format`, cache, held bands |
//! | resolve | [`resolve`] | draws, residency → what is drawn from what is held, units in use |
//! | report | [`report`] | → [`FrameReport`], [`DrawnTree`] |
//!
//! The loop is deterministic for a given scene, camera path and options (instances are visited
//! in id order; fetches complete before the frame ends). [`Streamer::stage_times`] times each
//! stage of the last frame.

mod billboard;
mod cached;
mod fetch;
mod geometry;
mod instances;
mod model;
mod needs;
mod report;
mod residency;
mod resolve;
mod schedule;
mod select;
mod view;

use std::sync::Arc;
use std::time::Instant;

use serde::Serialize;

pub use cached::CachedModel;
pub use geometry::PARALLEL_GEOMETRY_TREES;
pub use model::open::OPEN_REQUEST_LEN;
pub use model::{BARK_SIDES, OpenedTree, open_tree};
pub use report::{Drawn, DrawnTree, FrameReport, rate_bin};
pub use view::{Camera, Viewport};

use crate::cache::CacheStats;
use crate::lod::projection::{DEFAULT_LADDER, LadderStep, SWITCH_BLEND_BAND};
use crate::lod::{FlightParams, LodParams};
use crate::net::RangeSource;
use crate::scene::Manifest;
use geometry::GeometryStates;
use instances::Instances;
use model::Models;
use residency::Residency;
use select::Selection;

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

/// Wall time of each stage of one frame, milliseconds (the plan bench reads them).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct StageTimes {
    /// Loading instance tiles (network).
    pub instances_ms: f64,
    /// Opening models (network) and placing instances.
    pub models_ms: f64,
    /// Selection, with the geometry and needs stages.
    pub select_ms: f64,
    /// Scheduling (held bands refreshed, units ordered, ranges merged).
    pub schedule_ms: f64,
    /// Fetching (network).
    pub fetch_ms: f64,
    /// Checking and keeping what arrived.
    pub residency_ms: f64,
    /// Resolving draws against what is held, and marking units in use.
    pub resolve_ms: f64,
}

/// The streaming client for one scene: its stages' state, each owned by its stage.
#[derive(Debug)]
pub struct Streamer<S: RangeSource> {
    src: Arc<S>,
    manifest: Manifest,
    opts: StreamOptions,
    models: Models,
    instances: Instances,
    geometry: GeometryStates,
    selection: Selection,
    residency: Residency,
    frame: u64,
    corrupt_total: u64,
    drawn: Vec<DrawnTree>,
    times: StageTimes,
}

/// Milliseconds since `t`, and `t` moved to now.
fn lap(t: &mut Instant) -> f64 {
    let now = Instant::now();
    let ms = (now - *t).as_secs_f64() * 1e3;
    *t = now;
    ms
}

impl<S: RangeSource> Streamer<S> {
    /// A streamer for an already fetched manifest.
    pub fn with_manifest(src: Arc<S>, manifest: Manifest, opts: StreamOptions) -> Self {
        Self {
            src,
            models: Models::new(&manifest),
            instances: Instances::new(manifest.tiles.len()),
            geometry: GeometryStates::default(),
            residency: Residency::new(opts.cache_budget),
            selection: Selection::default(),
            manifest,
            opts,
            frame: 0,
            corrupt_total: 0,
            drawn: Vec::new(),
            times: StageTimes::default(),
        }
    }

    /// The manifest.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// Cache counters.
    pub fn cache_stats(&self) -> CacheStats {
        self.residency.stats()
    }

    /// The source.
    pub fn source(&self) -> &S {
        &self.src
    }

    /// Models that could not be opened (name, reason): bad files or missing ones. Their
    /// instances are not drawn.
    pub fn failed_models(&self) -> Vec<(String, String)> {
        self.models.failed(&self.manifest)
    }

    /// Models whose last opening read bytes that failed a check (name, reason): a corrupted
    /// transfer or a corrupt file. They are tried again every frame.
    pub fn retrying_models(&self) -> Vec<(String, String)> {
        self.models.retrying(&self.manifest)
    }

    /// Blocks that failed their check since the start.
    pub fn corrupt_blocks(&self) -> u64 {
        self.corrupt_total
    }

    /// What each visible tree was drawn as in the last frame (instances in id order).
    pub fn drawn(&self) -> &[DrawnTree] {
        &self.drawn
    }

    /// Wall time of each stage of the last frame.
    pub fn stage_times(&self) -> StageTimes {
        self.times
    }

    /// One frame: the stages in order (see the module doc).
    pub async fn frame(&mut self, cam: &Camera, dt: f32) -> FrameReport {
        let t_frame = Instant::now();
        let mut t = t_frame;
        let net0 = self.src.stats().snapshot();
        let mut corrupt = 0u64;
        let far = self.opts.viewport.far;

        // Instances: the tiles within the view distance.
        corrupt += self
            .instances
            .load_tiles(self.src.as_ref(), &self.manifest, cam.eye, far)
            .await;
        if let Some(from) = self.instances.take_reordered() {
            self.geometry.reorder(&from);
        }
        self.times.instances_ms = lap(&mut t);

        // Models: open those nearby instances use; keep what their opening reads carried.
        if self.models.any_closed() {
            let wanted = self.instances.models_near(cam.eye, far + 100.0);
            let opened = self.models.open(self.src.as_ref(), wanted).await;
            corrupt += opened.corrupt;
            for (m, (ranges, bodies)) in &opened.reads {
                corrupt += self.residency.keep_unasked(
                    &self.models,
                    *m,
                    ranges,
                    bodies,
                    &std::collections::HashSet::default(),
                );
            }
            self.instances.stale |= !opened.reads.is_empty();
        }
        if self.instances.stale {
            self.instances.place(&self.models);
            self.geometry.refresh_live();
        }
        self.times.models_ms = lap(&mut t);

        // Select (with geometry and needs): what each visible tree is drawn as.
        let t_plan = t;
        let frustum = view::frustum(&self.opts.viewport, cam);
        let sel = &mut self.selection;
        let visible = select::select(
            &self.models,
            &self.instances,
            &mut self.geometry,
            &self.opts,
            cam,
            &frustum,
            dt,
            self.frame,
            sel,
        );
        let nodes_evaluated: u64 = sel
            .geo
            .iter()
            .filter(|g| g.eye_model.is_some())
            .filter_map(|g| self.geometry.trees.get(g.inst as usize)?.lod.as_ref())
            .map(|st| st.evaluated() as u64)
            .sum();
        self.times.select_ms = lap(&mut t);

        // Schedule: what to fetch, ordered and merged.
        self.refresh_held_bands(|need| need.used && need.geometry);
        let plan = schedule::schedule(&self.models, &self.residency, &self.selection, cam, &self.opts);
        self.residency.record_misses(plan.misses);
        let plan_ms = t_plan.elapsed().as_secs_f64() * 1e3;
        self.times.schedule_ms = lap(&mut t);

        // Fetch, then keep what arrived (checked).
        let bodies = fetch::fetch_all(self.src.as_ref(), &self.models, &plan.requests).await;
        self.times.fetch_ms = lap(&mut t);
        for (req, got) in plan.requests.iter().zip(&bodies) {
            if let Ok(bodies) = got {
                corrupt += self.residency.store(&self.models, req, bodies);
            }
        }
        self.times.residency_ms = lap(&mut t);

        // Resolve: what is drawn from what is held.
        self.refresh_held_bands(|need| need.geometry);
        let resolved = resolve::resolve(
            &self.models,
            &self.instances,
            &self.geometry.trees,
            &self.selection,
            &self.residency,
        );
        self.residency.touch(&resolved.touches);
        self.drawn = resolved.drawn;
        self.times.resolve_ms = lap(&mut t);

        // Report.
        let net1 = self.src.stats().snapshot();
        self.corrupt_total += corrupt;
        let report = FrameReport {
            frame: self.frame,
            bytes: net1.bytes - net0.bytes,
            requests: net1.requests - net0.requests,
            retries: net1.retries - net0.retries,
            failures: net1.failures - net0.failures,
            corrupt_blocks: corrupt,
            cache_bytes: self.residency.used_bytes(),
            instances_loaded: self.instances.list.len(),
            visible,
            plan_ms,
            nodes_evaluated,
            frame_ms: t_frame.elapsed().as_secs_f64() * 1e3,
            ..resolved.report
        };
        self.residency.end_frame(self.frame);
        self.frame += 1;
        report
    }

    /// Brings the held band prefixes of the models whose need passes `which` up to date.
    fn refresh_held_bands(&mut self, which: impl Fn(&needs::Need) -> bool) {
        for (m, need) in self.selection.needs.iter().enumerate() {
            if which(need) {
                self.residency.refresh_held_bands(&self.models, m);
            }
        }
    }
}
