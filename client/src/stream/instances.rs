//! The instances stage: the scene's instance tiles near the camera, fetched from the version's
//! pack and checked, and each loaded instance's placement as culling reads it.
//!
//! Conventions: instances are kept in id order (every per-model sum of a frame is taken in that
//! order); positions are world metres on the ground plane (x, z); a tile's box bounds its placed
//! instances' bounding spheres.

use std::collections::{BTreeMap, BTreeSet};

use canopy_shared::pack::{PackInstance, decode_tile_records};
use glam::{Mat4, Vec3};

use super::model::{ModelState, Models};
use crate::lod::Frustum;
use bytes::Bytes;

use crate::net::{ByteRange, NetError};
use crate::scene::Manifest;

/// A loaded instance.
#[derive(Debug)]
pub(crate) struct Instance {
    pub inst: PackInstance,
    /// Manifest tile it came from.
    pub tile: u32,
}

/// What culling and the ladder read of an instance, computed once its model is open.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Placed {
    /// World centre of the tree's bounding sphere.
    pub c: Vec3,
    pub r: f32,
    /// Height (scaled).
    pub h: f32,
    pub model: u16,
    pub open: bool,
    /// Manifest tile it came from.
    pub tile: u32,
}

/// Bounds of a tile's placed instance spheres (world).
#[derive(Debug, Clone, Copy)]
pub(crate) struct TileBox {
    lo: Vec3,
    hi: Vec3,
}

/// A tile's relation to this frame's view volume (frustum and view distance).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum TileClass {
    /// No instance can be visible.
    Out,
    /// Every instance is inside: no per-instance test needed.
    In,
    /// Test each instance.
    Partial,
}

#[derive(Debug, Clone, PartialEq)]
enum TileState {
    Absent,
    Loaded,
    Failed,
}

/// The loaded instances and their placement.
#[derive(Debug, Default)]
pub(crate) struct Instances {
    tiles: Vec<TileState>,
    /// Loaded instances in id order.
    pub list: Vec<Instance>,
    /// Per instance (same order), valid unless `stale`.
    pub placed: Vec<Placed>,
    /// Per instance: inverse of its placement (model → world).
    pub inverse: Vec<Mat4>,
    tile_boxes: Vec<Option<TileBox>>,
    /// Instances were added or models opened since the last [`Instances::place`].
    pub stale: bool,
    /// After instances were added: the index each instance had before (`None`: new, or a
    /// record that replaced one), for stages that keep state per instance.
    reordered: Option<Vec<Option<usize>>>,
}

impl Instances {
    /// No instance yet, every tile of the manifest absent.
    pub fn new(tiles: usize) -> Self {
        Self {
            tiles: vec![TileState::Absent; tiles],
            ..Self::default()
        }
    }

    /// The tiles within `far` of `eye` not loaded, not failed and not in `loading`, with their
    /// ranges of the pack.
    pub fn tiles_to_load(
        &self,
        manifest: &Manifest,
        eye: Vec3,
        far: f32,
        loading: &BTreeSet<usize>,
    ) -> (Vec<usize>, Vec<ByteRange>) {
        let want: Vec<usize> = manifest
            .tiles_near(eye.x, eye.z, far)
            .into_iter()
            .filter(|&i| self.tiles[i] == TileState::Absent && !loading.contains(&i))
            .collect();
        let ranges = want
            .iter()
            .map(|&i| {
                let t = &manifest.tiles[i];
                t.offset..t.offset + t.length
            })
            .collect();
        (want, ranges)
    }

    /// Checks and adds the tiles that arrived; returns the number of corrupt tiles (tried again
    /// later).
    pub fn receive_tiles(&mut self, manifest: &Manifest, want: &[usize], got: Result<Vec<Bytes>, NetError>) -> u64 {
        let mut corrupt = 0;
        match got {
            Ok(bodies) => {
                let mut added = Vec::new();
                for (&i, body) in want.iter().zip(bodies) {
                    let t = &manifest.tiles[i];
                    match decode_tile_records(&body, t.crc32, manifest.models.len()) {
                        Ok(list) => {
                            added.extend(list.into_iter().map(|inst| Instance { inst, tile: i as u32 }));
                            self.tiles[i] = TileState::Loaded;
                        }
                        // Corrupt tile: try again next frame.
                        Err(_) => corrupt += 1,
                    }
                }
                self.add(added);
            }
            Err(e) if !e.is_retryable() => {
                for &i in want {
                    self.tiles[i] = TileState::Failed;
                }
            }
            Err(_) => {}
        }
        corrupt
    }

    /// Adds loaded instances (a later record of an id replaces the earlier one, with fresh
    /// state) and keeps them in id order.
    fn add(&mut self, added: Vec<Instance>) {
        if added.is_empty() {
            return;
        }
        let mut all: BTreeMap<u32, (Option<usize>, Instance)> = std::mem::take(&mut self.list)
            .into_iter()
            .enumerate()
            .map(|(k, i)| (i.inst.id, (Some(k), i)))
            .collect();
        for i in added {
            all.insert(i.inst.id, (None, i));
        }
        let (from, list): (Vec<Option<usize>>, Vec<Instance>) = all.into_values().unzip();
        self.list = list;
        self.reordered = Some(from);
        self.stale = true;
    }

    /// The instances' previous index, once after they were added ([`Self::reordered`]).
    pub fn take_reordered(&mut self) -> Option<Vec<Option<usize>>> {
        self.reordered.take()
    }

    /// Models used by an instance within `reach` of `eye`.
    pub fn models_near(&self, eye: Vec3, reach: f32) -> BTreeSet<usize> {
        let mut wanted = BTreeSet::new();
        for i in &self.list {
            let p = Vec3::from(i.inst.position);
            if p.distance(eye) <= reach {
                wanted.insert(usize::from(i.inst.model));
            }
        }
        wanted
    }

    /// Recomputes what culling reads of each instance and the tiles' bounds, after instances
    /// were added or models opened.
    pub fn place(&mut self, models: &Models) {
        self.placed.clear();
        self.inverse.clear();
        self.tile_boxes = vec![None; self.tiles.len()];
        for inst in &self.list {
            let m = usize::from(inst.inst.model);
            let Some(ModelState::Open(idx)) = models.state(m) else {
                self.placed.push(Placed {
                    c: Vec3::ZERO,
                    r: 0.0,
                    h: 0.0,
                    model: inst.inst.model,
                    open: false,
                    tile: inst.tile,
                });
                self.inverse.push(Mat4::IDENTITY);
                continue;
            };
            let (model_m, scale) = inst.inst.placement();
            let c = model_m.transform_point3(idx.center);
            let r = idx.radius * scale;
            self.placed.push(Placed {
                c,
                r,
                h: idx.height * scale,
                model: inst.inst.model,
                open: true,
                tile: inst.tile,
            });
            self.inverse.push(model_m.inverse());
            if let Some(b) = self.tile_boxes.get_mut(inst.tile as usize) {
                let (lo, hi) = (c - Vec3::splat(r.max(0.0)), c + Vec3::splat(r.max(0.0)));
                *b = Some(match *b {
                    Some(t) => TileBox {
                        lo: t.lo.min(lo),
                        hi: t.hi.max(hi),
                    },
                    None => TileBox { lo, hi },
                });
            }
        }
        self.stale = false;
    }

    /// Sorts every tile into out / in / partial for this frame's frustum and view distance.
    pub fn classify_tiles(&self, eye: Vec3, far: f32, frustum: &Frustum, out: &mut Vec<TileClass>) {
        out.clear();
        out.extend(
            self.tile_boxes
                .iter()
                .map(|b| b.map_or(TileClass::Out, |b| classify_box(b, eye, far, frustum))),
        );
    }
}

/// Where a box holding instance spheres lies against the view volume: `Out` only when every
/// sphere inside fails the per-instance test (beyond `far` or outside a plane), `In` only when
/// every sphere passes it.
fn classify_box(b: TileBox, eye: Vec3, far: f32, frustum: &Frustum) -> TileClass {
    // Margin (metres) that absorbs float rounding between the box and per-sphere tests.
    const EPS: f32 = 0.01;
    let (lo, hi) = (b.lo, b.hi);
    if !(lo.is_finite() && hi.is_finite() && eye.is_finite()) {
        return TileClass::Partial;
    }
    // Nearest and farthest points of the box from the eye.
    let near_pt = eye.clamp(lo, hi);
    let far_pt = Vec3::select(eye.cmplt((lo + hi) * 0.5), hi, lo);
    if near_pt.distance(eye) > far + EPS {
        return TileClass::Out;
    }
    let mut inside = far_pt.distance(eye) < far - EPS;
    for p in frustum.planes() {
        let n = p.truncate();
        // The corners with the largest and the smallest signed distance to the plane.
        let pos = Vec3::select(n.cmpge(Vec3::ZERO), hi, lo);
        let neg = Vec3::select(n.cmpge(Vec3::ZERO), lo, hi);
        if n.dot(pos) + p.w < -EPS {
            return TileClass::Out;
        }
        if n.dot(neg) + p.w < EPS {
            inside = false;
        }
    }
    if inside { TileClass::In } else { TileClass::Partial }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::DepthRange;
    use crate::stream::view::{Camera, Viewport};

    proptest::proptest! {
        /// Whole-tile decisions agree with the per-instance test for every sphere in the box.
        #[test]
        fn tile_classes_agree_with_the_instance_test(
            ex in -300.0f32..300.0, ey in 1.0f32..80.0, ez in -300.0f32..300.0, yaw in -3.2f32..3.2,
            pitch in -1.4f32..0.3, bx in -400.0f32..400.0, bz in -400.0f32..400.0, w in 1.0f32..120.0,
            spheres in proptest::collection::vec((0.0f32..1.0, 0.0f32..1.0, 0.0f32..1.0, 0.5f32..12.0), 1..12),
            far in 100.0f32..600.0,
        ) {
            let cam = Camera { eye: Vec3::new(ex, ey, ez), yaw, pitch };
            let vp = Viewport { far, ..Viewport::default() };
            let f = Frustum::from_view_proj(vp.projection() * cam.view(), DepthRange::ZeroToOne);
            let list: Vec<(Vec3, f32)> = spheres
                .iter()
                .map(|&(u, v, t, r)| (Vec3::new(bx + u * w, v * 25.0, bz + t * w), r))
                .collect();
            let lo = list.iter().fold(Vec3::splat(f32::INFINITY), |a, (c, r)| a.min(*c - Vec3::splat(*r)));
            let hi = list.iter().fold(Vec3::splat(f32::NEG_INFINITY), |a, (c, r)| a.max(*c + Vec3::splat(*r)));
            let class = classify_box(TileBox { lo, hi }, cam.eye, far, &f);
            for (c, r) in list {
                let passes = c.distance(cam.eye) - r <= far && f.intersects_sphere(c, r);
                match class {
                    TileClass::Out => proptest::prop_assert!(!passes),
                    TileClass::In => proptest::prop_assert!(passes),
                    TileClass::Partial => {}
                }
            }
        }
    }

    #[test]
    fn tiles_in_front_behind_and_beyond_the_view_distance() {
        let cam = Camera {
            eye: Vec3::new(0.0, 10.0, 0.0),
            yaw: 0.0,
            pitch: 0.0,
        };
        let vp = Viewport::default();
        let f = Frustum::from_view_proj(vp.projection() * cam.view(), DepthRange::ZeroToOne);
        let b = |z: f32| TileBox {
            lo: Vec3::new(-5.0, 0.0, z - 5.0),
            hi: Vec3::new(5.0, 20.0, z + 5.0),
        };
        assert_eq!(classify_box(b(-100.0), cam.eye, vp.far, &f), TileClass::In);
        assert_eq!(classify_box(b(100.0), cam.eye, vp.far, &f), TileClass::Out);
        assert_eq!(classify_box(b(-2000.0), cam.eye, vp.far, &f), TileClass::Out);
        assert_eq!(classify_box(b(-vp.far), cam.eye, vp.far, &f), TileClass::Partial);
        assert_eq!(classify_box(b(0.0), cam.eye, vp.far, &f), TileClass::Partial);
    }
}
