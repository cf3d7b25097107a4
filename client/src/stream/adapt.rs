//! Bandwidth adaptation: the detail the stream asks for follows the link, as adaptive-bitrate
//! video does. The backlog is the work waiting (bytes queued for the window and in flight) over
//! the measured rate; above [`HIGH_BACKLOG_S`] the detail level steps down, when what is not sent
//! yet is below [`LOW_BACKLOG_S`] it steps back up, at most once per [`ADAPT_INTERVAL_S`], so the queue holds
//! about a second of work. One policy for every link: nothing here depends on a preset.
//!
//! Conventions: level 1 is the configured LOD; level `d < 1` divides the ladder's switch
//! heights (ε, pixels) by `d` (trees become stand-ins sooner) and multiplies seed 004's weights
//! by `1/d` (geometry trees keep fewer leaves). A tree it takes off geometry is drawn as its
//! model's crossed-quad stand-in, which is held already, rather than on the next rung, which
//! would cost bytes the link does not have (`StreamOptions::stand_in_from_px`). An instant link
//! has no backlog: level 1.

use super::StreamOptions;

/// Lowest detail level.
pub const MIN_DETAIL: f32 = 0.5;
/// Backlog above which the level steps down, seconds.
pub const HIGH_BACKLOG_S: f64 = 4.0;
/// Backlog below which the level steps up, seconds.
pub const LOW_BACKLOG_S: f64 = 1.0;
/// Shortest time between two steps, seconds.
pub const ADAPT_INTERVAL_S: f64 = 0.5;
/// Factor of a step down (a step up divides by it).
const STEP: f32 = 0.8;

/// The detail level and when it last changed.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Detail {
    pub level: f32,
    changed_at: f64,
}

impl Default for Detail {
    fn default() -> Self {
        Self {
            level: 1.0,
            changed_at: f64::NEG_INFINITY,
        }
    }
}

impl Detail {
    /// Steps the level at time `now` for a backlog of `backlog_s` seconds (queued and in
    /// flight) of which `queued_s` is not sent yet; returns whether it changed. `None`: no
    /// measured rate (nothing to adapt to). It steps up on the queue alone: what is in flight is
    /// committed, and a long transfer of stand-ins must not hold the detail down.
    pub fn update(&mut self, now: f64, backlog_s: Option<f64>, queued_s: Option<f64>) -> bool {
        let (Some(b), Some(q)) = (backlog_s.filter(|b| b.is_finite()), queued_s.filter(|q| q.is_finite())) else {
            return false;
        };
        if now - self.changed_at < ADAPT_INTERVAL_S {
            return false;
        }
        let next = if b > HIGH_BACKLOG_S {
            (self.level * STEP).max(MIN_DETAIL)
        } else if q < LOW_BACKLOG_S {
            (self.level / STEP).min(1.0)
        } else {
            self.level
        };
        if (next - self.level).abs() < 1e-6 {
            return false;
        }
        self.level = next;
        self.changed_at = now;
        true
    }
}

/// `opts` at detail `level` (see the module doc).
pub(crate) fn at_level(opts: &StreamOptions, level: f32) -> StreamOptions {
    let mut o = opts.clone();
    if level < 1.0 && opts.lod_enabled {
        o.stand_in_from_px = opts
            .ladder
            .iter()
            .rfind(|s| s.rep.is_geometry())
            .map(|s| s.min_projected_px);
        let last = o.ladder.len().saturating_sub(1);
        for s in &mut o.ladder[..last] {
            s.min_projected_px /= level;
        }
        o.lod.weights = o.lod.weights.map(|w| w / level);
    }
    o
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_long_backlog_lowers_the_level_and_a_short_one_raises_it_back() {
        let mut d = Detail::default();
        assert!(!d.update(0.0, None, None), "no rate, no change");
        assert!(!d.update(0.0, Some(1.0), Some(1.0)), "inside the band");
        let mut t = 0.0;
        while d.update(t, Some(10.0), Some(10.0)) || t < 5.0 {
            t += 0.1;
            if t > 10.0 {
                break;
            }
        }
        assert_eq!(d.level, MIN_DETAIL);
        // Not faster than one step per interval.
        let before = d.level;
        assert!(d.update(t + ADAPT_INTERVAL_S, Some(3.0), Some(0.1)));
        assert!(!d.update(t + ADAPT_INTERVAL_S + 0.1, Some(0.1), Some(0.1)));
        assert!(d.level > before);
        let mut t = t + 1.0;
        for _ in 0..20 {
            d.update(t, Some(0.0), Some(0.0));
            t += ADAPT_INTERVAL_S;
        }
        assert_eq!(d.level, 1.0);
    }

    #[test]
    fn lower_levels_switch_to_stand_ins_sooner_and_keep_fewer_leaves() {
        let o = StreamOptions::default();
        let half = at_level(&o, 0.5);
        assert_eq!(half.ladder[0].min_projected_px, 2.0 * o.ladder[0].min_projected_px);
        assert_eq!(
            half.ladder.last().map(|s| s.min_projected_px),
            o.ladder.last().map(|s| s.min_projected_px)
        );
        assert!(half.lod.weights.iter().zip(&o.lod.weights).all(|(a, b)| *a == 2.0 * b));
        // What the lower level takes off geometry is drawn as the stand-in it holds.
        assert_eq!(half.stand_in_from_px, Some(o.ladder[0].min_projected_px));
        assert_eq!(at_level(&o, 1.0).stand_in_from_px, None);
        let full = StreamOptions {
            lod_enabled: false,
            ..o.clone()
        };
        assert_eq!(
            at_level(&full, 0.5).ladder[0].min_projected_px,
            o.ladder[0].min_projected_px
        );
    }
}
