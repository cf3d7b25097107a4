//! Billboard atlases (seeds 000 and 001), baked into section kind 7
//! (`canopy_shared::format::atlas`).
//!
//! Every view is rendered once, from the full model, with an orthographic camera framing the
//! tree's bounding sphere (centre of the model bounds, radius half their diagonal), at the
//! largest resolution; smaller resolutions are box-filtered from it (alpha-weighted colour), so a
//! view costs one render whatever the number of resolutions. Frames are PNG, RGBA with a
//! transparent background. A view in which no pixel is covered stores no image.
//!
//! Layouts: seed 001's latitude–longitude grid (azimuth and elevation steps configurable), a
//! hemi-octahedral grid (default 16 × 16) for three-frame blending
//! ([`canopy_shared::format::atlas::hemi_oct_blend`]), seed 000's two crossed quads, and seed
//! 001's irregular views (a photo set's directions, [`super::views`]), looked up by spherical
//! Delaunay triangulation ([`canopy_shared::format::atlas::ViewSphere`]).

use std::time::Instant;

use canopy_shared::format::SectionBody;
use canopy_shared::format::atlas::{
    AtlasCodec, AtlasLayout, AtlasLayoutKind, FrameImages, MAX_ATLAS_RESOLUTION, encode_atlases,
};
use canopy_shared::model::TreeModel;
use canopy_shared::raster::{
    BARK_ITEM, Camera, EMPTY_ITEM, RasterError, RasterMesh, RenderOptions, Scene, TreeMeshOptions, render,
};
use canopy_shared::tessellate::{TubeOptions, branch_tubes_thicker_than};
use glam::Vec3;
use rayon::prelude::*;

use super::vmi::{leaf_materials, leaf_texture};

/// Seed 001's latitude–longitude grid, in degrees.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LatLongOptions {
    /// Azimuth step; columns = ⌊360 / step⌉ (at least 1).
    pub azimuth_step_deg: f32,
    /// Elevation of the first row.
    pub elevation_min_deg: f32,
    /// Elevation of the last row (included when a whole number of steps away).
    pub elevation_max_deg: f32,
    /// Elevation step (rows = ⌊(max − min) / step⌋ + 1).
    pub elevation_step_deg: f32,
}

impl Default for LatLongOptions {
    fn default() -> Self {
        Self {
            azimuth_step_deg: 30.0,
            elevation_min_deg: 0.0,
            elevation_max_deg: 60.0,
            elevation_step_deg: 20.0,
        }
    }
}

/// Options of [`bake_atlases`].
#[derive(Debug, Clone, PartialEq)]
pub struct AtlasOptions {
    /// Image sides in pixels, strictly decreasing, each dividing the first (the first is
    /// rendered, the others box-filtered from it).
    pub resolutions: Vec<u16>,
    /// The latitude–longitude layout, if wanted.
    pub lat_long: Option<LatLongOptions>,
    /// Side of the hemi-octahedral grid, if wanted.
    pub hemi_oct_side: Option<u16>,
    /// The two crossed quads.
    pub crossed_quads: bool,
    /// Irregular views, `[azimuth, elevation]` in degrees (checked by
    /// [`super::views::check_views`]), if wanted.
    pub views: Option<Vec<[f32; 2]>>,
    /// Branches thinner than this radius, in pixels of the largest resolution, are left out of
    /// the renders (see [`far_tree_mesh`]).
    pub min_branch_radius_px: f32,
    /// Sides of the branch tubes in the renders.
    pub tube_sides: u32,
}

impl Default for AtlasOptions {
    fn default() -> Self {
        Self {
            resolutions: vec![128, 64],
            lat_long: Some(LatLongOptions::default()),
            hemi_oct_side: Some(canopy_shared::format::atlas::DEFAULT_HEMI_OCT_SIDE),
            crossed_quads: true,
            views: None,
            min_branch_radius_px: 0.1,
            tube_sides: 4,
        }
    }
}

/// Per-layout figures.
#[derive(Debug, Clone, PartialEq)]
pub struct LayoutReport {
    /// Layout name (`lat_long`, `hemi_oct`, `crossed`).
    pub name: &'static str,
    /// Frames in the grid.
    pub frames: usize,
    /// Frames stored (non-empty).
    pub stored: usize,
    /// Image bytes per resolution (same order as the resolutions).
    pub bytes_per_resolution: Vec<usize>,
    /// Seconds spent rendering and encoding this layout.
    pub seconds: f64,
}

impl LayoutReport {
    /// All image bytes of the layout.
    pub fn bytes(&self) -> usize {
        self.bytes_per_resolution.iter().sum()
    }
}

/// What [`bake_atlases`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct AtlasReport {
    /// Resolutions.
    pub resolutions: Vec<u16>,
    /// One entry per layout, in section order.
    pub layouts: Vec<LayoutReport>,
    /// Section bytes (table and images).
    pub bytes: usize,
    /// Bytes of the table (a client's first fetch).
    pub table_bytes: usize,
    /// Wall-clock seconds.
    pub seconds: f64,
}

/// Why the atlas bake failed.
#[derive(Debug, thiserror::Error)]
pub enum AtlasError {
    /// Options out of range.
    #[error("invalid atlas options: {0}")]
    Options(String),
    /// Rendering failed.
    #[error(transparent)]
    Raster(#[from] RasterError),
    /// PNG encoding failed.
    #[error("encoding a frame: {0}")]
    Image(#[from] image::ImageError),
    /// Section encoding failed.
    #[error(transparent)]
    Format(#[from] canopy_shared::format::FormatError),
    /// The irregular view set was refused.
    #[error(transparent)]
    Views(#[from] super::views::ViewSetError),
}

/// The tree mesh for far renders (billboards, silhouettes) at `pixel` metres per pixel: leaves
/// exactly as [`RasterMesh::from_tree`] builds them, the imported bark mesh, and branch tubes of
/// `tube_sides` sides for the branches whose largest radius is at least `min_radius_px` pixels.
///
/// Why: on a 300,000-leaf linden the 6-sided tubes of every twig are 3.5 M of 4.1 M triangles
/// and most of the render time, while a twig a few millimetres thick is a tenth of a pixel wide
/// at billboard resolution and covers almost no pixel centre.
pub fn far_tree_mesh(model: &TreeModel, pixel: f32, min_radius_px: f32, tube_sides: u32) -> RasterMesh {
    let bark = branch_tubes_thicker_than(
        model,
        TubeOptions {
            sides: tube_sides,
            caps: false,
        },
        min_radius_px * pixel,
    );
    let mut mesh = RasterMesh {
        normals: bark.normals,
        positions: bark.positions,
        indices: bark.indices,
        ..RasterMesh::default()
    };
    mesh.normals.resize(mesh.positions.len(), Vec3::ZERO);
    let imported = RasterMesh {
        positions: model.bark_mesh.positions.clone(),
        normals: if model.bark_mesh.normals.len() == model.bark_mesh.positions.len() {
            model.bark_mesh.normals.clone()
        } else {
            vec![Vec3::ZERO; model.bark_mesh.positions.len()]
        },
        indices: model.bark_mesh.indices.clone(),
        ..RasterMesh::default()
    };
    let leaves = RasterMesh::from_tree(
        model,
        &TreeMeshOptions {
            bark: false,
            ..TreeMeshOptions::default()
        },
    );
    // Concatenated by hand: every part has full per-vertex and per-triangle arrays here.
    let mut out = RasterMesh::default();
    for (m, bark) in [(mesh, true), (imported, true), (leaves, false)] {
        let base = out.positions.len() as u32;
        let t = m.triangle_count();
        out.indices.extend(m.indices.iter().map(|&i| i + base));
        out.normals.extend_from_slice(&m.normals);
        out.normals.resize(out.positions.len() + m.positions.len(), Vec3::ZERO);
        out.uvs.extend_from_slice(&m.uvs);
        out.uvs.resize(out.positions.len() + m.positions.len(), [0.0; 2]);
        out.positions.extend_from_slice(&m.positions);
        if bark {
            out.item_of_triangle.resize(out.item_of_triangle.len() + t, BARK_ITEM);
            out.material_of_triangle.resize(out.material_of_triangle.len() + t, 0);
        } else {
            out.item_of_triangle.extend_from_slice(&m.item_of_triangle);
            out.material_of_triangle.extend_from_slice(&m.material_of_triangle);
        }
    }
    out
}

fn layouts_of(opts: &AtlasOptions) -> Result<Vec<AtlasLayout>, AtlasError> {
    let bad = |m: &str| Err(AtlasError::Options(m.to_owned()));
    let mut out = Vec::new();
    if let Some(ll) = opts.lat_long {
        let ok = ll.azimuth_step_deg > 0.0
            && ll.elevation_step_deg > 0.0
            && ll.elevation_max_deg >= ll.elevation_min_deg
            && (-90.0..=90.0).contains(&ll.elevation_min_deg)
            && (-90.0..=90.0).contains(&ll.elevation_max_deg);
        if !ok {
            return bad("lat-long steps must be > 0 and elevations in [-90, 90], min ≤ max");
        }
        let cols = (360.0 / ll.azimuth_step_deg).round().max(1.0);
        let rows = ((ll.elevation_max_deg - ll.elevation_min_deg) / ll.elevation_step_deg + 1e-4).floor() + 1.0;
        if cols * rows > 16_384.0 {
            return bad("lat-long grid over 16,384 frames");
        }
        out.push(AtlasLayout {
            kind: AtlasLayoutKind::LatLong {
                elevation_min: ll.elevation_min_deg.to_radians(),
                elevation_step: ll.elevation_step_deg.to_radians(),
                // The stored step is the one that closes the circle exactly.
                azimuth_step: std::f32::consts::TAU / cols,
            },
            cols: cols as u16,
            rows: rows as u16,
            first_frame: 0,
        });
    }
    if let Some(n) = opts.hemi_oct_side {
        if n == 0 || n > 128 {
            return bad("hemi-octahedral side must be 1..=128");
        }
        out.push(AtlasLayout {
            kind: AtlasLayoutKind::HemiOctahedral,
            cols: n,
            rows: n,
            first_frame: 0,
        });
    }
    if opts.crossed_quads {
        out.push(AtlasLayout {
            kind: AtlasLayoutKind::CrossedQuads,
            cols: 2,
            rows: 1,
            first_frame: 0,
        });
    }
    if let Some(v) = &opts.views {
        super::views::check_views(v)?;
        out.push(AtlasLayout {
            kind: AtlasLayoutKind::Views,
            cols: v.len() as u16,
            rows: 1,
            first_frame: 0,
        });
    }
    let mut first = 0;
    for l in &mut out {
        l.first_frame = first;
        first += l.frame_count();
    }
    Ok(out)
}

/// Box-filters a `side²` RGBA image by an integer `factor`: alpha is the mean alpha, colour the
/// alpha-weighted mean (so transparent black does not darken the edges).
fn downsample(px: &[[u8; 4]], side: usize, factor: usize) -> Vec<[u8; 4]> {
    let out_side = side / factor;
    let mut out = Vec::with_capacity(out_side * out_side);
    for oy in 0..out_side {
        for ox in 0..out_side {
            let (mut c, mut a) = ([0u32; 3], 0u32);
            for y in oy * factor..(oy + 1) * factor {
                for x in ox * factor..(ox + 1) * factor {
                    let p = px[y * side + x];
                    let w = u32::from(p[3]);
                    for k in 0..3 {
                        c[k] += u32::from(p[k]) * w;
                    }
                    a += w;
                }
            }
            let n = (factor * factor) as u32;
            // No covered sample: transparent black.
            let avg = |v: u32| (v + a / 2).checked_div(a).unwrap_or(0) as u8;
            out.push([avg(c[0]), avg(c[1]), avg(c[2]), ((a + n / 2) / n) as u8]);
        }
    }
    out
}

/// PNG (best compression, adaptive filter) of a `width × height` RGBA8 image.
pub(crate) fn encode_png(px: &[[u8; 4]], width: u32, height: u32) -> Result<Vec<u8>, image::ImageError> {
    use image::ImageEncoder;
    let raw: Vec<u8> = px.iter().flatten().copied().collect();
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new_with_quality(
        &mut out,
        image::codecs::png::CompressionType::Best,
        image::codecs::png::FilterType::Adaptive,
    )
    .write_image(&raw, width, height, image::ExtendedColorType::Rgba8)?;
    Ok(out)
}

/// Bakes the billboard atlases of `model` (section kind 7, item count = frame-table entries,
/// stored or not) and reports bytes and time per layout.
///
/// Contract: every layout of `opts` is present in order lat-long, hemi-octahedral, crossed
/// quads, views (each view's frame in the set's order); a frame with no covered pixel stores no image; each stored frame has one PNG per
/// resolution and the root anchor of its view. Errors on bad options (resolutions not strictly
/// decreasing or not dividing the first, empty layout set) or a rendering failure.
pub fn bake_atlases(model: &TreeModel, opts: &AtlasOptions) -> Result<(SectionBody, AtlasReport), AtlasError> {
    let start = Instant::now();
    let res = &opts.resolutions;
    let top = res.first().copied().unwrap_or(0);
    if res.is_empty()
        || res.len() > canopy_shared::format::atlas::MAX_ATLAS_RESOLUTIONS
        || res.windows(2).any(|w| w[1] >= w[0])
        || res.iter().any(|&r| r == 0 || top % r != 0)
        || top > MAX_ATLAS_RESOLUTION
    {
        return Err(AtlasError::Options(
            "resolutions must be 1 to 4 strictly decreasing sides, each dividing the first".into(),
        ));
    }
    let layouts = layouts_of(opts)?;
    if layouts.is_empty() {
        return Err(AtlasError::Options("no layout selected".into()));
    }
    // The root (origin) is framed too, so its anchor always lies inside the image.
    let (lo, hi) = model.bounds().unwrap_or((Vec3::ZERO, Vec3::ZERO));
    let (lo, hi) = (lo.min(Vec3::ZERO), hi.max(Vec3::ZERO));
    let center = 0.5 * (lo + hi);
    let radius = (0.5 * (hi - lo).length()).max(1e-3);
    let mesh = far_tree_mesh(
        model,
        2.0 * radius / f32::from(top),
        opts.min_branch_radius_px,
        opts.tube_sides,
    );
    let mats = leaf_materials(model);
    let tex = [leaf_texture()];
    let scene = Scene::single(&mesh, &mats, &tex);
    let ropts = RenderOptions::default();
    let side = u32::from(top);

    let view_angles: Vec<[f32; 2]> = opts
        .views
        .iter()
        .flatten()
        .map(|&[a, e]| [a.to_radians(), e.to_radians()])
        .collect();
    let mut frames = Vec::new();
    let mut reports = Vec::new();
    for l in &layouts {
        let t0 = Instant::now();
        let mut rendered = Vec::with_capacity(l.frame_count() as usize);
        for local in 0..l.frame_count() {
            let dir = match l.kind {
                AtlasLayoutKind::Views => view_angles
                    .get(local as usize)
                    .map(|a| canopy_shared::format::atlas::lat_long_direction(a[0], a[1])),
                _ => l.direction(local),
            }
            .unwrap_or(Vec3::X);
            let cam = Camera::orbit_orthographic(center, radius, dir);
            let f = render(&scene, &cam, side, side, &ropts)?;
            let (root_u, root_v) = cam
                .project(Vec3::ZERO, side, side)
                .map_or((0.5, 0.0), |(p, _)| (p.x / side as f32, 1.0 - p.y / side as f32));
            let covered = f.item.iter().any(|&i| i != EMPTY_ITEM);
            rendered.push((root_u, root_v, covered.then_some(f.color)));
        }
        // PNG encoding is independent per frame: spread it over the cores.
        let encoded: Vec<FrameImages> = rendered
            .into_par_iter()
            .map(|(root_u, root_v, color)| -> Result<FrameImages, AtlasError> {
                let images = match color {
                    None => None,
                    Some(px) => Some(
                        res.iter()
                            .map(|&r| {
                                let factor = usize::from(top / r);
                                if factor == 1 {
                                    encode_png(&px, side, side)
                                } else {
                                    encode_png(&downsample(&px, side as usize, factor), u32::from(r), u32::from(r))
                                }
                            })
                            .collect::<Result<Vec<_>, _>>()?,
                    ),
                };
                Ok(FrameImages { root_u, root_v, images })
            })
            .collect::<Result<_, _>>()?;
        let mut per_res = vec![0usize; res.len()];
        for f in &encoded {
            for (k, img) in f.images.iter().flatten().enumerate() {
                per_res[k] += img.len();
            }
        }
        reports.push(LayoutReport {
            name: l.kind.name(),
            frames: l.frame_count() as usize,
            stored: encoded.iter().filter(|f| f.images.is_some()).count(),
            bytes_per_resolution: per_res,
            seconds: t0.elapsed().as_secs_f64(),
        });
        frames.extend(encoded);
    }
    let bytes = encode_atlases(AtlasCodec::Png, center, radius, res, &layouts, &view_angles, &frames)?;
    let table_bytes =
        canopy_shared::format::atlas::AtlasTable::table_len(res.len(), layouts.len(), view_angles.len(), frames.len());
    let report = AtlasReport {
        resolutions: res.clone(),
        layouts: reports,
        bytes: bytes.len(),
        table_bytes,
        seconds: start.elapsed().as_secs_f64(),
    };
    Ok((
        SectionBody {
            bytes,
            item_count: frames.len() as u32,
        },
        report,
    ))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use canopy_shared::format::atlas::{AtlasTable, decode_png_frame};
    use canopy_shared::model::{Leaf, Materials, ModelSource, TriangleMesh};

    /// A few leaves high above the origin, all facing +Z, and nothing else: seen edge-on from
    /// ±X the view is empty.
    fn sheet() -> TreeModel {
        let leaves = (0..9)
            .map(|i| Leaf {
                center: Vec3::new((i % 3) as f32 * 0.5, 3.0 + (i / 3) as f32 * 0.5, 0.0),
                normal: Vec3::Z,
                axis: Vec3::Y,
                width: 0.4,
                length: 0.4,
                branch: None,
                iteration: 0,
                material: 0,
            })
            .collect();
        TreeModel {
            name: "sheet".into(),
            branches: Vec::new(),
            leaves,
            bark_mesh: TriangleMesh::default(),
            materials: Materials::default(),
            iterations: 0,
            source: ModelSource::Gltf,
        }
    }

    #[test]
    fn bake_round_trips_and_skips_empty_frames() {
        let model = sheet();
        let opts = AtlasOptions {
            resolutions: vec![32, 16],
            lat_long: Some(LatLongOptions {
                azimuth_step_deg: 90.0,
                elevation_min_deg: 0.0,
                elevation_max_deg: 30.0,
                elevation_step_deg: 30.0,
            }),
            hemi_oct_side: Some(4),
            crossed_quads: true,
            ..AtlasOptions::default()
        };
        let (body, rep) = bake_atlases(&model, &opts).unwrap();
        assert_eq!(body.item_count, 8 + 16 + 2);
        let t = AtlasTable::decode(&body.bytes, body.bytes.len() as u64).unwrap();
        assert_eq!(t.frames.len(), 26);
        // Crossed quads: frame 0 looks from +X, edge-on to the sheet → empty; frame 1 from −Z.
        let crossed = &rep.layouts[2];
        assert_eq!((crossed.frames, crossed.stored), (2, 1));
        assert!(!t.frames[24].is_present() && t.frames[25].is_present());
        // Lat-long row 0, azimuth 0° and 180° are edge-on too.
        assert!(!t.frames[0].is_present() && !t.frames[2].is_present());
        assert!(t.frames[1].is_present());
        for (k, &side) in t.resolutions.iter().enumerate() {
            let img = t.image_bytes(&body.bytes, 25, k).unwrap().unwrap();
            let img = decode_png_frame(img, side).unwrap();
            assert!(img.pixels().any(|p| p[3] > 0));
            assert!(img.pixels().any(|p| p[3] == 0));
        }
        // Root anchor: the origin is framed too, below the leaves: inside the image, low.
        let f = &t.frames[25];
        assert!(f.root_v >= 0.0 && f.root_v < 0.5, "{f:?}");
        assert_eq!(rep.layouts.len(), 3);
        assert_eq!(rep.bytes, body.bytes.len());
    }

    #[test]
    fn irregular_views_bake_with_their_directions() {
        let opts = AtlasOptions {
            resolutions: vec![16],
            lat_long: None,
            hemi_oct_side: None,
            crossed_quads: false,
            // Edge-on from +X (empty), face-on from −Z, and from above at an angle.
            views: Some(vec![[0.0, 0.0], [90.0, 0.0], [45.0, 30.0]]),
            ..AtlasOptions::default()
        };
        let (body, rep) = bake_atlases(&sheet(), &opts).unwrap();
        let t = AtlasTable::decode(&body.bytes, body.bytes.len() as u64).unwrap();
        assert_eq!(t.layouts.len(), 1);
        assert_eq!(
            (rep.layouts[0].name, rep.layouts[0].frames, rep.layouts[0].stored),
            ("views", 3, 2)
        );
        assert!(!t.frames[0].is_present() && t.frames[1].is_present() && t.frames[2].is_present());
        let d = t.frame_direction(2).unwrap();
        let want = canopy_shared::format::atlas::lat_long_direction(45f32.to_radians(), 30f32.to_radians());
        assert!(d.distance(want) < 1e-6, "{d} {want}");
        // The lookup sees the same directions: from −Z the face-on frame is the nearest.
        let (k, _) = t.views.as_ref().unwrap().nearest(Vec3::NEG_Z, 0).unwrap();
        assert_eq!(k, 1);
    }

    #[test]
    fn far_mesh_matches_the_full_mesh_when_nothing_is_dropped() {
        let model = sheet();
        let far = far_tree_mesh(&model, 1.0, 0.0, 6);
        let full = RasterMesh::from_tree(&model, &TreeMeshOptions::default());
        assert_eq!(far.positions, full.positions);
        assert_eq!(far.indices, full.indices);
        assert_eq!(far.item_of_triangle, full.item_of_triangle);
        assert_eq!(far.material_of_triangle, full.material_of_triangle);
        far.validate(2).unwrap();
    }

    #[test]
    fn bad_options_are_rejected() {
        let m = sheet();
        for o in [
            AtlasOptions {
                resolutions: vec![64, 128],
                ..AtlasOptions::default()
            },
            AtlasOptions {
                resolutions: vec![128, 48],
                ..AtlasOptions::default()
            },
            AtlasOptions {
                resolutions: vec![],
                ..AtlasOptions::default()
            },
            AtlasOptions {
                lat_long: None,
                hemi_oct_side: None,
                crossed_quads: false,
                ..AtlasOptions::default()
            },
            AtlasOptions {
                hemi_oct_side: Some(0),
                ..AtlasOptions::default()
            },
            AtlasOptions {
                views: Some(vec![]),
                ..AtlasOptions::default()
            },
            AtlasOptions {
                views: Some(vec![[10.0, 0.0], [370.0, 0.0]]),
                ..AtlasOptions::default()
            },
        ] {
            assert!(bake_atlases(&m, &o).is_err(), "{o:?}");
        }
    }

    #[test]
    fn downsample_weights_colour_by_alpha() {
        let px = [[200, 100, 0, 255], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]];
        assert_eq!(downsample(&px, 2, 2), vec![[200, 100, 0, 64]]);
    }
}
