//! What `canopy eval` prints and writes besides its CSV files: the resolution note, the summary
//! tables (whole image and per distance band) and the HTML report.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Result;
use canopy_client::eval::report::{Report, write_report};
use canopy_client::eval::{BANDS, Band, BandScore};
use canopy_shared::chart::{LineChart, Series, write_line_chart};
use serde::Serialize;

use super::MethodSummary;

/// The viewer's default viewport, which a person looks at: scores at a smaller size say so.
pub const VIEWER_SIZE: (u32, u32) = (1280, 720);
/// Fewest samples per path for a curve (issue 21).
pub const CURVE_SAMPLES: usize = 8;

/// The size the images were scored at, and whether that is what a person sees.
#[derive(Debug, Clone, Serialize)]
pub struct Resolution {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Below the viewer's 1280 × 720 in either direction.
    pub reduced: bool,
    /// One line for the output.
    pub note: String,
}

impl Resolution {
    /// The resolution of `width × height`.
    pub fn new(width: u32, height: u32) -> Self {
        let reduced = width < VIEWER_SIZE.0 || height < VIEWER_SIZE.1;
        let note = if reduced {
            format!(
                "scored at {width}x{height}, below the viewer's {}x{}: small trees and leaves are fewer pixels \
                 than a person sees, so SSIM and FLIP miss detail there",
                VIEWER_SIZE.0, VIEWER_SIZE.1
            )
        } else {
            format!("scored at {width}x{height}, the viewport's resolution")
        };
        Self {
            width,
            height,
            reduced,
            note,
        }
    }
}

/// One band's means over a method's samples.
#[derive(Debug, Clone, Serialize)]
pub struct BandSummary {
    band: Band,
    /// Samples in which the band has pixels.
    samples: usize,
    /// Mean share of the image's pixels (over all samples).
    mean_pixel_share: f64,
    /// Mean SSIM over the samples with pixels in the band.
    mean_ssim: Option<f64>,
    /// Mean FLIP over the samples with pixels in the band.
    mean_flip: Option<f64>,
}

/// Per band, the means over the samples' band scores.
pub fn band_means(samples: &[&[BandScore; 3]]) -> Vec<BandSummary> {
    BANDS
        .iter()
        .enumerate()
        .map(|(k, &band)| {
            let all: Vec<&BandScore> = samples.iter().map(|s| &s[k]).collect();
            let with: Vec<&BandScore> = all.iter().copied().filter(|b| b.ssim.is_some()).collect();
            let mean = |g: &dyn Fn(&BandScore) -> Option<f64>| {
                (!with.is_empty()).then(|| with.iter().filter_map(|b| g(b)).sum::<f64>() / with.len() as f64)
            };
            BandSummary {
                band,
                samples: with.len(),
                mean_pixel_share: all.iter().map(|b| b.pixel_share).sum::<f64>() / all.len().max(1) as f64,
                mean_ssim: mean(&|b| b.ssim),
                mean_flip: mean(&|b| b.flip),
            }
        })
        .collect()
}

/// `ladder_sweep`: mean FLIP error in the mid band (trees 30–150 px tall, where the ladders
/// differ) against total bytes, one point per method, and `ladder_sweep.csv` with the whole-image
/// figures beside it: the lower left wins on perceptual quality per byte. The full-detail
/// reference (FLIP 0 by definition) and random order (same bytes as Canopy) are left out.
pub fn write_ladder_sweep(out: &Path, summaries: &[MethodSummary]) -> Result<Vec<PathBuf>> {
    let mut series = Vec::new();
    let mut csv = String::from("method,bytes,mean_flip,mid_flip,mean_ssim,mid_ssim,mean_triangle_share\n");
    for s in summaries.iter().filter(|s| {
        !matches!(
            s.method.as_str(),
            "canopy-random" | "full" | "whole-glb" | "whole-ctree"
        )
    }) {
        let mid = s.bands.iter().find(|b| b.band == Band::Mid);
        let mid_flip = mid.and_then(|b| b.mean_flip);
        let _ = writeln!(
            csv,
            "{},{},{},{},{},{},{}",
            s.method,
            s.bytes,
            opt(Some(s.mean_flip), 4),
            opt(mid_flip, 4),
            opt(Some(s.mean_ssim), 4),
            opt(mid.and_then(|b| b.mean_ssim), 4),
            opt(Some(s.mean_triangle_share), 4),
        );
        series.extend(mid_flip.map(|f| Series {
            name: s.method.replacen("canopy-ladder-", "ladder ", 1),
            points: vec![(s.bytes as f64, f)],
        }));
    }
    let csv_path = out.join("ladder_sweep.csv");
    std::fs::write(&csv_path, csv)?;
    let mut files = write_line_chart(
        &out.join("ladder_sweep"),
        &LineChart {
            title: "Mid-band FLIP error against bytes, per method (lower left is better)",
            x_label: "bytes fetched along the path",
            y_label: "mean FLIP, trees 30-150 px",
            series: &series,
            log_x: false,
        },
    )?;
    files.push(csv_path);
    Ok(files)
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or_else(|| "-".to_string(), |v| format!("{v:.digits$}"))
}

/// The whole-image table and the per-band table, on stdout.
pub fn print_tables(summaries: &[MethodSummary]) {
    println!(
        "{:<22} {:>12} {:>9} {:>9} {:>8} {:>9} {:>9} {:>9} {:>10} {:>14}",
        "method", "bytes", "SSIM", "min SSIM", "FLIP", "prec.", "recall", "popping", "tri share", "bytes@SSIM.95"
    );
    for s in summaries {
        println!(
            "{:<22} {:>12} {:>9.4} {:>9.4} {:>8.4} {:>9.4} {:>9.4} {:>9.5} {:>10.4} {:>14}",
            s.method,
            s.bytes,
            s.mean_ssim,
            s.min_ssim,
            s.mean_flip,
            s.mean_precision,
            s.mean_recall,
            s.mean_popping,
            s.mean_triangle_share,
            s.bytes_to_ssim_095.map_or("never".into(), |b| b.to_string())
        );
    }
    println!(
        "per band (trees >= {:.0} px near, {:.0}-{:.0} px mid, below far; a band's pixels are its trees' in either image):",
        canopy_client::eval::NEAR_MIN_PX,
        canopy_client::eval::MID_MIN_PX,
        canopy_client::eval::NEAR_MIN_PX
    );
    println!(
        "{:<22} {:>7} {:>8} {:>8} {:>7} {:>8} {:>8} {:>7} {:>8} {:>8}",
        "method", "near %", "SSIM", "FLIP", "mid %", "SSIM", "FLIP", "far %", "SSIM", "FLIP"
    );
    for s in summaries {
        print!("{:<22}", s.method);
        for b in &s.bands {
            print!(
                " {:>7.1} {:>8} {:>8}",
                100.0 * b.mean_pixel_share,
                opt(b.mean_ssim, 4),
                opt(b.mean_flip, 4)
            );
        }
        println!();
    }
    println!("time on the run's clock, s (first complete: every visible tree drawn, at least as a stand-in):");
    println!(
        "{:<22} {:>15} {:>10} {:>10} {:>10}",
        "method", "first complete", "SSIM .90", "SSIM .95", "target Q"
    );
    for s in summaries {
        println!(
            "{:<22} {:>15} {:>10} {:>10} {:>10}",
            s.method,
            opt(s.time_to_complete, 2),
            opt(s.time_to_ssim_090, 2),
            opt(s.time_to_ssim_095, 2),
            opt(s.time_to_quality_target, 2)
        );
    }
}

/// Writes `report.html` in `out`: notes, the table, the SVG charts and the strips.
#[allow(clippy::too_many_arguments)]
pub fn write_html_report(
    out: &Path,
    title: &str,
    resolution: &Resolution,
    sampled: usize,
    quality_target: Option<f64>,
    summaries: &[MethodSummary],
    charts: &[PathBuf],
    strips: &[(String, PathBuf)],
) -> Result<PathBuf> {
    let mut notes = vec![
        resolution.note.clone(),
        format!(
            "{sampled} sampled frames per method{}. SSIM: colour SSIM over a pale sky (1 = identical). \
             FLIP: NVIDIA's LDR-FLIP perceptual error at 67 pixels per degree (0 = indistinguishable, \
             lower is better). Bands: near trees are at least 150 px tall, mid 30-150 px, far below; \
             a band's scores are over the pixels its trees cover in either image.",
            if sampled < CURVE_SAMPLES {
                format!(" (fewer than {CURVE_SAMPLES}: the charts are not yet curves)")
            } else {
                String::new()
            }
        ),
    ];
    notes.push(
        "Bytes are each method's real transfer (discrete: whole level files on first use; whole-glb and \
         whole-ctree: each model's one file whole, its trees drawn once it has arrived)."
            .into(),
    );
    if let Some(q) = quality_target {
        notes.push(format!(
            "Times are on the run's clock. First complete: the first frame that draws every visible tree, at \
             least as a stand-in. To Q: the first sample from which every later one has SSIM at least Q = {q:.4}, 0.01 \
             under the lower of Canopy's and the discrete files' last SSIM (their settled SSIM when the run \
             lasts until both have settled)."
        ));
    }
    let mut columns: Vec<String> = [
        "method",
        "bytes",
        "SSIM",
        "FLIP",
        "precision",
        "recall",
        "popping",
        "first complete (s)",
        "to Q (s)",
    ]
    .iter()
    .map(ToString::to_string)
    .collect();
    for b in BANDS {
        columns.push(format!("{} %", b.name()));
        columns.push(format!("{} SSIM", b.name()));
        columns.push(format!("{} FLIP", b.name()));
    }
    let rows = summaries
        .iter()
        .map(|s| {
            let mut r = vec![
                s.method.clone(),
                s.bytes.to_string(),
                format!("{:.4}", s.mean_ssim),
                format!("{:.4}", s.mean_flip),
                format!("{:.4}", s.mean_precision),
                format!("{:.4}", s.mean_recall),
                format!("{:.5}", s.mean_popping),
                opt(s.time_to_complete, 2),
                opt(s.time_to_quality_target, 2),
            ];
            for b in &s.bands {
                r.push(format!("{:.1}", 100.0 * b.mean_pixel_share));
                r.push(opt(b.mean_ssim, 4));
                r.push(opt(b.mean_flip, 4));
            }
            r
        })
        .collect();
    let report = Report {
        title: title.to_string(),
        notes,
        columns,
        rows,
        charts: charts
            .iter()
            .filter(|p| p.extension().is_some_and(|e| e == "svg"))
            .cloned()
            .collect(),
        strips: strips.to_vec(),
    };
    Ok(write_report(&out.join("report.html"), &report)?)
}
