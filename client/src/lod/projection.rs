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
    /// Irregular views (seed 001's photographs): the three views of the spherical Delaunay
    /// triangle holding the view direction, blended (`ViewSphere::blend`).
    Views,
}

/// What is drawn for a whole tree.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Representation {
    /// Full geometry, leaves simplified per node by [`super::rate`].
    Geometry,
    /// Geometry grown `dropped` fewer L-system iterations (seed 000's middle level): the skeleton
    /// of iterations `≤ K − dropped` and the leaf nodes of branches born in them, each simplified
    /// per node as [`Representation::Geometry`]. A model without iterations (an import) draws
    /// it as geometry.
    Iterations {
        /// Iterations left out, ≥ 1.
        dropped: u8,
    },
    /// A billboard-cloud level (seed 002), 0 = finest; adjacent cloud rungs cross-fade
    /// ([`switch_blend`]).
    CloudLevel(u8),
    /// A crown contour hull level (seed 004), 0 = finest.
    Hull {
        /// Hull level index in the hulls section.
        level: u8,
    },
    /// An image billboard.
    Billboard(BillboardKind),
}

impl Representation {
    /// Iterations a geometry representation leaves out (0 for [`Representation::Geometry`]);
    /// `None` for the stand-ins.
    pub fn dropped_iterations(self) -> Option<u8> {
        match self {
            Representation::Geometry => Some(0),
            Representation::Iterations { dropped } => Some(dropped),
            _ => None,
        }
    }

    /// Whether the tree is drawn as geometry (every iteration or fewer).
    pub fn is_geometry(self) -> bool {
        self.dropped_iterations().is_some()
    }
}

/// The most iterations any geometry rung of `ladder` leaves out: how far a tree drawn as
/// geometry may fall short of its wanted iterations while the skeleton streams in (0: every
/// iteration is needed before a tree is drawn as geometry).
pub fn max_dropped_iterations(ladder: &[LadderStep]) -> u8 {
    ladder
        .iter()
        .filter_map(|s| s.rep.dropped_iterations())
        .max()
        .unwrap_or(0)
}

/// One rung: use `rep` while the projected height is at least `min_projected_px` (seed 000's ε).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LadderStep {
    /// ε in pixels.
    pub min_projected_px: f32,
    /// Representation of this rung.
    pub rep: Representation,
}

/// The default ladder: geometry down to 150 px, then a hemi-octahedral billboard. Chosen by a
/// sweep over ladders (`canopy eval --ladders`, demo flyover at 1280×720, log 2026-12-05) as
/// the best perceptual quality per byte among the ladders that draw no more triangles than
/// [`HULL_LADDER_SPEC`]: against it the mean FLIP error falls from 0.190 to 0.113 and in the mid
/// band (trees 30–150 px tall) from 0.642 to 0.356, for 1.21× the bytes and 0.94× the triangles
/// (2.5 M a frame on the demo flyover against 2.7 M). Solid hulls read as rocks; billboards
/// show the tree's own colours and gaps. Geometry further down scores better still
/// (`geometry:30,hemioct:0`: mid band 0.336) but draws 11× the triangles (29 M a frame), since
/// a tree's whole skeleton is drawn at any rate.
pub const DEFAULT_LADDER: [LadderStep; 2] = [
    LadderStep {
        min_projected_px: 150.0,
        rep: Representation::Geometry,
    },
    LadderStep {
        min_projected_px: 0.0,
        rep: Representation::Billboard(BillboardKind::HemiOct),
    },
];

/// [`DEFAULT_LADDER`] written as [`parse_ladder`] reads it.
pub const DEFAULT_LADDER_SPEC: &str = "geometry:150,hemioct:0";

/// The ladder with crown hulls (the default until 2026-12-05): geometry from 150 px, hull levels
/// 0 and 1 from 60 and 30 px, then a hemi-octahedral billboard. Fewest bytes.
pub const HULL_LADDER_SPEC: &str = "geometry:150,hull0:60,hull1:30,hemioct:0";

/// A ladder with billboard-cloud levels (seed 002) where [`HULL_LADDER_SPEC`] has hulls. A cloud
/// level `i` (ε_i = 0.1·(i+1)·r, r ≈ half the tree's height) shows a parallax error of
/// 0.05·(i+1)·px pixels on a tree `px` pixels tall: 3–7.5 px on each rung here.
pub const CLOUD_LADDER_SPEC: &str = "geometry:150,cloud0:60,cloud1:30,cloud2:20,hemioct:0";

/// `ladder` with each hull rung replaced by the billboard-cloud level of the same index (the
/// `canopy-clouds` method of `canopy eval`: the same switches, clouds in place of hulls).
pub fn with_clouds(ladder: &[LadderStep]) -> Vec<LadderStep> {
    ladder
        .iter()
        .map(|s| match s.rep {
            Representation::Hull { level } => LadderStep {
                rep: Representation::CloudLevel(level),
                ..*s
            },
            _ => *s,
        })
        .collect()
}

/// Width of the cross-fade about a switch between two rungs, as a fraction of the switch's ε:
/// from `ε·(1 + b)` down to `ε/(1 + b)` both rungs are drawn with complementary weights. Bands
/// of adjacent switches do not overlap while their ε differ by more than `(1 + b)² = 1.44×`
/// (as in [`CLOUD_LADDER_SPEC`]: 60, 30, 20 px).
pub const SWITCH_BLEND_BAND: f32 = 0.2;

/// The rung to blend with, and its weight, for a tree on rung `rung` (as
/// [`choose_representation`] picked it) with projected height `projected_px`: within `band` (a
/// fraction, e.g. [`SWITCH_BLEND_BAND`]) of the switch below it (ε of `rung`) the next coarser
/// rung, within `band` of the switch above it (ε of `rung − 1`) the next finer one; only rungs
/// `can_blend` accepts (the client: cloud levels). The partner's weight rises linearly in
/// projected size from 0 at the band's edge to ½ at the switch, so both weights are continuous
/// in distance (no pop when the rung changes). Where both bands hold (adjacent ε closer than
/// `(1 + band)²`) the nearer switch wins. `None` outside the bands, for a non-positive band, an
/// ε of 0, or a rung out of range.
pub fn switch_blend(
    ladder: &[LadderStep],
    rung: usize,
    projected_px: f32,
    band: f32,
    can_blend: impl Fn(usize) -> bool,
) -> Option<(usize, f32)> {
    if !(band > 0.0 && projected_px.is_finite()) || rung >= ladder.len() {
        return None;
    }
    let px = projected_px;
    let eps = ladder[rung].min_projected_px;
    // (partner, weight, distance to the switch as a fraction of the band)
    let below = (rung + 1 < ladder.len() && eps > 0.0 && px >= eps && px < eps * (1.0 + band) && can_blend(rung + 1))
        .then(|| {
            let f = (px - eps) / (band * eps);
            (rung + 1, (0.5 * (1.0 - f)).clamp(0.0, 0.5), f)
        });
    let above = (rung > 0).then(|| ladder[rung - 1].min_projected_px).and_then(|up| {
        let lo = up / (1.0 + band);
        (up > 0.0 && px < up && px >= lo && can_blend(rung - 1)).then(|| {
            let f = (up - px) / (up - lo);
            (rung - 1, (0.5 * (1.0 - f)).clamp(0.0, 0.5), f)
        })
    });
    match (below, above) {
        (Some(b), Some(a)) => Some(if a.2 < b.2 { (a.0, a.1) } else { (b.0, b.1) }),
        (Some(x), None) | (None, Some(x)) => Some((x.0, x.1)),
        (None, None) => None,
    }
}

/// Reads a ladder: comma-separated `representation:ε` rungs, finest first, ε in pixels and
/// non-increasing. Representations: `geometry`, `iterN` (geometry with the last N ≥ 1 L-system
/// iterations left out; `iter` = 1), `hullN` (hull level N; `hull` = level 0), `cloudN`
/// (billboard-cloud level N), `hemioct`, `latlong`, `crossed`.
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
            "views" => Representation::Billboard(BillboardKind::Views),
            n if n.starts_with("iter") => Representation::Iterations {
                dropped: match level("iter")? {
                    0 if n == "iter" => 1,
                    0 => return Err(format!("ladder rung {part:?}: iter0 drops nothing (use geometry)")),
                    d => d,
                },
            },
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
        let l = parse_ladder("geometry:300,iter:200,iter3:150,hull0:60").expect("valid");
        assert_eq!(l[1].rep, Representation::Iterations { dropped: 1 });
        assert_eq!(l[2].rep, Representation::Iterations { dropped: 3 });
        for bad in [
            "",
            "geometry",
            "geometry:x",
            "geometry:-1",
            "tree:5",
            "hull0:10,geometry:20",
            "hullx:3",
            "iter0:100",
            "iterx:100",
        ] {
            assert!(parse_ladder(bad).is_err(), "{bad}");
        }
        let hulls = parse_ladder(HULL_LADDER_SPEC).expect("hull ladder");
        assert_eq!(
            with_clouds(&hulls),
            parse_ladder("geometry:150,cloud0:60,cloud1:30,hemioct:0").expect("valid")
        );
        assert_eq!(with_clouds(&DEFAULT_LADDER), DEFAULT_LADDER.to_vec());
    }

    /// The weight each rung of a two-cloud ladder gets at projected height `px`.
    fn weights(ladder: &[LadderStep], px: f32) -> [f32; 3] {
        let w = weights5(ladder, px);
        [w[0], w[1], w[2]]
    }

    /// The weight each rung of a ladder of up to five rungs gets at projected height `px`
    /// (every pair of rungs may blend).
    fn weights5(ladder: &[LadderStep], px: f32) -> [f32; 5] {
        let k = ladder
            .iter()
            .position(|s| px >= s.min_projected_px)
            .unwrap_or(ladder.len() - 1);
        let mut w = [0.0; 5];
        match switch_blend(ladder, k, px, SWITCH_BLEND_BAND, |_| true) {
            Some((j, wj)) => {
                w[j] = wj;
                w[k] = 1.0 - wj;
            }
            None => w[k] = 1.0,
        }
        w
    }

    #[test]
    fn switch_blend_is_continuous_across_the_switch() {
        let ladder = parse_ladder("cloud0:60,cloud1:30,hemioct:0").expect("valid");
        // Far from any switch: one rung alone.
        assert_eq!(weights(&ladder, 100.0), [1.0, 0.0, 0.0]);
        assert_eq!(weights(&ladder, 45.0), [0.0, 1.0, 0.0]);
        // At the switch: half and half, from either side.
        let at = weights(&ladder, 60.0);
        assert!((at[0] - 0.5).abs() < 1e-6 && (at[1] - 0.5).abs() < 1e-6, "{at:?}");
        let below = weights(&ladder, 60.0 - 1e-3);
        assert!((below[0] - 0.5).abs() < 1e-3, "{below:?}");
        // Walking the projected size down in small steps never moves a weight by more than the
        // step allows (the steepest band is below the 30 px switch: ½ over 30 − 30/1.2 = 5 px,
        // 0.01 per 0.1 px step); a pop would move it by ½ or 1.
        let mut prev = weights(&ladder, 200.0);
        let mut px = 200.0f32;
        while px > 1.0 {
            px -= 0.1;
            let w = weights(&ladder, px);
            for (a, b) in w.iter().zip(prev) {
                assert!((a - b).abs() <= 0.011, "jump at {px}: {prev:?} -> {w:?}");
            }
            prev = w;
        }
        // Edges of the band: weight 0 just outside, no blend for ε = 0 or a bad input.
        let all = |_| true;
        assert_eq!(switch_blend(&ladder, 0, 75.0, SWITCH_BLEND_BAND, all), None);
        assert_eq!(switch_blend(&ladder, 2, 0.5, SWITCH_BLEND_BAND, all), None);
        assert_eq!(switch_blend(&ladder, 0, f32::NAN, SWITCH_BLEND_BAND, all), None);
        assert_eq!(switch_blend(&ladder, 0, 61.0, 0.0, all), None);
        assert_eq!(switch_blend(&ladder, 7, 61.0, SWITCH_BLEND_BAND, all), None);
        // A rung the caller cannot blend with is never a partner.
        assert_eq!(switch_blend(&ladder, 1, 31.0, SWITCH_BLEND_BAND, |j| j != 2), None);
        assert_eq!(
            switch_blend(&ladder, 1, 31.0, SWITCH_BLEND_BAND, all).map(|p| p.0),
            Some(2)
        );
        // The cloud ladder's bands do not overlap: continuous over its whole range too.
        let clouds = parse_ladder(CLOUD_LADDER_SPEC).expect("valid");
        let mut prev = weights5(&clouds, 300.0);
        let mut px = 300.0f32;
        while px > 1.0 {
            px -= 0.05;
            let w = weights5(&clouds, px);
            for (a, b) in w.iter().zip(prev) {
                assert!((a - b).abs() < 0.02, "jump at {px}: {prev:?} -> {w:?}");
            }
            prev = w;
        }
    }

    #[test]
    fn ladder_choice() {
        let hulls = parse_ladder(HULL_LADDER_SPEC).expect("hull ladder");
        let pick = |px| choose_representation(&hulls, px);
        assert_eq!(
            choose_representation(&DEFAULT_LADDER, 150.0),
            Some(Representation::Geometry)
        );
        assert_eq!(
            choose_representation(&DEFAULT_LADDER, 149.9),
            Some(Representation::Billboard(BillboardKind::HemiOct))
        );
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
