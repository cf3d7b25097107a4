//! Cameras (perspective and orthographic) and evenly spread viewpoints.

use glam::{Mat4, Vec2, Vec3, Vec4};

use super::RasterError;

/// A projection. All distances in metres, angles in radians.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Projection {
    /// Perspective with vertical field of view `fov_y`.
    Perspective {
        /// Vertical field of view, radians, in (0, π).
        fov_y: f32,
        /// Near plane distance, > 0.
        near: f32,
        /// Far plane distance, > `near`.
        far: f32,
    },
    /// Orthographic: the view volume spans `±half_height` vertically and
    /// `±half_height × aspect` horizontally.
    Orthographic {
        /// Half of the visible height, metres, > 0.
        half_height: f32,
        /// Near plane distance (may be negative), < `far`.
        near: f32,
        /// Far plane distance.
        far: f32,
    },
}

/// A camera: an eye looking at a target, with an up hint and a projection.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Eye position, world space.
    pub eye: Vec3,
    /// Point looked at, world space.
    pub target: Vec3,
    /// Up hint (need not be perpendicular to the view direction, must not be parallel to it).
    pub up: Vec3,
    /// Projection.
    pub projection: Projection,
}

impl Camera {
    /// A camera at `eye` looking at `target` with up hint `up`.
    pub fn look_at(eye: Vec3, target: Vec3, up: Vec3, projection: Projection) -> Self {
        Self {
            eye,
            target,
            up,
            projection,
        }
    }

    /// An orthographic camera that looks at the sphere (`center`, `radius`) from direction
    /// `dir` (pointing from the centre to the eye; need not be unit), framing the sphere
    /// exactly (the sphere touches the shorter image side). Near/far enclose the sphere.
    /// The up hint is +Y, or +Z when `dir` is within ~0.1° of ±Y.
    pub fn orbit_orthographic(center: Vec3, radius: f32, dir: Vec3) -> Self {
        let d = dir.normalize_or(Vec3::Z);
        let r = radius.max(f32::MIN_POSITIVE);
        Self {
            eye: center + d * (2.0 * r),
            target: center,
            up: up_hint(d),
            projection: Projection::Orthographic {
                half_height: r,
                near: r * 0.999,
                far: 3.0 * r * 1.001,
            },
        }
    }

    /// A perspective camera with vertical field of view `fov_y` that looks at the sphere
    /// (`center`, `radius`) from direction `dir`, at the distance where the sphere just fits
    /// the vertical field of view. Near/far enclose the sphere (near ≥ 1 % of the distance).
    pub fn orbit_perspective(center: Vec3, radius: f32, dir: Vec3, fov_y: f32) -> Self {
        let d = dir.normalize_or(Vec3::Z);
        let r = radius.max(f32::MIN_POSITIVE);
        let dist = r / (0.5 * fov_y).sin().max(1e-6);
        Self {
            eye: center + d * dist,
            target: center,
            up: up_hint(d),
            projection: Projection::Perspective {
                fov_y,
                near: (dist - r).max(dist * 0.01),
                far: dist + r * 1.001,
            },
        }
    }

    /// Checks that the camera is usable.
    pub fn validate(&self) -> Result<(), RasterError> {
        let fwd = self.target - self.eye;
        let bad = |m: &str| Err(RasterError::InvalidCamera(m.to_owned()));
        if !(self.eye.is_finite() && self.target.is_finite() && self.up.is_finite()) {
            return bad("non-finite eye, target or up");
        }
        if fwd.length_squared() == 0.0 {
            return bad("eye equals target");
        }
        if fwd.cross(self.up).length_squared() <= 1e-12 * fwd.length_squared() * self.up.length_squared() {
            return bad("up is parallel to the view direction");
        }
        match self.projection {
            Projection::Perspective { fov_y, near, far } => {
                if !(fov_y > 0.0 && fov_y < std::f32::consts::PI && near > 0.0 && far > near) {
                    return bad("perspective needs 0 < fov_y < π and 0 < near < far");
                }
            }
            Projection::Orthographic { half_height, near, far } => {
                if !(half_height > 0.0 && far > near && near.is_finite() && far.is_finite()) {
                    return bad("orthographic needs half_height > 0 and near < far");
                }
            }
        }
        Ok(())
    }

    /// World → view matrix (right-handed, looking down −Z).
    pub fn view(&self) -> Mat4 {
        Mat4::look_at_rh(self.eye, self.target, self.up)
    }

    /// View → clip matrix for an image of aspect `width / height`; clip depth `z/w ∈ [0, 1]`.
    pub fn projection_matrix(&self, aspect: f32) -> Mat4 {
        match self.projection {
            Projection::Perspective { fov_y, near, far } => Mat4::perspective_rh(fov_y, aspect, near, far),
            Projection::Orthographic { half_height, near, far } => {
                let hw = half_height * aspect;
                Mat4::orthographic_rh(-hw, hw, -half_height, half_height, near, far)
            }
        }
    }

    /// World → clip matrix: `projection_matrix(aspect) * view()`.
    pub fn view_projection(&self, aspect: f32) -> Mat4 {
        self.projection_matrix(aspect) * self.view()
    }

    /// Projects a world point for a `width × height` image: returns `(pixel, depth)` where
    /// `pixel` is in continuous pixel units (x right, y down, pixel centres at `k + 0.5`) and
    /// `depth` the NDC depth (0 near … 1 far). `None` if the point is behind the eye
    /// (`w ≤ 0`). Points outside the view volume are still returned.
    pub fn project(&self, p: Vec3, width: u32, height: u32) -> Option<(Vec2, f32)> {
        let aspect = width as f32 / height.max(1) as f32;
        let c = self.view_projection(aspect) * Vec4::new(p.x, p.y, p.z, 1.0);
        if c.w <= 0.0 {
            return None;
        }
        let ndc = c.truncate() / c.w;
        Some((ndc_to_pixel(ndc.x, ndc.y, width, height), ndc.z))
    }
}

/// NDC x/y → continuous pixel coordinates (x right, y down).
pub(crate) fn ndc_to_pixel(x: f32, y: f32, width: u32, height: u32) -> Vec2 {
    Vec2::new((x + 1.0) * 0.5 * width as f32, (1.0 - y) * 0.5 * height as f32)
}

/// +Y, unless `d` is (nearly) parallel to it.
fn up_hint(d: Vec3) -> Vec3 {
    if d.y.abs() > 0.999_999 { Vec3::Z } else { Vec3::Y }
}

/// `n` unit vectors spread evenly over the sphere (Fibonacci / golden-angle spiral).
///
/// Point `i` has `y = 1 − (2i + 1)/n` and azimuth `i × golden angle`; deterministic, no two
/// points coincide, and every point has about `4π/n` steradians to itself. `n = 0` gives an
/// empty list.
pub fn fibonacci_sphere(n: usize) -> Vec<Vec3> {
    spiral(n, -1.0)
}

/// `n` unit vectors spread evenly over the upper hemisphere (`y > 0`), same construction as
/// [`fibonacci_sphere`] with `y = 1 − (i + 0.5)/n`. Useful for trees standing on the ground.
pub fn fibonacci_hemisphere(n: usize) -> Vec<Vec3> {
    spiral(n, 0.0)
}

fn spiral(n: usize, y_min: f32) -> Vec<Vec3> {
    // Golden angle in radians: π (3 − √5).
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let t = (i as f64 + 0.5) / n as f64;
            let y = 1.0 - t * (1.0 - f64::from(y_min));
            let r = (1.0 - y * y).max(0.0).sqrt();
            let phi = golden * i as f64;
            Vec3::new((r * phi.cos()) as f32, y as f32, (r * phi.sin()) as f32).normalize()
        })
        .collect()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn fibonacci_sphere_is_unit_and_even() {
        let n = 200;
        let pts = fibonacci_sphere(n);
        assert_eq!(pts.len(), n);
        for p in &pts {
            assert!((p.length() - 1.0).abs() < 1e-5);
        }
        // Centroid near the origin, and nearest-neighbour angles within a factor of ~2 of the
        // ideal spacing sqrt(4π/n).
        let c: Vec3 = pts.iter().copied().sum::<Vec3>() / n as f32;
        assert!(c.length() < 0.02, "centroid {c}");
        let ideal = (4.0 * std::f32::consts::PI / n as f32).sqrt();
        for (i, p) in pts.iter().enumerate() {
            let nn = pts
                .iter()
                .enumerate()
                .filter(|&(j, _)| j != i)
                .map(|(_, q)| p.dot(*q).clamp(-1.0, 1.0).acos())
                .fold(f32::INFINITY, f32::min);
            assert!(nn > 0.5 * ideal && nn < 1.5 * ideal, "point {i}: nn {nn} ideal {ideal}");
        }
        // Each octant gets about n/8 points.
        let octant = pts.iter().filter(|p| p.x > 0.0 && p.y > 0.0 && p.z > 0.0).count();
        assert!((octant as f32 - n as f32 / 8.0).abs() < 6.0, "octant {octant}");
        let h = fibonacci_hemisphere(50);
        assert!(h.iter().all(|p| p.y > 0.0 && (p.length() - 1.0).abs() < 1e-5));
        assert!(fibonacci_sphere(0).is_empty());
    }

    #[test]
    fn ortho_and_perspective_project_known_points() {
        // Orthographic: eye on +Z looking at the origin, half height 2 → x = 1 maps to
        // 3/4 of a square image's width.
        let cam = Camera::look_at(
            Vec3::new(0.0, 0.0, 10.0),
            Vec3::ZERO,
            Vec3::Y,
            Projection::Orthographic {
                half_height: 2.0,
                near: 1.0,
                far: 20.0,
            },
        );
        cam.validate().unwrap();
        let (px, d) = cam.project(Vec3::new(1.0, 1.0, 0.0), 100, 100).unwrap();
        assert!((px - Vec2::new(75.0, 25.0)).length() < 1e-3, "{px}");
        assert!((d - 9.0 / 19.0).abs() < 1e-5);
        // Depth does not change x/y under orthographic projection.
        let (px2, _) = cam.project(Vec3::new(1.0, 1.0, -5.0), 100, 100).unwrap();
        assert!((px - px2).length() < 1e-3);

        // Perspective, fov 90°: at distance 10, y = 10 is the top edge; a point at half that
        // distance off-axis by the same amount also is.
        let cam = Camera::look_at(
            Vec3::new(0.0, 0.0, 10.0),
            Vec3::ZERO,
            Vec3::Y,
            Projection::Perspective {
                fov_y: std::f32::consts::FRAC_PI_2,
                near: 1.0,
                far: 100.0,
            },
        );
        let (px, d) = cam.project(Vec3::new(5.0, 0.0, 0.0), 200, 100).unwrap();
        // aspect 2: x = 5 at distance 10 is tan = 0.5 → NDC x = 0.25 → pixel 125.
        assert!((px - Vec2::new(125.0, 50.0)).length() < 1e-3, "{px}");
        let (far_px, _) = cam.project(Vec3::new(5.0, 0.0, -10.0), 200, 100).unwrap();
        assert!((far_px.x - 112.5).abs() < 1e-3, "{far_px}");
        // Depth of a point at view distance z: f/(f−n) · (1 − n/z).
        let want = 100.0 / 99.0 * (1.0 - 1.0 / 10.0);
        assert!((d - want).abs() < 1e-5);
        assert!(cam.project(Vec3::new(0.0, 0.0, 20.0), 10, 10).is_none());
    }

    #[test]
    fn orbit_cameras_frame_the_sphere() {
        for dir in fibonacci_sphere(16).into_iter().chain([Vec3::Y, -Vec3::Y]) {
            for cam in [
                Camera::orbit_orthographic(Vec3::new(1.0, 2.0, 3.0), 2.0, dir),
                Camera::orbit_perspective(Vec3::new(1.0, 2.0, 3.0), 2.0, dir, 0.8),
            ] {
                cam.validate().unwrap();
                let (px, d) = cam.project(Vec3::new(1.0, 2.0, 3.0), 64, 64).unwrap();
                assert!((px - Vec2::splat(32.0)).length() < 1e-2);
                assert!(d > 0.0 && d < 1.0);
            }
        }
    }
}
