//! Deterministic camera paths over a scene's bounds, for headless runs.
//!
//! A path is a function of time, so `--frames N` of a path is a prefix of `--frames M > N`.
//! Heights are above the ground: y = 0 for a flat scene, the terrain under the eye for one with a
//! terrain ([`camera_over`]). Every path keeps its eye inside the scene's bounds.
//!
//! | path | what it models | height | speed |
//! |---|---|---|---|
//! | `orbit` | a viewer circling the forest, looking at its centre | 40 m | 20 m/s |
//! | `flyover` | a drone crossing the forest, looking ahead and down 15° | 60 m | 25 m/s |
//! | `walk` | a person walking through the trees (eye inside crowns at times), turning gently | 1.7 m | 3 m/s |
//! | `lowflight` | seed 002's fast low flight, threat zone active | 25 m | 60 m/s |
//! | `turns` | rapid turns and speed changes (popping): heading swings ±90° every 2 s, speed between 0 and 40 m/s | 30 m | 20 m/s mean |

use glam::Vec3;

use crate::stream::Camera;

/// Frame interval of headless runs: 30 frames per second.
pub const FRAME_DT: f32 = 1.0 / 30.0;

/// A named camera path.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum PathKind {
    /// Circle around the centre.
    Orbit,
    /// Straight crossing at drone height.
    Flyover,
    /// Ground-level walk.
    Walk,
    /// Fast low flight (seed 002).
    Lowflight,
    /// Rapid turns and speed changes.
    Turns,
}

impl PathKind {
    /// Speed along the path, m/s.
    pub fn speed(self) -> f32 {
        match self {
            Self::Orbit | Self::Turns => 20.0,
            Self::Flyover => 25.0,
            Self::Walk => 3.0,
            Self::Lowflight => 60.0,
        }
    }

    /// Eye height, metres.
    pub fn height(self) -> f32 {
        match self {
            Self::Orbit => 40.0,
            Self::Flyover => 60.0,
            Self::Walk => 1.7,
            Self::Lowflight => 25.0,
            Self::Turns => 30.0,
        }
    }
}

/// The camera at time `t` seconds on `kind` played at `speed` m/s instead of the path's own
/// (0: the camera stays at the path's start).
pub fn camera_at_speed(kind: PathKind, bounds: Rect, t: f32, speed: f32) -> Camera {
    camera_at(kind, bounds, t * speed.max(0.0) / kind.speed())
}

/// Scene rectangle: min x, min z, max x, max z.
pub type Rect = [f32; 4];

/// The camera at time `t` seconds on `kind` over `bounds`.
pub fn camera_at(kind: PathKind, bounds: Rect, t: f32) -> Camera {
    let [x0, z0, x1, z1] = bounds;
    let (cx, cz) = ((x0 + x1) * 0.5, (z0 + z1) * 0.5);
    let (w, d) = ((x1 - x0).max(1.0), (z1 - z0).max(1.0));
    let h = kind.height();
    let v = kind.speed();
    match kind {
        PathKind::Orbit => {
            let r = 0.35 * w.min(d);
            let a = v * t / r;
            let eye = Vec3::new(cx + r * a.sin(), h, cz + r * a.cos());
            look_at(eye, Vec3::new(cx, 5.0, cz))
        }
        PathKind::Flyover | PathKind::Lowflight => {
            // West to east along the middle (lowflight: along a diagonal), bouncing at the edges.
            let (dir, len) = if kind == PathKind::Flyover {
                (Vec3::X, 0.9 * w)
            } else {
                (Vec3::new(w, 0.0, d).normalize(), 0.9 * (w * w + d * d).sqrt())
            };
            let s = bounce(v * t, len);
            let start = Vec3::new(cx, h, cz) - dir * (len * 0.5);
            let forward = if (v * t / len).floor() as i64 % 2 == 0 {
                dir
            } else {
                -dir
            };
            let pitch = if kind == PathKind::Flyover {
                -15f32.to_radians()
            } else {
                -5f32.to_radians()
            };
            Camera {
                eye: start + dir * s,
                yaw: forward.x.atan2(-forward.z),
                pitch,
            }
        }
        PathKind::Turns => {
            // Distance travelled s(t) = v·t − (v/ω)·sin(ω t): speed v·(1 − cos ω t) swings between
            // 0 and 2v every 2π/ω seconds; the heading swings ±90° at 0.5 Hz, looking 10° down.
            let w = 1.5f32;
            let s = v * t - (v / w) * (w * t).sin();
            let run = 0.8 * (x1 - x0).max(1.0);
            let x = x0 + 0.1 * (x1 - x0) + bounce(s, run);
            let heading = std::f32::consts::FRAC_PI_2 * (std::f32::consts::PI * t).sin();
            Camera {
                eye: Vec3::new(x, h, cz),
                yaw: std::f32::consts::FRAC_PI_2 + heading,
                pitch: -10f32.to_radians(),
            }
        }
        PathKind::Walk => {
            // Forward along x from the centre with a slow sinusoidal heading.
            let len = 0.8 * w;
            let s = bounce(v * t, len);
            let sway = 0.3 * (t * 0.2).sin();
            let eye = Vec3::new(cx - len * 0.5 + s, h, cz + 20.0 * (t * 0.05).sin());
            let back = (v * t / len).floor() as i64 % 2 == 1;
            let yaw = std::f32::consts::FRAC_PI_2 + sway + if back { std::f32::consts::PI } else { 0.0 };
            Camera { eye, yaw, pitch: 0.0 }
        }
    }
}

/// The camera at time `t` on `kind` played at `speed` m/s over a scene whose ground height at
/// `(x, z)` is `ground(x, z)`: the eye `eye_height` (the path's own when `None`) above the
/// ground under it; the orbit looks at the ground 5 m above the centre.
pub fn camera_over(
    kind: PathKind,
    bounds: Rect,
    t: f32,
    speed: f32,
    eye_height: Option<f32>,
    ground: &dyn Fn(f32, f32) -> f32,
) -> Camera {
    let mut cam = camera_at_speed(kind, bounds, t, speed);
    cam.eye.y = eye_height.unwrap_or(kind.height()) + ground(cam.eye.x, cam.eye.z);
    if kind == PathKind::Orbit {
        let (cx, cz) = ((bounds[0] + bounds[2]) * 0.5, (bounds[1] + bounds[3]) * 0.5);
        cam = look_at(cam.eye, Vec3::new(cx, 5.0 + ground(cx, cz), cz));
    }
    cam
}

/// Position along a segment of length `len` after travelling `s`, turning back at each end.
fn bounce(s: f32, len: f32) -> f32 {
    let len = len.max(1.0);
    let k = (s / len).floor();
    let f = s - k * len;
    if (k as i64) % 2 == 0 { f } else { len - f }
}

/// A camera at `eye` looking at `target`.
pub fn look_at(eye: Vec3, target: Vec3) -> Camera {
    let f = (target - eye).normalize_or_zero();
    Camera {
        eye,
        yaw: f.x.atan2(-f.z),
        pitch: f.y.clamp(-1.0, 1.0).asin(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const B: Rect = [-500.0, -400.0, 500.0, 400.0];

    #[test]
    fn paths_stay_inside_and_are_deterministic() {
        for kind in [
            PathKind::Orbit,
            PathKind::Flyover,
            PathKind::Walk,
            PathKind::Lowflight,
            PathKind::Turns,
        ] {
            for i in 0..3000 {
                let t = i as f32 * 0.37;
                let c = camera_at(kind, B, t);
                assert!(c.eye.is_finite() && c.yaw.is_finite() && c.pitch.is_finite());
                assert!(
                    c.eye.x >= B[0] && c.eye.x <= B[2] && c.eye.z >= B[1] && c.eye.z <= B[3],
                    "{kind:?} {t}"
                );
                assert!((c.eye.y - kind.height()).abs() < 1e-3);
                assert_eq!(c, camera_at(kind, B, t));
            }
        }
    }

    #[test]
    fn speed_matches_the_table() {
        for kind in [PathKind::Orbit, PathKind::Flyover, PathKind::Walk, PathKind::Lowflight] {
            let a = camera_at(kind, B, 1.0).eye;
            let b = camera_at(kind, B, 1.1).eye;
            let v = a.distance(b) / 0.1;
            assert!((v - kind.speed()).abs() / kind.speed() < 0.25, "{kind:?}: {v}");
        }
    }

    #[test]
    fn look_at_points_at_the_target() {
        let c = look_at(Vec3::new(0.0, 10.0, 0.0), Vec3::new(10.0, 0.0, 0.0));
        assert!((c.forward() - Vec3::new(1.0, -1.0, 0.0).normalize()).length() < 1e-5);
    }

    #[test]
    fn turns_change_speed_and_heading_fast() {
        let speeds: Vec<f32> = (0..84)
            .map(|i| {
                let t = i as f32 * 0.05;
                camera_at(PathKind::Turns, B, t)
                    .eye
                    .distance(camera_at(PathKind::Turns, B, t + 0.01).eye)
                    / 0.01
            })
            .collect();
        let (lo, hi) = speeds.iter().fold((f32::MAX, 0f32), |(a, b), &v| (a.min(v), b.max(v)));
        assert!(
            lo < 0.2 * PathKind::Turns.speed() && hi > 1.8 * PathKind::Turns.speed(),
            "{lo} {hi}"
        );
        let yaw = |t: f32| camera_at(PathKind::Turns, B, t).yaw;
        assert!(
            (yaw(0.5) - yaw(1.5)).abs() > 3.0,
            "heading swings by about 180° within a second"
        );
    }
}
