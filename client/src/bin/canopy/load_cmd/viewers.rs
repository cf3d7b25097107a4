//! The simulated viewers: each one's camera path and start time, its frame loop (back to back or
//! paced at `--fps`, cut off at the deadline), and the sampler that reads every viewer's network
//! counters once a second for the timeline.

use std::sync::Arc;
use std::time::Duration;

use canopy_client::cache::CacheStats;
use canopy_client::net::http::HttpSource;
use canopy_client::net::{NetCounters, RangeSource};
use canopy_client::paths::{FRAME_DT, PathKind, camera_at};
use canopy_client::stream::Streamer;
use indicatif::ProgressBar;
use tokio::task::JoinHandle;
use tokio::time::{Instant, MissedTickBehavior};

use super::PATH_OFFSET_S;
use super::report::Sample;

/// The camera paths, given to viewers in turn.
const KINDS: [PathKind; 4] = [PathKind::Orbit, PathKind::Flyover, PathKind::Walk, PathKind::Lowflight];

/// Camera path and starting path time (seconds) of viewer `i`.
pub fn viewer_path(i: u32) -> (PathKind, f64) {
    (KINDS[i as usize % KINDS.len()], f64::from(i) * PATH_OFFSET_S)
}

/// What a viewer task hands back.
#[derive(Debug, Default)]
pub(super) struct ViewerOutcome {
    pub(super) frames: u64,
    /// A frame was dropped at the deadline.
    pub(super) cut_off: bool,
    pub(super) frame_ms_sum: f64,
    pub(super) cache: CacheStats,
    pub(super) corrupt_blocks: u64,
    pub(super) failed_models: Vec<(String, String)>,
}

/// One running viewer.
pub(super) struct Viewer {
    pub(super) source: Arc<HttpSource>,
    pub(super) task: JoinHandle<ViewerOutcome>,
}

/// Runs frames of `streamer` along `kind` from path time `t0` until `deadline`.
pub(super) async fn run_viewer(
    mut streamer: Streamer<HttpSource>,
    kind: PathKind,
    t0: f64,
    bounds: [f32; 4],
    fps: f64,
    deadline: Instant,
) -> ViewerOutcome {
    let period = (fps > 0.0).then(|| Duration::from_secs_f64(1.0 / fps));
    let dt = period.map_or(f64::from(FRAME_DT), |p| p.as_secs_f64());
    let mut out = ViewerOutcome::default();
    let mut next = Instant::now();
    while Instant::now() < deadline {
        let cam = camera_at(kind, bounds, (t0 + out.frames as f64 * dt) as f32);
        let r = streamer.frame(&cam, dt as f32);
        out.frames += 1;
        out.frame_ms_sum += r.frame_ms;
        if let Some(p) = period {
            next += p;
            let now = Instant::now();
            if next > now {
                tokio::time::sleep_until(next.min(deadline)).await;
            } else {
                // Behind schedule: start the next frame now rather than bursting.
                next = now;
            }
        } else {
            // As fast as the network allows: the next frame once something has arrived (at
            // once when nothing is in flight), letting the sampler and the others run.
            if tokio::time::timeout_at(deadline, streamer.wait_for_arrival())
                .await
                .is_err()
            {
                // The run ended with this viewer's bytes still on their way.
                out.cut_off = true;
                break;
            }
            tokio::task::yield_now().await;
        }
    }
    out.cache = streamer.cache_stats();
    out.corrupt_blocks = streamer.corrupt_blocks();
    out.failed_models = streamer.failed_models();
    out
}

/// Network counters summed over the viewers (peak in flight: the largest of any one).
pub(super) fn totals(viewers: &[Viewer]) -> NetCounters {
    let mut t = NetCounters::default();
    for v in viewers {
        let s = v.source.stats().snapshot();
        t.requests += s.requests;
        t.bytes += s.bytes;
        t.retries += s.retries;
        t.failures += s.failures;
        t.peak_in_flight = t.peak_in_flight.max(s.peak_in_flight);
    }
    t
}

/// Reads the viewers' counters every second until `duration` seconds have passed.
pub(super) async fn sample(viewers: &[Viewer], start: Instant, duration: u64, bar: &ProgressBar) -> Vec<Sample> {
    let mut tick = tokio::time::interval_at(start + Duration::from_secs(1), Duration::from_secs(1));
    tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
    let mut timeline = Vec::with_capacity(duration as usize);
    let (mut prev_t, mut prev) = (start, NetCounters::default());
    for k in 1..=duration {
        tick.tick().await;
        let now = Instant::now();
        let cur = totals(viewers);
        let dt = (now - prev_t).as_secs_f64().max(1e-3);
        let s = Sample {
            seconds: (now - start).as_secs_f64(),
            requests_per_s: (cur.requests - prev.requests) as f64 / dt,
            mb_per_s: (cur.bytes - prev.bytes) as f64 / dt / 1e6,
        };
        timeline.push(s);
        bar.set_position(k);
        bar.set_message(format!("{:.0} req/s, {:.1} MB/s", s.requests_per_s, s.mb_per_s));
        (prev_t, prev) = (now, cur);
    }
    timeline
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn viewers_spread_over_paths_and_time() {
        let kinds: Vec<PathKind> = (0..8).map(|i| viewer_path(i).0).collect();
        assert_eq!(&kinds[..4], &KINDS);
        assert_eq!(&kinds[4..], &KINDS);
        assert_eq!(viewer_path(0).1, 0.0);
        assert!((viewer_path(3).1 - 21.9).abs() < 1e-9);
        assert_eq!(viewer_path(5), viewer_path(5));
    }
}
