//! Scores per distance band: near, mid and far trees by projected height, so that a poor
//! mid-ground is not averaged away by sky, ground and well-drawn near trees.
//!
//! A tree's band comes from its projected height in pixels of the scored image (the whole tree,
//! root to top, at its bounding sphere's nearest distance: the measure the LOD ladder switches
//! on): far below [`MID_MIN_PX`], mid from [`MID_MIN_PX`] to [`NEAR_MIN_PX`], near above. A band's
//! pixels are those where either image (reference or method) shows one of that band's trees, so
//! a stand-in that spills past the silhouette is scored on its spill and one that leaves holes on
//! its holes. A band's SSIM is [`canopy_shared::metrics::SsimMaps::masked`] (each pixel carries
//! its 8 × 8 window's SSIM), its FLIP the mean of the FLIP map over the band.
//!
//! Conventions: heights in pixels of the image scored; trees are named by instance id, as in
//! [`super::render_view_with_trees`]'s buffer.

use std::collections::HashMap;

use canopy_shared::metrics::{SsimMaps, masked_mean};

use super::EvalScene;
use crate::stream::{Camera, DrawnTree, Viewport};

/// Projected height from which a tree is in the near band, pixels.
pub const NEAR_MIN_PX: f32 = 150.0;
/// Projected height from which a tree is in the mid band, pixels (below: far).
pub const MID_MIN_PX: f32 = 30.0;

/// A distance band.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Band {
    /// At least [`NEAR_MIN_PX`] tall.
    Near,
    /// From [`MID_MIN_PX`] to [`NEAR_MIN_PX`].
    Mid,
    /// Below [`MID_MIN_PX`].
    Far,
}

/// The bands, near first.
pub const BANDS: [Band; 3] = [Band::Near, Band::Mid, Band::Far];

impl Band {
    /// The band of a tree `px` pixels tall.
    pub fn of_height(px: f32) -> Self {
        if px >= NEAR_MIN_PX {
            Band::Near
        } else if px >= MID_MIN_PX {
            Band::Mid
        } else {
            Band::Far
        }
    }

    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Band::Near => "near",
            Band::Mid => "mid",
            Band::Far => "far",
        }
    }

    fn index(self) -> usize {
        match self {
            Band::Near => 0,
            Band::Mid => 1,
            Band::Far => 2,
        }
    }
}

/// Projected height in pixels of tree `t` seen from `cam` in an image `image_height` pixels tall
/// (`None` when its model is not loaded).
pub fn projected_px(scene: &EvalScene, t: &DrawnTree, cam: &Camera, vp: &Viewport, image_height: u32) -> Option<f32> {
    let model = scene.models.get(usize::from(t.instance.model))?.as_ref()?;
    let xf = t.instance.placement().0;
    let s = xf.to_scale_rotation_translation().0.x;
    let dir = &model.tree.directory;
    let (lo, hi) = (dir.bounds_min, dir.bounds_max);
    let c = xf.transform_point3(0.5 * (lo + hi));
    let r = 0.5 * (hi - lo).length() * s;
    let d = crate::lod::sphere_distance(cam.eye, c, r);
    Some(crate::lod::projected_height(
        (hi.y - lo.y.min(0.0)) * s,
        d,
        image_height as f32,
        vp.fov_y,
    ))
}

/// The band of every tree of one view, by instance id.
#[derive(Debug, Clone, Default)]
pub struct BandMap {
    by_id: HashMap<u32, Band>,
}

impl BandMap {
    /// Bands of the trees of `lists` seen from `cam` in an image `image_height` pixels tall.
    pub fn new(scene: &EvalScene, lists: &[&[DrawnTree]], cam: &Camera, vp: &Viewport, image_height: u32) -> Self {
        let mut by_id = HashMap::new();
        for t in lists.iter().flat_map(|l| l.iter()) {
            if let std::collections::hash_map::Entry::Vacant(e) = by_id.entry(t.instance.id)
                && let Some(px) = projected_px(scene, t, cam, vp, image_height)
            {
                e.insert(Band::of_height(px));
            }
        }
        Self { by_id }
    }

    /// From known bands (tests, other scorers).
    pub fn from_bands(bands: impl IntoIterator<Item = (u32, Band)>) -> Self {
        Self {
            by_id: bands.into_iter().collect(),
        }
    }

    /// The band of tree `id`, if known.
    pub fn band(&self, id: u32) -> Option<Band> {
        self.by_id.get(&id).copied()
    }

    /// Per band (near, mid, far), the mask of pixels where `reference_trees` or `view_trees`
    /// (per-pixel instance ids, same length) shows one of the band's trees.
    pub fn masks(&self, reference_trees: &[u32], view_trees: &[u32]) -> [Vec<bool>; 3] {
        let mut masks = [0, 1, 2].map(|_| vec![false; reference_trees.len()]);
        for (i, (r, v)) in reference_trees.iter().zip(view_trees).enumerate() {
            for id in [r, v] {
                if let Some(b) = self.band(*id) {
                    masks[b.index()][i] = true;
                }
            }
        }
        masks
    }
}

/// One band's scores.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct BandScore {
    /// The band.
    pub band: Band,
    /// Share of the image's pixels in the band.
    pub pixel_share: f64,
    /// Colour SSIM over the band's pixels (`None`: no pixel in the band).
    pub ssim: Option<f64>,
    /// Mean FLIP error over the band's pixels (`None`: no pixel in the band).
    pub flip: Option<f64>,
}

/// Band scores from the SSIM maps and FLIP map of one image pair and its band masks.
pub fn band_scores(masks: &[Vec<bool>; 3], ssim: &SsimMaps, flip: &[f32]) -> [BandScore; 3] {
    BANDS.map(|band| {
        let mask = &masks[band.index()];
        let n = mask.iter().filter(|&&m| m).count();
        BandScore {
            band,
            pixel_share: n as f64 / mask.len().max(1) as f64,
            ssim: ssim.masked(mask),
            flip: masked_mean(flip, mask),
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heights_fall_in_the_issue_bands() {
        assert_eq!(Band::of_height(400.0), Band::Near);
        assert_eq!(Band::of_height(150.0), Band::Near);
        assert_eq!(Band::of_height(149.9), Band::Mid);
        assert_eq!(Band::of_height(30.0), Band::Mid);
        assert_eq!(Band::of_height(29.9), Band::Far);
        assert_eq!(Band::of_height(0.0), Band::Far);
    }

    #[test]
    fn a_pixel_belongs_to_the_bands_of_either_image() {
        let empty = canopy_shared::raster::EMPTY_ITEM;
        let map = BandMap::from_bands([(1, Band::Near), (2, Band::Mid), (3, Band::Far)]);
        // Reference: near, mid, empty, far, unknown tree. Method: near, far, mid, far, empty.
        let r = [1, 2, empty, 3, 9];
        let v = [1, 3, 2, 3, empty];
        let [near, mid, far] = map.masks(&r, &v);
        assert_eq!(near, [true, false, false, false, false]);
        assert_eq!(mid, [false, true, true, false, false]);
        assert_eq!(far, [false, true, false, true, false]);
        let ssim = SsimMaps {
            channels: [0, 1, 2].map(|_| vec![1.0, 0.5, 0.5, 0.9, 1.0]),
        };
        let flip = [0.0, 0.4, 0.6, 0.1, 0.0];
        let scores = band_scores(&[near, mid, far], &ssim, &flip);
        assert_eq!(scores.map(|s| s.band), BANDS);
        assert!((scores[1].pixel_share - 0.4).abs() < 1e-12);
        assert!((scores[1].flip.unwrap_or(0.0) - 0.5).abs() < 1e-6);
        assert!((scores[2].ssim.unwrap_or(0.0) - 0.7).abs() < 1e-6);
        let none = band_scores(&[vec![false; 5], vec![false; 5], vec![false; 5]], &ssim, &flip);
        assert!(
            none.iter()
                .all(|s| s.ssim.is_none() && s.flip.is_none() && s.pixel_share == 0.0)
        );
    }
}
