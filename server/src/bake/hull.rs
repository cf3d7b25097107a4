//! Crown contour hulls (seed 004), baked into section kind 6 (`canopy_shared::format::hull`).
//!
//! Method per level, in order of preference:
//!
//! 1. **Reconstruction** (seed 004): feature points are the tips (last skeleton point) of all
//!    branches, or for models without a skeleton the leaf centres (or bark vertices when there
//!    are no leaves). The crown centre is the centre of the leaves' bounds (of the feature
//!    points' when there are no leaves), the crown radius the largest feature-point distance
//!    from it; points nearer than `θ = theta_fraction × radius` to the centre are dropped, and
//!    their normals would point from the centre outward. [`surface::reconstruct`] replaces
//!    Poisson (see its module doc), then meshoptimizer simplifies to each budget.
//! 2. **Convex hull** of the leaf centres and tips, when there are fewer than `min_points`
//!    feature points, the reconstruction yields nothing, or the level's silhouette IoU is
//!    below `min_iou` and the convex hull's is higher.
//! 3. **Bounding box** of the same points when even the convex hull fails (flat or collinear
//!    input). It never fails.
//!
//! The silhouette IoU of each level is measured against the full tree (leaves with the alpha-
//! tested leaf texture, and bark less the twigs under a tenth of a pixel wide, see
//! [`far_tree_mesh`]) from `iou_views` Fibonacci-sphere directions with a perspective
//! camera far away (10° field of view, the tree's bounding sphere filling it) at `iou_size`²
//! pixels, and stored in the level table.

use std::time::Instant;

use canopy_shared::format::SectionBody;
use canopy_shared::format::hull::{HullMesh, HullMethod, encode_hulls};
use canopy_shared::metrics;
use canopy_shared::model::TreeModel;
use canopy_shared::raster::{
    Camera, RasterError, RasterMaterial, RasterMesh, RenderOptions, Scene, fibonacci_sphere, render,
};
use glam::Vec3;

use super::atlas::far_tree_mesh;
use super::surface::{self, Mesh, ReconstructOptions};
use super::vmi::{leaf_materials, leaf_texture};

/// Options of [`bake_hulls`].
#[derive(Debug, Clone, PartialEq)]
pub struct HullOptions {
    /// Triangle budgets, one level each, largest first.
    pub budgets: Vec<u32>,
    /// θ as a fraction of the crown radius: feature points nearer to the crown centre are
    /// dropped.
    pub theta_fraction: f32,
    /// Fewest feature points for a reconstruction.
    pub min_points: usize,
    /// A reconstructed level with a lower silhouette IoU is replaced by the convex hull when
    /// that scores higher.
    pub min_iou: f64,
    /// Reconstruction grid and kernel.
    pub reconstruct: ReconstructOptions,
    /// Views for the silhouette IoU (0: not measured, NaN stored; the fallback-by-IoU is then
    /// off).
    pub iou_views: usize,
    /// Square image side of the IoU renders, pixels.
    pub iou_size: u32,
    /// Points entering the convex hull (extreme points along this many directions).
    pub hull_directions: usize,
}

impl Default for HullOptions {
    fn default() -> Self {
        Self {
            budgets: vec![2000, 500, 120],
            theta_fraction: 0.3,
            min_points: 20,
            min_iou: 0.5,
            reconstruct: ReconstructOptions::default(),
            iou_views: 16,
            iou_size: 64,
            hull_directions: 256,
        }
    }
}

/// Where the feature points came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FeatureSource {
    /// Branch tips.
    BranchTips,
    /// Leaf centres (no skeleton).
    LeafCentres,
    /// Bark mesh vertices (no skeleton, no leaves).
    BarkVertices,
    /// Nothing to take points from.
    None,
}

/// One level of the report.
#[derive(Debug, Clone, PartialEq)]
pub struct HullLevelReport {
    /// Triangle budget asked for.
    pub budget: u32,
    /// Triangles stored.
    pub triangles: usize,
    /// Vertices stored.
    pub vertices: usize,
    /// Method used.
    pub method: HullMethod,
    /// Silhouette IoU against the full tree (NaN when not measured).
    pub iou: f64,
    /// Every edge shared by exactly two triangles.
    pub closed: bool,
}

/// What [`bake_hulls`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct HullReport {
    /// Source of the feature points.
    pub source: FeatureSource,
    /// Feature points before the θ filter.
    pub feature_points: usize,
    /// Feature points kept.
    pub kept_points: usize,
    /// Triangles of the reconstruction before simplification (0 if none).
    pub reconstructed_triangles: usize,
    /// Whether the reconstruction before simplification is closed (false if none).
    pub reconstructed_closed: bool,
    /// Levels, as stored.
    pub levels: Vec<HullLevelReport>,
    /// Section bytes.
    pub bytes: usize,
    /// Wall-clock seconds.
    pub seconds: f64,
}

/// Why the hull bake failed.
#[derive(Debug, thiserror::Error)]
pub enum HullError {
    /// Options out of range.
    #[error("invalid hull options: {0}")]
    Options(String),
    /// Rendering for the IoU failed.
    #[error(transparent)]
    Raster(#[from] RasterError),
    /// Encoding failed.
    #[error(transparent)]
    Format(#[from] canopy_shared::format::FormatError),
}

/// Feature points (see the module doc): `(source, all points, kept points)`.
pub fn feature_points(model: &TreeModel, theta_fraction: f32) -> (FeatureSource, Vec<Vec3>, Vec<Vec3>) {
    let tips: Vec<Vec3> = model
        .branches
        .iter()
        .filter_map(|b| b.points.last().map(|p| p.position))
        .collect();
    let (source, pts) = if !tips.is_empty() {
        (FeatureSource::BranchTips, tips)
    } else if !model.leaves.is_empty() {
        (
            FeatureSource::LeafCentres,
            model.leaves.iter().map(|l| l.center).collect(),
        )
    } else if !model.bark_mesh.positions.is_empty() {
        (FeatureSource::BarkVertices, model.bark_mesh.positions.clone())
    } else {
        (FeatureSource::None, Vec::new())
    };
    let pts: Vec<Vec3> = pts.into_iter().filter(|p| p.is_finite()).collect();
    let centre_of = |it: &mut dyn Iterator<Item = Vec3>| {
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for p in it {
            lo = lo.min(p);
            hi = hi.max(p);
        }
        (lo.cmple(hi).all()).then(|| 0.5 * (lo + hi))
    };
    let centre = centre_of(&mut model.leaves.iter().map(|l| l.center).filter(|p| p.is_finite()))
        .or_else(|| centre_of(&mut pts.iter().copied()))
        .unwrap_or(Vec3::ZERO);
    let radius = pts.iter().map(|p| p.distance(centre)).fold(0.0, f32::max);
    let theta = theta_fraction * radius;
    let kept = pts.iter().copied().filter(|p| p.distance(centre) >= theta).collect();
    (source, pts, kept)
}

/// Silhouette reference: coverage masks of the full tree from the IoU views.
struct Silhouettes {
    cameras: Vec<Camera>,
    masks: Vec<Vec<bool>>,
    size: u32,
}

impl Silhouettes {
    fn new(model: &TreeModel, views: usize, size: u32) -> Result<Self, RasterError> {
        let (lo, hi) = model.bounds().unwrap_or((Vec3::ZERO, Vec3::ONE));
        let (c, r) = (0.5 * (lo + hi), (0.5 * (hi - lo).length()).max(1e-3));
        let cameras: Vec<Camera> = fibonacci_sphere(views)
            .into_iter()
            .map(|d| Camera::orbit_perspective(c, r, d, 10f32.to_radians()))
            .collect();
        // Twigs under a tenth of a pixel wide are left out, as for the billboards.
        let mesh = far_tree_mesh(model, 2.0 * r / size as f32, 0.1, 4);
        let mats = leaf_materials(model);
        let tex = [leaf_texture()];
        let scene = Scene::single(&mesh, &mats, &tex);
        let opts = RenderOptions {
            shade: false,
            ..RenderOptions::default()
        };
        let masks = cameras
            .iter()
            .map(|cam| render(&scene, cam, size, size, &opts).map(|f| f.coverage()))
            .collect::<Result<_, _>>()?;
        Ok(Self { cameras, masks, size })
    }

    /// Mean IoU of `mesh`'s silhouettes with the tree's; NaN without views.
    fn iou(&self, mesh: &Mesh) -> Result<f64, RasterError> {
        if self.cameras.is_empty() {
            return Ok(f64::NAN);
        }
        let rm = RasterMesh {
            positions: mesh.positions.clone(),
            indices: mesh.indices.clone(),
            item_of_triangle: vec![0; mesh.triangle_count()],
            ..RasterMesh::default()
        };
        let mats = [RasterMaterial {
            alpha_cutoff: 0.0,
            double_sided: true,
            ..RasterMaterial::default()
        }];
        let scene = Scene::single(&rm, &mats, &[]);
        let opts = RenderOptions {
            shade: false,
            ..RenderOptions::default()
        };
        let mut sum = 0.0;
        for (cam, reference) in self.cameras.iter().zip(&self.masks) {
            let f = render(&scene, cam, self.size, self.size, &opts)?;
            // Both masks have the same size, so the metric cannot fail.
            sum += metrics::iou(reference, &f.coverage()).unwrap_or(0.0);
        }
        Ok(sum / self.cameras.len() as f64)
    }
}

/// Bakes the crown hulls of `model` into a section body (item count = levels) and a report.
///
/// Contract: one level per budget, in the given order, each with at most that many triangles
/// (the box fallback has 12, so budgets below 12 are rejected); never fails for lack of points
/// (the box fallback covers empty and degenerate models); errors only on bad options or a
/// rendering failure.
pub fn bake_hulls(model: &TreeModel, opts: &HullOptions) -> Result<(SectionBody, HullReport), HullError> {
    let start = Instant::now();
    if opts.budgets.is_empty()
        || opts.budgets.len() > canopy_shared::format::hull::MAX_HULL_LEVELS
        || opts.budgets.iter().any(|&b| b < 12)
        || !(0.0..1.0).contains(&opts.theta_fraction)
    {
        return Err(HullError::Options(
            "budgets must be 1..=16 values ≥ 12, theta_fraction in [0, 1)".into(),
        ));
    }
    let (source, all, kept) = feature_points(model, opts.theta_fraction);
    let recon = if kept.len() >= opts.min_points {
        surface::reconstruct(&kept, &opts.reconstruct)
    } else {
        None
    };
    // Fallback points: leaf centres plus the feature points.
    let mut hull_pts: Vec<Vec3> = model.leaves.iter().map(|l| l.center).collect();
    hull_pts.extend_from_slice(&all);
    let (fallback, fallback_method) = match surface::convex_hull(&hull_pts, opts.hull_directions) {
        Some(m) => (m, HullMethod::ConvexHull),
        None => (surface::bounding_box(&hull_pts), HullMethod::BoundingBox),
    };
    let sil = Silhouettes::new(model, opts.iou_views, opts.iou_size.max(8))?;
    let mut levels = Vec::with_capacity(opts.budgets.len());
    let mut reports = Vec::with_capacity(opts.budgets.len());
    // A hull is a stand-in for the tree: never spend more triangles on it than the tree has
    // (leaf quads and bark), so small imported trees get small hulls.
    let source_triangles = (2 * model.leaves.len() + model.bark_mesh.triangle_count()).max(12);
    for &asked in &opts.budgets {
        let budget = asked.min(u32::try_from(source_triangles).unwrap_or(u32::MAX));
        let fb = surface::simplify(&fallback, budget as usize);
        let mut chosen = None;
        if let Some(r) = &recon {
            let m = surface::simplify(r, budget as usize);
            let iou = sil.iou(&m)?;
            if m.triangle_count() >= 4 && (iou.is_nan() || iou >= opts.min_iou) {
                chosen = Some((m, HullMethod::Reconstruction, iou));
            } else {
                let fb_iou = sil.iou(&fb)?;
                chosen = Some(if fb_iou > iou || m.triangle_count() < 4 {
                    (fb.clone(), fallback_method, fb_iou)
                } else {
                    (m, HullMethod::Reconstruction, iou)
                });
            }
        }
        let (mesh, method, iou) = if let Some(c) = chosen {
            c
        } else {
            let iou = sil.iou(&fb)?;
            (fb, fallback_method, iou)
        };
        reports.push(HullLevelReport {
            budget,
            triangles: mesh.triangle_count(),
            vertices: mesh.positions.len(),
            method,
            iou,
            closed: mesh.is_closed(),
        });
        levels.push(HullMesh {
            method,
            iou: iou as f32,
            positions: mesh.positions,
            indices: mesh.indices,
        });
    }
    let bytes = encode_hulls(&levels)?;
    let report = HullReport {
        source,
        feature_points: all.len(),
        kept_points: kept.len(),
        reconstructed_triangles: recon.as_ref().map_or(0, Mesh::triangle_count),
        reconstructed_closed: recon.as_ref().is_some_and(Mesh::is_closed),
        levels: reports,
        bytes: bytes.len(),
        seconds: start.elapsed().as_secs_f64(),
    };
    Ok((
        SectionBody {
            bytes,
            item_count: levels.len() as u32,
        },
        report,
    ))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use canopy_shared::format::hull::decode_hulls;
    use canopy_shared::model::{Branch, Leaf, Materials, ModelSource, SkeletonPoint, TriangleMesh};

    fn leaf(center: Vec3) -> Leaf {
        Leaf {
            center,
            normal: Vec3::Z,
            axis: Vec3::Y,
            width: 0.3,
            length: 0.4,
            branch: None,
            iteration: 0,
            material: 0,
        }
    }

    /// A trunk with `n` twigs whose tips lie on a sphere, a leaf at each tip.
    fn ball_tree(n: usize) -> TreeModel {
        let c = Vec3::new(0.0, 4.0, 0.0);
        let mut branches = vec![Branch {
            points: vec![
                SkeletonPoint {
                    position: Vec3::ZERO,
                    radius: 0.2,
                },
                SkeletonPoint {
                    position: c,
                    radius: 0.1,
                },
            ],
            parent: None,
            level: 1,
            iteration: 0,
        }];
        let mut leaves = Vec::new();
        for d in fibonacci_sphere(n) {
            let tip = c + d * 2.5;
            branches.push(Branch {
                points: vec![
                    SkeletonPoint {
                        position: c,
                        radius: 0.05,
                    },
                    SkeletonPoint {
                        position: tip,
                        radius: 0.02,
                    },
                ],
                parent: Some(0),
                level: 2,
                iteration: 0,
            });
            leaves.push(leaf(tip));
        }
        TreeModel {
            name: "ball".into(),
            branches,
            leaves,
            bark_mesh: TriangleMesh::default(),
            materials: Materials::default(),
            iterations: 0,
            source: ModelSource::LSystem,
        }
    }

    #[test]
    fn ball_tree_reconstructs_within_budgets() {
        let model = ball_tree(600);
        let (body, rep) = bake_hulls(&model, &HullOptions::default()).unwrap();
        assert_eq!(rep.source, FeatureSource::BranchTips);
        assert_eq!(body.item_count, 3);
        let (_, meshes) = decode_hulls(&body.bytes).unwrap();
        for (l, m) in rep.levels.iter().zip(&meshes) {
            assert!(l.triangles <= l.budget as usize);
            assert_eq!(m.triangle_count(), l.triangles);
            // Measured 0.707, 0.713 and 0.746 for the three levels.
            assert!(l.iou > 0.68, "{l:?}");
        }
        assert_eq!(rep.levels[0].method, HullMethod::Reconstruction);
        assert!(rep.levels[0].closed);
    }

    #[test]
    fn flat_and_empty_models_fall_back() {
        // Flat: all leaves in one plane, no skeleton.
        let mut flat = ball_tree(0);
        flat.branches.clear();
        flat.leaves = (0..100)
            .map(|i| leaf(Vec3::new((i % 10) as f32, 1.0, (i / 10) as f32)))
            .collect();
        let opts = HullOptions {
            iou_views: 4,
            ..HullOptions::default()
        };
        let (body, rep) = bake_hulls(&flat, &opts).unwrap();
        assert_eq!(rep.source, FeatureSource::LeafCentres);
        assert!(
            rep.levels.iter().all(|l| l.method != HullMethod::Reconstruction),
            "{rep:?}"
        );
        assert_eq!(rep.levels[0].method, HullMethod::BoundingBox);
        decode_hulls(&body.bytes).unwrap();
        // Few tips: convex hull.
        let (_, rep) = bake_hulls(&ball_tree(10), &opts).unwrap();
        assert!(rep.levels.iter().all(|l| l.method == HullMethod::ConvexHull), "{rep:?}");
        // Nothing at all.
        let mut empty = ball_tree(0);
        empty.branches.clear();
        let (body, rep) = bake_hulls(&empty, &opts).unwrap();
        assert_eq!(rep.source, FeatureSource::None);
        assert_eq!(body.item_count, 3);
        assert!(
            bake_hulls(
                &empty,
                &HullOptions {
                    budgets: vec![4],
                    ..opts
                }
            )
            .is_err()
        );
    }
}
