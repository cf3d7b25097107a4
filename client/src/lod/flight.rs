//! Seed 002: view-dependent LOD for low-altitude flight (an optional policy).
//!
//! Levels are integers `0..=n`, 0 = full model, `n` = coarsest (`n` = number of distance bands).
//!
//! - **LOD_D** (distance): `sigma = [σ_0, σ_1, …, σ_{n−1}]` ascending; level `i` for
//!   `σ_{i−1} ≤ d < σ_i` (σ_{−1} = 0), level `n` for `d ≥ σ_{n−1}`.
//! - **LOD_V** (effective field): the field angle θ (degrees, full horizontal field) is split into
//!   `N = ⌊(θ/15 + 1)/2⌋·2` sectors of 15°, numbered `C = 1..N/2` outward from the centre line
//!   on either side. A tree at horizontal off-axis angle φ is in sector `C = ⌊|φ|/15°⌋ + 1`;
//!   `LOD_V = min(n, LOD_D + C − 1)`, and `n` when `C > N/2` (outside the effective field).
//!   φ is measured in the horizontal (XZ) plane; a tree straight below, or a camera looking
//!   straight down, has φ = 0. `LOD_DV = max(LOD_D, LOD_V)`.
//! - **LOD_T** (threat zone): radius `R = v·t` around the viewpoint's ground projection; a tree
//!   whose horizontal distance is ≤ R and whose height is ≥ the flight height H gets 0, others `n`;
//!   `LOD_DVT = min(LOD_DV, LOD_T)`.
//! - **Redundancy** (the scene's [`FlightTable`], `(H, v) → offset`, computed by the pre-pass
//!   `canopy redundancy`): the offset raises `LOD_DV` (capped at `n`) *before* the threat-zone
//!   minimum, so threat trees stay at level 0. H is the eye's height above the ground plane
//!   y = 0, v the camera's speed between frames.

use canopy_shared::flight_table::{FlightPolicyParams, FlightTable};
use glam::{Vec2, Vec3};

/// Sector width of the effective field of view, degrees.
pub const SECTOR_DEG: f32 = 15.0;

/// Policy parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct FlightParams {
    /// Distance band edges σ, ascending, metres.
    pub sigma: Vec<f32>,
    /// Full horizontal field angle θ, degrees (the seed's experiment: 120).
    pub field_deg: f32,
    /// Threat-zone time `t`, seconds (the seed's experiment: 2).
    pub threat_time_s: f32,
    /// Optional redundancy table.
    pub redundancy: Option<FlightTable>,
}

impl FlightParams {
    /// The policy's defaults: σ = 100, 250, 500, 1,000 m (levels 0..=4), the seed's field of
    /// 120° and threat time of 2 s, no table.
    pub fn standard() -> Self {
        Self {
            sigma: vec![100.0, 250.0, 500.0, 1000.0],
            field_deg: 120.0,
            threat_time_s: 2.0,
            redundancy: None,
        }
    }

    /// The policy a table was computed for, with the table: its offsets only hold for it.
    pub fn from_table(table: FlightTable) -> Self {
        Self {
            sigma: table.policy.sigma_m.clone(),
            field_deg: table.policy.field_deg,
            threat_time_s: table.policy.threat_time_s,
            redundancy: Some(table),
        }
    }

    /// The policy's parameters as a table records them.
    pub fn policy(&self) -> FlightPolicyParams {
        FlightPolicyParams {
            sigma_m: self.sigma.clone(),
            field_deg: self.field_deg,
            threat_time_s: self.threat_time_s,
        }
    }
}

/// The flying viewpoint.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlightView {
    /// Eye position.
    pub eye: Vec3,
    /// View direction (any length).
    pub forward: Vec3,
    /// Flight height H above the ground, metres.
    pub height: f32,
    /// Speed v, metres per second.
    pub speed: f32,
}

/// LOD_D: the number of band edges at or below `dist`.
pub fn lod_d(sigma: &[f32], dist: f32) -> u8 {
    sigma.iter().take_while(|&&s| dist >= s).count().min(255) as u8
}

/// `N = ⌊(θ/15 + 1)/2⌋·2`.
pub fn sector_count(field_deg: f32) -> u32 {
    let n = ((field_deg / SECTOR_DEG + 1.0) * 0.5).floor();
    if n.is_nan() || n < 0.0 { 0 } else { n as u32 * 2 }
}

/// Sector `C ∈ 1..=N/2` of a tree at off-axis angle `off_axis_deg`; `None` outside the effective
/// field.
pub fn sector(field_deg: f32, off_axis_deg: f32) -> Option<u32> {
    let c = (off_axis_deg.abs() / SECTOR_DEG).floor();
    let c = if c.is_nan() { 0 } else { c as u32 } + 1;
    (c <= sector_count(field_deg) / 2).then_some(c)
}

/// Horizontal off-axis angle (degrees, ≥ 0) of `target` seen from `eye` looking along `forward`.
pub fn off_axis_deg(eye: Vec3, forward: Vec3, target: Vec3) -> f32 {
    let f = Vec2::new(forward.x, forward.z).try_normalize();
    let t = Vec2::new(target.x - eye.x, target.z - eye.z).try_normalize();
    match (f, t) {
        (Some(f), Some(t)) => f.angle_to(t).abs().to_degrees(),
        _ => 0.0,
    }
}

/// `LOD_DVT` (with the redundancy offset) of a tree standing at `base` (ground point) of height
/// `tree_height`, `dist` away by the module's distance convention.
pub fn flight_level(p: &FlightParams, view: &FlightView, base: Vec3, tree_height: f32, dist: f32) -> u8 {
    let n = p.sigma.len().min(255) as u8;
    let d = lod_d(&p.sigma, dist);
    let v = match sector(p.field_deg, off_axis_deg(view.eye, view.forward, base)) {
        Some(c) => d.saturating_add((c - 1).min(255) as u8).min(n),
        None => n,
    };
    let dv = d.max(v);
    let offset = p.redundancy.as_ref().map_or(0, |t| t.offset(view.height, view.speed));
    let dv = dv.saturating_add(offset).min(n);
    let radius = (view.speed * p.threat_time_s).max(0.0);
    let horizontal = Vec2::new(base.x - view.eye.x, base.z - view.eye.z).length();
    let threat = horizontal <= radius && tree_height >= view.height;
    let t = if threat { 0 } else { n };
    dv.min(t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distance_bands() {
        let s = [100.0, 200.0, 400.0];
        assert_eq!(lod_d(&s, 0.0), 0);
        assert_eq!(lod_d(&s, 99.9), 0);
        assert_eq!(lod_d(&s, 100.0), 1);
        assert_eq!(lod_d(&s, 399.0), 2);
        assert_eq!(lod_d(&s, 1e9), 3);
        assert_eq!(lod_d(&[], 5.0), 0);
    }

    #[test]
    fn sectors() {
        assert_eq!(sector_count(120.0), 8); // ⌊(8 + 1)/2⌋·2
        assert_eq!(sector_count(90.0), 6); // ⌊3.5⌋·2
        assert_eq!(sector_count(100.0), 6);
        assert_eq!(sector_count(15.0), 2);
        assert_eq!(sector_count(10.0), 0);
        assert_eq!(sector(120.0, 0.0), Some(1));
        assert_eq!(sector(120.0, -14.9), Some(1));
        assert_eq!(sector(120.0, 15.0), Some(2));
        assert_eq!(sector(120.0, 59.9), Some(4));
        assert_eq!(sector(120.0, 60.0), None);
        assert_eq!(sector(10.0, 0.0), None);
    }

    #[test]
    fn off_axis() {
        let e = Vec3::ZERO;
        assert!(off_axis_deg(e, Vec3::NEG_Z, Vec3::new(0.0, 0.0, -10.0)).abs() < 1e-4);
        assert!((off_axis_deg(e, Vec3::NEG_Z, Vec3::new(10.0, 0.0, -10.0)) - 45.0).abs() < 1e-3);
        assert!((off_axis_deg(e, Vec3::NEG_Z, Vec3::new(-10.0, 5.0, -10.0)) - 45.0).abs() < 1e-3);
        assert!((off_axis_deg(e, Vec3::NEG_Z, Vec3::new(0.0, 0.0, 10.0)) - 180.0).abs() < 1e-3);
        assert_eq!(off_axis_deg(e, Vec3::NEG_Y, Vec3::new(3.0, 0.0, 0.0)), 0.0);
        assert_eq!(off_axis_deg(e, Vec3::NEG_Z, Vec3::new(0.0, -50.0, 0.0)), 0.0);
    }

    fn params() -> FlightParams {
        FlightParams {
            sigma: vec![100.0, 200.0, 400.0],
            field_deg: 120.0,
            threat_time_s: 2.0,
            redundancy: None,
        }
    }

    fn view() -> FlightView {
        FlightView {
            eye: Vec3::new(0.0, 50.0, 0.0),
            forward: Vec3::NEG_Z,
            height: 50.0,
            speed: 10.0,
        }
    }

    #[test]
    fn dvt_levels() {
        let p = params();
        let v = view();
        // Straight ahead, 150 m: LOD_D 1, C 1 → 1.
        assert_eq!(flight_level(&p, &v, Vec3::new(0.0, 0.0, -150.0), 20.0, 150.0), 1);
        // 45° off axis (C = 4): 1 + 3 = 4 → capped at n = 3.
        assert_eq!(flight_level(&p, &v, Vec3::new(150.0, 0.0, -150.0), 20.0, 150.0), 3);
        // 20° off axis (C = 2), 50 m: 0 + 1.
        let a = 20f32.to_radians();
        assert_eq!(
            flight_level(&p, &v, Vec3::new(50.0 * a.sin(), 0.0, -50.0 * a.cos()), 20.0, 50.0),
            1
        );
        // Behind: outside the field → n.
        assert_eq!(flight_level(&p, &v, Vec3::new(0.0, 0.0, 150.0), 20.0, 150.0), 3);
        // Threat zone R = 20 m: a tall tree behind within 20 m → 0; a short one → n.
        assert_eq!(flight_level(&p, &v, Vec3::new(0.0, 0.0, 15.0), 50.0, 10.0), 0);
        assert_eq!(flight_level(&p, &v, Vec3::new(0.0, 0.0, 15.0), 49.0, 10.0), 3);
        assert_eq!(flight_level(&p, &v, Vec3::new(0.0, 0.0, 25.0), 60.0, 10.0), 3);
    }

    fn table(offsets: Vec<Vec<u8>>) -> FlightTable {
        FlightTable {
            format: canopy_shared::flight_table::FLIGHT_TABLE_FORMAT.into(),
            format_version: canopy_shared::flight_table::FLIGHT_TABLE_VERSION,
            dh_m: 20.0,
            dv_mps: 10.0,
            offsets,
            policy: params().policy(),
            method: canopy_shared::flight_table::FlightTableMethod {
                metric: "ssim".into(),
                threshold: 0.95,
                width: 64,
                height: 36,
                fps: 30.0,
                viewpoints: 1,
                ladder: String::new(),
            },
        }
    }

    #[test]
    fn redundancy_offsets() {
        let t = table(vec![vec![0, 0, 1], vec![0, 1, 2]]);
        t.check().expect("a valid table");
        let p = FlightParams::from_table(t.clone());
        assert_eq!(p.sigma, params().sigma, "the table's policy");
        let v = FlightView {
            height: 40.0,
            speed: 30.0,
            ..view()
        };
        // Straight ahead 50 m: LOD_DV 0 + offset 2.
        assert_eq!(flight_level(&p, &v, Vec3::new(0.0, 0.0, -50.0), 20.0, 50.0), 2);
        // Threat zone (R = 60 m) still wins.
        assert_eq!(flight_level(&p, &v, Vec3::new(0.0, 0.0, -50.0), 45.0, 50.0), 0);
    }
}
