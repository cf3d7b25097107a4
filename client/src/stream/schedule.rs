//! The schedule stage: the frame's needs become requests. Per model, the units it needs and the
//! cache does not hold (the model's stand-in first, then skeleton iterations and bark, leaf
//! blocks from the leaf planner, [`crate::plan`], hull levels, atlas images and cloud levels); all of them
//! ordered once, best visual gain per byte first, and cut at the frame's byte budget; then per
//! model, sorted by offset and merged into ranges by the one merge rule
//! ([`crate::plan::merge_ranges_unless`]), never over a gap holding bytes the client has.
//!
//! Reads the selection and the residency; writes neither.

use canopy_shared::format::UnitCheck;

use super::StreamOptions;
use super::model::{Models, Unit};
use super::needs::leaf_gains;
use super::residency::Residency;
use super::select::Selection;
use super::transfers::Transfers;
use super::view::Camera;
use crate::cache::BlockKey;
use crate::net::ByteRange;
use crate::plan::{by_gain_per_byte, merge_ranges_unless, plan_leaf_ranges};

/// A unit to fetch: where it is, how to check it, and what it is worth.
#[derive(Debug, Clone)]
pub(crate) struct Want {
    pub key: BlockKey,
    pub range: ByteRange,
    pub check: UnitCheck,
    /// Visual gain (see [`super::needs`]); skeleton and bark: `f64::MAX`.
    pub gain: f64,
    /// 0: a stand-in every tree of the model can be drawn as
    /// ([`super::model::ModelIndex::stand_ins`]), sent before anything else; 1: the rest.
    pub tier: u8,
}

/// One model's request this frame.
#[derive(Debug, Clone)]
pub(crate) struct Request {
    /// Model index into the manifest.
    pub model: usize,
    /// Units asked for, sorted by start.
    pub wants: Vec<Want>,
    /// The merged byte ranges that carry them, sorted by start.
    pub ranges: Vec<ByteRange>,
}

/// The frame's requests, in model order.
#[derive(Debug, Default)]
pub(crate) struct Schedule {
    pub requests: Vec<Request>,
    /// Units needed, neither held nor in flight, before the cut (cache misses).
    pub misses: u64,
    /// Units needed and left for a later frame by the budget or the window.
    pub queued_units: usize,
    /// Their bytes.
    pub queued_bytes: u64,
    /// Stand-in units (tier 0) among them.
    pub stand_ins_queued: usize,
}

/// What the transfer window has room for this frame.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Window {
    /// Unit requests that may be sent.
    pub requests: usize,
    /// Bytes that may be sent.
    pub bytes: u64,
    /// Nothing is in flight.
    pub idle: bool,
    /// Only stand-in units (tier 0) may be sent.
    pub stand_ins_only: bool,
}

/// Plans the frame's requests from its selection: units neither held nor in flight. The held
/// band prefixes of the models drawn as geometry must be current
/// ([`Residency::refresh_held_bands`]).
pub(crate) fn schedule(
    models: &Models,
    residency: &Residency,
    transfers: &Transfers,
    window: Window,
    sel: &Selection,
    cam: &Camera,
    opts: &StreamOptions,
) -> Schedule {
    let mut all: Vec<(usize, Want)> = Vec::new();
    for (m, need) in sel.needs.iter().enumerate() {
        let Some(idx) = models.index(m).filter(|_| need.used) else {
            continue;
        };
        // Leaf nodes with bands still to fetch, and their gains (only those are read).
        let mut leaf_plan = None;
        if need.geometry {
            let nb = idx.band_count();
            let Some(hb) = residency.held_bands(m) else {
                continue;
            };
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
                leaf_gains(models, sel, m, cam, &opts.viewport, &missing, &mut gains);
                leaf_plan = plan_leaf_ranges(&idx.layout, idx.leaves_offset, &need.keep, &hb.bands, &gains).ok();
            }
        }
        let mut stand_ins: Vec<BlockKey> = Vec::new();
        let mut push = |unit: Option<Unit>, gain: f64, tier: u8| {
            let Some(Unit { key, range, check }) = unit else { return };
            if stand_ins.contains(&key) {
                return;
            }
            if tier == 0 {
                stand_ins.push(key);
            }
            if !residency.contains(m, key) && !transfers.has_unit(m, key) && range.end > range.start {
                all.push((
                    m,
                    Want {
                        key,
                        range,
                        check,
                        gain,
                        tier,
                    },
                ));
            }
        };
        // The stand-in first (the crossed quads' coarsest images, else the coarsest hull):
        // every tree of the model can be drawn once it is here.
        for unit in idx.stand_ins.iter().cloned() {
            let gain = match unit.key {
                BlockKey::Hull { level } => need.hull.get(usize::from(level)).copied().flatten(),
                _ => None,
            };
            push(Some(unit), gain.unwrap_or(0.0), 0);
        }
        if need.geometry {
            // Skeleton by iteration (those drawn: later ones are not asked for), bark mesh and
            // materials: small, needed before any leaf.
            for k in 0..=usize::from(need.iterations) {
                push(idx.skeleton_unit(k), f64::MAX, 1);
            }
            push(idx.bark_unit(), f64::MAX, 1);
            if let Some(plan) = leaf_plan {
                for r in plan.ranges {
                    let per_byte_gain = r.gain_per_byte();
                    for b in r.blocks {
                        push(Some(idx.leaf_unit(&b)), per_byte_gain * b.len as f64, 1);
                    }
                }
            }
        }
        for (level, g) in need.hull.iter().enumerate() {
            if let Some(g) = *g {
                push(idx.hull_unit(level), g, 1);
            }
        }
        let nres = sel.models[m].resolutions.max(1);
        for (k, g) in need.images.iter().enumerate() {
            let Some(g) = *g else { continue };
            let (frame, res) = ((k / nres) as u32, k % nres);
            // A finer image of the same frame that is wanted too, held or on its way serves
            // this tree as well (minified): its bytes are not fetched twice.
            let finer = (0..res).any(|r| {
                let key = BlockKey::Atlas {
                    frame,
                    resolution: r as u8,
                };
                need.images.get(k - res + r).copied().flatten().is_some()
                    || residency.contains(m, key)
                    || transfers.has_unit(m, key)
            });
            if !finer {
                push(idx.atlas_unit(frame, res as u8), g, 1);
            }
        }
        for (level, g) in need.clouds.iter().enumerate() {
            if let Some(g) = *g {
                push(idx.cloud_unit(level), g, 1);
            }
        }
    }
    // Best gain per byte first; cut at the budget (always at least one unit, so that a frame
    // with a tiny budget still makes progress).
    let len = |w: &Want| w.range.end - w.range.start;
    all.sort_by(|(ma, a), (mb, b)| {
        a.tier
            .cmp(&b.tier)
            .then_with(|| by_gain_per_byte(a.gain, len(a), b.gain, len(b)))
            .then(ma.cmp(mb))
            .then(a.range.start.cmp(&b.range.start))
    });
    let misses = all.len() as u64;
    let budget = opts.frame_byte_budget.unwrap_or(u64::MAX).min(window.bytes);
    let taken = cut(&all, window, budget);
    let keep = taken.iter().filter(|t| **t).count();
    let left = || all.iter().zip(&taken).filter(|(_, t)| !**t).map(|(mw, _)| mw);
    let queued: u64 = left().map(|(_, w)| len(w)).sum();
    let queued_units = all.len() - keep;
    let stand_ins_queued = left().filter(|(_, w)| w.tier == 0).count();
    let mut taken = taken.into_iter();
    all.retain(|_| taken.next().unwrap_or(false));
    // Per model, in model order (a stable sort keeps the gain order within each).
    all.sort_by_key(|(m, _)| *m);
    let mut requests: Vec<Request> = Vec::new();
    for (m, w) in all {
        match requests.last_mut() {
            Some(r) if r.model == m => r.wants.push(w),
            _ => requests.push(Request {
                model: m,
                wants: vec![w],
                ranges: Vec::new(),
            }),
        }
    }
    for r in &mut requests {
        r.wants.sort_by_key(|w| w.range.start);
        let m = r.model;
        r.ranges = merge_ranges_unless(r.wants.iter().map(|w| w.range.clone()), |a, b| {
            residency.gap_holds_cached(models, m, a, b) || transfers.overlaps(m, a, b)
        });
    }
    Schedule {
        requests,
        misses,
        queued_units,
        queued_bytes: queued,
        stand_ins_queued,
    }
}

/// Which of `all` (sorted: tier, then gain per byte) go this frame: in priority order, at most
/// `window.requests` models (one request each) and `budget` bytes, always at least one unit
/// when nothing is in flight, so that a tiny budget still makes progress; only stand-ins while
/// `window.stand_ins_only`. A model whose stand-in goes sends nothing else this frame: merged
/// into one request with the model's detail units, the stand-in arrives only with the last of
/// them (on slow4g the demo's first complete frame came 0.7 s later when that happened: log
/// 2026-12-04, "link model against a kernel-shaped link"). Its other units wait for a later
/// frame, while other models' units may go.
fn cut(all: &[(usize, Want)], window: Window, budget: u64) -> Vec<bool> {
    let len = |w: &Want| w.range.end - w.range.start;
    let mut spent = 0u64;
    let mut keep = 0usize;
    let mut picked: Vec<usize> = Vec::new();
    let mut stand_in_sent: Vec<usize> = Vec::new();
    let mut taken = vec![false; all.len()];
    for (k, (m, w)) in all.iter().enumerate() {
        if w.tier > 0 && stand_in_sent.contains(m) {
            continue;
        }
        let new_model = !picked.contains(m);
        if new_model && picked.len() >= window.requests {
            break;
        }
        // Over the budget: stop, except for a first unit when nothing is in flight (a unit
        // bigger than the whole window still goes, alone).
        if spent + len(w) > budget && (keep > 0 || !window.idle) {
            break;
        }
        // Stand-ins only while instance tiles or model openings are on their way: they share
        // the link, and every visible tree gets a stand-in before any tree gets more.
        if window.stand_ins_only && w.tier > 0 {
            break;
        }
        if new_model {
            picked.push(*m);
        }
        if w.tier == 0 {
            stand_in_sent.push(*m);
        }
        spent += len(w);
        keep += 1;
        taken[k] = true;
    }
    taken
}

#[cfg(test)]
mod tests {
    use super::*;

    fn want(start: u64, len: u64, tier: u8, hull_level: u16) -> Want {
        Want {
            key: if tier == 0 {
                BlockKey::Hull { level: hull_level }
            } else {
                BlockKey::Leaf {
                    band: 0,
                    leaf_node: start as u32,
                }
            },
            range: start..start + len,
            check: UnitCheck::Crc(0),
            gain: 1.0,
            tier,
        }
    }

    const OPEN: Window = Window {
        requests: 8,
        bytes: u64::MAX,
        idle: true,
        stand_ins_only: false,
    };

    /// The stand-in of model 0 goes alone; model 0's detail waits while model 1's, whose
    /// stand-in is held, goes; the next frame (the stand-in in flight) sends model 0's detail.
    #[test]
    fn a_stand_in_goes_alone_and_its_models_detail_next_frame() {
        let all = vec![
            (0, want(0, 2_000, 0, 2)),
            (0, want(5_000, 40_000, 1, 0)),
            (1, want(9_000, 30_000, 1, 0)),
        ];
        assert_eq!(cut(&all, OPEN, u64::MAX), vec![true, false, true]);
        let next = vec![(0, want(5_000, 40_000, 1, 0))];
        assert_eq!(cut(&next, OPEN, u64::MAX), vec![true]);
    }

    /// The window and the budget still cut in priority order, skipped units aside.
    #[test]
    fn the_window_and_the_budget_still_cut() {
        let all = vec![
            (0, want(0, 2_000, 0, 2)),
            (1, want(0, 2_000, 0, 2)),
            (2, want(0, 50_000, 1, 0)),
        ];
        let one = Window { requests: 1, ..OPEN };
        assert_eq!(cut(&all, one, u64::MAX), vec![true, false, false]);
        assert_eq!(cut(&all, OPEN, 10_000), vec![true, true, false]);
        let stand_ins = Window {
            stand_ins_only: true,
            ..OPEN
        };
        assert_eq!(cut(&all, stand_ins, u64::MAX), vec![true, true, false]);
        // A unit larger than the budget goes alone when nothing is in flight, not otherwise.
        let big = vec![(2, want(0, 50_000, 1, 0))];
        assert_eq!(cut(&big, OPEN, 10_000), vec![true]);
        let busy = Window { idle: false, ..OPEN };
        assert_eq!(cut(&big, busy, 10_000), vec![false]);
    }
}
