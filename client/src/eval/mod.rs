//! Evaluation: render what a client draws with the shared CPU rasterizer and compare it with the
//! full-detail scene (SSIM, perceptual FLIP error, both also per distance band, coverage
//! precision/recall, popping), and show it: image strips ([`strip`]) and an HTML report
//! ([`report`]).
//!
//! What is drawn for each tree comes from a [`crate::stream::DrawnTree`] list (the streamer's
//! record of what it drew from its cache). The geometry itself is taken from the model files
//! decoded whole: a drawn prefix of `k` leaves is the first `k` leaves of the node in the file,
//! byte for byte what the client's cached, CRC-checked blocks hold. Leaf textures are the bake's
//! procedural leaf mask, so billboards (baked with it) and geometry look alike.
//!
//! Rendering: one lit pass for geometry and hulls, one unlit pass for billboards (their images
//! already carry the bake's lighting), composited by depth. The rasterizer does not blend:
//! billboards draw the frame of largest weight (the GPU viewer blends up to three), and two
//! cross-fading cloud levels split the pixels with complementary 4 × 4 screen-door ranges (the
//! rasterizer's [`RasterMaterial::coverage`]), exactly as the viewer does.
//!
//! Conventions: world axes as the streamer's (Y up, metres, radians); images are sRGB RGBA,
//! row 0 at the top. The rendering itself is in `render.rs`.

use std::collections::HashMap;
use std::sync::OnceLock;

use canopy_shared::format::atlas::{AtlasTable, decode_png_frame};
use canopy_shared::format::cloud::{CloudQuad, CloudTable, decode_clouds};
use canopy_shared::format::directory::SectionKind;
use canopy_shared::format::hull::decode_hulls;
use canopy_shared::format::tree::{DecodedTree, section_bytes};
use canopy_shared::metrics::{DEFAULT_PIXELS_PER_DEGREE, coverage, flip, flip_rgba, ssim_maps_rgba, ssim_rgba};
use canopy_shared::model::TreeModel;
use canopy_shared::raster::{FULL_COVERAGE, Filter, RasterMaterial, RasterMesh, Texture, Wrap, tree_materials};
use canopy_shared::tessellate::{TubeOptions, branch_tubes_thicker_than};
use glam::Vec3;

use crate::stream::DrawnTree;

mod bands;
mod discrete;
pub mod redundancy;
mod render;
pub mod report;
pub mod strip;
pub use bands::{BANDS, Band, BandMap, BandScore, MID_MIN_PX, NEAR_MIN_PX, band_scores, projected_px};
pub use discrete::{DiscreteFiles, WholeFile};
pub use render::{RENDER_PASS_TRIANGLES, RenderMode, View, billboard_quad, render_view, render_view_with_trees};

/// Background the images are composited over for SSIM and popping (a pale sky).
pub const BACKGROUND: [u8; 3] = [200, 220, 240];
/// Colour of the terrain (linear RGB, as the viewer's ground).
pub const TERRAIN_COLOR: [f32; 4] = [0.16, 0.22, 0.08, 1.0];
/// Item of the terrain's pixels in a render (not a tree: [`View::covered`] leaves them out).
pub const TERRAIN_ITEM: u32 = u32::MAX - 2;
use crate::lod::bark::EVAL_BARK_SIDES;
pub use crate::lod::bark::{BARK_MIN_PIXELS, BARK_MIN_RADII};
/// Cap of the seed 004 leaf enlargement when drawing simplified nodes.
pub const ENLARGEMENT_CAP: f32 = 2.0;

/// Largest enlargement of a geometry tree's kept leaves: the pixel-scale budget's cap
/// ([`Drawn::Geometry`]'s `enlargement_cap`, 1 when off), raised to [`ENLARGEMENT_CAP`] when
/// seed 004's enlargement is asked for everywhere (`enlarge`).
pub fn enlargement_cap(enlarge: bool, budget_cap: f32) -> f32 {
    let budget_cap = if budget_cap.is_finite() {
        budget_cap.max(1.0)
    } else {
        1.0
    };
    if enlarge {
        budget_cap.max(ENLARGEMENT_CAP)
    } else {
        budget_cap
    }
}

/// Why evaluation failed.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// A model file did not decode.
    #[error("model {0}: {1}")]
    Model(String, canopy_shared::format::FormatError),
    /// Rendering failed.
    #[error(transparent)]
    Raster(#[from] canopy_shared::raster::RasterError),
    /// A metric failed.
    #[error(transparent)]
    Metrics(#[from] canopy_shared::metrics::MetricsError),
    /// Writing a strip or a report failed.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// A strip's inputs disagree.
    #[error("image strip: {0}")]
    Strip(String),
}

/// How a method picks the leaves of a simplified node.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LeafChoice {
    /// The first `k` in the file's order (VMI for a default bake).
    Prefix,
    /// `k` leaves chosen at random (seeded by instance and node): what a file in random order
    /// would give for the same bytes.
    Random,
}

/// One model decoded for rendering.
#[derive(Debug)]
pub struct EvalModel {
    tree: DecodedTree,
    /// Bark meshes without twigs thinner than [`BARK_MIN_RADII`]`[i]` metres.
    bark: Vec<RasterMesh>,
    /// Per iteration `k` below the last, the bark of the skeleton iterations `0..=k` per
    /// variant (seed 000's middle level), built on first use.
    bark_through: Vec<[OnceLock<RasterMesh>; BARK_MIN_RADII.len()]>,
    mat_offset: u16,
    hulls: Vec<RasterMesh>,
    atlas: Option<(AtlasTable, Vec<u8>)>,
    /// Billboard-cloud table and section bytes (`None`: no levels baked).
    clouds: Option<(CloudTable, Vec<u8>)>,
    /// Triangles at full detail (bark + 2 per leaf).
    pub full_triangles: u64,
    /// Every leaf, in file order: the mesh all full-detail instances share (built on first use).
    full_leaves: OnceLock<RasterMesh>,
}

impl EvalModel {
    /// The model's last iteration.
    pub fn last_iteration(&self) -> u8 {
        self.tree.directory.iteration_table.len().saturating_sub(1) as u8
    }

    /// Bark variant `variant` of the skeleton iterations `0..=k` (every iteration from the
    /// last on).
    fn bark_through(&self, k: u8, variant: usize) -> &RasterMesh {
        let variant = variant.min(BARK_MIN_RADII.len() - 1);
        let Some(slot) = self.bark_through.get(usize::from(k)) else {
            return &self.bark[variant];
        };
        slot[variant].get_or_init(|| {
            let table = &self.tree.directory.iteration_table;
            let end = table.get(usize::from(k)).map_or(0, |e| e.branches_end as usize);
            let mut model = empty_model(&self.tree);
            model.branches.truncate(end);
            let tubes = branch_tubes_thicker_than(
                &model,
                TubeOptions {
                    sides: EVAL_BARK_SIDES,
                    caps: false,
                },
                BARK_MIN_RADII[variant],
            );
            RasterMesh::from_bark(&[&tubes, &model.bark_mesh], self.mat_offset)
        })
    }
}

/// Every model of a scene, decoded, with the shared material table.
#[derive(Debug, Default)]
pub struct EvalScene {
    models: Vec<Option<EvalModel>>,
    materials: Vec<RasterMaterial>,
    textures: Vec<Texture>,
    billboard_textures: HashMap<(usize, u32, u8), Texture>,
    /// Cloud plane textures by (model, plane).
    cloud_textures: HashMap<(usize, u32), Texture>,
    /// The scene's terrain as one mesh (material and item set), drawn under every view.
    terrain: Option<RasterMesh>,
}

fn empty_model(tree: &DecodedTree) -> TreeModel {
    TreeModel {
        name: tree.directory.name.clone(),
        branches: tree.branches.clone(),
        leaves: Vec::new(),
        bark_mesh: tree.bark_mesh.clone(),
        materials: tree.materials.clone(),
        iterations: tree.directory.iterations,
        source: tree.directory.source,
    }
}

impl EvalScene {
    /// An empty scene with room for `models` models.
    pub fn new(models: usize) -> Self {
        Self {
            models: (0..models).map(|_| None).collect(),
            materials: Vec::new(),
            textures: vec![Texture::procedural_leaf(32)],
            billboard_textures: HashMap::new(),
            cloud_textures: HashMap::new(),
            terrain: None,
        }
    }

    /// Draws `ground` (the scene's whole terrain) under every view; `None`: no ground drawn.
    pub fn set_terrain(&mut self, ground: Option<&canopy_shared::terrain::Heightfield>) {
        self.terrain = ground.map(|h| {
            let material = self.materials.len() as u16;
            self.materials.push(RasterMaterial {
                color: TERRAIN_COLOR,
                double_sided: false,
                ..RasterMaterial::default()
            });
            let held = crate::terrain::HeldTerrain::from_heightfield(h);
            let mut mesh = RasterMesh::default();
            for (_, tile) in held.held_tiles() {
                let t = crate::terrain::tile_mesh(&h.grid, tile);
                let base = mesh.positions.len() as u32;
                mesh.positions.extend(t.positions);
                mesh.normals.extend(t.normals);
                mesh.indices.extend(t.indices.iter().map(|i| i + base));
            }
            let n = mesh.indices.len() / 3;
            mesh.item_of_triangle = vec![TERRAIN_ITEM; n];
            mesh.material_of_triangle = vec![material; n];
            mesh
        });
    }

    /// The terrain's mesh, when set.
    pub(crate) fn terrain(&self) -> Option<&RasterMesh> {
        self.terrain.as_ref()
    }

    /// Whether model `m` is loaded.
    pub fn has(&self, m: usize) -> bool {
        self.models.get(m).is_some_and(Option::is_some)
    }

    /// Decodes model `m` from its whole file.
    pub fn load(&mut self, m: usize, name: &str, bytes: &[u8]) -> Result<(), EvalError> {
        let tree = DecodedTree::decode(bytes).map_err(|e| EvalError::Model(name.into(), e))?;
        let model = empty_model(&tree);
        let mat_offset = self.materials.len() as u16;
        let mats = tree_materials(&model, &vec![Some(0); model.materials.leaf.len()]);
        let crown = {
            let n = tree.materials.leaf.len().max(1) as f32;
            let mut c = [0.0f32; 4];
            for l in &tree.materials.leaf {
                for (a, b) in c.iter_mut().zip(l.color) {
                    *a += b / n;
                }
            }
            RasterMaterial {
                color: [c[0], c[1], c[2], 1.0],
                texture: None,
                alpha_cutoff: 0.0,
                double_sided: false,
                coverage: FULL_COVERAGE,
            }
        };
        let crown_index = mat_offset + mats.len() as u16;
        self.materials.extend(mats);
        self.materials.push(crown);
        let bark: Vec<RasterMesh> = BARK_MIN_RADII
            .iter()
            .map(|&min_radius| {
                let tubes = branch_tubes_thicker_than(
                    &model,
                    TubeOptions {
                        sides: EVAL_BARK_SIDES,
                        caps: false,
                    },
                    min_radius,
                );
                RasterMesh::from_bark(&[&tubes, &model.bark_mesh], mat_offset)
            })
            .collect();
        let section = |k: SectionKind| {
            tree.directory
                .section(k)
                .and_then(|e| section_bytes(bytes, e).ok())
                .filter(|b| !b.is_empty())
        };
        let hulls = section(SectionKind::Hulls)
            .and_then(|b| decode_hulls(b).ok())
            .map(|(_, levels)| {
                levels
                    .into_iter()
                    .map(|h| RasterMesh {
                        item_of_triangle: vec![0; h.indices.len() / 3],
                        material_of_triangle: vec![crown_index; h.indices.len() / 3],
                        positions: h.positions,
                        indices: h.indices,
                        ..RasterMesh::default()
                    })
                    .collect()
            })
            .unwrap_or_default();
        let atlas = section(SectionKind::BillboardAtlases)
            .and_then(|b| AtlasTable::decode(b, b.len() as u64).ok().map(|t| (t, b.to_vec())));
        let clouds = section(SectionKind::BillboardClouds)
            .and_then(|b| decode_clouds(b).ok().map(|t| (t, b.to_vec())))
            .filter(|(t, _)| !t.levels.is_empty());
        let full_triangles = bark[0].triangle_count() as u64 + 2 * u64::from(tree.directory.leaf_count);
        let last = tree.directory.iteration_table.len().saturating_sub(1);
        self.models[m] = Some(EvalModel {
            tree,
            bark,
            bark_through: (0..last).map(|_| std::array::from_fn(|_| OnceLock::new())).collect(),
            mat_offset,
            hulls,
            atlas,
            clouds,
            full_triangles,
            full_leaves: OnceLock::new(),
        });
        Ok(())
    }

    /// Loads billboard frame `frame` at resolution `res` of model `m` into the texture cache and
    /// returns its root anchor `(u, v)`, the atlas's centre and radius, and the frame's direction.
    fn billboard_texture(&mut self, m: usize, frame: u32, res: u8) -> Option<(f32, f32, Vec3, f32, Vec3)> {
        let model = self.models.get(m)?.as_ref()?;
        let (table, section) = model.atlas.as_ref()?;
        let side = *table.resolutions.get(usize::from(res))?;
        let dir = table.frame_direction(frame)?;
        let f = table.frames.get(frame as usize)?;
        let (ru, rv) = (f.root_u, f.root_v);
        let (center, radius) = (table.center, table.radius);
        if let std::collections::hash_map::Entry::Vacant(slot) = self.billboard_textures.entry((m, frame, res)) {
            let bytes = table.image_bytes(section, frame, usize::from(res)).ok()??;
            let img = decode_png_frame(bytes, side).ok()?;
            slot.insert(Texture::from_image(&img).ok()?);
        }
        Some((ru, rv, center, radius, dir))
    }

    /// The planes of cloud level `level` of model `m` (section-wide index and quad) whose
    /// textures (bilinear, clamped) are in the texture cache.
    fn cloud_level(&mut self, m: usize, level: u8) -> Vec<(u32, CloudQuad)> {
        let Some(Some(model)) = self.models.get(m) else {
            return Vec::new();
        };
        let Some((table, section)) = &model.clouds else {
            return Vec::new();
        };
        let Some(l) = table.levels.get(usize::from(level)) else {
            return Vec::new();
        };
        let mut out = Vec::with_capacity(l.plane_count as usize);
        for p in l.first_plane..l.first_plane + l.plane_count {
            let plane = table.planes[p as usize];
            if let std::collections::hash_map::Entry::Vacant(v) = self.cloud_textures.entry((m, p)) {
                let Some(t) = cloud_texture(table, section, p) else {
                    continue;
                };
                v.insert(t);
            }
            out.push((p, plane.quad));
        }
        out
    }

    /// Full triangles of the drawn trees at full detail.
    pub fn full_triangles(&self, trees: &[DrawnTree]) -> u64 {
        trees
            .iter()
            .filter_map(|t| self.models.get(usize::from(t.instance.model))?.as_ref())
            .map(|m| m.full_triangles)
            .sum()
    }
}

/// Plane `p`'s texture (bilinear, clamped), `None` when it fails its check.
fn cloud_texture(table: &CloudTable, section: &[u8], p: u32) -> Option<Texture> {
    let plane = table.planes.get(p as usize)?;
    let bytes = table.texture_bytes(section, p as usize).ok()?;
    let img = CloudTable::decode_texture(plane, bytes).ok()?;
    let mut t = Texture::from_image(&img).ok()?;
    t.filter = Filter::Bilinear;
    t.wrap = Wrap::Clamp;
    Some(t)
}

/// Quality of one view against the reference.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Quality {
    /// Colour SSIM (min over R, G, B) over [`BACKGROUND`].
    pub ssim: f64,
    /// Coverage precision.
    pub precision: f64,
    /// Coverage recall.
    pub recall: f64,
}

/// SSIM and coverage of `view` against `reference`.
pub fn quality(reference: &View, view: &View) -> Result<Quality, EvalError> {
    let ssim = ssim_rgba(&reference.color, &view.color, view.width, view.height, BACKGROUND)?;
    let c = coverage(&reference.covered, &view.covered)?;
    Ok(Quality {
        ssim,
        precision: c.precision,
        recall: c.recall,
    })
}

/// What a person sees of one view against the reference: the perceptual error beside SSIM, and
/// both per distance band.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Perceptual {
    /// SSIM, precision and recall, as [`quality`].
    #[serde(flatten)]
    pub quality: Quality,
    /// Mean LDR-FLIP error over the image (0: indistinguishable; lower is better), at FLIP's
    /// default viewing condition ([`DEFAULT_PIXELS_PER_DEGREE`]).
    pub flip: f64,
    /// Near, mid and far bands.
    pub bands: [BandScore; 3],
}

/// [`Perceptual`] scores of `view` against `reference`, with the per-pixel FLIP map (for the
/// error image of a strip). `*_trees` are the per-pixel instance ids of
/// [`render_view_with_trees`]; `bands` names each tree's band.
pub fn perceptual(
    reference: &View,
    reference_trees: &[u32],
    view: &View,
    view_trees: &[u32],
    bands: &BandMap,
) -> Result<(Perceptual, Vec<f32>), EvalError> {
    let (ssim, maps) = ssim_maps_rgba(&reference.color, &view.color, view.width, view.height, BACKGROUND)?;
    let c = coverage(&reference.covered, &view.covered)?;
    let flip_map = flip_rgba(
        &reference.color,
        &view.color,
        view.width,
        view.height,
        BACKGROUND,
        DEFAULT_PIXELS_PER_DEGREE,
    )?;
    let masks = bands.masks(reference_trees, view_trees);
    let scores = Perceptual {
        quality: Quality {
            ssim,
            precision: c.precision,
            recall: c.recall,
        },
        flip: flip::mean(&flip_map),
        bands: band_scores(&masks, &maps, &flip_map),
    };
    Ok((scores, flip_map))
}

fn luminance(p: [u8; 4]) -> f32 {
    let a = f32::from(p[3]) / 255.0;
    let c = |i: usize| (f32::from(p[i]) * a + f32::from(BACKGROUND[i]) * (1.0 - a)) / 255.0;
    0.2126 * c(0) + 0.7152 * c(1) + 0.0722 * c(2)
}

/// Temporal popping: the mean over pixels of the frame-to-frame luminance change of the method
/// beyond the reference's own change, `max(0, |M_t − M_{t−1}| − |R_t − R_{t−1}|)`, in [0, 1].
/// Camera motion changes both alike and cancels; what is left is the method's own flicker.
pub fn popping(ref_prev: &View, ref_now: &View, prev: &View, now: &View) -> f64 {
    let n = now
        .color
        .len()
        .min(prev.color.len())
        .min(ref_now.color.len())
        .min(ref_prev.color.len());
    if n == 0 {
        return 0.0;
    }
    let mut sum = 0.0f64;
    for i in 0..n {
        let dm = (luminance(now.color[i]) - luminance(prev.color[i])).abs();
        let dr = (luminance(ref_now.color[i]) - luminance(ref_prev.color[i])).abs();
        sum += f64::from((dm - dr).max(0.0));
    }
    sum / n as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view(c: [u8; 4], cov: bool) -> View {
        View {
            width: 8,
            height: 8,
            color: vec![c; 64],
            covered: vec![cov; 64],
            triangles: 0,
        }
    }

    #[test]
    fn popping_cancels_the_reference_change() {
        let a = view([0, 0, 0, 255], true);
        let b = view([255, 255, 255, 255], true);
        // The reference changes as much as the method: no popping.
        assert_eq!(popping(&a, &b, &a, &b), 0.0);
        // Reference still, method flips black to white: full popping.
        assert!((popping(&a, &a, &a, &b) - 1.0).abs() < 1e-6);
        // Method still while the reference moves: not popping (clamped at 0).
        assert_eq!(popping(&a, &b, &a, &a), 0.0);
    }

    /// A forest of two trees: a near one (id 1, left half) and a mid one (id 2, right half),
    /// leafy (a fine two-tone pattern) over the sky in the top rows.
    fn two_trees(mid_as_blob: bool) -> (View, Vec<u32>) {
        let (w, h) = (64u32, 48u32);
        let mut color = Vec::new();
        let mut trees = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let tree = if y < 8 {
                    canopy_shared::raster::EMPTY_ITEM
                } else if x < w / 2 {
                    1
                } else {
                    2
                };
                let leafy = if (x / 2 + y / 2) % 2 == 0 {
                    [40, 110, 30, 255]
                } else {
                    [90, 160, 60, 255]
                };
                color.push(match tree {
                    2 if mid_as_blob => [65, 135, 45, 255],
                    1 | 2 => leafy,
                    _ => [0; 4],
                });
                trees.push(tree);
            }
        }
        let covered = color.iter().map(|c| c[3] > 0).collect();
        let view = View {
            width: w,
            height: h,
            color,
            covered,
            triangles: 0,
        };
        (view, trees)
    }

    #[test]
    fn a_blob_for_a_leafy_mid_tree_scores_worse_in_the_mid_band() {
        let bands = BandMap::from_bands([(1, Band::Near), (2, Band::Mid)]);
        let (reference, rt) = two_trees(false);
        let (blob, bt) = two_trees(true);
        let (same, _) = perceptual(&reference, &rt, &reference, &rt, &bands).expect("scores");
        let (wrong, map) = perceptual(&reference, &rt, &blob, &bt, &bands).expect("scores");
        assert!(same.flip < 1e-6 && (same.quality.ssim - 1.0).abs() < 1e-9, "{same:?}");
        assert!(wrong.flip > 0.01, "{wrong:?}");
        assert_eq!(map.len(), rt.len());
        let [near, mid, far] = wrong.bands;
        let (near_flip, mid_flip) = (near.flip.unwrap_or(1.0), mid.flip.unwrap_or(0.0));
        // The error is the mid tree's; the near band picks up only the filters' reach across the
        // boundary. (A 2-px pattern is near the limit of what FLIP's eye resolves at 67 px per
        // degree, so the blob of its mean colour differs mostly in features: 0.10.)
        assert!(
            mid_flip > 0.05 && mid_flip > 4.0 * near_flip,
            "near {near:?} mid {mid:?}"
        );
        assert!(
            mid.ssim.unwrap_or(1.0) < near.ssim.unwrap_or(0.0),
            "near {near:?} mid {mid:?}"
        );
        assert!(far.flip.is_none() && far.pixel_share == 0.0);
        assert!((mid.pixel_share - 0.5 * 40.0 / 48.0).abs() < 1e-9);
        // Whole-image FLIP is the band's diluted by the rest of the picture.
        assert!(wrong.flip < mid_flip);
    }

    #[test]
    fn identical_views_have_perfect_quality() {
        let a = view([10, 120, 30, 255], true);
        let q = quality(&a, &a).expect("quality");
        assert!((q.ssim - 1.0).abs() < 1e-9 && q.precision == 1.0 && q.recall == 1.0);
    }
}
