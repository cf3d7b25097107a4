//! The selection stage: what each visible tree is drawn as this frame, and what each model is
//! needed for. Instance tiles are culled as a whole first (out of view: skipped; wholly in
//! view: no per-instance test), then each instance by its bounding sphere; its representation
//! comes from its projected height (seed 000's ladder, [`crate::lod::projection`]) or, with the
//! flight policy, from seed 002's level ([`crate::lod::flight`]). A tree drawn as geometry is
//! handed to the geometry stage ([`super::geometry`]) for its per-node rates.
//!
//! Conventions: projected heights are in pixels of the viewport's height; a draw's gain is its
//! projected height squared (capped at 10⁴ px); instances are visited in id order, so every
//! per-model sum is taken in the same order whatever the culling.

use glam::{Mat4, Vec3};

use super::StreamOptions;
use super::billboard::{AtlasFrame, FrameSet};
use super::geometry::{
    self, GEOMETRY_BATCH, GeometryJobs, GeometryStates, PARALLEL_GEOMETRY_TREES, TreeState, with_pool,
};
use super::instances::{Instances, TileClass};
use super::model::{Models, supported};
use super::needs::{Need, keep_maxima};
use super::view::Camera;
use crate::lod::bark::bark_variant;
use crate::lod::occlusion::Horizon;
use crate::lod::projection::{Representation, projected_height_tan, switch_blend};
use crate::lod::{FlightView, Frustum, PixelBudget, pixel_budget};

/// What a model gives the per-instance loop, gathered once per frame.
#[derive(Debug, Default)]
pub(crate) struct ModelFrame {
    pub open: bool,
    /// Representation of each ladder rung, moved down past what the model lacks.
    pub rungs: Vec<Representation>,
    pub hull_levels: usize,
    pub cloud_levels: usize,
    pub resolutions: usize,
    /// The atlas as the billboard choice reads it.
    pub atlas: AtlasFrame,
}

/// [`Draw::clouds`] of a draw that is not a cloud.
const NO_CLOUDS: [(u8, f32); 2] = [(0, 0.0); 2];

/// What an instance wants drawn this frame.
#[derive(Debug)]
pub(crate) struct Draw {
    /// Index into the streamer's instances.
    pub inst: u32,
    pub model: usize,
    pub rep: Representation,
    pub frames: FrameSet,
    /// Cloud levels and weights (clouds only): the rung's level, and the adjacent rung's level
    /// with weight > 0 inside a cross-fade band ([`switch_blend`]).
    pub clouds: [(u8, f32); 2],
    /// Index into the frame's geometry draws (geometry only).
    pub geo: u32,
    /// Bark variant at the tree's distance ([`crate::lod::bark::bark_variant`]): what its bark
    /// costs when drawn as geometry, and at full detail.
    pub bark: u8,
}

/// Where a geometry draw's keep counts live.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum KeepOf {
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
pub(crate) struct GeoDraw {
    pub inst: u32,
    pub model: usize,
    pub model_m: Mat4,
    pub scale: f32,
    pub keep: KeepOf,
    /// World centre of the tree's bounding sphere.
    pub center: Vec3,
    /// The eye in the model frame, when the switch-control state is to be updated.
    pub eye_model: Option<Vec3>,
    /// The pixel-scale leaf budget this frame ([`PixelBudget::NONE`] when off or at full detail).
    pub budget: PixelBudget,
    /// Skeleton iterations drawn, `0..=K` (seed 000's middle level below `K`): leaf nodes of
    /// branches born later keep 0.
    pub iterations: u8,
    /// Skeleton iterations the tree needs held to be drawn whole: `iterations`, less the last
    /// ones whose branches are all thinner than its bark variant draws
    /// ([`ModelIndex::bark_iterations`](super::model::ModelIndex::bark_iterations)); all of
    /// them at full detail.
    pub skeleton_iterations: u8,
    /// Keep counts with culled nodes at 0 (and lowered to the pixel budget when it limits the
    /// tree), and which leaf nodes are visible: this frame's only when `keep` is
    /// [`KeepOf::Masked`] (the buffers are reused from earlier frames).
    pub culled_keep: Vec<u32>,
    pub culled_vis: Vec<bool>,
}

/// The selection's output and its buffers, reused between frames.
#[derive(Debug, Default)]
pub(crate) struct Selection {
    /// What each visible instance wants drawn, in instance order.
    pub draws: Vec<Draw>,
    /// The trees drawn as geometry, in instance order.
    pub geo: Vec<GeoDraw>,
    /// Culling buffers of earlier frames' geometry draws, reused.
    culled_pool: Vec<(Vec<u32>, Vec<bool>)>,
    /// Per model: what this frame needs of it.
    pub needs: Vec<Need>,
    /// Per model: what the instance loop reads of it.
    pub models: Vec<ModelFrame>,
    tile_class: Vec<TileClass>,
    /// Instances in view that the terrain hides, this frame.
    pub terrain_culled: usize,
    /// Their instance ids, in instance order.
    pub terrain_culled_ids: Vec<u32>,
}

/// Per model, what the per-instance loop reads; resets the needs.
fn prepare_models(models: &Models, opts: &StreamOptions, scratch: &mut Selection) {
    let n = models.len();
    scratch.models.resize_with(n, ModelFrame::default);
    scratch.needs.resize_with(n, Need::default);
    for (m, (mf, need)) in scratch.models.iter_mut().zip(&mut scratch.needs).enumerate() {
        need.used = false;
        need.geometry = false;
        need.geometry_missing = false;
        let Some(idx) = models.index(m) else {
            mf.open = false;
            continue;
        };
        mf.open = true;
        mf.rungs.clear();
        mf.rungs.extend(opts.ladder.iter().map(|s| supported(idx, s.rep)));
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

/// Selects every loaded instance's representation: fills `scratch` with the frame's draws and
/// needs (the geometry trees' keep counts from the geometry stage) and returns the number of
/// visible instances.
#[allow(clippy::too_many_arguments)] // The frame's inputs, each read-only but the two it fills.
pub(crate) fn select(
    models: &Models,
    instances: &Instances,
    states: &mut GeometryStates,
    opts: &StreamOptions,
    cam: &Camera,
    frustum: &Frustum,
    occlusion: Option<&Horizon>,
    ground: f32,
    dt: f32,
    speed: f32,
    frame: u64,
    scratch: &mut Selection,
) -> usize {
    let vp = opts.viewport;
    prepare_models(models, opts, scratch);
    let mut tile_class = std::mem::take(&mut scratch.tile_class);
    instances.classify_tiles(cam.eye, vp.far, frustum, &mut tile_class);
    scratch.draws.clear();
    let previous_geometry_trees = scratch.geo.len();
    for g in scratch.geo.drain(..) {
        scratch.culled_pool.push((g.culled_keep, g.culled_vis));
    }
    let mut visible = 0usize;
    scratch.terrain_culled = 0;
    scratch.terrain_culled_ids.clear();
    let mut geo_count = 0u32;
    let forward = cam.forward();
    let flight_view = FlightView {
        eye: cam.eye,
        forward,
        height: cam.eye.y - ground,
        speed,
    };
    let tan_half = (vp.fov_y * 0.5).tan();
    let screen = vp.height as f32;
    let metres_per_pixel = 2.0 * tan_half / screen.max(1.0);
    let Instances {
        list, placed, inverse, ..
    } = instances;
    // With the pool and enough geometry trees last frame, each geometry tree's update and
    // culling starts on the pool as soon as the loop meets it, while the loop goes on.
    let pipelined = opts.plan_on_pool && previous_geometry_trees >= PARALLEL_GEOMETRY_TREES;
    let (done_tx, done_rx) = std::sync::mpsc::channel::<(u32, GeoDraw)>();
    // Tree states are handed out in instance order: `rest` holds those from `base` on.
    let (mut rest, mut base): (&mut [TreeState], usize) = (states.trees.as_mut_slice(), 0);
    with_pool(pipelined, |pool| {
        // Geometry trees go to the pool a few at a time: each hand-off may wake a worker.
        let mut batch: Vec<(u32, &mut TreeState, GeoDraw)> = Vec::new();
        let jobs = GeometryJobs {
            models: models.as_slice(),
            lod: &opts.lod,
            frustum,
            dt,
        };
        // The loop reads the compact `placed` records; the instance itself only for geometry.
        for (i, pl) in placed.iter().enumerate() {
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
            if let Some(occ) = occlusion
                && occ.hides_sphere(c, r)
            {
                scratch.terrain_culled += 1;
                scratch.terrain_culled_ids.push(list[i].inst.id);
                continue;
            }
            visible += 1;
            let m = usize::from(pl.model);
            let Some(idx) = models.index(m) else {
                continue;
            };
            let mf = &scratch.models[m];
            // `sphere_distance`, from the centre distance already at hand.
            let dist = {
                let d = centre_dist - r.max(0.0);
                if d.is_finite() { d.max(0.0) } else { 0.0 }
            };
            let px = projected_height_tan(pl.h, dist, screen, tan_half);
            let scale = if idx.height > 0.0 { pl.h / idx.height } else { 1.0 };
            let bark = bark_variant(metres_per_pixel, dist, scale) as u8;
            let mut full_rate = false;
            let mut clouds = NO_CLOUDS;
            let wanted_geometry;
            // Drawn as its stand-in only because the adaptation lowered the detail.
            let mut adapted_stand_in = false;
            let rep = if !opts.lod_enabled {
                full_rate = true;
                wanted_geometry = true;
                supported(idx, Representation::Geometry)
            } else if let Some(fp) = &opts.flight {
                let pos = Vec3::from(list[i].inst.position);
                let level = crate::lod::flight::flight_level(fp, &flight_view, pos, pl.h, dist);
                full_rate = level == 0;
                let step = usize::from(level).min(opts.ladder.len().saturating_sub(1));
                let rep = opts.ladder.get(step).map_or(Representation::Geometry, |s| s.rep);
                wanted_geometry = rep.is_geometry();
                supported(idx, rep)
            } else {
                // `choose_representation`, with the model's support folded into the rungs.
                let x = if px.is_nan() { 0.0 } else { px };
                let k = opts
                    .ladder
                    .iter()
                    .position(|s| x >= s.min_projected_px)
                    .unwrap_or(opts.ladder.len().saturating_sub(1));
                let mut rep = mf.rungs.get(k).copied().unwrap_or(Representation::Geometry);
                wanted_geometry = opts.ladder.get(k).is_some_and(|s| s.rep.is_geometry());
                // Taken off geometry by the adaptation: the stand-in it holds, not a new rung.
                if !wanted_geometry && opts.stand_in_from_px.is_some_and(|p| x >= p) && idx.crossed.is_some() {
                    rep = Representation::Billboard(crate::lod::projection::BillboardKind::Crossed);
                    adapted_stand_in = true;
                }
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
            // Drawn as a stand-in only because the model's geometry part is not here yet.
            need.geometry_missing |= wanted_geometry && !idx.has_geometry();
            let gain = f64::from(px.min(1e4)).powi(2);
            match rep {
                Representation::Geometry | Representation::Iterations { .. } => {
                    let iterations = idx.drawn_iterations(rep.dropped_iterations().unwrap_or(0));
                    // Twigs the bark variant leaves out are neither fetched nor waited for (at
                    // full detail every iteration is).
                    let skeleton_iterations = if full_rate {
                        iterations
                    } else {
                        iterations.min(idx.bark_iterations(usize::from(bark)))
                    };
                    if !need.geometry {
                        need.geometry = true;
                        need.iterations = 0;
                        need.keep.clear();
                        need.keep.resize(idx.leaf_nodes.len(), 0);
                    }
                    need.iterations = need.iterations.max(skeleton_iterations);
                    let Some((tree, tail)) = std::mem::take(&mut rest)[i - base..].split_first_mut() else {
                        continue;
                    };
                    (rest, base) = (tail, i + 1);
                    let (model_m, scale) = list[i].inst.placement();
                    // The switch-control update and node culling run on the pool from here
                    // (`pool`), or after this loop.
                    let (keep, eye_model) = if tree.begin(full_rate, &idx.lod.leaf_table, frame) {
                        (KeepOf::State, Some(inverse[i].transform_point3(cam.eye)))
                    } else {
                        (KeepOf::Full, None)
                    };
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
                        iterations,
                        skeleton_iterations,
                        culled_keep,
                        culled_vis,
                    };
                    let gi = geo_count;
                    geo_count += 1;
                    if let Some(pool) = pool {
                        batch.push((gi, tree, g));
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
                        bark,
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
                        bark,
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
                        bark,
                    });
                }
                Representation::Billboard(kind) => {
                    // A tree waiting for its model's geometry part draws the stand-in it holds
                    // ([`super::resolve`]) and asks for nothing more.
                    let waiting_for_geometry = wanted_geometry && !idx.has_geometry();
                    let frames = if idx.atlas.is_some() && !waiting_for_geometry {
                        let dir = inverse[i].transform_vector3(cam.eye - c).normalize_or_zero();
                        // A tree the adaptation took off geometry draws the stand-in's own
                        // (coarsest) images: held already, nothing more to fetch.
                        let px = if adapted_stand_in { 0.0 } else { px };
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
                        bark,
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
        geometry::run_after_loop(
            models.as_slice(),
            &mut states.trees,
            &opts.lod,
            opts.plan_on_pool,
            frustum,
            dt,
            scratch,
        );
    }
    keep_maxima(models, &states.trees, scratch);
    // Trees that stopped being drawn as geometry lose their switch state.
    geometry::retire_states(states, &scratch.geo, frame);
    scratch.tile_class = tile_class;
    visible
}
