//! Bark level of detail: which twigs a geometry tree's bark leaves out at its distance, and with
//! how many tube sides. The viewer draws these variants, the CPU evaluation renders them (at
//! [`EVAL_BARK_SIDES`] sides), and the stream counts their triangles (`fly --json`), so all three
//! agree on what "drawn" means.
//!
//! Conventions: radii in model units (metres before instance scale); a variant `v` leaves out
//! every branch whose radius never reaches [`BARK_MIN_RADII`]`[v]`; variant 0 keeps every twig.

/// Bark variants: branches whose radius never reaches this many metres are left out. Every
/// rendering (reference included) uses, per tree, the coarsest variant whose dropped twigs are
/// all thinner than [`BARK_MIN_PIXELS`] of a pixel, as the bake's atlases do: tubes of a
/// hundredth of a pixel cost most of a forest's triangles and change nothing visible.
pub const BARK_MIN_RADII: [f32; 5] = [0.0, 0.003, 0.01, 0.03, 0.1];
/// Radius in pixels below which a twig may be left out of a rendering.
pub const BARK_MIN_PIXELS: f32 = 0.1;
/// Tube sides of each bark variant in the viewer: fewer as distance grows.
pub const BARK_VARIANT_SIDES: [u32; 5] = [6, 6, 5, 4, 3];
/// Tube sides of every bark variant in the CPU evaluation's renderings.
pub const EVAL_BARK_SIDES: u32 = 6;

/// The coarsest bark variant whose dropped twigs all project below [`BARK_MIN_PIXELS`], for a
/// tree of instance scale `scale` at `distance` metres (to its bounding sphere) seen with
/// `metres_per_pixel` metres per pixel at one metre (`2·tan(fov_y/2) / height`).
#[inline]
pub fn bark_variant(metres_per_pixel: f32, distance: f32, scale: f32) -> usize {
    let allowed = BARK_MIN_PIXELS * metres_per_pixel * distance / scale;
    BARK_MIN_RADII.iter().rposition(|&t| t <= allowed).unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The discrete LOD files' bark is the viewer's variants 0, 1, 2.
    #[test]
    fn discrete_levels_use_the_viewers_bark_variants() {
        use canopy_shared::discrete::{GEOMETRY_LEVELS, LEVEL_BARK_MIN_RADII, LEVEL_BARK_SIDES};
        assert_eq!(LEVEL_BARK_MIN_RADII[..], BARK_MIN_RADII[..GEOMETRY_LEVELS]);
        assert_eq!(LEVEL_BARK_SIDES[..], BARK_VARIANT_SIDES[..GEOMETRY_LEVELS]);
    }

    /// Near trees keep every twig; the variant coarsens with distance and with a smaller
    /// instance scale, and bad inputs fall back to every twig.
    #[test]
    fn the_variant_coarsens_with_distance() {
        let mpp = 2.0 * (30f32.to_radians()).tan() / 720.0;
        assert_eq!(bark_variant(mpp, 0.0, 1.0), 0);
        let mut last = 0;
        for d in [1.0, 10.0, 50.0, 200.0, 1000.0, 10_000.0] {
            let v = bark_variant(mpp, d, 1.0);
            assert!(v >= last, "variant {v} at {d} m after {last}");
            last = v;
        }
        assert_eq!(last, BARK_MIN_RADII.len() - 1);
        assert!(bark_variant(mpp, 200.0, 0.5) >= bark_variant(mpp, 200.0, 1.0));
        assert_eq!(bark_variant(mpp, f32::NAN, 1.0), 0);
        assert_eq!(bark_variant(mpp, 100.0, 0.0), BARK_MIN_RADII.len() - 1);
    }
}
