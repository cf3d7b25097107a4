//! Seed 002's visual-redundancy pre-pass: for each flight-height band ΔH and speed band Δv, the
//! largest level offset the low-flight policy may add before a viewer would notice.
//!
//! **The opinion score's stand-in.** Seed 002 raises the level while the mean opinion score
//! stays above 4. A panel is not at hand, so each cell is scored objectively: the frame the
//! policy draws with offset k against the frame it draws with offset 0, both *under the motion
//! of one frame at the band's speed* (each frame the average of [`SUBFRAMES`] renders spread over
//! the `v / fps` metres the camera travels in it: the blur an eye integrating over one frame
//! sees), by colour SSIM. SSIM ≥ 0.95 counts as MOS ≥ 4: the SSIM-to-MOS mapping of Zinner et
//! al. (2010), "Impact of frame rate and resolution on objective QoE metrics" (≥ 0.99 → 5
//! imperceptible, 0.95–0.99 → 4 perceptible but not annoying, 0.88–0.95 → 3 slightly
//! annoying). SSIM rather than FLIP because the mapping to MOS is published for it; FLIP's is
//! not. A cell passes offset k only if every viewpoint of its height band passes.
//!
//! **Conventions.** Heights are the eye's above the ground plane y = 0; a cell `(h, c)` is scored
//! at the middle of its height band and at the *lower* edge of its speed band (least blur: the
//! hardest case for the band). Viewpoints look along the scene's long axis and down at
//! `atan(H / LOOK_AHEAD_M)`, as a low flight looks ahead. Offsets grow from 0 one level at a
//! time and stop at the first that fails (a raised level that fails is never skipped over).

use glam::Vec3;

use super::View;
use crate::stream::Camera;

/// Renders averaged per frame for its motion blur.
pub const SUBFRAMES: usize = 4;
/// Where a viewpoint's line of sight meets the ground ahead, metres: pitch `−atan(H / this)`.
pub const LOOK_AHEAD_M: f32 = 400.0;
/// Steepest downward look of a viewpoint, radians.
pub const MAX_DOWN_PITCH: f32 = 1.05;

/// The eyes whose renders make one frame's motion blur at `speed` m/s: [`SUBFRAMES`] points
/// spread evenly over the `speed / fps` metres travelled along the view's heading, centred on
/// `cam.eye`. One eye at rest.
pub fn motion_eyes(cam: &Camera, speed: f32, fps: f32) -> Vec<Vec3> {
    let travel = if fps > 0.0 && speed.is_finite() {
        speed.max(0.0) / fps
    } else {
        0.0
    };
    if travel <= 0.0 {
        return vec![cam.eye];
    }
    let (s, c) = cam.yaw.sin_cos();
    let heading = Vec3::new(s, 0.0, -c);
    (0..SUBFRAMES)
        .map(|j| {
            let f = (j as f32 + 0.5) / SUBFRAMES as f32 - 0.5;
            cam.eye + heading * (travel * f)
        })
        .collect()
}

/// The average of `views` in linear light (sRGB decoded, averaged, encoded): one frame under
/// motion. Coverage is any view's. `None` for no views or views of different sizes.
pub fn blend_views(views: &[View]) -> Option<View> {
    let first = views.first()?;
    if views.iter().any(|v| v.width != first.width || v.height != first.height) {
        return None;
    }
    if views.len() == 1 {
        return Some(first.clone());
    }
    let lut: Vec<f32> = (0..=255u8).map(|b| srgb_to_linear(f32::from(b) / 255.0)).collect();
    let n = views.len() as f32;
    let color = (0..first.color.len())
        .map(|i| {
            let mut acc = [0.0f32; 4];
            for v in views {
                let p = v.color[i];
                for ch in 0..3 {
                    acc[ch] += lut[usize::from(p[ch])];
                }
                acc[3] += f32::from(p[3]) / 255.0;
            }
            let enc = |x: f32| (linear_to_srgb(x / n) * 255.0).round().clamp(0.0, 255.0) as u8;
            [
                enc(acc[0]),
                enc(acc[1]),
                enc(acc[2]),
                ((acc[3] / n) * 255.0).round().clamp(0.0, 255.0) as u8,
            ]
        })
        .collect();
    let covered = (0..first.covered.len())
        .map(|i| views.iter().any(|v| v.covered[i]))
        .collect();
    Some(View {
        width: first.width,
        height: first.height,
        color,
        covered,
        triangles: views.iter().map(|v| v.triangles).sum::<u64>() / views.len() as u64,
    })
}

fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

fn linear_to_srgb(c: f32) -> f32 {
    if c <= 0.003_130_8 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

/// `count` viewpoints at height `h` over a scene of ground bounds `[min x, min z, max x, max z]`:
/// spread along the middle of the short axis, from a quarter to three quarters of the long one,
/// each looking along the long axis (towards +X or −Z) and down at `atan(h / LOOK_AHEAD_M)`.
pub fn viewpoints(bounds: [f32; 4], count: usize, h: f32) -> Vec<Camera> {
    let [x0, z0, x1, z1] = bounds;
    let (w, d) = (x1 - x0, z1 - z0);
    let along_x = w >= d;
    let pitch = -(h.max(0.0) / LOOK_AHEAD_M).atan().min(MAX_DOWN_PITCH);
    (0..count)
        .map(|k| {
            let f = if count <= 1 {
                0.5
            } else {
                0.25 + 0.5 * k as f32 / (count - 1) as f32
            };
            let (eye, yaw) = if along_x {
                (Vec3::new(x0 + w * f, h, z0 + d * 0.5), std::f32::consts::FRAC_PI_2)
            } else {
                (Vec3::new(x0 + w * 0.5, h, z1 - d * f), 0.0)
            };
            Camera { eye, yaw, pitch }
        })
        .collect()
}

/// The table's search: for each cell `(h, c)` of `rows × cols`, the largest offset `k ≤ levels`
/// such that `passes(h, c, j)` holds for every `j` in `1..=k` (asked in that order, stopping at
/// the first failure; cells row by row). Errors from `passes` end the search.
pub async fn search_offsets<E>(
    rows: usize,
    cols: usize,
    levels: u8,
    mut passes: impl AsyncFnMut(usize, usize, u8) -> Result<bool, E>,
) -> Result<Vec<Vec<u8>>, E> {
    let mut table = vec![vec![0u8; cols]; rows];
    for (h, row) in table.iter_mut().enumerate() {
        for (c, cell) in row.iter_mut().enumerate() {
            let mut k = 0u8;
            while k < levels && passes(h, c, k + 1).await? {
                k += 1;
            }
            *cell = k;
        }
    }
    Ok(table)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(w: u32, h: u32, c: [u8; 4]) -> View {
        View {
            width: w,
            height: h,
            color: vec![c; (w * h) as usize],
            covered: vec![c[3] > 0; (w * h) as usize],
            triangles: 10,
        }
    }

    #[test]
    fn motion_eyes_span_one_frame_of_travel() {
        let cam = Camera {
            eye: Vec3::new(0.0, 50.0, 0.0),
            yaw: std::f32::consts::FRAC_PI_2,
            pitch: -0.3,
        };
        assert_eq!(motion_eyes(&cam, 0.0, 30.0), vec![cam.eye]);
        let e = motion_eyes(&cam, 60.0, 30.0);
        assert_eq!(e.len(), SUBFRAMES);
        // 2 m a frame along +X (yaw 90°), centred on the eye, level.
        let span = e[SUBFRAMES - 1].x - e[0].x;
        assert!(
            (span - 2.0 * (SUBFRAMES as f32 - 1.0) / SUBFRAMES as f32).abs() < 1e-4,
            "{span}"
        );
        let mid: Vec3 = e.iter().copied().sum::<Vec3>() / e.len() as f32;
        assert!(mid.distance(cam.eye) < 1e-4);
        assert!(e.iter().all(|p| (p.y - 50.0).abs() < 1e-6 && p.z.abs() < 1e-4));
        assert_eq!(motion_eyes(&cam, f32::NAN, 30.0), vec![cam.eye]);
    }

    #[test]
    fn blending_averages_in_linear_light() {
        let black = flat(4, 2, [0, 0, 0, 255]);
        let white = flat(4, 2, [255, 255, 255, 255]);
        let b = blend_views(&[black.clone(), white]).expect("same sizes");
        // Half the light is sRGB 188, not 128.
        assert!(b.color.iter().all(|p| p[0] == 188 && p[3] == 255), "{:?}", b.color[0]);
        let same = blend_views(&[black.clone(), black.clone()]).expect("same sizes");
        assert_eq!(same.color, black.color);
        assert!(blend_views(&[black, flat(2, 2, [0; 4])]).is_none());
        assert!(blend_views(&[]).is_none());
    }

    #[test]
    fn viewpoints_look_along_the_long_axis_and_down() {
        let v = viewpoints([0.0, 0.0, 1000.0, 400.0], 3, 100.0);
        assert_eq!(v.len(), 3);
        assert!((v[0].eye.x - 250.0).abs() < 1e-3 && (v[2].eye.x - 750.0).abs() < 1e-3);
        assert!(v.iter().all(|c| (c.eye.z - 200.0).abs() < 1e-3 && c.eye.y == 100.0));
        assert!(v.iter().all(|c| c.forward().x > 0.9));
        assert!((v[0].pitch + (100.0f32 / LOOK_AHEAD_M).atan()).abs() < 1e-5);
        let tall = viewpoints([0.0, 0.0, 100.0, 1000.0], 1, 1e6);
        assert!(tall[0].forward().z < 0.0 && (tall[0].pitch + MAX_DOWN_PITCH).abs() < 1e-5);
    }

    #[test]
    fn the_search_stops_at_the_first_failure() {
        let rt = tokio::runtime::Builder::new_current_thread().build().expect("runtime");
        let mut asked = Vec::new();
        // Passes while k ≤ h + c, except k = 2 in cell (1, 1): no skipping over it.
        let t = rt
            .block_on(search_offsets::<()>(2, 2, 3, async |h, c, k| {
                asked.push((h, c, k));
                Ok(usize::from(k) <= h + c && (h, c, k) != (1, 1, 2))
            }))
            .expect("no error");
        assert_eq!(t, vec![vec![0, 1], vec![1, 1]]);
        assert!(!asked.contains(&(1, 1, 3)), "past a failure: {asked:?}");
        let capped = rt
            .block_on(search_offsets::<()>(1, 1, 2, async |_, _, _| Ok(true)))
            .expect("no error");
        assert_eq!(capped, vec![vec![2]]);
        assert_eq!(
            rt.block_on(search_offsets(1, 1, 2, async |_, _, _| Err("boom"))),
            Err("boom")
        );
    }
}
