//! The view stage: where the camera is and what it sees.
//!
//! Conventions: world axes are right-handed with Y up, metres; yaw 0 looks along −Z and positive
//! yaw turns towards +X; pitch is positive upwards; angles in radians; projection depth 0..1.

use glam::{Mat4, Vec3};
use serde::Serialize;

use crate::lod::{DepthRange, Frustum};

/// A camera: eye and orientation. Yaw 0 looks along −Z, positive yaw turns towards +X; pitch is
/// positive upwards. Radians.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Eye position, metres.
    pub eye: Vec3,
    /// Heading, radians.
    pub yaw: f32,
    /// Elevation of the view direction, radians.
    pub pitch: f32,
}

impl Camera {
    /// Unit view direction.
    pub fn forward(&self) -> Vec3 {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        Vec3::new(sy * cp, sp, -cy * cp)
    }

    /// World → view matrix (right-handed, Y up).
    pub fn view(&self) -> Mat4 {
        let f = self.forward();
        let up = if f.cross(Vec3::Y).length_squared() < 1e-8 {
            Vec3::Z
        } else {
            Vec3::Y
        };
        Mat4::look_to_rh(self.eye, f, up)
    }
}

/// Viewport and projection.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Viewport {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels (seed 000's `L`).
    pub height: u32,
    /// Vertical field of view, radians (seed 000's `α`).
    pub fov_y: f32,
    /// Near plane, metres.
    pub near: f32,
    /// View distance: farther instances are neither loaded nor drawn, metres.
    pub far: f32,
}

impl Default for Viewport {
    fn default() -> Self {
        Self {
            width: 1280,
            height: 720,
            fov_y: 60f32.to_radians(),
            near: 0.1,
            far: 1500.0,
        }
    }
}

impl Viewport {
    /// Projection (depth 0..1).
    pub fn projection(&self) -> Mat4 {
        Mat4::perspective_rh(
            self.fov_y,
            self.width as f32 / self.height.max(1) as f32,
            self.near,
            self.far,
        )
    }
}

/// The frame's view volume: the frustum of `vp` from `cam` (the view distance is tested apart).
pub(crate) fn frustum(vp: &Viewport, cam: &Camera) -> Frustum {
    Frustum::from_view_proj(vp.projection() * cam.view(), DepthRange::ZeroToOne)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_axes() {
        let c = Camera {
            eye: Vec3::ZERO,
            yaw: 0.0,
            pitch: 0.0,
        };
        assert!((c.forward() - Vec3::NEG_Z).length() < 1e-6);
        let c = Camera {
            yaw: std::f32::consts::FRAC_PI_2,
            ..c
        };
        assert!((c.forward() - Vec3::X).length() < 1e-6);
        let c = Camera {
            pitch: -std::f32::consts::FRAC_PI_2 + 1e-4,
            ..c
        };
        assert!(c.forward().y < -0.99);
        // Looking straight down still gives a valid view matrix.
        assert!(c.view().is_finite());
    }
}
