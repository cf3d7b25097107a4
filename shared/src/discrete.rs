//! Discrete LOD files: the baseline a glTF viewer with level files uses (Bao et al. 2012;
//! Needle's progressive glTF), which both sides must agree on. The server writes each model's
//! levels as whole `.glb` files beside its `.ctree` and lists them in the scene manifest
//! ([`crate::manifest::ManifestModel::levels`]); the client's evaluation downloads them whole.
//!
//! Conventions: level 0 is the finest. Geometry levels `k < GEOMETRY_LEVELS` keep each node's
//! VMI prefix at rate [`LEVEL_RATES`]`[k]` (rate 0 = every leaf); level [`BILLBOARD_LEVEL`] is the
//! crossed-quad billboard (seed 000) at the atlas's top resolution. A tree `px` pixels tall is
//! drawn at the first level whose threshold `LEVEL_PX_FACTORS[k] · g` it reaches, where `g` is the
//! projected height down to which Canopy's ladder draws geometry, so both methods switch to
//! images at the same size.
//!
//! | level | content | bark | drawn from |
//! |---|---|---|---|
//! | 0 | every leaf | every twig, 6-sided tubes | ≥ 4·g px |
//! | 1 | rate 0.75 (a quarter of the leaves) | branches reaching 3 mm, 6 sides | ≥ 2·g px |
//! | 2 | rate 0.9375 | branches reaching 1 cm, 5 sides | ≥ g px |
//! | 3 | crossed-quad billboard | — | below |

/// Geometry levels (0, 1, 2).
pub const GEOMETRY_LEVELS: usize = 3;
/// Simplification rate of geometry levels 0, 1, 2.
pub const LEVEL_RATES: [f32; GEOMETRY_LEVELS] = [0.0, 0.75, 0.9375];
/// Projected-height thresholds of geometry levels 0, 1, 2 as multiples of `g`.
pub const LEVEL_PX_FACTORS: [f32; GEOMETRY_LEVELS] = [4.0, 2.0, 1.0];
/// Per geometry level, the radius (metres) a branch must reach to be in the level's bark: the
/// viewer's bark variants 0, 1, 2 (`client/src/lod/bark.rs`), so a coarser level drops the twigs
/// the client itself leaves out of smaller trees.
pub const LEVEL_BARK_MIN_RADII: [f32; GEOMETRY_LEVELS] = [0.0, 0.003, 0.01];
/// Per geometry level, the sides of its branch tubes (the viewer's variants 0, 1, 2).
pub const LEVEL_BARK_SIDES: [u32; GEOMETRY_LEVELS] = [6, 6, 5];
/// The billboard level.
pub const BILLBOARD_LEVEL: u8 = GEOMETRY_LEVELS as u8;
/// Levels a model has: its geometry levels and the billboard.
pub const LEVEL_COUNT: usize = GEOMETRY_LEVELS + 1;

/// The asset name of level `level` of the model whose `.ctree` has the 16-hex-digit hash prefix
/// `source` (`<model>-lod<level>-<source>`): a level file names the exact model file it was made
/// from, so a model baked again never takes the old one's levels.
pub fn level_name(model: &str, level: u8, source: &str) -> String {
    format!("{model}-lod{level}-{source}")
}

/// The model, level and source hash an asset name of [`level_name`] holds, if it is one.
pub fn parse_level_name(name: &str) -> Option<(&str, u8, &str)> {
    let (rest, source) = name.rsplit_once('-')?;
    let (model, level) = rest.rsplit_once("-lod")?;
    let ok = !model.is_empty()
        && source.len() == 16
        && source.bytes().all(|b| b.is_ascii_hexdigit())
        && level.len() == 1
        && level.bytes().all(|b| b.is_ascii_digit());
    let level: u8 = level.parse().ok()?;
    (ok && usize::from(level) < LEVEL_COUNT).then_some((model, level, source))
}

/// The level a tree `px` pixels tall is drawn at, for geometry down to `geometry_px`.
pub fn level_for(px: f32, geometry_px: f32) -> u8 {
    let g = geometry_px.max(0.0);
    LEVEL_PX_FACTORS
        .iter()
        .position(|&f| px >= f * g)
        .map_or(BILLBOARD_LEVEL, |k| k as u8)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_others_are_not_levels() {
        let h = "0123456789abcdef";
        for k in 0..LEVEL_COUNT as u8 {
            assert_eq!(
                parse_level_name(&level_name("small_shrub-v3", k, h)),
                Some(("small_shrub-v3", k, h))
            );
        }
        assert_eq!(parse_level_name("linden"), None);
        assert_eq!(parse_level_name("linden-lod1"), None);
        assert_eq!(parse_level_name(&format!("linden-lod4-{h}")), None);
        assert_eq!(parse_level_name(&format!("linden-lod01-{h}")), None);
        assert_eq!(parse_level_name(&format!("-lod1-{h}")), None);
        assert_eq!(parse_level_name(&format!("linden-lodx-{h}")), None);
        assert_eq!(parse_level_name("linden-lod1-0123"), None);
    }

    #[test]
    fn levels_follow_the_thresholds() {
        assert_eq!(level_for(600.0, 150.0), 0);
        assert_eq!(level_for(599.0, 150.0), 1);
        assert_eq!(level_for(300.0, 150.0), 1);
        assert_eq!(level_for(150.0, 150.0), 2);
        assert_eq!(level_for(149.9, 150.0), BILLBOARD_LEVEL);
        // Geometry down to 0 px: every tree at level 0.
        assert_eq!(level_for(0.0, 0.0), 0);
    }
}
