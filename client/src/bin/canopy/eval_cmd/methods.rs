//! The methods `canopy eval` scores and the options that add or pick them: their names, the
//! checked `--ladders`, `--detail-scales` and `--sample-at` values, and the tests a method's draw
//! list is put to (complete, all geometry).

use std::collections::{BTreeSet, HashSet};

use anyhow::Result;
use canopy_client::lod::projection::{LadderStep, parse_ladder};
use canopy_client::stream::DrawnTree;

pub(super) const METHODS: [&str; 7] = [
    "canopy",
    "canopy-random",
    "discrete",
    "full",
    "canopy-clouds",
    "whole-glb",
    "whole-ctree",
];
/// Methods whose draw lists are full detail's own entries (rendered as the reference is when
/// they draw the same trees).
pub(super) const FULL_DETAIL_METHODS: [&str; 3] = ["full", "whole-glb", "whole-ctree"];

/// The `--ladders` ladders, parsed and named; none given twice.
pub(super) fn ladder_variants(given: &[String]) -> Result<Vec<(String, Vec<LadderStep>)>> {
    let mut out: Vec<(String, Vec<LadderStep>)> = Vec::with_capacity(given.len());
    for spec in given.iter().map(|s| s.trim()).filter(|s| !s.is_empty()) {
        let ladder = parse_ladder(spec).map_err(|e| anyhow::anyhow!("--ladders {spec:?}: {e}"))?;
        let name = ladder_method(spec);
        if out.iter().any(|(n, _)| n == &name) {
            anyhow::bail!("--ladders lists {spec:?} twice");
        }
        out.push((name, ladder));
    }
    Ok(out)
}

/// Name of the method that draws with ladder `spec`: rungs `NAME@PX` joined by `+`, so that the
/// name has no comma (CSV) and no colon (file names).
pub(super) fn ladder_method(spec: &str) -> String {
    let rungs: Vec<String> = spec
        .split(',')
        .map(str::trim)
        .filter(|p| !p.is_empty())
        .map(|p| p.replacen(':', "@", 1))
        .collect();
    format!("canopy-ladder-{}", rungs.join("+"))
}

/// The `--detail-scales` factors, checked: each in [0, 1] (−0 read as 0), none given twice.
pub(super) fn detail_scales(given: &[f32]) -> Result<Vec<f32>> {
    let mut out: Vec<f32> = Vec::with_capacity(given.len());
    for &s in given {
        if !(0.0..=1.0).contains(&s) {
            anyhow::bail!("--detail-scales takes factors between 0 and 1, not {s}");
        }
        let s = s + 0.0;
        if out.contains(&s) {
            anyhow::bail!("--detail-scales lists {s} twice");
        }
        out.push(s);
    }
    Ok(out)
}

/// Name of the method that scales the weights by `s`.
pub(super) fn scaled_method(s: f32) -> String {
    format!("canopy-weights-x{s}")
}

/// The frames nearest to the `--sample-at` times (at least frame 1), checked.
pub(super) fn sample_frames(times: &[f64], frame_time: f64) -> Result<BTreeSet<u32>> {
    times
        .iter()
        .map(|&t| {
            if !(t.is_finite() && t >= 0.0) {
                anyhow::bail!("--sample-at takes times in seconds ≥ 0, not {t}");
            }
            Ok(((t / frame_time).round().min(f64::from(u32::MAX))) as u32).map(|f| f.max(1))
        })
        .collect()
}

/// Whether every tree of `list` is drawn as geometry (what the reference's full render draws).
pub(super) fn all_geometry(list: &[DrawnTree]) -> bool {
    list.iter()
        .all(|t| matches!(t.what, canopy_client::stream::Drawn::Geometry { .. }))
}

/// Whether `list` draws every tree of `wanted` (instance ids).
pub(super) fn draws_all(list: &[DrawnTree], wanted: &HashSet<u32>) -> bool {
    list.len() >= wanted.len() && {
        let drawn: HashSet<u32> = list.iter().map(|t| t.instance.id).collect();
        wanted.iter().all(|id| drawn.contains(id))
    }
}

#[cfg(test)]
mod tests {
    use super::{detail_scales, ladder_variants};

    #[test]
    fn detail_scales_are_checked() {
        assert_eq!(detail_scales(&[0.75, 0.0, 1.0]).ok(), Some(vec![0.75, 0.0, 1.0]));
        let zero = detail_scales(&[-0.0]).ok().and_then(|v| v.first().copied());
        assert!(zero.is_some_and(|z| z == 0.0 && z.is_sign_positive()), "{zero:?}");
        for bad in [
            &[1.5][..],
            &[-0.1],
            &[f32::NAN],
            &[f32::INFINITY],
            &[0.5, 0.5],
            &[0.0, -0.0],
        ] {
            let err = detail_scales(bad).err().map(|e| e.to_string()).unwrap_or_default();
            assert!(err.contains("--detail-scales"), "{bad:?}: {err}");
        }
    }

    #[test]
    fn ladders_are_checked_and_named() {
        let given = vec![
            " geometry:60, hemioct:0 ".to_string(),
            String::new(),
            "geometry:150,hull1:30,hemioct:0".into(),
        ];
        let names: Vec<String> = ladder_variants(&given)
            .map(|v| v.into_iter().map(|(n, _)| n).collect())
            .unwrap_or_default();
        assert_eq!(
            names,
            [
                "canopy-ladder-geometry@60+hemioct@0",
                "canopy-ladder-geometry@150+hull1@30+hemioct@0"
            ]
        );
        assert!(names.iter().all(|n| !n.contains(',') && !n.contains(':')), "{names:?}");
        for bad in [
            vec!["geometry:60,hemioct:0".to_string(), "geometry:60,hemioct:0".into()],
            vec!["bush:60,hemioct:0".into()],
            vec!["geometry:sixty".into()],
        ] {
            let err = ladder_variants(&bad).err().map(|e| e.to_string()).unwrap_or_default();
            assert!(err.contains("--ladders"), "{bad:?}: {err}");
        }
    }
}
