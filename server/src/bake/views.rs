//! Irregular view sets for the billboard atlas (seed 001's photographs): read from JSON,
//! generated like a photographer's set, and checked before a frame is rendered.
//!
//! Conventions: azimuth and elevation in degrees as the atlas module defines them (Y up,
//! azimuth from +X toward −Z, elevation above the horizon); a view set is a list of
//! `[azimuth, elevation]` pairs, one frame each, in frame order.
//!
//! JSON input: `[{"azimuth_deg": 12.5, "elevation_deg": 10}, …]`, as a photo set's camera
//! poses give them (distance is not used: frames are orthographic renders of the model).

use canopy_shared::format::atlas::lat_long_direction;
use canopy_shared::rng::SplitMix64;
use serde::Deserialize;

/// Most frames of a view set (a frame table holds at most 65,536 frames in all layouts).
pub const MAX_VIEWS: usize = 16_384;
/// Two views closer than this angle (degrees) are the same view: refused.
pub const MIN_VIEW_SEPARATION_DEG: f32 = 0.01;

/// Why a view set was refused.
#[derive(Debug, thiserror::Error)]
pub enum ViewSetError {
    /// The JSON could not be read as a list of views.
    #[error("view set JSON: {0}")]
    Json(#[from] serde_json::Error),
    /// No view.
    #[error("the view set is empty")]
    Empty,
    /// More views than a frame table holds.
    #[error("the view set has {0} views, at most {MAX_VIEWS}")]
    TooMany(usize),
    /// A view's angles are not finite, or the elevation is outside ±90°.
    #[error("view {index}: azimuth {azimuth} and elevation {elevation} must be finite, elevation in [-90, 90] degrees")]
    Angles {
        /// Index in the set.
        index: usize,
        /// Azimuth given.
        azimuth: f32,
        /// Elevation given.
        elevation: f32,
    },
    /// Two views look from the same direction.
    #[error("views {0} and {1} look from the same direction (under {MIN_VIEW_SEPARATION_DEG}° apart)")]
    Duplicate(usize, usize),
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ViewJson {
    azimuth_deg: f32,
    elevation_deg: f32,
}

/// Parses a JSON view set and checks it ([`check_views`]); azimuths are wrapped to
/// `(-180, 180]`.
pub fn parse_views(json: &str) -> Result<Vec<[f32; 2]>, ViewSetError> {
    let list: Vec<ViewJson> = serde_json::from_str(json)?;
    let views: Vec<[f32; 2]> = list.iter().map(|v| [v.azimuth_deg, v.elevation_deg]).collect();
    check_views(&views)?;
    Ok(views.into_iter().map(|[a, e]| [wrap_deg(a), e]).collect())
}

fn wrap_deg(a: f32) -> f32 {
    let w = a.rem_euclid(360.0);
    if w > 180.0 { w - 360.0 } else { w }
}

/// Checks a view set (degrees): 1 to [`MAX_VIEWS`] views, finite angles, elevations within
/// ±90°, no two within [`MIN_VIEW_SEPARATION_DEG`] of each other.
pub fn check_views(views: &[[f32; 2]]) -> Result<(), ViewSetError> {
    if views.is_empty() {
        return Err(ViewSetError::Empty);
    }
    if views.len() > MAX_VIEWS {
        return Err(ViewSetError::TooMany(views.len()));
    }
    for (index, &[azimuth, elevation]) in views.iter().enumerate() {
        if !(azimuth.is_finite() && elevation.is_finite() && (-90.0..=90.0).contains(&elevation)) {
            return Err(ViewSetError::Angles {
                index,
                azimuth,
                elevation,
            });
        }
    }
    let dirs: Vec<glam::Vec3> = views
        .iter()
        .map(|&[a, e]| lat_long_direction(a.to_radians(), e.to_radians()))
        .collect();
    let min_cos = MIN_VIEW_SEPARATION_DEG.to_radians().cos();
    // Sorted by y, only neighbours within the separation in y can be duplicates.
    let mut order: Vec<usize> = (0..dirs.len()).collect();
    order.sort_by(|&a, &b| dirs[a].y.total_cmp(&dirs[b].y));
    let dy = MIN_VIEW_SEPARATION_DEG.to_radians();
    for (i, &a) in order.iter().enumerate() {
        for &b in &order[i + 1..] {
            if dirs[b].y - dirs[a].y > dy {
                break;
            }
            if dirs[a].dot(dirs[b]) >= min_cos {
                return Err(ViewSetError::Duplicate(a.min(b), a.max(b)));
            }
        }
    }
    Ok(())
}

/// A photographer's view set of `n` views (at most [`MAX_VIEWS`]; degrees), fixed by `seed`: most taken walking
/// round the tree at −5° to 35° elevation but never on its far side (azimuths within ±130°,
/// a 100° gap), one in seven from a drone at 50° to 85°. Irregular, with a gap and nothing
/// from below: what seed 001's irregular lookup has to cope with.
pub fn photo_views(n: usize, seed: u64) -> Vec<[f32; 2]> {
    let mut rng = SplitMix64::new(seed);
    let n = n.min(MAX_VIEWS);
    let min_cos = MIN_VIEW_SEPARATION_DEG.to_radians().cos();
    let mut out: Vec<[f32; 2]> = Vec::with_capacity(n);
    let mut dirs: Vec<glam::Vec3> = Vec::with_capacity(n);
    while out.len() < n {
        let (az, el) = if out.len().is_multiple_of(7) {
            (rng.uniform(-180.0, 180.0), rng.uniform(50.0, 85.0))
        } else {
            (rng.uniform(-130.0, 130.0), rng.uniform(-5.0, 35.0))
        };
        let (az, el) = (az as f32, el as f32);
        let d = lat_long_direction(az.to_radians(), el.to_radians());
        if dirs.iter().all(|e| e.dot(d) < min_cos) {
            out.push([az, el]);
            dirs.push(d);
        }
    }
    out
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn json_view_sets_parse_and_bad_ones_are_refused() {
        let v =
            parse_views(r#"[{"azimuth_deg": 370, "elevation_deg": 10}, {"azimuth_deg": -90, "elevation_deg": 80}]"#)
                .unwrap();
        assert_eq!(v, vec![[10.0, 10.0], [-90.0, 80.0]]);
        let err = |j: &str| parse_views(j).unwrap_err().to_string();
        assert!(err("[]").contains("empty"));
        assert!(err("{").contains("JSON"));
        assert!(err(r#"[{"azimuth_deg": 1}]"#).contains("JSON"));
        assert!(err(r#"[{"azimuth_deg": 1, "elevation_deg": 2, "distance": 3}]"#).contains("JSON"));
        assert!(err(r#"[{"azimuth_deg": 0, "elevation_deg": 91}]"#).contains("elevation in [-90, 90]"));
        // The same direction twice, also as 0° and 360°, and all azimuths at the zenith.
        assert!(
            err(r#"[{"azimuth_deg": 0, "elevation_deg": 5}, {"azimuth_deg": 360, "elevation_deg": 5}]"#)
                .contains("views 0 and 1")
        );
        assert!(
            err(r#"[{"azimuth_deg": 0, "elevation_deg": 90}, {"azimuth_deg": 120, "elevation_deg": 90}]"#)
                .contains("same direction")
        );
        assert!(matches!(
            check_views(&vec![[0.0, 0.0]; MAX_VIEWS + 1]),
            Err(ViewSetError::TooMany(_))
        ));
        assert!(matches!(
            check_views(&[[f32::NAN, 0.0]]),
            Err(ViewSetError::Angles { .. })
        ));
    }

    #[test]
    fn photo_sets_are_irregular_with_a_gap() {
        let v = photo_views(60, 3);
        assert_eq!(v.len(), 60);
        check_views(&v).unwrap();
        assert_eq!(v, photo_views(60, 3));
        assert!(
            v.iter()
                .all(|&[a, e]| (-5.0..=85.0).contains(&e) && (-180.0..=180.0).contains(&a))
        );
        // The far side (|azimuth| > 130°) is seen only from the drone.
        assert!(v.iter().filter(|&&[a, _]| a.abs() > 130.0).all(|&[_, e]| e >= 50.0));
    }
}
