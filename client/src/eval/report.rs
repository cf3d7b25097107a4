//! One HTML page for an evaluation: its notes, the summary table, the charts (SVG, inlined) and
//! the image strips (PNG, linked by paths relative to the page), so the folder that holds the
//! page is the whole report and opens without a network.
//!
//! Conventions: every text is HTML-escaped; image paths are written relative to the page's
//! folder with `/` separators; charts whose file is missing are skipped with a note.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::EvalError;

/// What one report shows.
#[derive(Debug, Clone, Default)]
pub struct Report {
    /// Page title.
    pub title: String,
    /// Paragraphs above the table (settings, what the figures mean).
    pub notes: Vec<String>,
    /// Table header.
    pub columns: Vec<String>,
    /// Table rows, one cell per column.
    pub rows: Vec<Vec<String>>,
    /// SVG charts to inline.
    pub charts: Vec<PathBuf>,
    /// Image strips: caption and PNG path.
    pub strips: Vec<(String, PathBuf)>,
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// `path` relative to `base` when it lies under it, with `/` separators (else as given).
fn relative(path: &Path, base: &Path) -> String {
    let p = path.strip_prefix(base).unwrap_or(path);
    p.components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect::<Vec<_>>()
        .join("/")
}

/// Writes `report` as `path` (an `.html` file) and returns the path.
pub fn write_report(path: &Path, report: &Report) -> Result<PathBuf, EvalError> {
    let base = path.parent().unwrap_or(Path::new(""));
    let mut h = String::new();
    let _ = write!(
        h,
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{t}</title>\n<style>\
         body{{font-family:sans-serif;margin:1.5em;max-width:1400px}}\
         table{{border-collapse:collapse}}td,th{{border:1px solid #bbb;padding:2px 8px;text-align:right}}\
         td:first-child,th:first-child{{text-align:left}}\
         figure{{margin:1em 0}}img{{max-width:100%;image-rendering:pixelated}}\
         .charts svg{{max-width:48%;height:auto;margin:0.5%}}</style></head><body>\n<h1>{t}</h1>\n",
        t = escape(&report.title)
    );
    for n in &report.notes {
        let _ = writeln!(h, "<p>{}</p>", escape(n));
    }
    h.push_str("<h2>Summary</h2>\n<table><tr>");
    for c in &report.columns {
        let _ = write!(h, "<th>{}</th>", escape(c));
    }
    h.push_str("</tr>\n");
    for r in &report.rows {
        h.push_str("<tr>");
        for c in r {
            let _ = write!(h, "<td>{}</td>", escape(c));
        }
        h.push_str("</tr>\n");
    }
    h.push_str("</table>\n<h2>Charts</h2>\n<div class=\"charts\">\n");
    for c in &report.charts {
        match std::fs::read_to_string(c) {
            Ok(svg) => {
                // The SVG element itself: an XML declaration is not allowed inside HTML.
                let start = svg.find("<svg").unwrap_or(0);
                h.push_str(&svg[start..]);
                h.push('\n');
            }
            Err(e) => {
                let _ = writeln!(
                    h,
                    "<p>chart {} missing: {}</p>",
                    escape(&c.display().to_string()),
                    escape(&e.to_string())
                );
            }
        }
    }
    h.push_str(
        "</div>\n<h2>Image strips</h2>\n<p>Each strip: the method's rendering | full detail | FLIP error \
                (black: none, red to pale yellow: most).</p>\n",
    );
    for (caption, p) in &report.strips {
        let src = relative(p, base);
        let _ = writeln!(
            h,
            "<figure><img src=\"{}\" alt=\"{c}\"><figcaption>{c}</figcaption></figure>",
            escape(&src),
            c = escape(caption)
        );
    }
    h.push_str("</body></html>\n");
    if !base.as_os_str().is_empty() {
        std::fs::create_dir_all(base)?;
    }
    std::fs::write(path, h)?;
    Ok(path.to_path_buf())
}

/// The `src` of every `<img>` of an HTML page, in order.
pub fn image_sources(html: &str) -> Vec<String> {
    html.split("<img src=\"")
        .skip(1)
        .filter_map(|rest| rest.split('"').next())
        .map(|s| {
            s.replace("&amp;", "&")
                .replace("&quot;", "\"")
                .replace("&lt;", "<")
                .replace("&gt;", ">")
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn report_inlines_charts_and_links_existing_strips() {
        let dir = std::env::temp_dir().join(format!("canopy-report-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("strips")).expect("dir");
        let chart = dir.join("c.svg");
        std::fs::write(
            &chart,
            "<?xml version=\"1.0\"?>\n<svg width=\"10\" height=\"10\"><rect/></svg>",
        )
        .expect("svg");
        let strip = dir.join("strips/frame00030-canopy.png");
        canopy_shared::metrics::write_png(&strip, 2, 1, &[[1, 2, 3, 255]; 2]).expect("png");
        let report = Report {
            title: "demo <flyover>".into(),
            notes: vec!["scored at 1280x720".into()],
            columns: vec!["method".into(), "FLIP".into()],
            rows: vec![vec!["canopy".into(), "0.123".into()]],
            charts: vec![chart, dir.join("missing.svg")],
            strips: vec![("frame 30: canopy".into(), strip)],
        };
        let path = write_report(&dir.join("report.html"), &report).expect("report");
        let html = std::fs::read_to_string(&path).expect("html");
        assert!(
            html.contains("demo &lt;flyover&gt;") && html.contains("<td>0.123</td>"),
            "{html}"
        );
        assert!(html.contains("<svg width=\"10\"") && !html.contains("<?xml"), "{html}");
        assert!(html.contains("missing.svg"));
        let srcs = image_sources(&html);
        assert_eq!(srcs, ["strips/frame00030-canopy.png"]);
        assert!(srcs.iter().all(|s| dir.join(s).is_file()));
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }
}
