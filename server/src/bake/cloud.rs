//! Stochastic billboard clouds (seed 002, after Lacewell et al.'s stochastic variant of Décoret's
//! billboard clouds), baked into section kind 8 (`canopy_shared::format::cloud`).
//!
//! # Method
//!
//! The input is the tree's triangles as the atlases render them ([`super::atlas::far_tree_mesh`]:
//! two per leaf, branch tubes thick enough to cover a texel, the imported bark mesh). Level `i`
//! (1-based) has the plane-distance threshold `ε_i = ε_scale · i · r`, `r` the bounding-sphere
//! radius (seed 002: ε = 0.1·p·r). A triangle is **valid** for a plane when all its vertices lie
//! within ε_i of it. Planes are chosen one at a time until the triangles are covered:
//!
//! 1. **Candidates (the stochastic part).** `candidates` planes, each through the centroid of an
//!    uncovered triangle drawn with probability ∝ its area; its normal is the triangle's own on
//!    even draws and a random direction on odd ones (small leaves in every orientation make a
//!    single leaf's plane a poor slab of foliage). Level i > 1 is built from level i − 1: every
//!    plane of level i − 1 is a candidate too, so a coarser level keeps a finer level's plane
//!    wherever that is still the densest choice and adjacent levels blend without popping.
//! 2. **Density.** A candidate's score is the area of the uncovered valid triangles projected on
//!    it (`area · |n_t · n_p|`), estimated on a random sample of at most `score_samples`
//!    uncovered triangles (Lacewell's estimate), times the view-line weight below.
//! 3. **Selection and refit.** The densest candidate wins; its offset is moved to the
//!    area-weighted mean offset of its valid triangles (twice, kept only when the density grows),
//!    so the slab centres on the foliage it covers.
//! 4. **Greedy removal.** Every uncovered triangle valid for the winner (all of them, not only
//!    the sample) is assigned to it and removed.
//!
//! A level stops when the uncovered area is below `residual` of the total or at `max_planes`
//! planes; the remaining triangles are assigned to the plane nearest their centroid (beyond ε:
//! they keep their pixels at the cost of parallax). The report gives that residual per level.
//!
//! **Textures.** Each plane's quad is the bounding rectangle of its triangles projected on it
//! (axes: the plane's projection of +Y as "up", or −Z for a horizontal plane), grown to whole
//! texels of `texel_i = ε_i / (pixel_error · texels_per_pixel)` metres (ε_i projects to
//! `pixel_error` pixels at the level's switch distance, so a texel is `1/texels_per_pixel` of a
//! screen pixel there), capped at `max_texture` pixels a side. The texture is an orthographic,
//! shaded render of the plane's triangles with the shared CPU rasterizer, looking along −n,
//! RGBA with straight alpha, PNG. With **texture density** (seed 002) every triangle within 2ε_i
//! of the plane whose centroid projects inside the quad is drawn on it too, not only those
//! assigned to it.
//!
//! **View-line penalty** (seed 002, eq. 1–2), when a flight height H is given: level i's line of
//! sight has elevation `φ_v = atan(H / σ_i)` (σ_i the level's switch distance,
//! [`canopy_shared::format::cloud::CloudLevel::switch_distance`]); a plane whose normal makes
//! angle `φ_n = asin(|n_y|)` with the ground gets weight
//! `s = max(S_FLOOR, 1 − |φ_v − φ_n| · 2/π)`. The printed formula, `s(i) = φ_v(i) − φ_n · 2/π`,
//! is ambiguous (precedence, sign, and it is negative for most planes); the text says planes
//! whose normal is parallel to the line of sight are preferred, which this reading does: s = 1
//! when the normal's elevation equals the sight line's and falls linearly to 0 at a right
//! angle. The floor [`S_FLOOR`] keeps every plane choosable so every triangle can be covered.
//! The weight multiplies each triangle's projected area, so it multiplies the plane's density.
//!
//! Deterministic: one [`SplitMix64`] stream per level, seeded from `seed` and the level; the
//! sampled scores are summed in a fixed order.

use std::time::Instant;

use canopy_shared::format::SectionBody;
use canopy_shared::format::cloud::{
    CloudHeader, CloudLevel, CloudQuad, LevelTextures, MAX_CLOUD_LEVELS, MAX_CLOUD_TEXTURE, PlaneTexture, TextureRange,
    encode_clouds,
};
use canopy_shared::model::TreeModel;
use canopy_shared::raster::{Camera, Projection, RasterError, RasterMesh, RenderOptions, Scene, render};
use canopy_shared::rng::SplitMix64;
use glam::Vec3;
use rayon::prelude::*;

use super::atlas::{encode_png, far_tree_mesh};
use super::vmi::{leaf_materials, leaf_texture};

/// Smallest view-line weight, so that every plane stays choosable.
pub const S_FLOOR: f32 = 0.05;

/// Options of [`bake_clouds`].
#[derive(Debug, Clone, PartialEq)]
pub struct CloudOptions {
    /// Levels n (1..=16).
    pub levels: usize,
    /// ε_i = `epsilon_scale` · i · r (seed 002: 0.1).
    pub epsilon_scale: f32,
    /// Draw every triangle within 2ε on a plane, not only its own (seed 002's texture density).
    pub texture_density: bool,
    /// Flight height H, metres, of seed 002's view-line penalty; `None` disables it.
    pub view_line_height: Option<f32>,
    /// Screen pixels that ε_i subtends at level i's switch distance.
    pub pixel_error: f32,
    /// Screen height, pixels, of the switch distances.
    pub screen_height: f32,
    /// Vertical field of view, radians, of the switch distances.
    pub fov_y: f32,
    /// Texels per screen pixel at the switch distance.
    pub texels_per_pixel: f32,
    /// Largest texture side, pixels.
    pub max_texture: u16,
    /// Candidate planes drawn per chosen plane.
    pub candidates: usize,
    /// Uncovered triangles sampled to score candidates.
    pub score_samples: usize,
    /// Stop a level when the uncovered area falls below this fraction of the total.
    pub residual: f32,
    /// Most planes per level.
    pub max_planes: usize,
    /// Leave out branch tubes thinner than this many texels of level 1.
    pub min_branch_radius_texels: f32,
    /// Seed of the random streams.
    pub seed: u64,
}

impl Default for CloudOptions {
    fn default() -> Self {
        Self {
            levels: 3,
            epsilon_scale: 0.1,
            texture_density: false,
            view_line_height: None,
            pixel_error: 4.0,
            screen_height: 1080.0,
            fov_y: 60f32.to_radians(),
            texels_per_pixel: 2.0,
            max_texture: 512,
            candidates: 48,
            score_samples: 8192,
            residual: 0.01,
            max_planes: 64,
            min_branch_radius_texels: 0.25,
            seed: 1,
        }
    }
}

/// Why the cloud bake failed.
#[derive(Debug, thiserror::Error)]
pub enum CloudBakeError {
    /// Options out of range.
    #[error("invalid cloud options: {0}")]
    Options(String),
    /// Rendering a texture failed.
    #[error(transparent)]
    Raster(#[from] RasterError),
    /// PNG encoding failed.
    #[error("encoding a cloud texture: {0}")]
    Image(#[from] image::ImageError),
    /// Section encoding failed.
    #[error(transparent)]
    Format(#[from] canopy_shared::format::FormatError),
}

/// Figures of one level.
#[derive(Debug, Clone, PartialEq)]
pub struct CloudLevelReport {
    /// ε_i, metres.
    pub epsilon: f32,
    /// Switch distance σ_i, metres.
    pub distance: f32,
    /// Planes.
    pub planes: usize,
    /// Texture bytes.
    pub bytes: usize,
    /// Texels of all textures.
    pub texels: u64,
    /// Fraction of the triangle area left to the nearest plane beyond ε.
    pub residual_area: f32,
    /// Mean |n_y| of the planes, area-weighted (0: all vertical, 1: all horizontal).
    pub mean_abs_normal_y: f32,
}

/// What [`bake_clouds`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct CloudReport {
    /// Triangles the planes were fitted to.
    pub triangles: usize,
    /// One entry per level.
    pub levels: Vec<CloudLevelReport>,
    /// Section bytes (table and textures).
    pub bytes: usize,
    /// Table bytes (a client's first fetch).
    pub table_bytes: usize,
    /// Seconds choosing planes.
    pub plane_seconds: f64,
    /// Seconds rendering and encoding textures.
    pub texture_seconds: f64,
}

/// One triangle of the input, with what the plane search needs.
#[derive(Debug, Clone, Copy)]
struct Tri {
    v: [Vec3; 3],
    centroid: Vec3,
    normal: Vec3,
    area: f32,
}

impl Tri {
    /// Largest distance of a vertex from the plane (`n`, `d`).
    fn max_dist(&self, n: Vec3, d: f32) -> f32 {
        self.v.iter().map(|p| (n.dot(*p) - d).abs()).fold(0.0, f32::max)
    }
}

/// A chosen plane: unit normal and offset (n·x = d).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Plane {
    n: Vec3,
    d: f32,
}

/// Seed 002's view-line weight of a plane with unit normal `n` for a sight line of elevation
/// `phi_v` (radians): `max(S_FLOOR, 1 − |φ_v − φ_n|·2/π)` with `φ_n = asin(|n_y|)` (see the
/// module doc for why this reading of the printed formula).
pub fn view_line_weight(n: Vec3, phi_v: f32) -> f32 {
    let phi_n = n.y.abs().clamp(0.0, 1.0).asin();
    (1.0 - (phi_v - phi_n).abs() * std::f32::consts::FRAC_2_PI).max(S_FLOOR)
}

fn triangles(mesh: &RasterMesh) -> Vec<Tri> {
    mesh.indices
        .chunks_exact(3)
        .map(|t| {
            let v = [
                mesh.positions[t[0] as usize],
                mesh.positions[t[1] as usize],
                mesh.positions[t[2] as usize],
            ];
            let c = (v[1] - v[0]).cross(v[2] - v[0]);
            Tri {
                v,
                centroid: (v[0] + v[1] + v[2]) / 3.0,
                normal: c.normalize_or(Vec3::Y),
                area: 0.5 * c.length(),
            }
        })
        .collect()
}

/// A random unit vector (uniform on the sphere).
fn random_direction(rng: &mut SplitMix64) -> Vec3 {
    let y = rng.uniform(-1.0, 1.0) as f32;
    let a = rng.uniform(0.0, std::f64::consts::TAU) as f32;
    let s = (1.0 - y * y).max(0.0).sqrt();
    Vec3::new(s * a.cos(), y, s * a.sin())
}

/// Index drawn from `cum` (inclusive prefix sums of non-negative weights) ∝ weight.
fn draw(cum: &[f64], rng: &mut SplitMix64) -> usize {
    let total = cum.last().copied().unwrap_or(0.0);
    let x = rng.next_f64() * total;
    cum.partition_point(|&c| c <= x).min(cum.len().saturating_sub(1))
}

/// Density of plane `p` on the sampled triangles, and its valid members' weighted mean offset.
fn density(tris: &[Tri], sample: &[u32], p: Plane, eps: f32, weight: f32) -> (f64, f32) {
    let (mut s, mut wsum, mut dsum) = (0f64, 0f64, 0f64);
    for &i in sample {
        let t = &tris[i as usize];
        if t.max_dist(p.n, p.d) <= eps {
            let a = f64::from(t.area * t.normal.dot(p.n).abs());
            s += a;
            wsum += f64::from(t.area);
            dsum += f64::from(t.area * p.n.dot(t.centroid));
        }
    }
    let centre = if wsum > 0.0 { (dsum / wsum) as f32 } else { p.d };
    (s * f64::from(weight), centre)
}

/// Chooses one level's planes and assigns every triangle to one of them: `(planes, owner)`,
/// `owner[t]` the plane of triangle t. `seeds` are the previous level's planes (candidates).
/// `residual` returns the fraction of the area assigned beyond ε.
fn choose_planes(
    tris: &[Tri],
    eps: f32,
    phi_v: Option<f32>,
    seeds: &[Plane],
    opts: &CloudOptions,
    rng: &mut SplitMix64,
) -> (Vec<Plane>, Vec<u32>, f32) {
    let total_area: f64 = tris.iter().map(|t| f64::from(t.area)).sum();
    let mut owner = vec![u32::MAX; tris.len()];
    let mut uncovered: Vec<u32> = (0..tris.len() as u32).collect();
    let mut planes: Vec<Plane> = Vec::new();
    let weight = |n: Vec3| phi_v.map_or(1.0, |pv| view_line_weight(n, pv));
    loop {
        let left: f64 = uncovered.iter().map(|&i| f64::from(tris[i as usize].area)).sum();
        if uncovered.is_empty() || left <= f64::from(opts.residual) * total_area || planes.len() >= opts.max_planes {
            break;
        }
        // Sample of uncovered triangles: scores and candidate draws come from it.
        let sample: Vec<u32> = if uncovered.len() <= opts.score_samples {
            uncovered.clone()
        } else {
            (0..opts.score_samples)
                .map(|_| uncovered[rng.below(uncovered.len() as u64) as usize])
                .collect()
        };
        let mut cum = Vec::with_capacity(sample.len());
        let mut acc = 0f64;
        for &i in &sample {
            acc += f64::from(tris[i as usize].area);
            cum.push(acc);
        }
        let mut cands: Vec<Plane> = seeds.to_vec();
        for k in 0..opts.candidates {
            let t = &tris[sample[draw(&cum, rng)] as usize];
            let n = if k % 2 == 0 { t.normal } else { random_direction(rng) };
            cands.push(Plane {
                n,
                d: n.dot(t.centroid),
            });
        }
        let scored: Vec<(f64, f32)> = cands
            .par_iter()
            .map(|p| density(tris, &sample, *p, eps, weight(p.n)))
            .collect();
        let Some((best_i, &(mut best_s, mut centre))) = scored
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.0.total_cmp(&b.1.0).then(b.0.cmp(&a.0)))
        else {
            break;
        };
        let mut best = cands[best_i];
        for _ in 0..2 {
            let moved = Plane { n: best.n, d: centre };
            let (s, c) = density(tris, &sample, moved, eps, weight(moved.n));
            if s > best_s {
                (best, best_s, centre) = (moved, s, c);
            } else {
                break;
            }
        }
        let id = planes.len() as u32;
        let before = uncovered.len();
        uncovered.retain(|&i| {
            let valid = tris[i as usize].max_dist(best.n, best.d) <= eps;
            if valid {
                owner[i as usize] = id;
            }
            !valid
        });
        if uncovered.len() == before {
            // Nothing valid (degenerate input): give the drawn triangle its own plane.
            let t = uncovered[0];
            let tri = &tris[t as usize];
            best = Plane {
                n: tri.normal,
                d: tri.normal.dot(tri.centroid),
            };
            owner[t as usize] = id;
            uncovered.swap_remove(0);
        }
        planes.push(best);
    }
    let mut residual = 0f64;
    if !planes.is_empty() {
        for &i in &uncovered {
            let t = &tris[i as usize];
            let (k, _) = planes
                .iter()
                .enumerate()
                .map(|(k, p)| (k, (p.n.dot(t.centroid) - p.d).abs()))
                .fold((0, f32::INFINITY), |a, b| if b.1 < a.1 { b } else { a });
            owner[i as usize] = k as u32;
            residual += f64::from(t.area);
        }
    }
    let frac = if total_area > 0.0 {
        (residual / total_area) as f32
    } else {
        0.0
    };
    (planes, owner, frac)
}

/// In-plane axes (u, v) with `u × v = n`: v is +Y projected on the plane (−Z when the plane is
/// horizontal).
fn plane_axes(n: Vec3) -> (Vec3, Vec3) {
    let up = if n.y.abs() > 0.99 { -Vec3::Z } else { Vec3::Y };
    let v = (up - n * n.dot(up)).normalize();
    (v.cross(n), v)
}

/// The quad of `plane` around the triangles `members` and its texture size and texel.
fn fit_quad(tris: &[Tri], members: &[u32], plane: Plane, texel: f32, max_side: u16) -> (CloudQuad, u16, u16) {
    let (u, v) = plane_axes(plane.n);
    let (mut lo, mut hi) = (glam::Vec2::splat(f32::INFINITY), glam::Vec2::splat(f32::NEG_INFINITY));
    for &i in members {
        for p in tris[i as usize].v {
            let q = glam::Vec2::new(u.dot(p), v.dot(p));
            lo = lo.min(q);
            hi = hi.max(q);
        }
    }
    if lo.cmpgt(hi).any() {
        (lo, hi) = (glam::Vec2::ZERO, glam::Vec2::ZERO);
    }
    let ext = (hi - lo).max(glam::Vec2::splat(1e-4));
    let texel = texel.max(ext.max_element() / f32::from(max_side));
    let w = ((ext.x / texel).ceil() as u16).clamp(1, max_side);
    let h = ((ext.y / texel).ceil() as u16).clamp(1, max_side);
    let size = glam::Vec2::new(f32::from(w), f32::from(h)) * texel;
    let c = 0.5 * (lo + hi) - 0.5 * size;
    let origin = plane.n * plane.d + u * c.x + v * c.y;
    (
        CloudQuad {
            normal: plane.n,
            d: plane.d,
            origin,
            edge_u: u * size.x,
            edge_v: v * size.y,
        },
        w,
        h,
    )
}

/// Copies the triangles `members` of `mesh` into a mesh of their own.
fn sub_mesh(mesh: &RasterMesh, members: &[u32]) -> RasterMesh {
    let mut out = RasterMesh::default();
    for &t in members {
        let t = t as usize;
        for k in 0..3 {
            let vi = mesh.indices[3 * t + k] as usize;
            out.indices.push(out.positions.len() as u32);
            out.positions.push(mesh.positions[vi]);
            out.normals.push(mesh.normals.get(vi).copied().unwrap_or(Vec3::ZERO));
            out.uvs.push(mesh.uvs.get(vi).copied().unwrap_or([0.0; 2]));
        }
        out.item_of_triangle.push(mesh.item_of_triangle[t]);
        out.material_of_triangle
            .push(mesh.material_of_triangle.get(t).copied().unwrap_or(0));
    }
    out
}

/// Renders `members` of `mesh` onto `quad` (orthographic along −n, upright, `w × h`).
fn render_plane(
    model: &TreeModel,
    mesh: &RasterMesh,
    tris: &[Tri],
    members: &[u32],
    quad: &CloudQuad,
    w: u16,
    h: u16,
) -> Result<Vec<[u8; 4]>, RasterError> {
    let sub = sub_mesh(mesh, members);
    let n = quad.normal;
    let (mut above, mut below) = (0f32, 0f32);
    for &i in members {
        for p in tris[i as usize].v {
            let o = n.dot(p) - quad.d;
            above = above.max(o);
            below = below.min(o);
        }
    }
    let margin = 0.01 * (quad.edge_u.length() + quad.edge_v.length()) + 1e-3;
    let centre = quad.origin + 0.5 * (quad.edge_u + quad.edge_v);
    let eye = centre + n * (above + margin);
    let cam = Camera::look_at(
        eye,
        centre,
        quad.edge_v,
        Projection::Orthographic {
            half_height: 0.5 * quad.edge_v.length(),
            near: 0.5 * margin,
            far: above - below + 2.0 * margin,
        },
    );
    let mats = leaf_materials(model);
    let tex = [leaf_texture()];
    let scene = Scene::single(&sub, &mats, &tex);
    let f = render(&scene, &cam, u32::from(w), u32::from(h), &RenderOptions::default())?;
    Ok(f.color)
}

/// Bakes `opts.levels` levels of stochastic billboard clouds of `model` (section kind 8, item
/// count = levels).
///
/// Contract: level i (1-based) has ε_i = `epsilon_scale`·i·r and at least one plane; every
/// triangle of the far mesh is drawn on at least one plane of every level (its own: within ε_i
/// of it unless it is in the reported residual); textures are PNG of at most `max_texture`
/// pixels a side; the same model and options give the same bytes. An empty model gives an empty
/// section. Errors on bad options or a rendering failure.
pub fn bake_clouds(model: &TreeModel, opts: &CloudOptions) -> Result<(SectionBody, CloudReport), CloudBakeError> {
    let bad = |m: &str| Err(CloudBakeError::Options(m.to_owned()));
    if !(1..=MAX_CLOUD_LEVELS).contains(&opts.levels) {
        return bad("levels must be 1..=16");
    }
    if !(opts.epsilon_scale > 0.0 && opts.epsilon_scale.is_finite()) {
        return bad("ε scale must be positive");
    }
    if opts.view_line_height.is_some_and(|h| !(h > 0.0 && h.is_finite())) {
        return bad("view-line height must be positive");
    }
    let ok = opts.pixel_error > 0.0
        && opts.screen_height > 0.0
        && opts.texels_per_pixel > 0.0
        && opts.fov_y > 0.0
        && opts.fov_y < std::f32::consts::PI
        && (1..=MAX_CLOUD_TEXTURE).contains(&opts.max_texture)
        && opts.candidates > 0
        && opts.score_samples > 0
        && opts.max_planes > 0
        && (0.0..1.0).contains(&opts.residual);
    if !ok {
        return bad("screen model, texture size, candidate, sample, plane counts or residual out of range");
    }
    let (lo, hi) = model.bounds().unwrap_or((Vec3::ZERO, Vec3::ZERO));
    let (lo, hi) = (lo.min(Vec3::ZERO), hi.max(Vec3::ZERO));
    let center = 0.5 * (lo + hi);
    let radius = (0.5 * (hi - lo).length()).max(1e-3);
    let eps = |i: usize| opts.epsilon_scale * i as f32 * radius;
    let texel = |i: usize| eps(i) / (opts.pixel_error * opts.texels_per_pixel);
    let level_distance = |e: f32| {
        CloudLevel {
            first_plane: 0,
            plane_count: 1,
            epsilon: e,
            texel: 1.0,
            textures: TextureRange::default(),
        }
        .switch_distance(opts.pixel_error, opts.screen_height, opts.fov_y)
    };
    let mesh = far_tree_mesh(model, texel(1), opts.min_branch_radius_texels, 4);
    let tris = triangles(&mesh);
    let mut report = CloudReport {
        triangles: tris.len(),
        levels: Vec::new(),
        bytes: 0,
        table_bytes: 0,
        plane_seconds: 0.0,
        texture_seconds: 0.0,
    };
    if tris.iter().all(|t| t.area <= 0.0) {
        return Ok((SectionBody::default(), report));
    }
    let mut levels = Vec::with_capacity(opts.levels);
    let mut seeds: Vec<Plane> = Vec::new();
    for i in 1..=opts.levels {
        let t0 = Instant::now();
        let (e, tx) = (eps(i), texel(i));
        let sigma = level_distance(e);
        let phi_v = opts.view_line_height.map(|h| (h / sigma).atan());
        let mut rng = SplitMix64::new(opts.seed ^ (0xC10D_0000 + i as u64));
        let (planes, owner, residual) = choose_planes(&tris, e, phi_v, &seeds, opts, &mut rng);
        let mut members: Vec<Vec<u32>> = vec![Vec::new(); planes.len()];
        for (t, &o) in owner.iter().enumerate() {
            if let Some(m) = members.get_mut(o as usize) {
                m.push(t as u32);
            }
        }
        let quads: Vec<(CloudQuad, u16, u16)> = planes
            .iter()
            .zip(&members)
            .map(|(p, m)| fit_quad(&tris, m, *p, tx, opts.max_texture))
            .collect();
        if opts.texture_density {
            // Seed 002: every triangle within 2ε whose centroid falls inside the quad.
            for ((q, _, _), m) in quads.iter().zip(members.iter_mut()) {
                let (u, v) = (
                    q.edge_u / q.edge_u.length_squared(),
                    q.edge_v / q.edge_v.length_squared(),
                );
                let extra: Vec<u32> = (0..tris.len() as u32)
                    .into_par_iter()
                    .filter(|&t| {
                        let tr = &tris[t as usize];
                        let rel = tr.centroid - q.origin;
                        let (s, r) = (rel.dot(u), rel.dot(v));
                        tr.max_dist(q.normal, q.d) <= 2.0 * e && (0.0..=1.0).contains(&s) && (0.0..=1.0).contains(&r)
                    })
                    .collect();
                let own: std::collections::HashSet<u32> = m.iter().copied().collect();
                m.extend(extra.into_iter().filter(|t| !own.contains(t)));
            }
        }
        report.plane_seconds += t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        let textures: Vec<PlaneTexture> = quads
            .par_iter()
            .zip(members.par_iter())
            .map(|((q, w, h), m)| -> Result<PlaneTexture, CloudBakeError> {
                let px = render_plane(model, &mesh, &tris, m, q, *w, *h)?;
                Ok(PlaneTexture {
                    quad: *q,
                    width: *w,
                    height: *h,
                    bytes: encode_png(&px, u32::from(*w), u32::from(*h))?,
                })
            })
            .collect::<Result<_, _>>()?;
        report.texture_seconds += t1.elapsed().as_secs_f64();
        let area: f32 = quads.iter().map(|q| q.0.area()).sum();
        report.levels.push(CloudLevelReport {
            epsilon: e,
            distance: sigma,
            planes: planes.len(),
            bytes: textures.iter().map(|t| t.bytes.len()).sum(),
            texels: textures.iter().map(|t| u64::from(t.width) * u64::from(t.height)).sum(),
            residual_area: residual,
            mean_abs_normal_y: quads.iter().map(|q| q.0.area() * q.0.normal.y.abs()).sum::<f32>() / area.max(1e-12),
        });
        seeds = planes;
        levels.push(LevelTextures {
            epsilon: e,
            texel: tx,
            planes: textures,
        });
    }
    let header = CloudHeader {
        center,
        radius,
        texture_density: opts.texture_density,
        view_line_height: opts.view_line_height,
    };
    let bytes = encode_clouds(&header, &levels)?;
    report.bytes = bytes.len();
    report.table_bytes =
        canopy_shared::format::cloud::CloudTable::table_len(levels.len(), levels.iter().map(|l| l.planes.len()).sum());
    Ok((
        SectionBody {
            bytes,
            item_count: levels.len() as u32,
        },
        report,
    ))
}

/// Test model: `n` leaves of side `size` in a sphere of radius 3 around (0, 4, 0), random
/// orientations, no branches.
#[cfg(test)]
pub(crate) fn leaf_ball(n: usize, size: f32, seed: u64) -> TreeModel {
    use canopy_shared::model::{Leaf, Materials, ModelSource, TriangleMesh};
    let mut rng = SplitMix64::new(seed);
    let leaves = (0..n)
        .map(|_| {
            let p = loop {
                let p = Vec3::new(
                    rng.uniform(-1.0, 1.0) as f32,
                    rng.uniform(-1.0, 1.0) as f32,
                    rng.uniform(-1.0, 1.0) as f32,
                );
                if p.length() <= 1.0 {
                    break p;
                }
            };
            let normal = random_direction(&mut rng);
            let axis = normal.any_orthonormal_vector();
            Leaf {
                center: Vec3::new(0.0, 4.0, 0.0) + 3.0 * p,
                normal,
                axis,
                width: size,
                length: size,
                branch: None,
                iteration: 0,
                material: 0,
            }
        })
        .collect();
    TreeModel {
        name: "ball".into(),
        branches: Vec::new(),
        leaves,
        bark_mesh: TriangleMesh::default(),
        materials: Materials::default(),
        iterations: 0,
        source: ModelSource::Gltf,
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use canopy_shared::format::cloud::{CloudTable, decode_clouds};

    fn small_opts() -> CloudOptions {
        CloudOptions {
            max_texture: 64,
            candidates: 24,
            ..CloudOptions::default()
        }
    }

    #[test]
    fn levels_coarsen_and_round_trip() {
        let model = leaf_ball(600, 0.15, 3);
        let (body, rep) = bake_clouds(&model, &small_opts()).unwrap();
        assert_eq!(body.item_count, 3);
        let t = decode_clouds(&body.bytes).unwrap();
        assert_eq!(t.levels.len(), 3);
        for (k, l) in t.levels.iter().enumerate() {
            assert!((l.epsilon - 0.1 * (k + 1) as f32 * t.radius).abs() < 1e-4);
            let imgs = t
                .decode_level(
                    k,
                    &body.bytes[t.level_range(k).unwrap().start as usize..t.level_range(k).unwrap().end as usize],
                )
                .unwrap();
            assert!(
                imgs.iter().all(|i| i.pixels().any(|p| p.0[3] > 0)),
                "level {k}: empty texture"
            );
        }
        let counts: Vec<usize> = rep.levels.iter().map(|l| l.planes).collect();
        assert!(counts[0] > counts[2], "planes per level {counts:?}");
        assert!(rep.levels.iter().all(|l| l.residual_area <= 0.02 || l.planes == 64));
        // Deterministic.
        let (again, _) = bake_clouds(&model, &small_opts()).unwrap();
        assert_eq!(again.bytes, body.bytes);
    }

    #[test]
    fn every_triangle_lies_within_epsilon_of_its_plane() {
        let model = leaf_ball(300, 0.1, 5);
        let mesh = far_tree_mesh(&model, 0.01, 0.0, 4);
        let tris = triangles(&mesh);
        let opts = CloudOptions {
            residual: 0.0,
            max_planes: 10_000,
            ..small_opts()
        };
        let mut rng = SplitMix64::new(1);
        let (planes, owner, residual) = choose_planes(&tris, 0.4, None, &[], &opts, &mut rng);
        assert_eq!(residual, 0.0);
        for (t, &o) in tris.iter().zip(&owner) {
            let p = planes[o as usize];
            assert!(t.max_dist(p.n, p.d) <= 0.4 + 1e-5);
        }
    }

    #[test]
    fn view_line_weight_prefers_normals_along_the_sight_line() {
        let horizontal_normal = Vec3::X;
        let vertical_normal = Vec3::Y;
        // Low flight (sight line nearly horizontal): vertical planes (horizontal normals) win.
        assert!(view_line_weight(horizontal_normal, 0.05) > 0.9);
        assert_eq!(view_line_weight(vertical_normal, 0.0), S_FLOOR);
        // Looking straight down: horizontal planes win.
        assert!(view_line_weight(vertical_normal, 1.5) > 0.9);
        assert!(view_line_weight(horizontal_normal, 1.5) < 0.1);
        // 45° normal, 45° sight line: weight 1.
        assert!(
            (view_line_weight(Vec3::new(1.0, 1.0, 0.0).normalize(), std::f32::consts::FRAC_PI_4) - 1.0).abs() < 1e-5
        );
    }

    #[test]
    fn view_line_penalty_moves_plane_normals_toward_the_sight_line() {
        let model = leaf_ball(800, 0.12, 9);
        let run = |h: Option<f32>| {
            let o = CloudOptions {
                levels: 1,
                view_line_height: h,
                ..small_opts()
            };
            bake_clouds(&model, &o).unwrap().1.levels[0].mean_abs_normal_y
        };
        let none = run(None);
        // Low flight: σ_1 is hundreds of metres, φ_v ≈ 0 → planes turn vertical (|n_y| falls).
        let low = run(Some(1.0));
        // Looking almost straight down → planes turn horizontal (|n_y| grows).
        let high = run(Some(1.0e5));
        assert!(low < none, "low {low} vs none {none}");
        assert!(high > none, "high {high} vs none {none}");
        assert!(high - low > 0.3, "{low} .. {high}");
    }

    #[test]
    fn texture_density_draws_more_triangles_on_the_same_planes() {
        let model = leaf_ball(400, 0.15, 11);
        let plain = bake_clouds(&model, &small_opts()).unwrap().0;
        let dense = bake_clouds(
            &model,
            &CloudOptions {
                texture_density: true,
                ..small_opts()
            },
        )
        .unwrap()
        .0;
        let (a, b) = (
            decode_clouds(&plain.bytes).unwrap(),
            decode_clouds(&dense.bytes).unwrap(),
        );
        // Same planes (the option changes textures only), more opaque texels.
        assert_eq!(a.planes.len(), b.planes.len());
        assert_eq!(b.flags & canopy_shared::format::cloud::CLOUD_FLAG_TEXTURE_DENSITY, 1);
        let opaque = |t: &CloudTable, bytes: &[u8]| -> usize {
            (0..t.planes.len())
                .map(|i| {
                    let img = CloudTable::decode_texture(&t.planes[i], t.texture_bytes(bytes, i).unwrap()).unwrap();
                    img.pixels().filter(|p| p.0[3] > 0).count()
                })
                .sum()
        };
        assert!(opaque(&b, &dense.bytes) > opaque(&a, &plain.bytes));
    }

    #[test]
    fn few_large_leaves_and_degenerate_input() {
        // Three big leaves far apart: each needs its own plane at level 1.
        let mut m = leaf_ball(3, 1.5, 2);
        m.leaves[0].center = Vec3::new(-6.0, 3.0, 0.0);
        m.leaves[1].center = Vec3::new(6.0, 3.0, 2.0);
        m.leaves[2].center = Vec3::new(0.0, 9.0, -6.0);
        let (body, rep) = bake_clouds(&m, &small_opts()).unwrap();
        let t = decode_clouds(&body.bytes).unwrap();
        assert!(rep.levels[0].planes >= 2, "{rep:?}");
        assert!(t.levels.iter().all(|l| l.plane_count >= 1));
        // Nothing to draw: empty section.
        let mut empty = m.clone();
        empty.leaves.clear();
        let (body, _) = bake_clouds(&empty, &small_opts()).unwrap();
        assert!(body.bytes.is_empty() && body.item_count == 0);
        // Bad options.
        for o in [
            CloudOptions {
                levels: 0,
                ..small_opts()
            },
            CloudOptions {
                levels: 17,
                ..small_opts()
            },
            CloudOptions {
                epsilon_scale: 0.0,
                ..small_opts()
            },
            CloudOptions {
                view_line_height: Some(-1.0),
                ..small_opts()
            },
            CloudOptions {
                max_texture: 4096,
                ..small_opts()
            },
        ] {
            assert!(bake_clouds(&m, &o).is_err(), "{o:?}");
        }
    }

    #[test]
    fn hundreds_of_thousands_of_small_leaves() {
        // 200,000 leaves of 2 cm: the plane search works on a sample, so the level count and
        // texture sizes stay bounded and every level covers the crown.
        let model = leaf_ball(200_000, 0.02, 17);
        let opts = CloudOptions {
            max_texture: 128,
            ..CloudOptions::default()
        };
        let (body, rep) = bake_clouds(&model, &opts).unwrap();
        assert_eq!(rep.triangles, 400_000);
        let t = decode_clouds(&body.bytes).unwrap();
        assert_eq!(t.levels.len(), 3);
        for (k, l) in rep.levels.iter().enumerate() {
            assert!(l.planes >= 1 && l.planes <= opts.max_planes, "level {k}: {l:?}");
            assert!(
                l.residual_area <= opts.residual + 1e-3 || l.planes == opts.max_planes,
                "{l:?}"
            );
        }
        assert!(t.planes.iter().all(|p| p.width <= 128 && p.height <= 128));
        // A dense ball is covered by slabs: fewer planes at coarser levels.
        assert!(rep.levels[0].planes > rep.levels[2].planes, "{:?}", rep.levels);
    }

    #[test]
    fn quad_texture_is_upright_and_unmirrored() {
        // One leaf facing +Z at x > 0, one smaller at x < 0: the plane faces ±Z; seen from its
        // normal side, +X is right when n = +Z.
        let (u, v) = plane_axes(Vec3::Z);
        assert!((u - Vec3::X).length() < 1e-6 && (v - Vec3::Y).length() < 1e-6);
        let (u, v) = plane_axes(Vec3::Y);
        assert!(u.cross(v).dot(Vec3::Y) > 0.999);
    }
}
