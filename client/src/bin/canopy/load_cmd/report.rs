//! The load report: totals over the viewers ([`summarize`]), the cache hit rate, `load.json` and
//! the charts of requests/s and MB/s over time ([`write_outputs`]), and the text printed without
//! `--json`. Rates are per second of measured time; sizes in bytes unless a name says MB (10^6).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use canopy_client::net::http::RangeMode;
use canopy_client::net::{LatencyHistogram, NetCounters};
use canopy_client::scene::Manifest;
use canopy_shared::chart::{LineChart, Series, write_line_chart};
use serde::Serialize;

use super::LoadArgs;
use super::viewers::ViewerOutcome;
use crate::cli::peak_rss_bytes;

/// Failed-model reasons kept for the report.
const FAILED_MODEL_EXAMPLES: usize = 5;

/// One second of the time series.
#[derive(Debug, Clone, Copy, Serialize)]
pub(super) struct Sample {
    /// Seconds since the start.
    pub(super) seconds: f64,
    pub(super) requests_per_s: f64,
    pub(super) mb_per_s: f64,
}

/// Latency of every request of every viewer, send to last body byte (bucket upper edges, ±9 %).
#[derive(Debug, Serialize)]
pub(super) struct LatencyReport {
    pub(super) samples: u64,
    pub(super) p50_ms: f64,
    pub(super) p95_ms: f64,
    pub(super) p99_ms: f64,
    pub(super) max_ms: f64,
}

/// The report printed and written to `load.json`.
#[derive(Debug, Serialize)]
pub(super) struct LoadReport {
    pub(super) url: String,
    pub(super) scene: String,
    pub(super) version: u64,
    pub(super) clients: u32,
    pub(super) duration_s: u64,
    /// Start to the last viewer stopping.
    pub(super) elapsed_s: f64,
    /// Frames per second per viewer; 0 = back to back.
    pub(super) fps: f64,
    pub(super) cache_mb: u64,
    pub(super) view_distance: f32,
    pub(super) range_mode: RangeMode,
    pub(super) max_in_flight: usize,
    /// Manifest bytes, fetched once before the run (not counted below).
    pub(super) manifest_bytes: u64,
    pub(super) requests: u64,
    pub(super) requests_per_s: f64,
    /// Highest one-second rate of the timeline.
    pub(super) requests_per_s_peak: f64,
    pub(super) bytes: u64,
    pub(super) bytes_per_s: f64,
    /// Highest one-second rate of the timeline, bytes/s.
    pub(super) bytes_per_s_peak: f64,
    pub(super) latency: LatencyReport,
    /// `failed_fetches + corrupt_blocks + failed_models + viewers_lost`.
    pub(super) errors: u64,
    /// Fetches that failed after every retry.
    pub(super) failed_fetches: u64,
    pub(super) corrupt_blocks: u64,
    /// Models a viewer could not open (summed over viewers).
    pub(super) failed_models: u64,
    /// A few `name: reason` of failed models.
    pub(super) failed_model_examples: Vec<String>,
    /// Viewer tasks that panicked (their cache counters are lost; their network counters are not).
    pub(super) viewers_lost: u64,
    pub(super) retries: u64,
    /// Block look-ups that found the block (every block drawn, every frame).
    pub(super) cache_hits: u64,
    /// Block look-ups that did not.
    pub(super) cache_misses: u64,
    /// Blocks fetched and offered to the cache (insertions and refusals).
    pub(super) cache_blocks_fetched: u64,
    /// `hits / (hits + max(misses, blocks fetched))`: the share of block uses served without
    /// the network.
    pub(super) cache_hit_rate: f64,
    pub(super) frames: u64,
    pub(super) frames_per_viewer_mean: f64,
    pub(super) frames_per_viewer_min: u64,
    pub(super) frames_per_viewer_max: u64,
    /// Viewers whose last frame was dropped at the deadline.
    pub(super) frames_cut_off: u64,
    pub(super) frame_ms_mean: f64,
    /// Most requests in flight at once in any one viewer.
    pub(super) peak_in_flight_per_viewer: u64,
    pub(super) peak_rss_bytes: u64,
    pub(super) timeline: Vec<Sample>,
    /// Chart files written.
    pub(super) charts: Vec<String>,
}

/// Totals over the viewers (rates and the timeline are filled in by the caller).
pub(super) fn summarize(
    a: &LoadArgs,
    m: &Manifest,
    manifest_bytes: u64,
    outcomes: &[ViewerOutcome],
    lost: u64,
    net: &NetCounters,
    latency: &LatencyHistogram,
) -> LoadReport {
    let hits: u64 = outcomes.iter().map(|o| o.cache.hits).sum();
    let misses: u64 = outcomes.iter().map(|o| o.cache.misses).sum();
    let fetched: u64 = outcomes.iter().map(|o| o.cache.insertions + o.cache.rejections).sum();
    let frames: u64 = outcomes.iter().map(|o| o.frames).sum();
    let corrupt: u64 = outcomes.iter().map(|o| o.corrupt_blocks).sum();
    let failed_models: u64 = outcomes.iter().map(|o| o.failed_models.len() as u64).sum();
    let mut examples: Vec<String> = outcomes
        .iter()
        .flat_map(|o| o.failed_models.iter().map(|(n, e)| format!("{n}: {e}")))
        .collect();
    examples.sort();
    examples.dedup();
    examples.truncate(FAILED_MODEL_EXAMPLES);
    let frame_ms: f64 = outcomes.iter().map(|o| o.frame_ms_sum).sum();
    LoadReport {
        url: a.scene.url.clone(),
        scene: m.scene.clone(),
        version: m.version,
        clients: a.clients,
        duration_s: a.duration,
        elapsed_s: 0.0,
        fps: a.fps,
        cache_mb: a.cache_mb,
        view_distance: a.view_distance,
        range_mode: a.scene.range_mode,
        max_in_flight: a.scene.max_in_flight.max(1),
        manifest_bytes,
        requests: net.requests,
        requests_per_s: 0.0,
        requests_per_s_peak: 0.0,
        bytes: net.bytes,
        bytes_per_s: 0.0,
        bytes_per_s_peak: 0.0,
        latency: LatencyReport {
            samples: latency.count(),
            p50_ms: latency.quantile_ms(0.5),
            p95_ms: latency.quantile_ms(0.95),
            p99_ms: latency.quantile_ms(0.99),
            max_ms: latency.quantile_ms(1.0),
        },
        errors: net.failures + corrupt + failed_models + lost,
        failed_fetches: net.failures,
        corrupt_blocks: corrupt,
        failed_models,
        failed_model_examples: examples,
        viewers_lost: lost,
        retries: net.retries,
        cache_hits: hits,
        cache_misses: misses,
        cache_blocks_fetched: fetched,
        cache_hit_rate: hit_rate(hits, misses, fetched),
        frames,
        frames_per_viewer_mean: frames as f64 / outcomes.len().max(1) as f64,
        frames_per_viewer_min: outcomes.iter().map(|o| o.frames).min().unwrap_or(0),
        frames_per_viewer_max: outcomes.iter().map(|o| o.frames).max().unwrap_or(0),
        frames_cut_off: outcomes.iter().filter(|o| o.cut_off).count() as u64,
        frame_ms_mean: frame_ms / frames.max(1) as f64,
        peak_in_flight_per_viewer: net.peak_in_flight,
        peak_rss_bytes: peak_rss_bytes(),
        timeline: Vec::new(),
        charts: Vec::new(),
    }
}

/// Share of block uses served from the cache. The streamer plans with `contains`, which counts
/// nothing, so a block that had to be fetched may never show as a miss: the blocks fetched stand
/// in for the misses when they are more.
fn hit_rate(hits: u64, misses: u64, fetched: u64) -> f64 {
    let misses = misses.max(fetched);
    hits as f64 / (hits + misses).max(1) as f64
}

/// Writes the charts and `load.json` under `dir`; records the chart paths in the report.
pub(super) fn write_outputs(dir: &Path, report: &mut LoadReport) -> Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut written = Vec::new();
    let title_r = format!("{} clients: requests per second", report.clients);
    let title_b = format!("{} clients: throughput", report.clients);
    let charts = [
        (
            "requests",
            title_r.as_str(),
            "requests/s",
            "requests/s",
            report
                .timeline
                .iter()
                .map(|s| (s.seconds, s.requests_per_s))
                .collect::<Vec<_>>(),
        ),
        (
            "throughput",
            title_b.as_str(),
            "MB/s",
            "MB/s",
            report.timeline.iter().map(|s| (s.seconds, s.mb_per_s)).collect(),
        ),
    ];
    for (stem, title, y_label, name, points) in charts {
        let series = [Series {
            name: name.into(),
            points,
        }];
        let files = write_line_chart(
            &dir.join(stem),
            &LineChart {
                title,
                x_label: "seconds",
                y_label,
                series: &series,
                log_x: false,
            },
        )?;
        report.charts.extend(files.iter().map(|p| p.display().to_string()));
        written.extend(files);
    }
    let json = dir.join("load.json");
    let text = serde_json::to_string_pretty(&*report)?;
    std::fs::write(&json, text + "\n").with_context(|| format!("writing {}", json.display()))?;
    written.push(json);
    Ok(written)
}

/// The report as text, a few lines.
pub(super) fn text_report(r: &LoadReport) -> String {
    let mut s = String::new();
    let fps = if r.fps > 0.0 {
        format!("{} fps each", r.fps)
    } else {
        "frames back to back".into()
    };
    let _ = writeln!(
        s,
        "{} v{}: {} clients for {} s ({:.2} s measured), {fps}, cache {} MiB each",
        r.scene, r.version, r.clients, r.duration_s, r.elapsed_s, r.cache_mb
    );
    let _ = writeln!(
        s,
        "requests: {} ({:.1}/s, peak {:.0}/s); bytes: {:.2} MB ({:.2} MB/s, peak {:.2} MB/s)",
        r.requests,
        r.requests_per_s,
        r.requests_per_s_peak,
        r.bytes as f64 / 1e6,
        r.bytes_per_s / 1e6,
        r.bytes_per_s_peak / 1e6
    );
    let l = &r.latency;
    let _ = writeln!(
        s,
        "latency ({} requests): p50 {:.2} ms, p95 {:.2} ms, p99 {:.2} ms, max {:.2} ms",
        l.samples, l.p50_ms, l.p95_ms, l.p99_ms, l.max_ms
    );
    let _ = writeln!(
        s,
        "errors: {} ({} failed fetches, {} corrupt blocks, {} failed models, {} viewers lost); {} retries",
        r.errors, r.failed_fetches, r.corrupt_blocks, r.failed_models, r.viewers_lost, r.retries
    );
    for e in &r.failed_model_examples {
        let _ = writeln!(s, "  failed model {e}");
    }
    let _ = writeln!(
        s,
        "cache hit rate {:.4} ({} block uses from the cache, {} blocks fetched, {} misses counted)",
        r.cache_hit_rate, r.cache_hits, r.cache_blocks_fetched, r.cache_misses
    );
    let _ = writeln!(
        s,
        "frames per viewer: mean {:.1}, min {}, max {} ({:.1} ms mean frame; {} cut off at the end)",
        r.frames_per_viewer_mean, r.frames_per_viewer_min, r.frames_per_viewer_max, r.frame_ms_mean, r.frames_cut_off
    );
    let _ = writeln!(
        s,
        "peak in flight per viewer {}; peak RSS {:.1} MB",
        r.peak_in_flight_per_viewer,
        r.peak_rss_bytes as f64 / 1e6
    );
    s
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use canopy_client::cache::CacheStats;

    use super::*;
    use crate::load_cmd::tests::parse;

    #[test]
    fn text_report_mentions_every_figure() {
        let m = Manifest {
            format: "canopy-scene".into(),
            format_version: 1,
            scene: "demo".into(),
            name: "Demo".into(),
            version: 3,
            bounds: canopy_client::scene::ManifestBounds {
                min: [0.0, 0.0],
                max: [1.0, 1.0],
            },
            instance_count: 0,
            models: vec![],
            pack: canopy_client::scene::ManifestPack {
                url: "/assets/p".into(),
                sha256: String::new(),
                size: 0,
                tables_len: 0,
            },
            tiles: vec![],
            terrain: None,
        };
        let a = parse(&["--clients", "2", "--duration", "5"]).expect("args");
        let outcomes = [
            ViewerOutcome {
                frames: 10,
                cache: CacheStats {
                    hits: 3,
                    misses: 1,
                    ..CacheStats::default()
                },
                failed_models: vec![("oak".into(), "bad".into())],
                ..ViewerOutcome::default()
            },
            ViewerOutcome {
                frames: 4,
                cut_off: true,
                ..ViewerOutcome::default()
            },
        ];
        let net = NetCounters {
            requests: 20,
            bytes: 2_000_000,
            retries: 1,
            failures: 2,
            peak_in_flight: 3,
        };
        let h = LatencyHistogram::default();
        h.record(Duration::from_millis(2));
        let r = summarize(&a, &m, 100, &outcomes, 0, &net, &h);
        assert_eq!(r.errors, 3);
        assert_eq!(
            (
                r.frames,
                r.frames_per_viewer_min,
                r.frames_per_viewer_max,
                r.frames_cut_off
            ),
            (14, 4, 10, 1)
        );
        assert!((r.cache_hit_rate - 0.75).abs() < 1e-12);
        assert_eq!(hit_rate(0, 0, 0), 0.0);
        assert!(
            (hit_rate(9, 0, 1) - 0.9).abs() < 1e-12,
            "fetched blocks count as misses"
        );
        assert!((hit_rate(9, 1, 0) - 0.9).abs() < 1e-12);
        assert!(r.latency.p50_ms >= 2.0 && r.latency.p50_ms <= 2.2);
        let t = text_report(&r);
        for want in [
            "2 clients",
            "requests: 20",
            "p99",
            "errors: 3",
            "hit rate 0.7500",
            "failed model oak: bad",
        ] {
            assert!(t.contains(want), "{want:?} missing from\n{t}");
        }
    }
}
