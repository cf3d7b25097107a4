//! `canopy eval`'s charts: the quality-against-bytes curve of `--detail-scales` and the per-run
//! charts (quality against bytes, SSIM and FLIP per frame, mid-band FLIP, bytes per frame).

use std::path::{Path, PathBuf};

use anyhow::Result;
use canopy_shared::chart::{LineChart, Series, write_line_chart};

use super::{METHODS, MethodSummary, Sample, scaled_method};

/// `quality_curve`: mean SSIM against total bytes, Canopy's weight factors joined into one curve
/// (factor 1 is `canopy`), beside the other methods' points and the SSIM 0.95 line.
pub(super) fn write_detail_curve(out: &Path, scales: &[f32], summaries: &[MethodSummary]) -> Result<Vec<PathBuf>> {
    let point = |name: &str| {
        summaries
            .iter()
            .find(|s| s.method == name)
            .map(|s| (s.bytes.max(1) as f64, s.mean_ssim))
    };
    let mut curve: Vec<(f64, f64)> = std::iter::once(point(METHODS[0]))
        .chain(scales.iter().map(|&s| point(&scaled_method(s))))
        .flatten()
        .collect();
    curve.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut series = vec![Series {
        name: std::iter::once("canopy, weights × 1".to_string())
            .chain(scales.iter().map(ToString::to_string))
            .collect::<Vec<_>>()
            .join(", "),
        points: curve,
    }];
    for name in [METHODS[1], METHODS[2], METHODS[3]] {
        series.extend(point(name).map(|p| Series {
            name: name.to_string(),
            points: vec![p],
        }));
    }
    let xs = series.iter().flat_map(|s| s.points.iter().map(|p| p.0));
    let (lo, hi) = xs.fold((f64::INFINITY, 0f64), |(a, b), x| (a.min(x), b.max(x)));
    if lo.is_finite() {
        series.push(Series {
            name: "SSIM 0.95".to_string(),
            points: vec![(lo, 0.95), (hi, 0.95)],
        });
    }
    Ok(write_line_chart(
        &out.join("quality_curve"),
        &LineChart {
            title: "Mean SSIM against total bytes, by weight factor",
            x_label: "bytes (log)",
            y_label: "mean SSIM vs full detail",
            series: &series,
            log_x: true,
        },
    )?)
}

pub(super) fn write_charts(
    out: &Path,
    methods: &[String],
    samples: &[Sample],
    frames_csv: &Path,
) -> Result<Vec<PathBuf>> {
    let by = |f: &dyn Fn(&Sample) -> (f64, f64)| -> Vec<Series> {
        methods
            .iter()
            .map(|name| Series {
                name: name.clone(),
                points: samples.iter().filter(|s| &s.method == name).map(f).collect(),
            })
            .collect()
    };
    let mut files = Vec::new();
    let q_bytes = by(&|s| (s.cumulative_bytes.max(1) as f64, s.ssim));
    files.extend(write_line_chart(
        &out.join("quality_vs_bytes"),
        &LineChart {
            title: "SSIM against cumulative bytes",
            x_label: "cumulative bytes (log)",
            y_label: "SSIM vs full detail",
            series: &q_bytes,
            log_x: true,
        },
    )?);
    // On the run's clock, so that a modelled link's waits show (frames are 1/30 s apart unless
    // `--frame-time` says otherwise).
    let q_time = by(&|s| (s.time_s, s.ssim));
    files.extend(write_line_chart(
        &out.join("quality_over_time"),
        &LineChart {
            title: "SSIM over time (the run's clock)",
            x_label: "seconds",
            y_label: "SSIM vs full detail",
            series: &q_time,
            log_x: false,
        },
    )?);
    let flip_frame = by(&|s| (f64::from(s.frame), s.flip));
    files.extend(write_line_chart(
        &out.join("flip_per_frame"),
        &LineChart {
            title: "Mean FLIP error per sampled frame (lower is better)",
            x_label: "frame",
            y_label: "FLIP vs full detail",
            series: &flip_frame,
            log_x: false,
        },
    )?);
    // Samples without mid-band pixels are left out of the mid-band curve.
    let mid_flip: Vec<Series> = methods
        .iter()
        .map(|name| Series {
            name: name.clone(),
            points: samples
                .iter()
                .filter(|s| &s.method == name)
                .filter_map(|s| Some((f64::from(s.frame), s.bands[1].flip?)))
                .collect(),
        })
        .collect();
    files.extend(write_line_chart(
        &out.join("mid_flip_per_frame"),
        &LineChart {
            title: "Mid band (30-150 px trees): FLIP error per sampled frame",
            x_label: "frame",
            y_label: "FLIP over the mid band's pixels",
            series: &mid_flip,
            log_x: false,
        },
    )?);
    let text = std::fs::read_to_string(frames_csv)?;
    let mut per: Vec<Series> = methods
        .iter()
        .map(|n| Series {
            name: n.clone(),
            points: Vec::new(),
        })
        .collect();
    for line in text.lines().skip(1) {
        let v: Vec<f64> = line.split(',').filter_map(|x| x.parse().ok()).collect();
        if v.len() == methods.len() + 1 {
            for (k, s) in per.iter_mut().enumerate() {
                s.points.push((v[0], v[k + 1] / 1024.0));
            }
        }
    }
    files.extend(write_line_chart(
        &out.join("bytes_per_frame"),
        &LineChart {
            title: "KiB fetched per frame",
            x_label: "frame",
            y_label: "KiB",
            series: &per,
            log_x: false,
        },
    )?);
    Ok(files)
}
