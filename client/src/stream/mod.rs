//! The client frame loop: from a camera to the bytes the LOD needs, requested, checked and drawn
//! from what is held. A frame is a list of stages with plain types between them; each stage is
//! one module with one job, and none writes another's state. The frame never waits for the
//! network: transfers run as tasks, and each frame takes in what has arrived since the last.
//!
//! | stage | module | reads → gives |
//! |---|---|---|
//! | arrivals | [`transfers`] | finished tasks → tiles, openings, unit bodies; the link estimate |
//! | view | [`view`] | camera, viewport → frustum |
//! | terrain | [`crate::terrain`] | manifest, eye → terrain tile loads started, nearest first |
//! | instances | [`instances`] | manifest, eye → tile loads started; loaded tiles placed |
//! | models | [`model`] ([`model::open`], [`model::index`]) | nearby instances → openings started; opened indexes (immutable) |
//! | occlusion | [`crate::lod::occlusion`] | terrain held (and the tiles' bounds), camera → the horizon the ground makes, per azimuth and distance |
//! | select | [`select`] | instances, indexes, frustum, occlusion → draws per instance, needs per model |
//! | geometry | [`geometry`] | geometry draws → per-node keep counts; owns per-tree LOD state |
//! | needs | [`needs`] | geometry draws → each model's keep maxima, leaf-node gains |
//! | schedule | [`schedule`] | needs, residency, in flight → requests: stand-ins first, then gain per byte, cut at the window |
//! | transfers | [`transfers`] | requests → tasks in flight (network only) |
//! | residency | [`residency`] | arrived bodies → units checked by `canopy_shared::format`, cache, held bands |
//! | resolve | [`resolve`] | draws, residency → what is drawn from what is held, units in use |
//! | report | [`report`] | → [`FrameReport`], [`DrawnTree`] |
//!
//! Clock: the source's where it has one (a [`LinkedSource`] on a virtual clock: headless runs
//! are deterministic for a given scene, path, link and frame time; instances are visited in id
//! order), else wall time. [`Streamer::stage_times`] times each stage of the last frame.

mod adapt;
mod billboard;
mod cached;
mod geometry;
mod instances;
mod model;
mod needs;
mod report;
mod residency;
mod resolve;
mod schedule;
mod select;
mod transfers;
mod view;

use std::collections::HashSet;
use std::sync::Arc;
use std::time::Instant;

use serde::Serialize;

pub use adapt::{ADAPT_INTERVAL_S, HIGH_BACKLOG_S, LOW_BACKLOG_S, MIN_DETAIL};
pub use cached::CachedModel;
pub use geometry::PARALLEL_GEOMETRY_TREES;
pub use model::open::OPEN_REQUEST_LEN;
pub use model::{OpenedTree, open_tree};
pub use report::{Drawn, DrawnTree, FrameReport, rate_bin};
pub use transfers::{FIRST_WINDOW_BYTES, LinkEstimate, MIN_WINDOW_BYTES, WINDOW_EXTRA_S};
pub use view::{Camera, Viewport};

use crate::cache::CacheStats;
use crate::lod::occlusion::Horizon;
use crate::lod::projection::{DEFAULT_LADDER, LadderStep, SWITCH_BLEND_BAND};
use crate::lod::{FlightParams, LodParams};
use crate::net::RangeSource;
use crate::net::linked::LinkedSource;
use crate::scene::Manifest;
use crate::terrain::HeldTerrain;
use geometry::GeometryStates;
use instances::Instances;
use model::Models;
use residency::Residency;
use select::Selection;
use transfers::{Arrival, Clock, MAX_UNIT_REQUESTS, Transfers};

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
    /// Cull trees the scene's terrain hides ([`crate::lod::occlusion`]), before anything is
    /// fetched for them. Conservative: a tree any pixel shows is kept.
    pub terrain_culling: bool,
    /// Plan a frame's geometry trees on rayon's pool (see [`PARALLEL_GEOMETRY_TREES`]). Off
    /// where many streamers already share the cores (`canopy load`): handing work to the pool
    /// and back then costs more than it saves.
    pub plan_on_pool: bool,
    /// Trees at least this tall (pixels) that the ladder does not draw as geometry are drawn as
    /// their model's crossed-quad stand-in, which every model holds first. The bandwidth
    /// adaptation sets it to the configured geometry switch, so that a tree it takes off
    /// geometry costs no more bytes than it holds (`None`: off; the ladder alone).
    pub stand_in_from_px: Option<f32>,
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
            terrain_culling: true,
            plan_on_pool: true,
            stand_in_from_px: None,
        }
    }
}

/// Wall time of each stage of one frame, milliseconds (the plan bench reads them).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct StageTimes {
    /// Loading instance tiles (network).
    pub instances_ms: f64,
    /// The terrain's horizon map.
    pub occlusion_ms: f64,
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
    terrain: Option<HeldTerrain>,
    /// The terrain's horizon map, re-aimed and rebuilt each frame in one buffer (boxed: the
    /// streamer lives in futures whose size clippy bounds).
    horizon: Box<Horizon>,
    geometry: GeometryStates,
    selection: Selection,
    residency: Residency,
    frame: u64,
    corrupt_total: u64,
    drawn: Vec<DrawnTree>,
    times: StageTimes,
    clock: Clock,
    transfers: Transfers,
    queued_units: usize,
    /// The options as given; `opts` is them at the current detail level.
    base_opts: StreamOptions,
    detail: adapt::Detail,
    /// The eye of the last frame, for the camera's speed (seed 002's v).
    last_eye: Option<glam::Vec3>,
    /// Speed given instead of the measured one ([`Streamer::set_flight_speed`]).
    speed_override: Option<f32>,
    /// The camera's speed in the last frame, m/s.
    speed: f32,
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
        let clock = Clock::new();
        Self {
            src,
            models: Models::new(&manifest),
            instances: Instances::new(manifest.tiles.len()),
            terrain: manifest.terrain.as_ref().map(HeldTerrain::new),
            horizon: Box::default(),
            geometry: GeometryStates::default(),
            residency: Residency::new(opts.cache_budget),
            selection: Selection::default(),
            manifest,
            base_opts: opts.clone(),
            detail: adapt::Detail::default(),
            opts,
            frame: 0,
            corrupt_total: 0,
            drawn: Vec::new(),
            times: StageTimes::default(),
            clock,
            transfers: Transfers::new(clock),
            queued_units: 0,
            last_eye: None,
            speed_override: None,
            speed: 0.0,
        }
    }

    /// Sets the speed seed 002's policy sees (its threat zone and redundancy offset), m/s;
    /// `None`: the camera's own, from its motion between frames (0 in the first frame). The
    /// redundancy pre-pass evaluates speeds at fixed viewpoints with it.
    pub fn set_flight_speed(&mut self, speed: Option<f32>) {
        self.speed_override = speed.filter(|v| v.is_finite()).map(|v| v.max(0.0));
    }

    /// The speed seed 002's policy saw in the last frame, m/s.
    pub fn flight_speed(&self) -> f32 {
        self.speed
    }

    /// The scene's terrain as held (`None`: the scene has none; its ground is y = 0).
    pub fn terrain(&self) -> Option<&HeldTerrain> {
        self.terrain.as_ref()
    }

    /// Ids of the instances the terrain hid in the last frame (in view otherwise; neither drawn
    /// nor fetched for).
    pub fn terrain_culled_ids(&self) -> &[u32] {
        &self.selection.terrain_culled_ids
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

    /// The stream's clock, seconds: the source's where it has one (a virtual link), else wall
    /// time since the streamer was made.
    pub fn now(&self) -> f64 {
        self.clock.now(self.src.as_ref())
    }

    /// The link as the client has measured it.
    pub fn link_estimate(&self) -> LinkEstimate {
        self.transfers.estimate(self.now())
    }

    /// Waits until some transfer has arrived (returns at once when none is in flight): for
    /// loops that run frames as fast as the network allows (`canopy load` without `--fps`).
    pub async fn wait_for_arrival(&mut self) {
        self.transfers.wait().await;
    }

    /// Whether anything is in flight or waiting for the window (as of the last frame).
    pub fn pending(&self) -> bool {
        self.transfers.in_flight() > 0 || self.queued_units > 0
    }

    /// One frame: the stages in order (see the module doc). Never waits for the network: what
    /// has arrived since the last frame is taken in, what is missing is requested, and the
    /// frame draws what is held. Transfers run as tasks on the current tokio runtime, which
    /// must exist (inside `block_on`, a `#[tokio::main]` or after `Runtime::enter`).
    pub fn frame(&mut self, cam: &Camera, dt: f32) -> FrameReport {
        let t_frame = Instant::now();
        let mut t = t_frame;
        let net0 = self.src.stats().snapshot();
        let mut corrupt = 0u64;
        let far = self.opts.viewport.far;

        // Arrivals: tiles, openings and units that came in since the last frame, checked.
        let mut arrived = 0u64;
        for a in self.transfers.drain() {
            match a {
                Arrival::Tiles { tiles, result } => {
                    arrived += result.as_ref().map_or(0, |b| b.iter().map(|x| x.len() as u64).sum());
                    corrupt += self.instances.receive_tiles(&self.manifest, &tiles, result);
                }
                Arrival::Terrain { tiles, result } => {
                    if let (Ok(bodies), Some(t)) = (result, self.terrain.as_mut()) {
                        arrived += bodies.iter().map(|x| x.len() as u64).sum::<u64>();
                        corrupt += t.receive(&tiles, &bodies);
                    }
                }
                Arrival::Opened { model, result } => {
                    let (reads, bad) = self.models.receive(model, *result);
                    corrupt += u64::from(bad);
                    if let Some((ranges, bodies)) = reads {
                        arrived += bodies.iter().map(|x| x.len() as u64).sum::<u64>();
                        corrupt +=
                            self.residency
                                .keep_unasked(&self.models, model, &ranges, &bodies, &HashSet::default());
                        self.instances.stale = true;
                    }
                }
                Arrival::Geometry { model, result } => {
                    let (reads, bad) = self.models.receive_geometry(model, *result);
                    corrupt += u64::from(bad);
                    if let Some((ranges, bodies)) = reads {
                        // The head came with the opening.
                        arrived += bodies.iter().skip(1).map(|x| x.len() as u64).sum::<u64>();
                        self.residency.forget_bands(model);
                        corrupt +=
                            self.residency
                                .keep_unasked(&self.models, model, &ranges, &bodies, &HashSet::default());
                        // The root sphere replaces the bounds' sphere in placement.
                        self.instances.stale = true;
                    }
                }
                Arrival::Units { request, result } => {
                    if let Ok(bodies) = result {
                        arrived += bodies.iter().map(|x| x.len() as u64).sum::<u64>();
                        corrupt += self.residency.store(&self.models, &request, &bodies);
                    }
                }
            }
        }
        self.times.residency_ms = lap(&mut t);

        // Terrain: its tiles within the view distance, nearest first (occlusion, the ground).
        if let Some(terrain) = &self.terrain {
            let in_flight: Vec<usize> = self.transfers.terrain.iter().copied().collect();
            let (tiles, ranges) = terrain.tiles_to_load(cam.eye, far, &in_flight);
            if !tiles.is_empty()
                && let Some(url) = self.manifest.terrain.as_ref().map(|t| t.url.clone())
            {
                self.transfers.load_terrain(&self.src, &url, tiles, ranges);
            }
        }
        // Instances: the tiles within the view distance; placed once models are open.
        let (tiles, ranges) = self
            .instances
            .tiles_to_load(&self.manifest, cam.eye, far, &self.transfers.tiles);
        if !tiles.is_empty() {
            let url = self.manifest.pack.url.clone();
            self.transfers.load_tiles(&self.src, &url, tiles, ranges);
        }
        if let Some(from) = self.instances.take_reordered() {
            self.geometry.reorder(&from);
        }
        self.times.instances_ms = lap(&mut t);

        // Models: open those nearby instances use.
        if self.models.any_closed() {
            let wanted = self.instances.models_near(cam.eye, far + 100.0);
            for (m, url, size) in self.models.to_open(wanted, &self.transfers.opening) {
                self.transfers.open(&self.src, m, &url, size);
            }
        }
        if self.instances.stale {
            self.instances.place(&self.models);
            self.geometry.refresh_live();
        }
        self.times.models_ms = lap(&mut t);

        // Select (with geometry and needs): what each visible tree is drawn as.
        let t_plan = t;
        let moved = self.last_eye.map_or(0.0, |e| e.distance(cam.eye));
        self.last_eye = Some(cam.eye);
        self.speed = self
            .speed_override
            .unwrap_or(if dt > 0.0 && moved.is_finite() { moved / dt } else { 0.0 });
        let frustum = view::frustum(&self.opts.viewport, cam);
        let t_occ = Instant::now();
        let occluding = self.occlusion(cam);
        self.times.occlusion_ms = t_occ.elapsed().as_secs_f64() * 1e3;
        // Seed 002's H: the eye's height above the ground under it (where the tile is not held
        // yet, above the tile's highest sample: never judged higher than it is).
        let ground = self
            .terrain
            .as_ref()
            .map_or(0.0, |t| t.ceiling_at(cam.eye.x, cam.eye.z).unwrap_or(t.grid.height_min));
        let sel = &mut self.selection;
        let visible = select::select(
            &self.models,
            &self.instances,
            &mut self.geometry,
            &self.opts,
            cam,
            &frustum,
            occluding.then_some(&*self.horizon),
            ground,
            dt,
            self.speed,
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

        // Schedule: what to fetch, ordered, cut at the window and merged.
        self.refresh_held_bands(|need| need.used && need.geometry);
        let (requests_out, bytes_out) = self.transfers.units_in_flight();
        let now = self.now();
        let window = schedule::Window {
            requests: MAX_UNIT_REQUESTS.saturating_sub(requests_out),
            bytes: self.transfers.window_bytes(now).saturating_sub(bytes_out),
            idle: requests_out == 0,
            stand_ins_only: !(self.transfers.tiles.is_empty() && self.transfers.opening.is_empty()),
        };
        let plan = schedule::schedule(
            &self.models,
            &self.residency,
            &self.transfers,
            window,
            &self.selection,
            cam,
            &self.opts,
        );
        self.residency.record_misses(plan.misses);
        self.queued_units = plan.queued_units;
        // Adaptation: the detail asked for next frame follows the backlog at the measured rate.
        // Work waiting: units queued and about to be sent, transfers in flight, and geometry
        // parts wanted but not started.
        let sent: u64 = plan
            .requests
            .iter()
            .flat_map(|q| &q.ranges)
            .map(|x| x.end - x.start)
            .sum();
        let parts: u64 = (0..self.models.len())
            .filter(|&m| self.selection.needs.get(m).is_some_and(|n| n.geometry_missing))
            .filter(|&m| self.models.lacks_geometry(m) && !self.transfers.opening_geometry.contains(&m))
            .filter_map(|m| self.models.index(m))
            .map(|idx| transfers::geometry_part_len(&idx.directory))
            .sum();
        let queued = plan.queued_bytes + parts;
        let waiting = queued + sent + self.transfers.bytes_in_flight();
        let rate = self.transfers.estimate(now).rate.filter(|r| r.is_finite() && *r > 0.0);
        let (backlog, queued_s) = (rate.map(|r| waiting as f64 / r), rate.map(|r| queued as f64 / r));
        if self.base_opts.lod_enabled && self.detail.update(now, backlog, queued_s) {
            self.opts = adapt::at_level(&self.base_opts, self.detail.level);
        }
        // Geometry parts (node tables: the bulk of an opening) once every visible tree has its
        // stand-in on the way: no tile, opening or stand-in unit waiting.
        if !window.stand_ins_only && plan.stand_ins_queued == 0 {
            for m in 0..self.models.len() {
                let wanted = self.selection.needs.get(m).is_some_and(|n| n.geometry_missing);
                if wanted
                    && self.models.lacks_geometry(m)
                    && !self.transfers.opening_geometry.contains(&m)
                    && let Some(idx) = self.models.index(m)
                {
                    let (dir, head) = (idx.directory.clone(), idx.head.clone());
                    let url = self.models.url(m).to_string();
                    self.transfers.open_geometry(&self.src, m, &url, dir, head);
                }
            }
        }
        let plan_ms = t_plan.elapsed().as_secs_f64() * 1e3;
        self.times.schedule_ms = lap(&mut t);

        // Fetch: send the requests; their bodies arrive in a later frame.
        for req in plan.requests {
            let url = self.models.url(req.model).to_string();
            self.transfers.request(&self.src, &url, req);
        }
        self.times.fetch_ms = lap(&mut t);

        // Resolve: what is drawn from what is held.
        self.refresh_held_bands(|need| need.geometry);
        let resolved = resolve::resolve(
            &self.models,
            &self.instances,
            &self.geometry.trees,
            &self.selection,
            &self.residency,
            crate::lod::projection::max_dropped_iterations(&self.opts.ladder),
        );
        self.residency.touch(&resolved.touches);
        self.drawn = resolved.drawn;
        self.times.resolve_ms = lap(&mut t);

        // Report.
        let net1 = self.src.stats().snapshot();
        self.corrupt_total += corrupt;
        let (requests_in_flight, bytes_in_flight) = self.transfers.units_in_flight();
        let est = self.transfers.estimate(now);
        let tiles_loading = self.transfers.tiles.len();
        let terrain_loading = self.transfers.terrain.len();
        let terrain_tiles = self.terrain.as_ref().map_or(0, HeldTerrain::held);
        let models_opening = self.transfers.opening.len();
        let geometry_parts_loading = self.transfers.opening_geometry.len();
        let report = FrameReport {
            frame: self.frame,
            time_s: self.now(),
            bytes: net1.bytes - net0.bytes,
            bytes_arrived: arrived,
            requests: net1.requests - net0.requests,
            retries: net1.retries - net0.retries,
            failures: net1.failures - net0.failures,
            corrupt_blocks: corrupt,
            cache_bytes: self.residency.used_bytes(),
            instances_loaded: self.instances.list.len(),
            visible,
            terrain_culled: self.selection.terrain_culled,
            terrain_tiles,
            terrain_loading,
            tiles_loading,
            models_opening,
            geometry_parts_loading,
            requests_in_flight,
            bytes_in_flight,
            units_queued: plan.queued_units,
            detail: self.detail.level,
            bytes_queued: plan.queued_bytes,
            rate_estimate: est.rate.filter(|r| r.is_finite()),
            rtt_estimate: est.rtt,
            plan_ms,
            nodes_evaluated,
            frame_ms: t_frame.elapsed().as_secs_f64() * 1e3,
            ..resolved.report
        };
        let report = FrameReport {
            complete: report.is_complete(),
            ..report
        };
        self.residency.end_frame(self.frame);
        self.frame += 1;
        report
    }

    /// Builds the frame's horizon map; `false` (no culling) without a terrain, with culling off,
    /// or with the eye not known to be above the ground.
    fn occlusion(&mut self, cam: &Camera) -> bool {
        let Some(t) = self
            .terrain
            .as_ref()
            .filter(|_| self.opts.terrain_culling && self.opts.lod_enabled)
        else {
            return false;
        };
        let Some(ceiling) = t.ceiling_at(cam.eye.x, cam.eye.z) else {
            return false;
        };
        if cam.eye.y.partial_cmp(&ceiling) != Some(std::cmp::Ordering::Greater) {
            return false;
        }
        let vp = &self.opts.viewport;
        let aspect = vp.width as f32 / vp.height.max(1) as f32;
        self.horizon.aim(cam.view(), vp.fov_y, aspect);
        self.horizon.build(t, vp.far);
        true
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

impl<S: RangeSource> Streamer<LinkedSource<S>> {
    /// One frame of a headless run on the virtual clock: the frame, then the link moved to
    /// `t_next` seconds (what arrives by then is drawn by the next frame). The report's byte,
    /// request, retry and failure counts cover both, so that each frame is charged for what it
    /// asked for, deterministically.
    pub async fn frame_until(&mut self, cam: &Camera, dt: f32, t_next: f64) -> FrameReport {
        let net0 = self.src.stats().snapshot();
        let mut r = self.frame(cam, dt);
        self.src.advance_to(t_next).await;
        let net1 = self.src.stats().snapshot();
        r.bytes = net1.bytes - net0.bytes;
        r.requests = net1.requests - net0.requests;
        r.retries = net1.retries - net0.retries;
        r.failures = net1.failures - net0.failures;
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::net::{ByteRange, NetError, NetStats};
    use bytes::Bytes;
    use glam::Vec3;

    /// A source whose requests never end: a link that has gone quiet.
    #[derive(Debug, Default)]
    struct Stalled(NetStats);

    impl RangeSource for Stalled {
        async fn get(&self, _: &str) -> Result<Bytes, NetError> {
            std::future::pending().await
        }
        async fn fetch(&self, _: &str, _: &[ByteRange]) -> Result<Vec<Bytes>, NetError> {
            std::future::pending().await
        }
        fn stats(&self) -> &NetStats {
            &self.0
        }
    }

    fn manifest() -> Manifest {
        let v = serde_json::json!({
            "format": "canopy-scene", "format_version": 1, "scene": "s", "name": "S", "version": 2,
            "bounds": {"min": [-10.0, -10.0], "max": [10.0, 10.0]},
            "instance_count": 3,
            "models": [{"name": "a", "url": "/assets/trees/a.0.ctree", "sha256": "00", "size": 1000}],
            "pack": {"url": "/assets/scenes/s/v2.0.cpack", "sha256": "00", "size": 64 + 100 + 84, "tables_len": 164},
            "tiles": [{"level": 0, "x": 0, "z": 0, "count": 3, "offset": 164, "length": 84, "crc32": 0,
                       "bounds": [-10.0, -10.0, 10.0, 10.0]}]
        });
        Manifest::parse(v.to_string().as_bytes()).expect("valid manifest")
    }

    #[tokio::test]
    async fn a_frame_never_waits_for_the_network() {
        let mut s = Streamer::with_manifest(Arc::new(Stalled::default()), manifest(), StreamOptions::default());
        let cam = crate::paths::look_at(Vec3::new(0.0, 20.0, -30.0), Vec3::ZERO);
        // Each frame returns although no request ever ends: the frame is not async, so it
        // cannot wait.
        for f in 0..5 {
            let r = s.frame(&cam, 1.0 / 30.0);
            assert_eq!(r.frame, f);
            assert_eq!(r.tiles_loading, 1, "the tile is asked for once and stays in flight");
            assert!(!r.complete && !r.is_idle());
        }
        assert!(s.pending());
    }

    /// Seed 002's v is the camera's speed between frames, unless given.
    #[tokio::test]
    async fn the_flight_speed_follows_the_camera() {
        let mut s = Streamer::with_manifest(Arc::new(Stalled::default()), manifest(), StreamOptions::default());
        let mut cam = crate::paths::look_at(Vec3::new(0.0, 20.0, -30.0), Vec3::ZERO);
        s.frame(&cam, 0.1);
        assert_eq!(s.flight_speed(), 0.0, "no motion before the first frame");
        cam.eye.x += 3.0;
        s.frame(&cam, 0.1);
        assert!((s.flight_speed() - 30.0).abs() < 1e-3, "{}", s.flight_speed());
        s.set_flight_speed(Some(55.0));
        s.frame(&cam, 0.1);
        assert_eq!(s.flight_speed(), 55.0);
        s.set_flight_speed(Some(f32::NAN));
        cam.eye.z += 1.0;
        s.frame(&cam, 0.0);
        assert_eq!(s.flight_speed(), 0.0, "no time passed: no speed; NaN is no override");
    }
}
