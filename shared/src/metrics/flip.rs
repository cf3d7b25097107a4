//! LDR-FLIP (Andersson et al., "FLIP: A Difference Evaluator for Alternating Images", HPG 2020):
//! the per-pixel perceptual error a viewer sees when flipping between a reference and a test
//! image, in [0, 1] (0: indistinguishable). Lower is better; the mean over pixels is the usual
//! single figure.
//!
//! Why a port and not the `nv-flip` crate: `nv-flip` (0.1.2) wraps NVIDIA's C++ through FFI and
//! compiles FLIP's C++ with tinyexr and stb_image (about 25,000 lines of headers) on every clean
//! build, where CI has 2 cores; its last release is from 2023 (FLIP 1.2). The LDR pipeline is a
//! few separable convolutions and colour transforms: this module is that pipeline from the paper
//! and NVIDIA's reference code, without new dependencies, and per-pixel maps are what the
//! distance bands need. It matches NVIDIA's `flip-evaluator` 1.7 (PyPI) to within 0.001 mean
//! error on the test images of this module (see the tests).
//!
//! Pipeline, per the paper: sRGB → linear RGB → YCxCz; colour: each opponent channel filtered by
//! its contrast sensitivity function (Gaussian mixtures sized by pixels per degree), clamped to
//! the RGB cube, to Hunt-adjusted L\*a\*b\*, HyAB distance, compressed (`^0.7`) and remapped so
//! that 95 % of the range covers the lower 40 % of the largest difference (green–blue); features:
//! edges and points of the normalised luminance (first and second Gaussian derivatives), their
//! magnitude differences; the error is `ΔE_c^(1 − ΔE_f)`.
//!
//! Conventions: images are row-major sRGB8 RGB, row 0 at the top; borders are clamped (edge
//! pixels repeat), as in the reference code. Viewing condition in pixels per degree of visual
//! angle ([`DEFAULT_PIXELS_PER_DEGREE`]: FLIP's default, a 0.7 m wide 4K monitor at 0.7 m).

use rayon::prelude::*;

use super::MetricsError;

/// FLIP's default viewing condition: 0.7 m from a 0.7 m wide monitor of 3,840 pixels.
pub const DEFAULT_PIXELS_PER_DEGREE: f32 = 67.020_645;

const QC: f32 = 0.7;
const QF: f32 = 0.5;
const PC: f32 = 0.4;
const PT: f32 = 0.95;
/// Width (degrees) of the feature detectors' Gaussian.
const FEATURE_WIDTH: f32 = 0.082;

/// Linear sRGB → XYZ (D65).
const RGB_TO_XYZ: [[f32; 3]; 3] = [
    [
        10_135_552.0 / 24_577_794.0,
        8_788_810.0 / 24_577_794.0,
        4_435_075.0 / 24_577_794.0,
    ],
    [
        2_613_072.0 / 12_288_897.0,
        8_788_810.0 / 12_288_897.0,
        887_015.0 / 12_288_897.0,
    ],
    [
        1_425_312.0 / 73_733_382.0,
        8_788_810.0 / 73_733_382.0,
        70_074_185.0 / 73_733_382.0,
    ],
];
/// XYZ → linear sRGB.
const XYZ_TO_RGB: [[f32; 3]; 3] = [
    [3.241_003_2, -1.537_399, -0.498_615_9],
    [-0.969_224_3, 1.875_93, 0.041_554_226],
    [0.055_639_42, -0.204_011_2, 1.057_149],
];

fn mul(m: &[[f32; 3]; 3], v: [f32; 3]) -> [f32; 3] {
    [0, 1, 2].map(|r| m[r][0] * v[0] + m[r][1] * v[1] + m[r][2] * v[2])
}

/// The reference white: XYZ of linear RGB (1, 1, 1).
fn white() -> [f32; 3] {
    mul(&RGB_TO_XYZ, [1.0; 3])
}

fn srgb_to_linear(c: u8) -> f32 {
    let c = f32::from(c) / 255.0;
    if c <= 0.040_45 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

fn xyz_to_ycxcz(xyz: [f32; 3], w: [f32; 3]) -> [f32; 3] {
    let [x, y, z] = [xyz[0] / w[0], xyz[1] / w[1], xyz[2] / w[2]];
    [116.0 * y - 16.0, 500.0 * (x - y), 200.0 * (y - z)]
}

fn ycxcz_to_xyz(c: [f32; 3], w: [f32; 3]) -> [f32; 3] {
    let y = (c[0] + 16.0) / 116.0;
    let x = c[1] / 500.0 + y;
    let z = y - c[2] / 200.0;
    [x * w[0], y * w[1], z * w[2]]
}

/// Linear RGB → L\*a\*b\* with the Hunt adjustment (a\*, b\* scaled by L\*/100).
fn hunt_lab(rgb: [f32; 3], w: [f32; 3]) -> [f32; 3] {
    let xyz = mul(&RGB_TO_XYZ, rgb);
    let delta = 6.0f32 / 29.0;
    let f = |t: f32| {
        if t > delta * delta * delta {
            t.cbrt()
        } else {
            t / (3.0 * delta * delta) + 4.0 / 29.0
        }
    };
    let (fx, fy, fz) = (f(xyz[0] / w[0]), f(xyz[1] / w[1]), f(xyz[2] / w[2]));
    let l = 116.0 * fy - 16.0;
    [l, 0.01 * l * 500.0 * (fx - fy), 0.01 * l * 200.0 * (fy - fz)]
}

fn hyab(a: [f32; 3], b: [f32; 3]) -> f32 {
    (a[0] - b[0]).abs() + ((a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// A planar single-channel image.
struct Plane {
    width: usize,
    height: usize,
    data: Vec<f32>,
}

/// `src` convolved with `kx` along rows then `ky` along columns (odd lengths, centred), borders
/// clamped.
fn separable(src: &Plane, kx: &[f32], ky: &[f32]) -> Plane {
    let (w, h) = (src.width, src.height);
    let (rx, ry) = ((kx.len() / 2) as isize, (ky.len() / 2) as isize);
    let mut tmp = vec![0.0f32; w * h];
    tmp.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let line = &src.data[y * w..(y + 1) * w];
        for (x, out) in row.iter_mut().enumerate() {
            let mut s = 0.0;
            for (k, &c) in kx.iter().enumerate() {
                let xi = (x as isize + k as isize - rx).clamp(0, w as isize - 1) as usize;
                s += c * line[xi];
            }
            *out = s;
        }
    });
    let mut data = vec![0.0f32; w * h];
    data.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (k, &c) in ky.iter().enumerate() {
            let yi = (y as isize + k as isize - ry).clamp(0, h as isize - 1) as usize;
            let line = &tmp[yi * w..(yi + 1) * w];
            for (o, &v) in row.iter_mut().zip(line) {
                *o += c * v;
            }
        }
    });
    Plane {
        width: w,
        height: h,
        data,
    }
}

/// The contrast sensitivity filter of one opponent channel as weighted separable Gaussians:
/// `(weight, 1-D kernel)` terms whose 2-D sum is normalised to 1.
fn csf_terms(ppd: f32, channel: usize) -> Vec<(f32, Vec<f32>)> {
    // (a1, b1, a2, b2) of Y, Cx, Cz.
    const PARAMS: [[f32; 4]; 3] = [
        [1.0, 0.0047, 0.0, 1e-5],
        [1.0, 0.0053, 0.0, 1e-5],
        [34.1, 0.04, 13.5, 0.025],
    ];
    let max_b = 0.04f32;
    let radius = (3.0 * (max_b / (2.0 * std::f32::consts::PI.powi(2))).sqrt() * ppd).ceil() as i32;
    let p = PARAMS[channel];
    let pi = std::f32::consts::PI;
    let mut terms: Vec<(f32, Vec<f32>)> = [(p[0], p[1]), (p[2], p[3])]
        .into_iter()
        .filter(|&(a, _)| a > 0.0)
        .map(|(a, b)| {
            let k: Vec<f32> = (-radius..=radius)
                .map(|i| {
                    let d = i as f32 / ppd;
                    (-pi * pi * d * d / b).exp()
                })
                .collect();
            (a * (pi / b).sqrt(), k)
        })
        .collect();
    let total: f32 = terms.iter().map(|(wt, k)| wt * k.iter().sum::<f32>().powi(2)).sum();
    for (wt, _) in &mut terms {
        *wt /= total;
    }
    terms
}

/// The edge (first-derivative) and point (second-derivative) detectors along one axis, and the
/// Gaussian across it, each normalised as FLIP does (positive and negative weights summing to
/// ±1 over the 2-D kernel).
fn feature_kernels(ppd: f32) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let sd = 0.5 * FEATURE_WIDTH * ppd;
    let radius = (3.0 * sd).ceil() as i32;
    let g: Vec<f32> = (-radius..=radius)
        .map(|x| (-(x * x) as f32 / (2.0 * sd * sd)).exp())
        .collect();
    let gsum: f32 = g.iter().sum();
    let across: Vec<f32> = g.iter().map(|v| v / gsum).collect();
    let normalise = |k: Vec<f32>| {
        let pos: f32 = k.iter().filter(|&&v| v > 0.0).sum();
        let neg: f32 = -k.iter().filter(|&&v| v < 0.0).sum::<f32>();
        k.into_iter()
            .map(|v| {
                if v > 0.0 {
                    v / pos
                } else if v < 0.0 {
                    v / neg
                } else {
                    0.0
                }
            })
            .collect::<Vec<f32>>()
    };
    let edge = normalise((-radius..=radius).zip(&g).map(|(x, &gv)| -(x as f32) * gv).collect());
    let point = normalise(
        (-radius..=radius)
            .zip(&g)
            .map(|(x, &gv)| ((x * x) as f32 / (sd * sd) - 1.0) * gv)
            .collect(),
    );
    (edge, point, across)
}

/// Per-pixel feature magnitudes (edge, point) of the normalised luminance.
fn features(y: &Plane, ppd: f32) -> (Vec<f32>, Vec<f32>) {
    let (edge, point, across) = feature_kernels(ppd);
    let ex = separable(y, &edge, &across);
    let ey = separable(y, &across, &edge);
    let px = separable(y, &point, &across);
    let py = separable(y, &across, &point);
    let mag = |a: &Plane, b: &Plane| -> Vec<f32> { a.data.iter().zip(&b.data).map(|(x, y)| x.hypot(*y)).collect() };
    (mag(&ex, &ey), mag(&px, &py))
}

/// One image in YCxCz, channel by channel.
fn to_ycxcz(rgb: &[[u8; 3]], width: usize, height: usize) -> [Plane; 3] {
    let w = white();
    let lut: Vec<f32> = (0..=255u8).map(srgb_to_linear).collect();
    let mut planes = [0, 1, 2].map(|_| Plane {
        width,
        height,
        data: Vec::with_capacity(rgb.len()),
    });
    for p in rgb {
        let c = xyz_to_ycxcz(mul(&RGB_TO_XYZ, p.map(|v| lut[usize::from(v)])), w);
        for (plane, v) in planes.iter_mut().zip(c) {
            plane.data.push(v);
        }
    }
    planes
}

/// Hunt-adjusted L\*a\*b\* of the CSF-filtered image, per pixel.
fn filtered_lab(ycxcz: &[Plane; 3], ppd: f32) -> Vec<[f32; 3]> {
    let filtered: Vec<Plane> = ycxcz
        .iter()
        .enumerate()
        .map(|(c, plane)| {
            let mut out: Option<Plane> = None;
            for (wt, k) in csf_terms(ppd, c) {
                let f = separable(plane, &k, &k);
                match out.as_mut() {
                    None => {
                        out = Some(Plane {
                            data: f.data.iter().map(|v| v * wt).collect(),
                            ..f
                        });
                    }
                    Some(o) => o.data.iter_mut().zip(&f.data).for_each(|(a, b)| *a += b * wt),
                }
            }
            out.unwrap_or(Plane {
                width: plane.width,
                height: plane.height,
                data: plane.data.clone(),
            })
        })
        .collect();
    let w = white();
    (0..filtered[0].data.len())
        .into_par_iter()
        .map(|i| {
            let c = [filtered[0].data[i], filtered[1].data[i], filtered[2].data[i]];
            let rgb = mul(&XYZ_TO_RGB, ycxcz_to_xyz(c, w)).map(|v| v.clamp(0.0, 1.0));
            hunt_lab(rgb, w)
        })
        .collect()
}

/// The LDR-FLIP error map of `test` against `reference` (sRGB8 RGB, `width × height`, row-major)
/// at `pixels_per_degree`: one value in [0, 1] per pixel.
pub fn flip_map(
    reference: &[[u8; 3]],
    test: &[[u8; 3]],
    width: u32,
    height: u32,
    pixels_per_degree: f32,
) -> Result<Vec<f32>, MetricsError> {
    let n = width as usize * height as usize;
    for img in [reference, test] {
        if img.len() != n || n == 0 {
            return Err(MetricsError::BadBuffer {
                len: img.len(),
                width,
                height,
            });
        }
    }
    if !(pixels_per_degree.is_finite() && pixels_per_degree > 0.0) {
        return Err(MetricsError::SizeMismatch(
            "pixels per degree".into(),
            pixels_per_degree.to_string(),
        ));
    }
    let (w, h) = (width as usize, height as usize);
    let ppd = pixels_per_degree;
    let (r, t) = (to_ycxcz(reference, w, h), to_ycxcz(test, w, h));
    let (lab_r, lab_t) = (filtered_lab(&r, ppd), filtered_lab(&t, ppd));
    let luminance = |p: &[Plane; 3]| Plane {
        width: w,
        height: h,
        data: p[0].data.iter().map(|v| (v + 16.0) / 116.0).collect(),
    };
    let (edge_r, point_r) = features(&luminance(&r), ppd);
    let (edge_t, point_t) = features(&luminance(&t), ppd);
    let wt = white();
    let cmax = hyab(hunt_lab([0.0, 1.0, 0.0], wt), hunt_lab([0.0, 0.0, 1.0], wt)).powf(QC);
    let pccmax = PC * cmax;
    Ok((0..n)
        .into_par_iter()
        .map(|i| {
            let e = hyab(lab_r[i], lab_t[i]).powf(QC);
            let colour = if e < pccmax {
                PT / pccmax * e
            } else {
                PT + (e - pccmax) / (cmax - pccmax) * (1.0 - PT)
            };
            let fd = (edge_r[i] - edge_t[i]).abs().max((point_r[i] - point_t[i]).abs());
            let feature = (std::f32::consts::FRAC_1_SQRT_2 * fd).powf(QF);
            colour.powf(1.0 - feature).clamp(0.0, 1.0)
        })
        .collect())
}

/// Mean of an error map (0 for an empty one).
pub fn mean(map: &[f32]) -> f64 {
    if map.is_empty() {
        0.0
    } else {
        map.iter().map(|&v| f64::from(v)).sum::<f64>() / map.len() as f64
    }
}

/// The magma colour map (FLIP's error-map colouring), `v` in [0, 1]: black-purple for no error,
/// through red to pale yellow for the largest.
pub fn magma(v: f32) -> [u8; 3] {
    const STOPS: [[f32; 3]; 9] = [
        [0.0, 0.0, 4.0],
        [28.0, 16.0, 68.0],
        [79.0, 18.0, 123.0],
        [129.0, 37.0, 129.0],
        [181.0, 54.0, 122.0],
        [229.0, 80.0, 100.0],
        [251.0, 135.0, 97.0],
        [254.0, 194.0, 135.0],
        [252.0, 253.0, 191.0],
    ];
    let x = if v.is_finite() { v.clamp(0.0, 1.0) } else { 1.0 } * (STOPS.len() - 1) as f32;
    let i = (x.floor() as usize).min(STOPS.len() - 2);
    let f = x - i as f32;
    [0, 1, 2].map(|c| (STOPS[i][c] + (STOPS[i + 1][c] - STOPS[i][c]) * f).round() as u8)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A test pattern: a blue-to-green gradient with a dark disc and thin stripes.
    pub(super) fn pattern(w: u32, h: u32, shift: u32) -> Vec<[u8; 3]> {
        (0..h)
            .flat_map(|y| {
                (0..w).map(move |x| {
                    let (dx, dy) = (x as i32 - (w / 2) as i32 - shift as i32, y as i32 - (h / 2) as i32);
                    if dx * dx + dy * dy < (h as i32 / 4).pow(2) {
                        [40, 60, 30]
                    } else if (x / 3) % 5 == 0 && y < h / 3 {
                        [230, 230, 220]
                    } else {
                        [(x * 255 / w) as u8, 180, (y * 255 / h) as u8]
                    }
                })
            })
            .collect()
    }

    #[test]
    fn identical_images_have_no_error() {
        let a = pattern(48, 32, 0);
        let m = flip_map(&a, &a, 48, 32, DEFAULT_PIXELS_PER_DEGREE).unwrap();
        assert!(
            m.iter().all(|&v| v.abs() < 1e-5),
            "{:?}",
            m.iter().copied().fold(0.0f32, f32::max)
        );
    }

    #[test]
    fn more_change_is_more_error_and_bounded() {
        let (w, h) = (64u32, 48u32);
        let a = pattern(w, h, 0);
        let small = pattern(w, h, 1);
        let large = pattern(w, h, 6);
        let inverted: Vec<[u8; 3]> = a.iter().map(|p| p.map(|v| 255 - v)).collect();
        let e = |b: &[[u8; 3]]| mean(&flip_map(&a, b, w, h, DEFAULT_PIXELS_PER_DEGREE).unwrap());
        let (es, el, ei) = (e(&small), e(&large), e(&inverted));
        assert!(0.0 < es && es < el && el < ei && ei <= 1.0, "{es} {el} {ei}");
        let m = flip_map(&a, &inverted, w, h, DEFAULT_PIXELS_PER_DEGREE).unwrap();
        assert!(m.iter().all(|v| (0.0..=1.0).contains(v)));
    }

    /// NVIDIA's own implementation (`flip-evaluator` 1.7 from PyPI, `evaluate(a, b, "LDR")` on
    /// these patterns as float arrays) gives mean errors 0.066 105 5 (disc shifted by 3 px) and
    /// 0.961 206 2 (colours inverted).
    #[test]
    fn matches_nvidia_flip_evaluator() {
        let (w, h) = (96u32, 64u32);
        let a = pattern(w, h, 0);
        let shifted = pattern(w, h, 3);
        let inverted: Vec<[u8; 3]> = a.iter().map(|p| p.map(|v| 255 - v)).collect();
        let e = |b: &[[u8; 3]]| mean(&flip_map(&a, b, w, h, DEFAULT_PIXELS_PER_DEGREE).unwrap());
        let (es, ei) = (e(&shifted), e(&inverted));
        assert!((es - 0.066_105_5).abs() < 1e-4, "{es}");
        assert!((ei - 0.961_206_2).abs() < 1e-3, "{ei}");
    }

    #[test]
    fn bad_input_is_an_error() {
        let a = pattern(8, 8, 0);
        assert!(flip_map(&a, &a[1..], 8, 8, DEFAULT_PIXELS_PER_DEGREE).is_err());
        assert!(flip_map(&a, &a, 8, 8, 0.0).is_err());
        assert!(flip_map(&[], &[], 0, 0, DEFAULT_PIXELS_PER_DEGREE).is_err());
    }

    #[test]
    fn kernels_are_normalised() {
        for c in 0..3 {
            let s: f32 = csf_terms(DEFAULT_PIXELS_PER_DEGREE, c)
                .iter()
                .map(|(wt, k)| wt * k.iter().sum::<f32>().powi(2))
                .sum();
            assert!((s - 1.0).abs() < 1e-5, "channel {c}: {s}");
        }
        let (edge, point, across) = feature_kernels(DEFAULT_PIXELS_PER_DEGREE);
        assert!((across.iter().sum::<f32>() - 1.0).abs() < 1e-5);
        for k in [&edge, &point] {
            let pos: f32 = k.iter().filter(|&&v| v > 0.0).sum();
            let neg: f32 = k.iter().filter(|&&v| v < 0.0).sum();
            assert!((pos - 1.0).abs() < 1e-5 && (neg + 1.0).abs() < 1e-5);
        }
    }

    #[test]
    fn magma_runs_dark_to_light() {
        let lum = |c: [u8; 3]| u32::from(c[0]) + u32::from(c[1]) + u32::from(c[2]);
        let steps: Vec<u32> = (0..=10).map(|i| lum(magma(i as f32 / 10.0))).collect();
        assert!(steps.windows(2).all(|w| w[0] < w[1]), "{steps:?}");
        assert_eq!(magma(f32::NAN), magma(1.0));
    }
}
