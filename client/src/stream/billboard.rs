//! Billboard frame choice: which atlas frames (and which resolution) a billboard of each kind
//! draws for a view direction, gathered once per model and frame so that the per-instance loop
//! does not allocate.
//!
//! Conventions: directions are unit vectors in the model frame, tree → eye; a frame index is
//! the atlas table's (layouts' first frames added); resolution 0 is the largest side.

use std::sync::Arc;
use std::sync::atomic::{AtomicU32, Ordering};

use canopy_shared::format::atlas::{
    AtlasLayout, AtlasLayoutKind, AtlasTable, ViewSphere, hemi_oct_blend, lat_long_nearest,
};
use glam::Vec3;

use crate::lod::projection::BillboardKind;

/// Up to three billboard frames `(frame, resolution index, weight)`, without allocating.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct FrameSet {
    pub len: u8,
    items: [(u32, u8, f32); 3],
}

impl FrameSet {
    pub fn as_slice(&self) -> &[(u32, u8, f32)] {
        &self.items[..usize::from(self.len)]
    }

    pub fn push(&mut self, x: (u32, u8, f32)) {
        if let Some(slot) = self.items.get_mut(usize::from(self.len)) {
            *slot = x;
            self.len += 1;
        }
    }
}

/// What the billboard choice reads of an atlas table, gathered once per model and frame.
#[derive(Debug, Default)]
pub(crate) struct AtlasFrame {
    /// Stored sides, finest first.
    sides: Vec<u16>,
    /// Layout of each billboard kind (hemi-oct, lat-long, crossed, views).
    layouts: [Option<AtlasLayout>; 4],
    /// Whether each frame has an image.
    present: Vec<bool>,
    /// The views layout's triangulation.
    views: Option<Arc<ViewSphere>>,
    /// Last located triangle: the next walk starts there (trees of one model are seen from
    /// nearby directions). Atomic because plans run on a thread pool; any value is valid.
    hint: AtomicU32,
}

impl AtlasFrame {
    pub fn set(&mut self, a: Option<&AtlasTable>) {
        self.sides.clear();
        self.present.clear();
        self.layouts = [None; 4];
        self.views = None;
        let Some(a) = a else { return };
        self.views.clone_from(&a.views);
        self.sides.extend_from_slice(&a.resolutions);
        self.present.extend(
            a.frames
                .iter()
                .map(canopy_shared::format::atlas::AtlasFrame::is_present),
        );
        for (k, kind) in [
            BillboardKind::HemiOct,
            BillboardKind::LatLong,
            BillboardKind::Crossed,
            BillboardKind::Views,
        ]
        .into_iter()
        .enumerate()
        {
            self.layouts[k] = a.layouts.iter().find(|l| layout_is(kind, &l.kind)).copied();
        }
    }

    /// Frames (and the resolution index) a billboard of `kind` needs for a view from `dir_model`
    /// (unit, model frame, tree → eye), at `px` projected pixels: up to three, weights summing
    /// to 1 where the layout blends.
    #[inline]
    pub fn frames(&self, kind: BillboardKind, dir_model: Vec3, px: f32) -> FrameSet {
        let res = self.sides.iter().rposition(|&s| f32::from(s) >= px).unwrap_or(0) as u8;
        let k = match kind {
            BillboardKind::HemiOct => 0,
            BillboardKind::LatLong => 1,
            BillboardKind::Crossed => 2,
            BillboardKind::Views => 3,
        };
        let mut out = FrameSet::default();
        let Some(layout) = &self.layouts[k] else {
            return out;
        };
        let mut push = |f: u32, w: f32| {
            let f = layout.first_frame + f;
            if self.present.get(f as usize).copied().unwrap_or(false) {
                out.push((f, res, w));
            }
        };
        match kind {
            BillboardKind::HemiOct => {
                for (f, w) in hemi_oct_blend(dir_model, u32::from(layout.cols)) {
                    if w > 0.0 {
                        push(f, w);
                    }
                }
            }
            BillboardKind::LatLong => {
                if let Some(f) = lat_long_nearest(layout, dir_model) {
                    push(f, 1.0);
                }
            }
            BillboardKind::Crossed => {
                push(0, 0.5);
                push(1, 0.5);
            }
            BillboardKind::Views => {
                if let Some(v) = &self.views {
                    let hint = self.hint.load(Ordering::Relaxed);
                    let b = v.blend(dir_model, hint);
                    for &(f, w) in b.as_slice() {
                        if w > 0.0 {
                            push(f, w);
                        }
                    }
                    if let Some(t) = b.triangle {
                        self.hint.store(t, Ordering::Relaxed);
                    }
                }
            }
        }
        out
    }
}

/// Whether an atlas layout serves billboards of `kind`.
fn layout_is(kind: BillboardKind, k: &AtlasLayoutKind) -> bool {
    matches!(
        (kind, k),
        (BillboardKind::HemiOct, AtlasLayoutKind::HemiOctahedral)
            | (BillboardKind::LatLong, AtlasLayoutKind::LatLong { .. })
            | (BillboardKind::Crossed, AtlasLayoutKind::CrossedQuads)
            | (BillboardKind::Views, AtlasLayoutKind::Views)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Frames a billboard of `kind` needs ([`AtlasFrame::frames`]), gathered from `a`.
    fn billboard_frames(a: &AtlasTable, kind: BillboardKind, dir_model: Vec3, px: f32) -> Vec<(u32, u8, f32)> {
        let mut g = AtlasFrame::default();
        g.set(Some(a));
        g.frames(kind, dir_model, px).as_slice().to_vec()
    }

    /// The choice as first written (allocating, per tree), the reference for [`AtlasFrame::frames`].
    fn reference_billboard_frames(
        a: &AtlasTable,
        kind: BillboardKind,
        dir_model: Vec3,
        px: f32,
    ) -> Vec<(u32, u8, f32)> {
        let res = a.resolutions.iter().rposition(|&s| f32::from(s) >= px).unwrap_or(0) as u8;
        let Some(layout) = a.layouts.iter().find(|l| layout_is(kind, &l.kind)) else {
            return Vec::new();
        };
        let local: Vec<(u32, f32)> = match kind {
            BillboardKind::HemiOct => hemi_oct_blend(dir_model, u32::from(layout.cols))
                .into_iter()
                .filter(|(_, w)| *w > 0.0)
                .collect(),
            BillboardKind::LatLong => lat_long_nearest(layout, dir_model)
                .map(|f| (f, 1.0))
                .into_iter()
                .collect(),
            BillboardKind::Crossed => vec![(0, 0.5), (1, 0.5)],
            BillboardKind::Views => a
                .views
                .as_ref()
                .map(|v| {
                    v.blend(dir_model, 0)
                        .as_slice()
                        .iter()
                        .copied()
                        .filter(|(_, w)| *w > 0.0)
                        .collect()
                })
                .unwrap_or_default(),
        };
        local
            .into_iter()
            .map(|(f, w)| (layout.first_frame + f, w))
            .filter(|&(f, _)| {
                a.frames
                    .get(f as usize)
                    .is_some_and(canopy_shared::format::atlas::AtlasFrame::is_present)
            })
            .map(|(f, w)| (f, res, w))
            .collect()
    }

    /// A table with all four layouts (lat-long 12 × 4 from 0° in 20° steps, hemi-oct 4 × 4,
    /// crossed, 12 irregular views), every frame present at two resolutions.
    fn atlas() -> AtlasTable {
        use canopy_shared::format::atlas::{AtlasCodec, AtlasFrame as TableFrame, ImageEntry};
        let layouts = vec![
            AtlasLayout {
                kind: AtlasLayoutKind::LatLong {
                    elevation_min: 0.0,
                    elevation_step: 20f32.to_radians(),
                    azimuth_step: 30f32.to_radians(),
                },
                cols: 12,
                rows: 4,
                first_frame: 0,
            },
            AtlasLayout {
                kind: AtlasLayoutKind::HemiOctahedral,
                cols: 4,
                rows: 4,
                first_frame: 48,
            },
            AtlasLayout {
                kind: AtlasLayoutKind::CrossedQuads,
                cols: 2,
                rows: 1,
                first_frame: 64,
            },
            AtlasLayout {
                kind: AtlasLayoutKind::Views,
                cols: 12,
                rows: 1,
                first_frame: 66,
            },
        ];
        let view_angles: Vec<[f32; 2]> = (0..12)
            .map(|i| {
                [
                    (i as f32 * 29.0 - 170.0).to_radians(),
                    ((i * 37 % 80) as f32).to_radians(),
                ]
            })
            .collect();
        let dirs: Vec<Vec3> = view_angles
            .iter()
            .map(|a| canopy_shared::format::atlas::lat_long_direction(a[0], a[1]))
            .collect();
        let image = ImageEntry {
            offset: 1,
            length: 1,
            crc: 0,
        };
        AtlasTable {
            codec: AtlasCodec::Png,
            center: Vec3::ZERO,
            radius: 1.0,
            resolutions: vec![128, 64],
            layouts,
            frames: vec![
                TableFrame {
                    root_u: 0.5,
                    root_v: 0.0,
                    images: vec![image; 2],
                };
                78
            ],
            views: Some(Arc::new(ViewSphere::new(&dirs))),
            view_angles,
        }
    }

    #[test]
    fn billboards_seen_from_straight_above_and_the_side() {
        let a = atlas();
        let up = Vec3::Y;
        // Hemi-oct covers the zenith: weights sum to 1 over frames of its own layout.
        let h = billboard_frames(&a, BillboardKind::HemiOct, up, 10.0);
        assert!(!h.is_empty() && h.iter().all(|&(f, _, _)| (48..64).contains(&f)));
        assert!((h.iter().map(|x| x.2).sum::<f32>() - 1.0).abs() < 1e-4, "{h:?}");
        // Lat-long has no frame above 60°: straight above clamps to the top row (the failure
        // case of seed 001's grid, measured in benchmarks/log.md).
        let l = billboard_frames(&a, BillboardKind::LatLong, up, 10.0);
        assert_eq!(l.len(), 1);
        assert!((36..48).contains(&l[0].0), "{l:?}");
        // Crossed quads are two vertical images whatever the view.
        let c = billboard_frames(&a, BillboardKind::Crossed, up, 10.0);
        assert_eq!(c.iter().map(|x| x.0).collect::<Vec<_>>(), vec![64, 65]);
        // Resolution: the smallest side at least the projected size, else the largest.
        assert_eq!(billboard_frames(&a, BillboardKind::Crossed, Vec3::X, 50.0)[0].1, 1);
        assert_eq!(billboard_frames(&a, BillboardKind::Crossed, Vec3::X, 100.0)[0].1, 0);
        assert_eq!(billboard_frames(&a, BillboardKind::Crossed, Vec3::X, 1000.0)[0].1, 0);
        // A degenerate direction (eye at the centre) never panics.
        let _ = billboard_frames(&a, BillboardKind::HemiOct, Vec3::ZERO, 10.0);
        let _ = billboard_frames(&a, BillboardKind::LatLong, Vec3::ZERO, 10.0);
    }

    proptest::proptest! {
        /// The per-model billboard choice gives exactly the frames and weights of the reference.
        #[test]
        fn gathered_atlas_choice_matches_the_reference(
            x in -1.0f32..1.0, y in -1.0f32..1.0, z in -1.0f32..1.0, px in 0.0f32..300.0,
        ) {
            let dir = Vec3::new(x, y, z).normalize_or_zero();
            let a = atlas();
            let mut g = AtlasFrame::default();
            g.set(Some(&a));
            for kind in [BillboardKind::HemiOct, BillboardKind::LatLong, BillboardKind::Crossed] {
                let got = g.frames(kind, dir, px).as_slice().to_vec();
                proptest::prop_assert_eq!(got, reference_billboard_frames(&a, kind, dir, px));
            }
            // Views: the walk starts from the last tree's triangle, the reference from
            // triangle 0; the triangle holding the direction is the same (on a shared edge
            // either, with the fourth vertex at weight 0), so frames of weight over 1e-4 and
            // their weights agree.
            let big = |v: Vec<(u32, u8, f32)>| {
                let mut v: Vec<_> = v.into_iter().filter(|x| x.2 > 1e-4).collect();
                v.sort_by_key(|x| x.0);
                v
            };
            let got = big(g.frames(BillboardKind::Views, dir, px).as_slice().to_vec());
            let want = big(reference_billboard_frames(&a, BillboardKind::Views, dir, px));
            proptest::prop_assert_eq!(got.len(), want.len());
            for (x, y) in got.iter().zip(&want) {
                proptest::prop_assert!(x.0 == y.0 && x.1 == y.1 && (x.2 - y.2).abs() < 1e-4, "{got:?} {want:?}");
            }
            if dir != Vec3::ZERO {
                proptest::prop_assert!(!got.is_empty() && got.iter().all(|x| (66..78).contains(&x.0)));
            }
        }
    }
}
