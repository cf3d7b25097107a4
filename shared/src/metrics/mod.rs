//! Image-quality metrics for simplification: coverage precision / recall / IoU, colour SSIM,
//! the perceptual LDR-FLIP error ([`flip`]), both as maps that can be averaged over a mask (a
//! distance band's pixels), and a PNG writer for debugging.
//!
//! Coverage masks are `&[bool]` per pixel (row-major); `true` = covered (alpha > 0, or an item
//! is present: [`crate::raster::Frame::coverage`], [`mask_from_alpha`]).

use std::path::Path;

use crate::raster::RasterError;

pub mod flip;
pub use flip::{DEFAULT_PIXELS_PER_DEGREE, flip_map, magma};

/// Errors of the metrics.
#[derive(Debug, thiserror::Error)]
pub enum MetricsError {
    /// The two inputs have different sizes.
    #[error("size mismatch: {0} vs {1}")]
    SizeMismatch(String, String),
    /// The colour buffer does not match `width × height`.
    #[error("colour buffer of {len} pixels for a {width}x{height} image")]
    BadBuffer {
        /// Pixels given.
        len: usize,
        /// Width.
        width: u32,
        /// Height.
        height: u32,
    },
    /// SSIM computation failed.
    #[error("ssim: {0}")]
    Ssim(#[from] image_compare::CompareError),
}

/// Coverage agreement between an approximation `A` and a reference `R`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CoverageStats {
    /// |A ∩ R| / |A|: fraction of the approximation's pixels that the reference covers too.
    /// 1 when A is empty (no false positives).
    pub precision: f64,
    /// |A ∩ R| / |R|: fraction of the reference's pixels that the approximation covers.
    /// 1 when R is empty (nothing to miss).
    pub recall: f64,
    /// |A ∩ R| / |A ∪ R| (silhouette IoU); 1 when both are empty.
    pub iou: f64,
    /// |A|.
    pub approx_pixels: u64,
    /// |R|.
    pub reference_pixels: u64,
    /// |A ∩ R|.
    pub both_pixels: u64,
}

/// Coverage precision, recall and IoU of `approx` against `reference` (same length).
///
/// Edge cases: both empty → all three are 1; A empty, R not → precision 1, recall 0, IoU 0;
/// R empty, A not → precision 0, recall 1, IoU 0.
pub fn coverage(reference: &[bool], approx: &[bool]) -> Result<CoverageStats, MetricsError> {
    if reference.len() != approx.len() {
        return Err(MetricsError::SizeMismatch(
            reference.len().to_string(),
            approx.len().to_string(),
        ));
    }
    let (mut a, mut r, mut both) = (0u64, 0u64, 0u64);
    for (&rr, &aa) in reference.iter().zip(approx) {
        a += u64::from(aa);
        r += u64::from(rr);
        both += u64::from(aa && rr);
    }
    Ok(stats(a, r, both))
}

fn stats(a: u64, r: u64, both: u64) -> CoverageStats {
    let ratio = |num: u64, den: u64| if den == 0 { 1.0 } else { num as f64 / den as f64 };
    let union = a + r - both;
    CoverageStats {
        precision: ratio(both, a),
        recall: ratio(both, r),
        iou: ratio(both, union),
        approx_pixels: a,
        reference_pixels: r,
        both_pixels: both,
    }
}

/// Item precision and recall: like [`coverage`], but a pixel counts as shared only when both
/// item buffers show the *same* item there (`empty` marks no item). A simplification that reveals
/// leaves the full tree hides loses precision; one that drops visible leaves loses recall. This is
/// the measure that separates leaf orders: plain coverage precision of a leaf subset is always 1.
pub fn item_agreement(reference: &[u32], approx: &[u32], empty: u32) -> Result<CoverageStats, MetricsError> {
    if reference.len() != approx.len() {
        return Err(MetricsError::SizeMismatch(
            reference.len().to_string(),
            approx.len().to_string(),
        ));
    }
    let (mut a, mut r, mut both) = (0u64, 0u64, 0u64);
    for (&rr, &aa) in reference.iter().zip(approx) {
        a += u64::from(aa != empty);
        r += u64::from(rr != empty);
        both += u64::from(aa != empty && aa == rr);
    }
    Ok(stats(a, r, both))
}

/// Silhouette IoU of two masks (see [`coverage`]).
pub fn iou(reference: &[bool], approx: &[bool]) -> Result<f64, MetricsError> {
    coverage(reference, approx).map(|c| c.iou)
}

/// Coverage mask from RGBA pixels: `alpha > 0`.
pub fn mask_from_alpha(rgba: &[[u8; 4]]) -> Vec<bool> {
    rgba.iter().map(|p| p[3] > 0).collect()
}

fn rgb_over(rgba: &[[u8; 4]], width: u32, height: u32, bg: [u8; 3]) -> Result<image::RgbImage, MetricsError> {
    let bad = || MetricsError::BadBuffer {
        len: rgba.len(),
        width,
        height,
    };
    if rgba.len() != width as usize * height as usize {
        return Err(bad());
    }
    // Composite over the background in sRGB space (cheap; this is a metric, not a renderer).
    let raw: Vec<u8> = rgba
        .iter()
        .flat_map(|p| {
            let a = u32::from(p[3]);
            [0, 1, 2].map(|c| ((u32::from(p[c]) * a + u32::from(bg[c]) * (255 - a) + 127) / 255) as u8)
        })
        .collect();
    image::RgbImage::from_raw(width, height, raw).ok_or_else(bad)
}

/// Colour SSIM of two RGBA images of `width × height`, each composited over `background`
/// first: `image_compare`'s MSSIM (8×8 windows) per channel, the minimum over R, G, B.
/// 1 for identical images; lower is worse (may be negative).
pub fn ssim_rgba(
    reference: &[[u8; 4]],
    approx: &[[u8; 4]],
    width: u32,
    height: u32,
    background: [u8; 3],
) -> Result<f64, MetricsError> {
    let a = rgb_over(reference, width, height, background)?;
    let b = rgb_over(approx, width, height, background)?;
    let s = image_compare::rgb_similarity_structure(&image_compare::Algorithm::MSSIMSimple, &a, &b)?;
    Ok(s.score)
}

/// Per-pixel colour SSIM of two RGBA images (composited over `background`), one map per
/// channel R, G, B: each pixel holds its 8 × 8 window's SSIM, so the mean of a channel's map over
/// every pixel is that channel's score and [`ssim_rgba`] is the minimum of the three.
#[derive(Debug, Clone, PartialEq)]
pub struct SsimMaps {
    /// Per channel, row-major per pixel.
    pub channels: [Vec<f32>; 3],
}

impl SsimMaps {
    /// SSIM over the pixels of `mask` (same length as the maps): per channel the mean over the
    /// masked pixels, the minimum over channels; `None` when the mask selects nothing.
    pub fn masked(&self, mask: &[bool]) -> Option<f64> {
        let n = mask.iter().filter(|&&m| m).count();
        if n == 0 || mask.len() != self.channels[0].len() {
            return None;
        }
        self.channels
            .iter()
            .map(|c| {
                c.iter()
                    .zip(mask)
                    .filter(|(_, m)| **m)
                    .map(|(&v, _)| f64::from(v))
                    .sum::<f64>()
                    / n as f64
            })
            .reduce(f64::min)
    }
}

/// [`ssim_rgba`]'s score and its per-pixel maps. `image_compare` keeps its maps behind a
/// private type, so the windows are computed here exactly as its `MSSIMSimple` does them
/// (8 × 8 windows from the top-left, clipped at the borders; its sums of squares, not
/// variances); the score is still `image_compare`'s.
pub fn ssim_maps_rgba(
    reference: &[[u8; 4]],
    approx: &[[u8; 4]],
    width: u32,
    height: u32,
    background: [u8; 3],
) -> Result<(f64, SsimMaps), MetricsError> {
    const WINDOW: usize = 8;
    const C1: f64 = (0.01 * 255.0) * (0.01 * 255.0);
    const C2: f64 = (0.03 * 255.0) * (0.03 * 255.0);
    let a = rgb_over(reference, width, height, background)?;
    let b = rgb_over(approx, width, height, background)?;
    let score = image_compare::rgb_similarity_structure(&image_compare::Algorithm::MSSIMSimple, &a, &b)?.score;
    let (w, h) = (width as usize, height as usize);
    let (ra, rb) = (a.as_raw(), b.as_raw());
    let channels = [0usize, 1, 2].map(|c| {
        let mut map = vec![0.0f32; w * h];
        for y0 in (0..h).step_by(WINDOW) {
            for x0 in (0..w).step_by(WINDOW) {
                let (y1, x1) = ((y0 + WINDOW).min(h), (x0 + WINDOW).min(w));
                let px = |raw: &[u8], x: usize, y: usize| f64::from(raw[(y * w + x) * 3 + c]);
                let pixels = || (y0..y1).flat_map(move |y| (x0..x1).map(move |x| (x, y)));
                let n = ((y1 - y0) * (x1 - x0)) as f64;
                let mx = pixels().map(|(x, y)| px(ra, x, y)).sum::<f64>() / n;
                let my = pixels().map(|(x, y)| px(rb, x, y)).sum::<f64>() / n;
                let (mut vx, mut vy, mut cxy) = (0.0, 0.0, 0.0);
                for (x, y) in pixels() {
                    let (dx, dy) = (px(ra, x, y) - mx, px(rb, x, y) - my);
                    vx += dx * dx;
                    vy += dy * dy;
                    cxy += dx * dy;
                }
                let s = ((2.0 * mx * my + C1) * (2.0 * cxy + C2)) / ((mx * mx + my * my + C1) * (vx + vy + C2));
                for (x, y) in pixels() {
                    map[y * w + x] = s as f32;
                }
            }
        }
        map
    });
    Ok((score, SsimMaps { channels }))
}

/// LDR-FLIP error map ([`flip::flip_map`]) of two RGBA images composited over `background`.
pub fn flip_rgba(
    reference: &[[u8; 4]],
    approx: &[[u8; 4]],
    width: u32,
    height: u32,
    background: [u8; 3],
    pixels_per_degree: f32,
) -> Result<Vec<f32>, MetricsError> {
    let rgb = |img: &[[u8; 4]]| -> Result<Vec<[u8; 3]>, MetricsError> {
        Ok(rgb_over(img, width, height, background)?
            .pixels()
            .map(|p| p.0)
            .collect())
    };
    flip_map(&rgb(reference)?, &rgb(approx)?, width, height, pixels_per_degree)
}

/// Mean of `map` over the pixels of `mask` (same length); `None` when the mask selects nothing.
pub fn masked_mean(map: &[f32], mask: &[bool]) -> Option<f64> {
    if map.len() != mask.len() {
        return None;
    }
    let (sum, n) = map
        .iter()
        .zip(mask)
        .filter(|(_, m)| **m)
        .fold((0.0f64, 0u64), |(s, n), (&v, _)| (s + f64::from(v), n + 1));
    (n > 0).then(|| sum / n as f64)
}

/// Writes RGBA8 pixels (row-major, row 0 at the top) as a PNG file.
pub fn write_png(path: &Path, width: u32, height: u32, rgba: &[[u8; 4]]) -> Result<(), RasterError> {
    let raw: Vec<u8> = rgba.iter().flatten().copied().collect();
    let img = image::RgbaImage::from_raw(width, height, raw)
        .ok_or_else(|| RasterError::InvalidTexture(format!("{} pixels for a {width}x{height} PNG", rgba.len())))?;
    img.save_with_format(path, image::ImageFormat::Png)?;
    Ok(())
}

/// A false-colour RGBA image of an item buffer for debugging: each item a stable hashed colour,
/// empty pixels transparent.
pub fn item_false_color(items: &[u32]) -> Vec<[u8; 4]> {
    items
        .iter()
        .map(|&i| {
            if i == crate::raster::EMPTY_ITEM {
                [0; 4]
            } else {
                let h = i.wrapping_mul(0x9E37_79B9).rotate_left(13) ^ 0x5bd1_e995;
                [
                    (h >> 24) as u8 | 0x40,
                    (h >> 16) as u8 | 0x40,
                    (h >> 8) as u8 | 0x40,
                    255,
                ]
            }
        })
        .collect()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn coverage_edge_cases() {
        let r = [true, true, false, false];
        let c = coverage(&r, &r).unwrap();
        assert_eq!((c.precision, c.recall, c.iou), (1.0, 1.0, 1.0));
        let c = coverage(&r, &[false, false, true, true]).unwrap();
        assert_eq!((c.precision, c.recall, c.iou), (0.0, 0.0, 0.0));
        let c = coverage(&r, &[true, false, true, false]).unwrap();
        assert_eq!((c.precision, c.recall), (0.5, 0.5));
        assert!((c.iou - 1.0 / 3.0).abs() < 1e-12);
        let c = coverage(&[false; 4], &[false; 4]).unwrap();
        assert_eq!((c.precision, c.recall, c.iou), (1.0, 1.0, 1.0));
        let c = coverage(&r, &[false; 4]).unwrap();
        assert_eq!((c.precision, c.recall, c.iou), (1.0, 0.0, 0.0));
        assert!(coverage(&r, &[true]).is_err());
    }

    #[test]
    fn ssim_identical_is_one() {
        let (w, h) = (32u32, 24u32);
        let img: Vec<[u8; 4]> = (0..w * h)
            .map(|i| {
                [
                    (i * 7 % 256) as u8,
                    (i * 13 % 256) as u8,
                    (i % 256) as u8,
                    if i % 3 == 0 { 0 } else { 255 },
                ]
            })
            .collect();
        let s = ssim_rgba(&img, &img, w, h, [0, 0, 0]).unwrap();
        assert!((s - 1.0).abs() < 1e-9, "{s}");
        let other: Vec<[u8; 4]> = img.iter().map(|p| [255 - p[0], p[2], p[1], 255]).collect();
        assert!(ssim_rgba(&img, &other, w, h, [0, 0, 0]).unwrap() < 0.9);
        assert!(ssim_rgba(&img, &img[1..], w, h, [0, 0, 0]).is_err());
    }

    #[test]
    fn ssim_maps_agree_with_the_score_and_mask() {
        let (w, h) = (32u32, 16u32);
        let a: Vec<[u8; 4]> = (0..w * h)
            .map(|i| [(i * 7 % 256) as u8, (i * 3 % 256) as u8, 90, 255])
            .collect();
        // The right half differs; the left half is identical.
        let b: Vec<[u8; 4]> = a
            .iter()
            .enumerate()
            .map(|(i, p)| {
                if i as u32 % w >= w / 2 {
                    [p[1], p[0], 200, 255]
                } else {
                    *p
                }
            })
            .collect();
        let (score, maps) = ssim_maps_rgba(&a, &b, w, h, [0, 0, 0]).unwrap();
        assert!((score - ssim_rgba(&a, &b, w, h, [0, 0, 0]).unwrap()).abs() < 1e-6);
        let all = vec![true; (w * h) as usize];
        assert!((maps.masked(&all).unwrap() - score).abs() < 1e-4);
        let left: Vec<bool> = (0..w * h).map(|i| i % w < w / 2).collect();
        let right: Vec<bool> = left.iter().map(|l| !l).collect();
        assert!((maps.masked(&left).unwrap() - 1.0).abs() < 1e-6);
        assert!(maps.masked(&right).unwrap() < score);
        assert_eq!(maps.masked(&vec![false; all.len()]), None);
        let fl = flip_rgba(&a, &b, w, h, [0, 0, 0], DEFAULT_PIXELS_PER_DEGREE).unwrap();
        let (l, r) = (masked_mean(&fl, &left).unwrap(), masked_mean(&fl, &right).unwrap());
        assert!(l < r, "{l} {r}");
        assert_eq!(masked_mean(&fl, &[true]), None);
    }

    #[test]
    fn png_roundtrip() {
        let dir = std::env::temp_dir().join(format!("canopy-metrics-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t.png");
        let px = vec![[10, 20, 30, 40]; 6];
        write_png(&path, 3, 2, &px).unwrap();
        let t = crate::raster::Texture::load_png(&path).unwrap();
        assert_eq!((t.width(), t.height()), (3, 2));
        assert!(write_png(&path, 4, 2, &px).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
