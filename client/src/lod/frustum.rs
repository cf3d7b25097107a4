//! Conservative frustum culling of bounding spheres.
//!
//! Planes are extracted from a view-projection matrix (Gribb–Hartmann) and normalised, with
//! normals pointing into the frustum. A sphere is culled only when it lies entirely on the outer
//! side of one plane; spheres near a frustum corner may be kept though invisible (conservative).
//! A plane that degenerates (e.g. the far plane of an infinite projection) is dropped.
//! [`Frustum::in_frame_of`] moves the planes into an instance's frame, so that the spheres of a
//! model's nodes are tested once per model table rather than placed per instance.

use glam::{Mat4, Vec3, Vec4};

/// Clip-space depth convention of the projection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DepthRange {
    /// `0 ≤ z ≤ w` (wgpu, Vulkan, D3D; glam's `perspective_rh`).
    ZeroToOne,
    /// `−w ≤ z ≤ w` (OpenGL; glam's `perspective_rh_gl`).
    NegOneToOne,
}

/// Up to six planes `(n, d)` with `n·p + d ≥ 0` inside, `|n| = 1`.
#[derive(Debug, Clone, PartialEq)]
pub struct Frustum {
    planes: Vec<Vec4>,
}

impl Frustum {
    /// Planes of `view_proj` (projection × view).
    pub fn from_view_proj(view_proj: Mat4, depth: DepthRange) -> Self {
        let r0 = view_proj.row(0);
        let r1 = view_proj.row(1);
        let r2 = view_proj.row(2);
        let r3 = view_proj.row(3);
        let near = match depth {
            DepthRange::ZeroToOne => r2,
            DepthRange::NegOneToOne => r3 + r2,
        };
        let raw = [r3 + r0, r3 - r0, r3 + r1, r3 - r1, near, r3 - r2];
        let planes = raw.into_iter().filter_map(normalised).collect();
        Self { planes }
    }

    /// Planes kept.
    pub fn planes(&self) -> &[Vec4] {
        &self.planes
    }

    /// The planes that a sphere (`center`, `radius`) is not entirely inside of. Testing a part
    /// of that sphere against the result is the same as testing it against every plane.
    #[must_use]
    pub fn crossing(&self, center: Vec3, radius: f32) -> Self {
        Self {
            planes: self
                .planes
                .iter()
                .copied()
                .filter(|p| {
                    // Kept when not surely inside (NaN included).
                    let inside = p.truncate().dot(center) + p.w >= radius;
                    !inside
                })
                .collect(),
        }
    }

    /// These planes in the frame that `model` maps into this frustum's frame (for a placed
    /// instance: its model frame), each normalised again, so that a sphere given in that frame
    /// (centre, and radius in its units) is tested as its image would be, up to rounding. For
    /// a similarity (rotation, uniform scale, translation) the image of a sphere is a sphere,
    /// so this is exact but for rounding. A plane that degenerates is dropped (more is kept).
    #[must_use]
    pub fn in_frame_of(&self, model: Mat4) -> Self {
        let t = model.transpose();
        Self {
            planes: self.planes.iter().map(|p| t * *p).filter_map(normalised).collect(),
        }
    }

    /// Whether the sphere may be visible. NaN inputs are kept (never culled).
    pub fn intersects_sphere(&self, center: Vec3, radius: f32) -> bool {
        let r = radius.max(0.0);
        self.planes.iter().all(|p| {
            let s = p.truncate().dot(center) + p.w;
            s.is_nan() || s >= -r
        })
    }
}

/// `p` with a unit normal; `None` when the normal degenerates (zero or not finite).
fn normalised(p: Vec4) -> Option<Vec4> {
    let len = p.truncate().length();
    (len.is_finite() && len > 1e-12).then(|| p / len)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f32::consts::FRAC_PI_2;

    fn frustum(depth: DepthRange) -> Frustum {
        let proj = match depth {
            DepthRange::ZeroToOne => Mat4::perspective_rh(FRAC_PI_2, 1.0, 1.0, 100.0),
            DepthRange::NegOneToOne => Mat4::perspective_rh_gl(FRAC_PI_2, 1.0, 1.0, 100.0),
        };
        // Eye at origin looking down −Z (Y up).
        let view = Mat4::look_at_rh(Vec3::ZERO, Vec3::NEG_Z, Vec3::Y);
        Frustum::from_view_proj(proj * view, depth)
    }

    #[test]
    fn spheres_inside_outside_and_straddling() {
        for depth in [DepthRange::ZeroToOne, DepthRange::NegOneToOne] {
            let f = frustum(depth);
            assert_eq!(f.planes().len(), 6);
            assert!(f.intersects_sphere(Vec3::new(0.0, 0.0, -10.0), 1.0));
            // Behind the eye.
            assert!(!f.intersects_sphere(Vec3::new(0.0, 0.0, 10.0), 1.0));
            // Beyond far (100), and straddling it.
            assert!(!f.intersects_sphere(Vec3::new(0.0, 0.0, -102.0), 1.0));
            assert!(f.intersects_sphere(Vec3::new(0.0, 0.0, -100.5), 1.0));
            // 90° fov: at z = −10 the side plane is x = 10; sphere at x = 12 r = 1 is out
            // (distance to the plane 2/√2 ≈ 1.41 > 1), at x = 11 r = 1 in (0.71 < 1).
            assert!(!f.intersects_sphere(Vec3::new(12.0, 0.0, -10.0), 1.0));
            assert!(f.intersects_sphere(Vec3::new(11.0, 0.0, -10.0), 1.0));
            assert!(!f.intersects_sphere(Vec3::new(0.0, -12.0, -10.0), 1.0));
            // Camera inside a sphere: kept.
            assert!(f.intersects_sphere(Vec3::new(0.0, 0.0, 1.0), 3.0));
            assert!(f.intersects_sphere(Vec3::new(f32::NAN, 0.0, 0.0), 1.0));
        }
    }

    proptest::proptest! {
        /// Conservative: a sphere around any point inside the clip volume is never culled.
        #[test]
        fn never_culls_a_visible_point(
            x in -1.0f32..1.0, y in -1.0f32..1.0, z in 0.0f32..1.0, r in 0.0f32..5.0,
            ex in -50.0f32..50.0, ez in -50.0f32..50.0, yaw in 0.0f32..std::f32::consts::TAU,
        ) {
            let eye = Vec3::new(ex, 2.0, ez);
            let dir = Vec3::new(yaw.sin(), -0.2, -yaw.cos());
            let vp = Mat4::perspective_rh(1.0, 1.5, 0.5, 300.0) * Mat4::look_at_rh(eye, eye + dir, Vec3::Y);
            let f = Frustum::from_view_proj(vp, DepthRange::ZeroToOne);
            let p = vp.inverse().project_point3(Vec3::new(x, y, z));
            proptest::prop_assume!(p.is_finite());
            proptest::prop_assert!(f.intersects_sphere(p, r));
        }
    }

    #[test]
    fn infinite_far_plane_is_dropped() {
        let proj = Mat4::perspective_infinite_rh(FRAC_PI_2, 1.0, 1.0);
        let f = Frustum::from_view_proj(proj, DepthRange::ZeroToOne);
        assert_eq!(f.planes().len(), 5);
        assert!(f.intersects_sphere(Vec3::new(0.0, 0.0, -1e6), 1.0));
    }

    #[test]
    fn crossing_keeps_the_planes_a_sphere_straddles() {
        let f = frustum(DepthRange::ZeroToOne);
        // Centred in view, radius 1: inside every plane.
        assert!(f.crossing(Vec3::new(0.0, 0.0, -10.0), 1.0).planes().is_empty());
        // Straddling the right side plane only.
        let c = Vec3::new(10.0, 0.0, -10.0);
        let sub = f.crossing(c, 1.0);
        assert_eq!(sub.planes().len(), 1);
        for p in [c, c + Vec3::X, c - Vec3::X * 0.9, c + Vec3::new(0.5, 0.5, 0.0)] {
            assert_eq!(sub.intersects_sphere(p, 0.1), f.intersects_sphere(p, 0.1), "{p}");
        }
    }

    proptest::proptest! {
        /// A sphere given in an instance's frame is culled against `in_frame_of` as its placed
        /// image is against the frustum, wherever its image is not within rounding of a plane.
        #[test]
        fn planes_in_a_model_frame_test_spheres_as_their_images(
            cx in -30.0f32..30.0, cy in -5.0f32..30.0, cz in -30.0f32..30.0, r in 0.0f32..8.0,
            scale in 0.2f32..4.0, rot in -3.2f32..3.2, tx in -300.0f32..300.0, tz in -300.0f32..300.0,
            ex in -40.0f32..40.0, ez in -40.0f32..40.0, yaw in -3.2f32..3.2, pitch in -1.2f32..1.2,
        ) {
            let model = Mat4::from_scale_rotation_translation(
                Vec3::splat(scale),
                glam::Quat::from_rotation_y(rot),
                Vec3::new(tx, 0.0, tz),
            );
            let eye = Vec3::new(tx + ex, 5.0, tz + ez);
            let dir = Vec3::new(yaw.sin() * pitch.cos(), pitch.sin(), -yaw.cos() * pitch.cos());
            let vp = Mat4::perspective_rh(1.0, 1.6, 0.5, 400.0) * Mat4::look_at_rh(eye, eye + dir, Vec3::Y);
            let world = Frustum::from_view_proj(vp, DepthRange::ZeroToOne);
            let local = world.in_frame_of(model);
            proptest::prop_assert_eq!(local.planes().len(), world.planes().len());
            let c = Vec3::new(cx, cy, cz);
            let (wc, wr) = (model.transform_point3(c), r * scale);
            // Distance of the image's surface to the nearest plane: skip the rounding band.
            let margin = world
                .planes()
                .iter()
                .map(|p| (p.truncate().dot(wc) + p.w + wr).abs())
                .fold(f32::INFINITY, f32::min);
            proptest::prop_assume!(margin > 1e-3);
            proptest::prop_assert_eq!(local.intersects_sphere(c, r), world.intersects_sphere(wc, wr));
        }
    }

    #[test]
    fn degenerate_model_frames_drop_planes() {
        let f = frustum(DepthRange::ZeroToOne);
        // A transform that collapses everything to a point: no plane survives, nothing is culled.
        assert!(f.in_frame_of(Mat4::ZERO).planes().is_empty());
        assert!(
            f.in_frame_of(Mat4::from_scale(Vec3::splat(f32::NAN)))
                .planes()
                .is_empty()
        );
    }
}
