//! Seed 000: screen-projection thresholds and the per-tree representation.
//!
//! Projected height of a tree of height `l` at distance `d`, with vertical field of view `α` and
//! viewport height `L` pixels: `l' = l·L / (2d·tan(α/2))`. Level `i` with tolerance `ε_i` (pixels)
//! is used out to `d_i = l·L / (2ε_i·tan(α/2))`, the distance at which `l' = ε_i`: a smaller `ε`
//! keeps the level out to a larger distance, i.e. finer.
//!
//! Choosing a representation is therefore "the first rung of the ladder whose `ε` the projected
//! height reaches": rungs are ordered fine to coarse with non-increasing `ε`.

/// How a billboard atlas is sampled (format §billboard atlases).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum BillboardKind {
    /// Hemi-octahedral atlas, three frames blended (`hemi_oct_blend`).
    HemiOct,
    /// Latitude/longitude grid, nearest frame (`lat_long_nearest`, seed 001).
    LatLong,
    /// Two quads crossed at 90° (seed 000's improved billboard).
    Crossed,
}

/// What is drawn for a whole tree.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Representation {
    /// Full geometry, leaves simplified per node by [`super::rate`].
    Geometry,
    /// A billboard-cloud level (placeholder: the cloud section is empty until its bake lands).
    CloudLevel(u8),
    /// A crown contour hull level (seed 004), 0 = finest.
    Hull {
        /// Hull level index in the hulls section.
        level: u8,
    },
    /// An image billboard.
    Billboard(BillboardKind),
}

/// One rung: use `rep` while the projected height is at least `min_projected_px` (seed 000's ε).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LadderStep {
    /// ε in pixels.
    pub min_projected_px: f32,
    /// Representation of this rung.
    pub rep: Representation,
}

/// A default ladder: geometry from 150 px, hull levels 0 and 1 from 60 and 30 px, then a
/// hemi-octahedral billboard.
pub const DEFAULT_LADDER: [LadderStep; 4] = [
    LadderStep {
        min_projected_px: 150.0,
        rep: Representation::Geometry,
    },
    LadderStep {
        min_projected_px: 60.0,
        rep: Representation::Hull { level: 0 },
    },
    LadderStep {
        min_projected_px: 30.0,
        rep: Representation::Hull { level: 1 },
    },
    LadderStep {
        min_projected_px: 0.0,
        rep: Representation::Billboard(BillboardKind::HemiOct),
    },
];

/// [`DEFAULT_LADDER`] written as [`parse_ladder`] reads it.
pub const DEFAULT_LADDER_SPEC: &str = "geometry:150,hull0:60,hull1:30,hemioct:0";

/// Reads a ladder: comma-separated `representation:ε` rungs, finest first, ε in pixels and
/// non-increasing. Representations: `geometry`, `hullN` (hull level N; `hull` = level 0),
/// `cloudN` (billboard-cloud level N), `hemioct`, `latlong`, `crossed`.
pub fn parse_ladder(spec: &str) -> Result<Vec<LadderStep>, String> {
    let mut out: Vec<LadderStep> = Vec::new();
    for part in spec.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let (name, eps) = part
            .split_once(':')
            .ok_or_else(|| format!("ladder rung {part:?} is not NAME:PIXELS"))?;
        let eps: f32 = eps
            .trim()
            .parse()
            .map_err(|_| format!("ladder rung {part:?}: {eps:?} is not a number"))?;
        if !(eps.is_finite() && eps >= 0.0) {
            return Err(format!("ladder rung {part:?}: ε must be a finite number ≥ 0"));
        }
        let level = |prefix: &str| -> Result<u8, String> {
            let rest = &name[prefix.len()..];
            if rest.is_empty() {
                Ok(0)
            } else {
                rest.parse()
                    .map_err(|_| format!("ladder rung {part:?}: bad level {rest:?}"))
            }
        };
        let rep = match name.trim() {
            "geometry" => Representation::Geometry,
            "hemioct" => Representation::Billboard(BillboardKind::HemiOct),
            "latlong" => Representation::Billboard(BillboardKind::LatLong),
            "crossed" => Representation::Billboard(BillboardKind::Crossed),
            n if n.starts_with("hull") => Representation::Hull { level: level("hull")? },
            n if n.starts_with("cloud") => Representation::CloudLevel(level("cloud")?),
            n => return Err(format!("ladder rung {part:?}: unknown representation {n:?}")),
        };
        if out.last().is_some_and(|l| l.min_projected_px < eps) {
            return Err(format!("ladder rung {part:?}: ε must not increase from rung to rung"));
        }
        out.push(LadderStep {
            min_projected_px: eps,
            rep,
        });
    }
    if out.is_empty() {
        return Err("the ladder is empty".into());
    }
    Ok(out)
}

/// `l' = l·L / (2d·tan(α/2))` in pixels. `d ≤ 0` (eye inside the tree's sphere) gives
/// `f32::INFINITY`; a degenerate field of view (`tan(α/2) ≤ 0` or non-finite) gives 0.
pub fn projected_height(height: f32, distance: f32, screen_px: f32, fov_y: f32) -> f32 {
    projected_height_tan(height, distance, screen_px, (fov_y * 0.5).tan())
}

/// [`projected_height`] with `tan(α/2)` given (computed once per frame rather than per tree).
#[inline]
pub fn projected_height_tan(height: f32, distance: f32, screen_px: f32, tan_half_fov: f32) -> f32 {
    let t = tan_half_fov;
    if !(t.is_finite() && t > 0.0) || height.is_nan() {
        return 0.0;
    }
    if distance.is_nan() || distance <= 0.0 {
        return f32::INFINITY;
    }
    (height * screen_px / (2.0 * distance * t)).max(0.0)
}

/// `d_i = l·L / (2ε·tan(α/2))`, the distance out to which a level with tolerance `eps` pixels
/// is used. `eps ≤ 0` gives `f32::INFINITY` (the level is used at every distance).
pub fn threshold_distance(height: f32, screen_px: f32, fov_y: f32, eps: f32) -> f32 {
    let t = (fov_y * 0.5).tan();
    if !(t.is_finite() && t > 0.0) {
        return 0.0;
    }
    if eps.is_nan() || eps <= 0.0 {
        return f32::INFINITY;
    }
    (height * screen_px / (2.0 * eps * t)).max(0.0)
}

/// The first rung whose ε the projected height reaches; the last rung when none does; `None`
/// only for an empty ladder.
pub fn choose_representation(ladder: &[LadderStep], projected_px: f32) -> Option<Representation> {
    let px = if projected_px.is_nan() { 0.0 } else { projected_px };
    ladder
        .iter()
        .find(|s| px >= s.min_projected_px)
        .or(ladder.last())
        .map(|s| s.rep)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f32::consts::FRAC_PI_2;

    #[test]
    fn projected_height_hand_value() {
        // 90° fov: tan(45°) = 1; l = 20 m, L = 1000 px, d = 100 m: 20·1000/(2·100·1) = 100 px.
        assert!((projected_height(20.0, 100.0, 1000.0, FRAC_PI_2) - 100.0).abs() < 1e-3);
    }

    #[test]
    fn threshold_is_inverse_of_projection() {
        // l = 20, L = 1000, ε = 50, tan = 1: d = 20·1000/(2·50) = 200 m, where l' = 50 px.
        let d = threshold_distance(20.0, 1000.0, FRAC_PI_2, 50.0);
        assert!((d - 200.0).abs() < 1e-3);
        assert!((projected_height(20.0, d, 1000.0, FRAC_PI_2) - 50.0).abs() < 1e-3);
        // Smaller ε, larger distance (finer).
        assert!(threshold_distance(20.0, 1000.0, FRAC_PI_2, 25.0) > d);
    }

    #[test]
    fn degenerate_inputs() {
        assert_eq!(projected_height(20.0, 0.0, 1000.0, FRAC_PI_2), f32::INFINITY);
        assert_eq!(projected_height(20.0, f32::NAN, 1000.0, FRAC_PI_2), f32::INFINITY);
        assert_eq!(projected_height(20.0, 10.0, 1000.0, 0.0), 0.0);
        assert_eq!(threshold_distance(20.0, 1000.0, FRAC_PI_2, 0.0), f32::INFINITY);
        assert_eq!(threshold_distance(20.0, 1000.0, 0.0, 1.0), 0.0);
    }

    #[test]
    fn ladder_spec_round_trip_and_errors() {
        assert_eq!(
            parse_ladder(DEFAULT_LADDER_SPEC).expect("default"),
            DEFAULT_LADDER.to_vec()
        );
        let l = parse_ladder("geometry:80, hull:40, cloud2:20, crossed:0").expect("valid");
        assert_eq!(l[1].rep, Representation::Hull { level: 0 });
        assert_eq!(l[2].rep, Representation::CloudLevel(2));
        for bad in [
            "",
            "geometry",
            "geometry:x",
            "geometry:-1",
            "tree:5",
            "hull0:10,geometry:20",
            "hullx:3",
        ] {
            assert!(parse_ladder(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn ladder_choice() {
        let pick = |px| choose_representation(&DEFAULT_LADDER, px);
        assert_eq!(pick(f32::INFINITY), Some(Representation::Geometry));
        assert_eq!(pick(150.0), Some(Representation::Geometry));
        assert_eq!(pick(149.9), Some(Representation::Hull { level: 0 }));
        assert_eq!(pick(30.0), Some(Representation::Hull { level: 1 }));
        assert_eq!(pick(1.0), Some(Representation::Billboard(BillboardKind::HemiOct)));
        assert_eq!(pick(f32::NAN), Some(Representation::Billboard(BillboardKind::HemiOct)));
        let strict = [LadderStep {
            min_projected_px: 10.0,
            rep: Representation::CloudLevel(2),
        }];
        assert_eq!(choose_representation(&strict, 1.0), Some(Representation::CloudLevel(2)));
        assert_eq!(choose_representation(&[], 1.0), None);
    }
}
