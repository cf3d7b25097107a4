//! Image-quality metrics for simplification: coverage precision / recall / IoU, colour SSIM,
//! and a PNG writer for debugging.
//!
//! Coverage masks are `&[bool]` per pixel (row-major); `true` = covered (alpha > 0, or an item
//! is present: [`crate::raster::Frame::coverage`], [`mask_from_alpha`]).

use std::path::Path;

use crate::raster::RasterError;

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
