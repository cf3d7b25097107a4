//! Line charts written as PNG and SVG (plotters, with the embedded DejaVu Sans Mono font so no
//! system font library is needed).

use std::path::{Path, PathBuf};
use std::sync::Once;

use plotters::prelude::*;
use plotters::style::FontStyle;

/// The chart font (DejaVu Sans Mono, `assets/fonts/DejaVu-LICENSE.txt`).
const FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSansMono.ttf");
const FAMILY: &str = "sans-serif";

static REGISTER: Once = Once::new();

/// One named line.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend label.
    pub name: String,
    /// Points `(x, y)`, drawn in the order given; non-finite points are skipped.
    pub points: Vec<(f64, f64)>,
}

/// What to draw.
#[derive(Debug, Clone, PartialEq)]
pub struct LineChart<'a> {
    /// Title.
    pub title: &'a str,
    /// X axis label.
    pub x_label: &'a str,
    /// Y axis label.
    pub y_label: &'a str,
    /// Lines.
    pub series: &'a [Series],
    /// Logarithmic x axis (positive x only).
    pub log_x: bool,
}

/// Why a chart could not be written.
#[derive(Debug, thiserror::Error)]
pub enum ChartError {
    /// Drawing or encoding failed.
    #[error("chart {path}: {message}")]
    Draw {
        /// File.
        path: String,
        /// What plotters said.
        message: String,
    },
}

const COLORS: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

fn bounds(c: &LineChart<'_>) -> (f64, f64, f64, f64) {
    let pts = c
        .series
        .iter()
        .flat_map(|s| s.points.iter())
        .filter(|(x, y)| x.is_finite() && y.is_finite() && (!c.log_x || *x > 0.0));
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in pts {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    if x0 > x1 {
        return (if c.log_x { 1.0 } else { 0.0 }, 10.0, 0.0, 1.0);
    }
    if x1 <= x0 {
        x1 = x0 + 1.0;
    }
    if y1 <= y0 {
        y1 = y0 + 1.0;
    }
    let pad = (y1 - y0) * 0.05;
    // Room at both ends so that points on the edges stay visible.
    let (x0, x1) = if c.log_x {
        (x0 / 1.3, x1 * 1.3)
    } else {
        let px = (x1 - x0) * 0.03;
        (x0 - px, x1 + px)
    };
    (x0, x1, y0 - pad, y1 + pad)
}

/// Short axis labels: 12M, 1.5k, 300, 0.25.
fn human(x: f64) -> String {
    let a = x.abs();
    let (v, unit) = if a >= 1e9 {
        (x / 1e9, "G")
    } else if a >= 1e6 {
        (x / 1e6, "M")
    } else if a >= 1e4 {
        (x / 1e3, "k")
    } else {
        (x, "")
    };
    let text = if v.fract().abs() < 1e-9 || v.abs() >= 100.0 {
        format!("{v:.0}")
    } else {
        format!("{v:.2}")
            .trim_end_matches('0')
            .trim_end_matches('.')
            .to_string()
    };
    format!("{text}{unit}")
}

fn draw<DB: DrawingBackend>(root: &DrawingArea<DB, plotters::coord::Shift>, c: &LineChart<'_>) -> Result<(), String>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE).map_err(|e| e.to_string())?;
    let (x0, x1, y0, y1) = bounds(c);
    let mut b = ChartBuilder::on(root);
    b.caption(c.title, (FAMILY, 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70);
    macro_rules! body {
        ($chart:expr) => {{
            let mut chart = $chart;
            chart
                .configure_mesh()
                .x_label_formatter(&|x: &f64| human(*x))
                .x_desc(c.x_label)
                .y_desc(c.y_label)
                .label_style((FAMILY, 13))
                .draw()
                .map_err(|e| e.to_string())?;
            for (i, s) in c.series.iter().enumerate() {
                let color = COLORS[i % COLORS.len()];
                let pts: Vec<(f64, f64)> = s
                    .points
                    .iter()
                    .copied()
                    .filter(|(x, y)| x.is_finite() && y.is_finite() && (!c.log_x || *x > 0.0))
                    .collect();
                chart
                    .draw_series(pts.iter().map(|&p| Circle::new(p, 3, color.filled())))
                    .map_err(|e| e.to_string())?;
                chart
                    .draw_series(LineSeries::new(pts, color.stroke_width(2)))
                    .map_err(|e| e.to_string())?
                    .label(s.name.clone())
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2)));
            }
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .label_font((FAMILY, 13))
                .position(SeriesLabelPosition::LowerRight)
                .draw()
                .map_err(|e| e.to_string())?;
        }};
    }
    if c.log_x {
        body!(
            b.build_cartesian_2d((x0..x1).log_scale(), y0..y1)
                .map_err(|e| e.to_string())?
        );
    } else {
        body!(b.build_cartesian_2d(x0..x1, y0..y1).map_err(|e| e.to_string())?);
    }
    root.present().map_err(|e| e.to_string())
}

/// Writes `stem.png` (960 × 540) and `stem.svg`; returns both paths.
pub fn write_line_chart(stem: &Path, c: &LineChart<'_>) -> Result<Vec<PathBuf>, ChartError> {
    REGISTER.call_once(|| {
        // The font is compiled in and known to parse; a failure would only cost the PNG's text.
        let _ = plotters::style::register_font(FAMILY, FontStyle::Normal, FONT);
    });
    let png = stem.with_extension("png");
    let svg = stem.with_extension("svg");
    let err = |p: &Path, m: String| ChartError::Draw {
        path: p.display().to_string(),
        message: m,
    };
    // Drawn into memory and encoded with the workspace's `image` (plotters' own encoder would
    // compile a second, older `image`).
    let (w, h) = (960u32, 540u32);
    let mut rgb = vec![0u8; (w * h * 3) as usize];
    draw(&BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area(), c).map_err(|m| err(&png, m))?;
    image::save_buffer(&png, &rgb, w, h, image::ExtendedColorType::Rgb8).map_err(|e| err(&png, e.to_string()))?;
    draw(&SVGBackend::new(&svg, (w, h)).into_drawing_area(), c).map_err(|m| err(&svg, m))?;
    Ok(vec![png, svg])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axis_labels_are_short() {
        assert_eq!(human(12_000_000.0), "12M");
        assert_eq!(human(1_500_000.0), "1.5M");
        assert_eq!(human(25_000.0), "25k");
        assert_eq!(human(300.0), "300");
        assert_eq!(human(0.25), "0.25");
        assert_eq!(human(0.0), "0");
    }

    #[test]
    fn writes_png_and_svg_with_text() {
        let dir = std::env::temp_dir().join(format!("canopy-chart-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("mkdir");
        let series = [
            Series {
                name: "a".into(),
                points: vec![(1.0, 0.5), (10.0, 0.9), (100.0, f64::NAN)],
            },
            Series {
                name: "b".into(),
                points: vec![],
            },
        ];
        for log_x in [false, true] {
            let files = write_line_chart(
                &dir.join(format!("c{log_x}")),
                &LineChart {
                    title: "SSIM against bytes",
                    x_label: "bytes",
                    y_label: "SSIM",
                    series: &series,
                    log_x,
                },
            )
            .expect("chart");
            let png = image::open(&files[0]).expect("png decodes").to_rgb8();
            assert_eq!(png.dimensions(), (960, 540));
            // Text and lines drew dark pixels on the white background.
            assert!(png.pixels().filter(|p| p.0.iter().all(|&c| c < 100)).count() > 500);
            let svg = std::fs::read_to_string(&files[1]).expect("svg");
            assert!(svg.contains("SSIM against bytes"));
        }
        std::fs::remove_dir_all(&dir).ok();
    }
}
