//! `eval-clouds`: the billboard-cloud levels of a `.ctree` against the full tree, beside the other
//! stand-ins a client can fetch instead (VMI prefixes, the hemi-octahedral billboard, the crown
//! hulls), at each level's distance: bytes against quality.
//!
//! **Distances.** Level i is meant from its switch distance σ_i, where ε_i subtends
//! `pixel_error` pixels on a screen `screen_height` pixels high with vertical field of view
//! `fov_y` ([`CloudLevel::switch_distance`]; the bake's defaults). Each level is evaluated at
//! `σ_i · f` for every factor f of `distance_factors`: f = 1 is the level's own distance, f < 1
//! is nearer than it is meant for (where billboard clouds fail: parallax between planes and
//! magnified texels). Distances are clamped to at least 1.2 bounding radii.
//!
//! **Images.** At distance D the image is the screen's crop around the tree: a perspective view
//! of the bounding sphere (field of view `2·asin(r/D)`) at the screen's pixel density, so the
//! resolution is the tree's size in pixels there (clamped to `16..=max_resolution`). Views are
//! [`crate::eval::eval_directions`]. Each method is rendered with the shared CPU rasterizer:
//!
//! - reference: the full tree (leaves with the alpha-tested leaf texture, bark tubes), lit;
//! - cloud level: its quads with their textures, alpha-tested, unlit (the textures are lit renders);
//! - VMI prefix at rate R: the file's first `round(n·(1 − R))` leaves of every node, lit;
//! - hemi-oct billboard: the frame nearest to the view direction (largest blend weight) as a quad
//!   facing that frame's direction, textured, unlit (a client blends three; one is the lower bound);
//! - hull level k: the mesh in the first leaf material's colour, lit.
//!
//! **Figures** (means over views): coverage precision / recall of "anything drawn" masks, the
//! same with a 1-pixel tolerance ([`tolerant_coverage`]), and colour SSIM over a grey background
//! (`canopy_shared::metrics`). SSIM compares methods at one distance; across distances it is not
//! comparable (a large near image is mostly smooth regions and scores higher). Up close, the
//! tolerant precision and recall are what show a cloud's failure: leaves drawn up to ε away from
//! where they are. **Bytes** are what a client
//! fetches for that stand-in of one tree: cloud level = cloud table + the level's textures;
//! prefix = header + directory + node table + materials + skeleton + bark mesh + the leaf bands
//! that hold the prefix; billboard = atlas table + one frame at the smallest stored resolution
//! at least as large as the image (else the largest); hull = hull table + the level.

use std::path::{Path, PathBuf};

use canopy_shared::chart::{ChartError, LineChart, Series, write_line_chart};
use canopy_shared::format::atlas::{AtlasLayoutKind, AtlasTable, decode_png_frame, hemi_oct_blend};
use canopy_shared::format::cloud::{CLOUD_QUAD_UVS, CloudLevel, CloudQuad, CloudTable, decode_clouds};
use canopy_shared::format::directory::SectionKind;
use canopy_shared::format::hull::{HullMesh, HullTable, decode_hulls};
use canopy_shared::format::leaf::{BandLayout, keep_count};
use canopy_shared::format::tree::section_bytes;
use canopy_shared::format::{DecodedTree, FormatError, HEADER_LEN};
use canopy_shared::metrics;
use canopy_shared::raster::{
    Camera, FULL_COVERAGE, Filter, Frame, QuadBatch, RasterError, RasterMaterial, RasterMesh, RenderOptions, Scene,
    Texture, Wrap, render,
};
use glam::Vec3;
use rayon::prelude::*;
use serde::Serialize;

use crate::eval::{EvalError, eval_directions, flatten, render_tree};

/// Options of [`eval_clouds`].
#[derive(Debug, Clone)]
pub struct CloudEvalOptions {
    /// Views per distance.
    pub views: usize,
    /// Multiples of each level's switch distance to evaluate at (1 = its own; < 1 nearer).
    pub distance_factors: Vec<f32>,
    /// Screen pixels ε_i subtends at σ_i.
    pub pixel_error: f32,
    /// Screen height, pixels.
    pub screen_height: f32,
    /// Vertical field of view, radians.
    pub fov_y: f32,
    /// Largest image side.
    pub max_resolution: u32,
    /// VMI-prefix rates to compare with.
    pub rates: Vec<f32>,
}

impl Default for CloudEvalOptions {
    fn default() -> Self {
        let c = crate::bake::cloud::CloudOptions::default();
        Self {
            views: 8,
            distance_factors: vec![1.0, 0.25],
            pixel_error: c.pixel_error,
            screen_height: c.screen_height,
            fov_y: c.fov_y,
            max_resolution: 1024,
            rates: vec![0.5, 0.9, 0.98],
        }
    }
}

/// Why the evaluation failed.
#[derive(Debug, thiserror::Error)]
pub enum CloudEvalError {
    /// The file has no billboard clouds.
    #[error("the file has no billboard clouds (bake without --no-clouds)")]
    NoClouds,
    /// A bad option.
    #[error("invalid option: {0}")]
    Options(String),
    /// A section (the billboard clouds included) failed to decode.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// Rendering failed.
    #[error(transparent)]
    Raster(#[from] RasterError),
    /// A metric failed.
    #[error(transparent)]
    Metrics(#[from] metrics::MetricsError),
    /// The shared evaluation helpers failed.
    #[error(transparent)]
    Eval(#[from] EvalError),
}

/// One method at one distance, means over views.
#[derive(Debug, Clone, Serialize)]
pub struct MethodRow {
    /// `cloud`, `vmi_prefix`, `hemi_oct`, `hull`.
    pub method: &'static str,
    /// Cloud level (1-based), rate, hull level: what distinguishes rows of one method.
    pub variant: String,
    /// Bytes a client fetches for this stand-in.
    pub bytes: u64,
    /// Planes (clouds), leaves (prefixes), triangles (hulls), image side (billboard).
    pub size: u64,
    /// Colour SSIM.
    pub ssim: f64,
    /// Coverage precision.
    pub coverage_precision: f64,
    /// Coverage recall.
    pub coverage_recall: f64,
    /// Coverage precision with a 1-pixel tolerance ([`tolerant_coverage`]).
    pub tolerant_precision: f64,
    /// Coverage recall with a 1-pixel tolerance.
    pub tolerant_recall: f64,
}

/// All methods at one distance.
#[derive(Debug, Clone, Serialize)]
pub struct DistanceReport {
    /// The cloud level whose switch distance this is (1-based).
    pub level: usize,
    /// Multiple of its switch distance.
    pub factor: f32,
    /// Distance to the tree centre, metres.
    pub distance: f32,
    /// Image side, pixels (the tree's size on screen there).
    pub resolution: u32,
    /// Rows: the level's cloud first, then every other method.
    pub rows: Vec<MethodRow>,
}

/// The whole report.
#[derive(Debug, Clone, Serialize)]
pub struct CloudEvalReport {
    /// Tree name.
    pub name: String,
    /// Leaves.
    pub leaves: u64,
    /// Views per distance.
    pub views: usize,
    /// Per level: (ε, switch distance, planes, bytes).
    pub levels: Vec<LevelSummary>,
    /// One entry per (level, factor).
    pub distances: Vec<DistanceReport>,
}

/// Table figures of one level.
#[derive(Debug, Clone, Serialize)]
pub struct LevelSummary {
    /// Level (1-based).
    pub level: usize,
    /// ε_i, metres.
    pub epsilon: f32,
    /// Switch distance σ_i, metres.
    pub switch_distance: f32,
    /// Planes.
    pub planes: u32,
    /// Cloud table + the level's textures.
    pub bytes: u64,
}

/// Textured quads, unlit, alpha-tested: a cloud level or a billboard.
struct QuadSet {
    batch: QuadBatch,
}

impl QuadSet {
    fn new(quads: &[(CloudQuad, image::RgbaImage)]) -> Result<Self, RasterError> {
        let mut batch = QuadBatch::default();
        for (q, img) in quads {
            let mut t = Texture::from_image(img)?;
            t.filter = Filter::Bilinear;
            t.wrap = Wrap::Clamp;
            let t = batch.add_texture(t);
            batch.push(t, q.corners(), CLOUD_QUAD_UVS, q.normal, FULL_COVERAGE);
        }
        Ok(Self { batch })
    }

    fn render(&self, cam: &Camera, res: u32) -> Result<Frame, RasterError> {
        render(&self.batch.scene(), cam, res, res, &RenderOptions::unlit())
    }
}

/// Writes one chart per distance of `report` into `dir`: colour SSIM against the bytes a client
/// fetches (log), a line per method (cloud level, hemi-octahedral frame, hull levels, VMI
/// prefixes, each sorted by bytes): where a cloud level sits on the bytes-versus-quality chart.
/// Files: `<tree>-L<level>-x<factor>.png` and `.svg` (factor `0_25` for 0.25). Returns the
/// paths written.
pub fn write_charts(report: &CloudEvalReport, dir: &Path) -> Result<Vec<PathBuf>, ChartError> {
    let mut files = Vec::new();
    for dr in &report.distances {
        let mut series: Vec<Series> = Vec::new();
        for r in &dr.rows {
            let name = match r.method {
                "cloud" => format!("cloud level {}", dr.level),
                "hemi_oct" => "hemi-oct frame".to_string(),
                "hull" => "hull levels".to_string(),
                "vmi_prefix" => "VMI prefixes".to_string(),
                m => m.to_string(),
            };
            let point = (r.bytes.max(1) as f64, r.ssim);
            match series.iter_mut().find(|s| s.name == name) {
                Some(s) => s.points.push(point),
                None => series.push(Series {
                    name,
                    points: vec![point],
                }),
            }
        }
        for s in &mut series {
            s.points.sort_by(|a, b| a.0.total_cmp(&b.0));
        }
        let title = format!(
            "{}: cloud level {} at {:.0} m (x{}), {} px",
            report.name, dr.level, dr.distance, dr.factor, dr.resolution
        );
        // No '.' in the stem: the chart writer sets the extension.
        let factor = format!("{}", dr.factor).replace('.', "_");
        let stem = dir.join(format!("{}-L{}-x{factor}", report.name, dr.level));
        files.extend(write_line_chart(
            &stem,
            &LineChart {
                title: &title,
                x_label: "bytes fetched for one tree (log)",
                y_label: "SSIM vs full tree",
                series: &series,
                log_x: true,
            },
        )?);
    }
    Ok(files)
}

/// Coverage precision and recall with a 1-pixel tolerance on square `side²` masks: an
/// approximation pixel counts as right when the reference covers any pixel of its 3 × 3
/// neighbourhood, a reference pixel as found when the approximation does. Why: far away, leaves
/// are a pixel or two and a stand-in resampled from a texture lands them a pixel off; exact
/// coverage calls that a miss and a false positive at once.
pub fn tolerant_coverage(reference: &[bool], approx: &[bool], side: usize) -> (f64, f64) {
    let dilate = |m: &[bool]| -> Vec<bool> {
        let mut out = vec![false; m.len()];
        for y in 0..side {
            for x in 0..side {
                if m[y * side + x] {
                    for yy in y.saturating_sub(1)..(y + 2).min(side) {
                        for xx in x.saturating_sub(1)..(x + 2).min(side) {
                            out[yy * side + xx] = true;
                        }
                    }
                }
            }
        }
        out
    };
    let (dr, da) = (dilate(reference), dilate(approx));
    let ratio = |n: usize, d: usize| if d == 0 { 1.0 } else { n as f64 / d as f64 };
    let a = approx.iter().filter(|&&v| v).count();
    let r = reference.iter().filter(|&&v| v).count();
    let a_ok = approx.iter().zip(&dr).filter(|(a, d)| **a && **d).count();
    let r_ok = reference.iter().zip(&da).filter(|(r, d)| **r && **d).count();
    (ratio(a_ok, a), ratio(r_ok, r))
}

fn hull_mesh(h: &HullMesh) -> RasterMesh {
    RasterMesh {
        positions: h.positions.clone(),
        indices: h.indices.clone(),
        item_of_triangle: vec![0; h.triangle_count()],
        ..RasterMesh::default()
    }
}

/// The camera at distance `dist` from `center` along `dir` whose image just holds the sphere.
fn camera_at(center: Vec3, radius: f32, dir: Vec3, dist: f32) -> Camera {
    let fov = 2.0 * (radius / dist).clamp(1e-4, 0.999).asin();
    Camera::orbit_perspective(center, radius, dir, fov)
}

/// Image side at distance `dist`: the sphere's size on the screen of `opts`.
fn resolution_at(radius: f32, dist: f32, opts: &CloudEvalOptions) -> u32 {
    let half = (radius / dist).clamp(1e-4, 0.999).asin();
    let px = opts.screen_height * half.tan() / (0.5 * opts.fov_y).tan();
    (px.ceil() as u32).clamp(16, opts.max_resolution.max(16))
}

/// Bytes of the geometry a client fetches for a uniform rate: header, directory, node table,
/// materials, skeleton, bark mesh and the leaf bands that hold every node's prefix.
fn prefix_bytes(tree: &DecodedTree, rate: f32) -> u64 {
    let d = &tree.directory;
    let len = |k: SectionKind| d.section(k).map_or(0, |e| e.length);
    let counts: Vec<u32> = tree.node_leaves.iter().map(|v| v.len() as u32).collect();
    let layout = BandLayout::new(&d.band_edges, &counts);
    let bands = counts
        .iter()
        .map(|&n| layout.bands_for_keep(n, keep_count(n, rate)))
        .max()
        .unwrap_or(0);
    let leaves = if bands == 0 {
        0
    } else {
        layout.band_range(bands - 1).end
    };
    HEADER_LEN as u64
        + u64::from(tree.header.directory_len)
        + len(SectionKind::NodeTable)
        + len(SectionKind::Materials)
        + len(SectionKind::Skeleton)
        + len(SectionKind::BarkMesh)
        + leaves
}

/// Renders needed by [`eval_clouds`] (for a progress bar).
pub fn render_count(levels: usize, hulls: usize, opts: &CloudEvalOptions) -> u64 {
    (levels * opts.distance_factors.len() * opts.views * (3 + opts.rates.len() + hulls)) as u64
}

/// Evaluates every cloud level of `file` (bytes of a whole `.ctree`, decoded as `tree`) at its
/// distances beside the other stand-ins. `tick` is called once per view and method.
pub fn eval_clouds(
    file: &[u8],
    tree: &DecodedTree,
    opts: &CloudEvalOptions,
    tick: &(dyn Fn() + Sync),
) -> Result<CloudEvalReport, CloudEvalError> {
    if opts.views == 0 || opts.distance_factors.iter().any(|f| !(*f > 0.0 && f.is_finite())) {
        return Err(CloudEvalError::Options("views ≥ 1 and distance factors > 0".into()));
    }
    if let Some(r) = opts.rates.iter().find(|r| !(0.0..1.0).contains(*r)) {
        return Err(CloudEvalError::Options(format!("rate {r} not in [0, 1)")));
    }
    let dir = &tree.directory;
    let sec = |k: SectionKind| -> Result<&[u8], FormatError> {
        let e = dir.section(k).ok_or_else(|| FormatError::Invalid {
            what: "section table",
            detail: format!("no {} section", k.name()),
        })?;
        section_bytes(file, e)
    };
    let cloud_sec = sec(SectionKind::BillboardClouds)?;
    let clouds = decode_clouds(cloud_sec)?;
    if clouds.levels.is_empty() {
        return Err(CloudEvalError::NoClouds);
    }
    let cloud_table_len = CloudTable::table_len(clouds.levels.len(), clouds.planes.len()) as u64;
    let level_quads: Vec<QuadSet> = (0..clouds.levels.len())
        .map(|k| -> Result<QuadSet, CloudEvalError> {
            let planes = clouds.level_planes(k);
            let quads = planes
                .iter()
                .enumerate()
                .map(|(j, p)| {
                    let i = clouds.levels[k].first_plane as usize + j;
                    Ok((
                        p.quad,
                        CloudTable::decode_texture(p, clouds.texture_bytes(cloud_sec, i)?)?,
                    ))
                })
                .collect::<Result<Vec<_>, FormatError>>()?;
            Ok(QuadSet::new(&quads)?)
        })
        .collect::<Result<_, _>>()?;

    let hull_sec = sec(SectionKind::Hulls)?;
    let hulls: Vec<(HullMesh, u64)> = if hull_sec.is_empty() {
        Vec::new()
    } else {
        let (t, meshes) = decode_hulls(hull_sec)?;
        let tl = HullTable::table_len(t.levels.len()) as u64;
        meshes
            .into_iter()
            .zip(&t.levels)
            .map(|(m, e)| (m, tl + u64::from(e.length)))
            .collect()
    };
    let leaf_color = tree.materials.leaf.first().map_or([0.2, 0.4, 0.1, 1.0], |m| m.color);
    let hull_material = [RasterMaterial {
        color: leaf_color,
        texture: None,
        alpha_cutoff: 0.0,
        double_sided: true,
        coverage: FULL_COVERAGE,
    }];
    let hull_meshes: Vec<RasterMesh> = hulls.iter().map(|(m, _)| hull_mesh(m)).collect();

    let atlas_sec = sec(SectionKind::BillboardAtlases)?;
    let atlas = if atlas_sec.is_empty() {
        None
    } else {
        let t = AtlasTable::decode(atlas_sec, atlas_sec.len() as u64)?;
        t.layouts
            .iter()
            .find(|l| l.kind == AtlasLayoutKind::HemiOctahedral)
            .copied()
            .map(|l| (t, l))
    };

    let (model, lists) = flatten(tree);
    let center = clouds.center;
    let radius = clouds.radius;
    let dirs = eval_directions(opts.views);

    let mut distances = Vec::new();
    for (k, level) in clouds.levels.iter().enumerate() {
        let sigma = level.switch_distance(opts.pixel_error, opts.screen_height, opts.fov_y);
        for &f in &opts.distance_factors {
            let dist = (sigma * f).max(1.2 * radius);
            let res = resolution_at(radius, dist, opts);
            let cams: Vec<Camera> = dirs.iter().map(|&d| camera_at(center, radius, d, dist)).collect();
            let refs: Vec<Frame> = cams
                .par_iter()
                .map(|c| {
                    let r = render_tree(&model, None, 1.0, c, res);
                    tick();
                    r
                })
                .collect::<Result<_, _>>()?;
            let score = |frames: Vec<Frame>| -> Result<[f64; 5], CloudEvalError> {
                let mut acc = [0f64; 5];
                for (r, a) in refs.iter().zip(&frames) {
                    let (rc, ac) = (r.coverage(), a.coverage());
                    let cov = metrics::coverage(&rc, &ac)?;
                    let (tp, tr) = tolerant_coverage(&rc, &ac, res as usize);
                    acc[0] += metrics::ssim_rgba(&r.color, &a.color, res, res, [128, 128, 128])?;
                    acc[1] += cov.precision;
                    acc[2] += cov.recall;
                    acc[3] += tp;
                    acc[4] += tr;
                }
                let n = frames.len().max(1) as f64;
                Ok(acc.map(|v| v / n))
            };
            let row = |method, variant: String, bytes, size, s: [f64; 5]| MethodRow {
                method,
                variant,
                bytes,
                size,
                ssim: s[0],
                coverage_precision: s[1],
                coverage_recall: s[2],
                tolerant_precision: s[3],
                tolerant_recall: s[4],
            };
            let mut rows = Vec::new();
            // The level's own cloud.
            let frames = cams
                .par_iter()
                .map(|c| {
                    let r = level_quads[k].render(c, res);
                    tick();
                    r
                })
                .collect::<Result<Vec<_>, _>>()?;
            rows.push(row(
                "cloud",
                format!("level {}", k + 1),
                cloud_table_len + u64::from(level.textures.length),
                u64::from(level.plane_count),
                score(frames)?,
            ));
            for &rate in &opts.rates {
                let subset: Vec<u32> = lists
                    .iter()
                    .flat_map(|l| l[..keep_count(l.len() as u32, rate) as usize].iter().copied())
                    .collect();
                let frames = cams
                    .par_iter()
                    .map(|c| {
                        let r = render_tree(&model, Some(&subset), 1.0, c, res);
                        tick();
                        r
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                rows.push(row(
                    "vmi_prefix",
                    format!("rate {rate}"),
                    prefix_bytes(tree, rate),
                    subset.len() as u64,
                    score(frames)?,
                ));
            }
            if let Some((t, layout)) = &atlas {
                let side = u32::from(layout.cols);
                let r_idx = t.resolutions.iter().rposition(|&s| u32::from(s) >= res).unwrap_or(0);
                let mut frames = Vec::with_capacity(cams.len());
                let mut bytes = 0u64;
                for (c, &d) in cams.iter().zip(&dirs) {
                    let blend = hemi_oct_blend(d, side);
                    let best = blend.iter().max_by(|a, b| a.1.total_cmp(&b.1)).map_or(0, |w| w.0);
                    let frame = layout.first_frame + best;
                    let f = match t.image_bytes(atlas_sec, frame, r_idx)? {
                        Some(img) => {
                            bytes += img.len() as u64;
                            let img = decode_png_frame(img, t.resolutions[r_idx])?;
                            let fd = t.frame_direction(frame).unwrap_or(Vec3::Y);
                            QuadSet::new(&[(billboard_quad(t.center, t.radius, fd), img)])?.render(c, res)?
                        }
                        None => QuadSet::new(&[])?.render(c, res)?,
                    };
                    tick();
                    frames.push(f);
                }
                let tl = AtlasTable::table_len(
                    t.resolutions.len(),
                    t.layouts.len(),
                    t.view_angles.len(),
                    t.frames.len(),
                ) as u64;
                rows.push(row(
                    "hemi_oct",
                    format!("{}² nearest frame", t.resolutions[r_idx]),
                    tl + bytes / cams.len().max(1) as u64,
                    u64::from(t.resolutions[r_idx]),
                    score(frames)?,
                ));
            }
            for (h, ((m, bytes), mesh)) in hulls.iter().zip(&hull_meshes).enumerate() {
                let scene = Scene::single(mesh, &hull_material, &[]);
                let frames = cams
                    .par_iter()
                    .map(|c| {
                        let r = render(&scene, c, res, res, &RenderOptions::default());
                        tick();
                        r
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                rows.push(row(
                    "hull",
                    format!("level {h}"),
                    *bytes,
                    m.triangle_count() as u64,
                    score(frames)?,
                ));
            }
            distances.push(DistanceReport {
                level: k + 1,
                factor: f,
                distance: dist,
                resolution: res,
                rows,
            });
        }
    }
    let levels = clouds
        .levels
        .iter()
        .enumerate()
        .map(|(k, l): (usize, &CloudLevel)| LevelSummary {
            level: k + 1,
            epsilon: l.epsilon,
            switch_distance: l.switch_distance(opts.pixel_error, opts.screen_height, opts.fov_y),
            planes: l.plane_count,
            bytes: cloud_table_len + u64::from(l.textures.length),
        })
        .collect();
    Ok(CloudEvalReport {
        name: dir.name.clone(),
        leaves: model.leaves.len() as u64,
        views: opts.views,
        levels,
        distances,
    })
}

/// The quad of an atlas frame seen from `d`: the framing sphere's square, perpendicular to `d`,
/// oriented like the frame's camera (up hint +Y, +Z near the poles).
fn billboard_quad(center: Vec3, radius: f32, d: Vec3) -> CloudQuad {
    let d = d.normalize_or(Vec3::Y);
    let up = if d.y.abs() > 0.999_999 { Vec3::Z } else { Vec3::Y };
    let v = (up - d * d.dot(up)).normalize();
    let u = v.cross(d);
    let origin = center - (u + v) * radius;
    CloudQuad {
        normal: d,
        d: d.dot(origin),
        origin,
        edge_u: u * 2.0 * radius,
        edge_v: v * 2.0 * radius,
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::bake::cloud::{CloudOptions, leaf_ball};
    use crate::bake::hull::HullOptions;
    use crate::bake::{BakeOptions, bake_model};
    use canopy_shared::format::{LeafOrder, encode_tree};

    #[test]
    fn clouds_fail_up_close_and_the_report_says_so() {
        let model = leaf_ball(1500, 0.2, 21);
        let opts = BakeOptions {
            order: LeafOrder::Random,
            atlas: None,
            hull: Some(HullOptions {
                iou_views: 2,
                iou_size: 16,
                ..HullOptions::default()
            }),
            cloud: Some(CloudOptions {
                levels: 2,
                max_texture: 96,
                ..CloudOptions::default()
            }),
            ..BakeOptions::default()
        };
        let (baked, _) = bake_model(&model, &opts).unwrap();
        let file = encode_tree(&baked).unwrap();
        let tree = DecodedTree::decode(&file).unwrap();
        let eopts = CloudEvalOptions {
            views: 3,
            distance_factors: vec![1.0, 0.05],
            rates: vec![0.9],
            max_resolution: 256,
            ..CloudEvalOptions::default()
        };
        let rep = eval_clouds(&file, &tree, &eopts, &|| ()).unwrap();
        assert_eq!(rep.levels.len(), 2);
        assert_eq!(rep.distances.len(), 4);
        let cloud = |level: usize, factor: f32| -> MethodRow {
            let d = rep
                .distances
                .iter()
                .find(|d| d.level == level && d.factor == factor)
                .unwrap();
            d.rows.iter().find(|r| r.method == "cloud").unwrap().clone()
        };
        for level in [1, 2] {
            let (far, near) = (cloud(level, 1.0), cloud(level, 0.05));
            // Up close the parallax between a leaf and its plane (up to ε) is many pixels: the
            // cloud draws leaves where the tree has none and misses where it has them, beyond
            // the 1-pixel tolerance. (SSIM is not compared: it rises with image size here, the
            // near image being mostly smooth leaf and background.)
            assert!(
                near.tolerant_recall < far.tolerant_recall - 0.03 && near.tolerant_precision < far.tolerant_precision,
                "level {level}: near {near:?} far {far:?}"
            );
            for r in [&far, &near] {
                assert!((0.0..=1.0).contains(&r.coverage_precision) && (0.0..=1.0).contains(&r.coverage_recall));
            }
        }
        // Every other stand-in present in the file is reported beside the cloud.
        let d = &rep.distances[0];
        assert!(d.rows.iter().any(|r| r.method == "vmi_prefix"));
        assert_eq!(d.rows.iter().filter(|r| r.method == "hull").count(), 3);
        assert!(d.resolution < rep.distances[1].resolution);
        // One chart per distance, PNG and SVG, each with a line per method.
        let dir = std::env::temp_dir().join(format!("canopy-cloud-charts-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let files = write_charts(&rep, &dir).unwrap();
        assert_eq!(files.len(), 2 * rep.distances.len());
        assert!(files.iter().any(|f| f.ends_with("ball-L1-x0_05.svg")), "{files:?}");
        for f in &files {
            assert!(std::fs::metadata(f).unwrap().len() > 1000, "{}", f.display());
        }
        let svg = std::fs::read_to_string(
            files
                .iter()
                .find(|f| f.extension().is_some_and(|e| e == "svg"))
                .unwrap(),
        )
        .unwrap();
        for name in ["cloud level 1", "hull levels", "VMI prefixes"] {
            assert!(svg.contains(name), "{name} missing from the chart");
        }
        let _ = std::fs::remove_dir_all(&dir);
        // A file without clouds is an error, not an empty report.
        let (mut plain, _) = bake_model(
            &model,
            &BakeOptions {
                cloud: None,
                atlas: None,
                hull: None,
                order: LeafOrder::Random,
                ..BakeOptions::default()
            },
        )
        .unwrap();
        plain.clouds = canopy_shared::format::SectionBody::default();
        let file = encode_tree(&plain).unwrap();
        let tree = DecodedTree::decode(&file).unwrap();
        assert!(matches!(
            eval_clouds(&file, &tree, &eopts, &|| ()),
            Err(CloudEvalError::NoClouds)
        ));
    }
}
