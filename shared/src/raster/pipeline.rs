//! The rasterization pipeline: vertex transform, homogeneous clipping, fixed-point triangle
//! setup, binning to row bands, and per-band rasterization with a depth test, alpha test and
//! deferred Lambert shading.

use std::path::Path;

use glam::{Mat3, Mat4, Vec2, Vec3, Vec4};
use rayon::prelude::*;

use super::scene::{FULL_COVERAGE, Instance, Scene, dither_threshold};
use super::texture::linear_to_srgb;
use super::{BAND_ROWS, Camera, EMPTY_ITEM, GUARD_BAND, MAX_IMAGE_SIZE, RasterError};

/// Sub-pixel bits of the fixed-point vertex snap.
const SUBPIXEL_BITS: u32 = 8;
const SUBPIXEL: f32 = (1 << SUBPIXEL_BITS) as f32;
const ONE_PIXEL: i64 = 1 << SUBPIXEL_BITS;
const HALF_PIXEL: i64 = ONE_PIXEL / 2;
/// Triangles per setup chunk: the unit of parallel setup and binning (fixed, so binning does
/// not depend on the thread count).
const CHUNK_TRIANGLES: usize = 4096;

/// Simple lighting: ambient plus one directional light (Lambert).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lighting {
    /// Direction *towards* the light, world space (normalised internally).
    pub sun_direction: Vec3,
    /// Directional light intensity.
    pub sun: f32,
    /// Ambient intensity.
    pub ambient: f32,
}

impl Default for Lighting {
    fn default() -> Self {
        Self {
            sun_direction: Vec3::new(0.3, 1.0, 0.2),
            sun: 0.7,
            ambient: 0.35,
        }
    }
}

/// Options of [`render`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderOptions {
    /// Produce the colour buffer (else [`Frame::color`] is empty and shading is skipped).
    pub shade: bool,
    /// Colour of empty pixels (sRGB, straight alpha). Transparent black by default.
    pub clear_color: [u8; 4],
    /// Lighting.
    pub lighting: Lighting,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            shade: true,
            clear_color: [0; 4],
            lighting: Lighting::default(),
        }
    }
}

impl RenderOptions {
    /// Shaded with ambient light 1 and no sun: textures as they are (billboards, cloud planes,
    /// whose images carry the bake's lighting).
    pub fn unlit() -> Self {
        Self {
            lighting: Lighting {
                sun: 0.0,
                ambient: 1.0,
                ..Lighting::default()
            },
            ..Self::default()
        }
    }
}

/// A rendered image. All buffers are row-major, row 0 at the top, `width × height` long.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// NDC depth of the visible fragment (0 near … 1 far), `f32::INFINITY` where empty.
    pub depth: Vec<f32>,
    /// Item id of the visible fragment, [`EMPTY_ITEM`] where empty.
    pub item: Vec<u32>,
    /// sRGB RGBA8 colour, straight alpha; empty unless [`RenderOptions::shade`].
    pub color: Vec<[u8; 4]>,
}

impl Frame {
    /// Number of pixels.
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Coverage mask: `true` where some item is visible.
    pub fn coverage(&self) -> Vec<bool> {
        self.item.iter().map(|&i| i != EMPTY_ITEM).collect()
    }

    /// Visible pixel count of every item present, sorted by item id (empty pixels excluded).
    pub fn item_pixel_counts(&self) -> Vec<(u32, u32)> {
        let mut items: Vec<u32> = self.item.iter().copied().filter(|&i| i != EMPTY_ITEM).collect();
        items.sort_unstable();
        let mut out: Vec<(u32, u32)> = Vec::new();
        for i in items {
            match out.last_mut() {
                Some((last, n)) if *last == i => *n += 1,
                _ => out.push((i, 1)),
            }
        }
        out
    }

    /// The colour buffer as an `image` buffer (`None` if not shaded).
    pub fn to_rgba_image(&self) -> Option<image::RgbaImage> {
        if self.color.len() != self.pixel_count() {
            return None;
        }
        let raw: Vec<u8> = self.color.iter().flatten().copied().collect();
        image::RgbaImage::from_raw(self.width, self.height, raw)
    }

    /// Writes the colour buffer as PNG (an error if not shaded).
    pub fn write_png(&self, path: &Path) -> Result<(), RasterError> {
        crate::metrics::write_png(path, self.width, self.height, &self.color)
    }
}

/// A triangle after setup: snapped screen vertices (oriented so that the signed area is
/// positive), per-vertex attributes for perspective-correct interpolation, bounds and ids.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Tri {
    /// 24.8 fixed-point pixel coordinates (x right, y down).
    v: [[i32; 2]; 3],
    /// NDC depth per vertex.
    pub(crate) z: [f32; 3],
    /// 1 / w per vertex.
    iw: [f32; 3],
    /// uv / w per vertex.
    uv: [Vec2; 3],
    /// World normal / w per vertex (zero when shading is off).
    n: [Vec3; 3],
    /// 1 / (twice the signed area in fixed-point units²).
    inv_area: f32,
    /// Inclusive pixel bounds: min x, min y, max x, max y.
    bbox: [u16; 4],
    pub(crate) item: u32,
    material: u16,
    /// Seen from the back (normals flip when shading).
    back: bool,
    /// Needs the alpha test.
    alpha: bool,
}

/// Setup output for one chunk of input triangles.
#[derive(Debug)]
struct Chunk {
    /// For each band, copies of the chunk's triangles that touch it, in submission order.
    /// Copies (not indices) so that each band streams through contiguous memory: with
    /// indices, the gather of scattered 128-byte triangles dominated the run time.
    bins: Vec<Vec<Tri>>,
}

/// A scene set up for one camera and image size: ready to rasterize band by band.
#[derive(Debug)]
pub(crate) struct Prepared<'s> {
    scene: &'s Scene<'s>,
    chunks: Vec<Chunk>,
    height: u32,
}

/// A vertex in clip space with its attributes.
#[derive(Debug, Clone, Copy)]
struct ClipVert {
    pos: Vec4,
    uv: Vec2,
    n: Vec3,
}

impl ClipVert {
    fn lerp(self, o: ClipVert, t: f32) -> ClipVert {
        ClipVert {
            pos: self.pos.lerp(o.pos, t),
            uv: self.uv.lerp(o.uv, t),
            n: self.n.lerp(o.n, t),
        }
    }
}

/// Signed distances to the six clip planes (inside ≥ 0): near, far, left, right, bottom, top.
fn plane_distances(p: Vec4) -> [f32; 6] {
    let g = GUARD_BAND * p.w;
    [p.z, p.w - p.z, p.x + g, g - p.x, p.y + g, g - p.y]
}

fn outcode(p: Vec4) -> u8 {
    plane_distances(p).iter().enumerate().fold(
        0,
        |acc, (k, &d)| {
            if d < 0.0 || d.is_nan() { acc | (1 << k) } else { acc }
        },
    )
}

/// Sutherland–Hodgman clip of a convex polygon against all six planes.
fn clip_polygon(input: &[ClipVert]) -> Vec<ClipVert> {
    let mut poly: Vec<ClipVert> = input.to_vec();
    for plane in 0..6 {
        if poly.is_empty() {
            break;
        }
        let mut out = Vec::with_capacity(poly.len() + 2);
        for i in 0..poly.len() {
            let a = poly[i];
            let b = poly[(i + 1) % poly.len()];
            let da = plane_distances(a.pos)[plane];
            let db = plane_distances(b.pos)[plane];
            if da >= 0.0 {
                out.push(a);
            }
            if (da >= 0.0) != (db >= 0.0) {
                out.push(a.lerp(b, da / (da - db)));
            }
        }
        poly = out;
    }
    poly
}

/// Per-instance data needed while assembling triangles.
struct InstanceCtx<'a> {
    inst: &'a Instance<'a>,
    clip: Vec<Vec4>,
    normal_matrix: Mat3,
    shade: bool,
}

impl<'s> Prepared<'s> {
    /// Transforms, clips, sets up and bins every triangle of `scene`.
    pub(crate) fn new(
        scene: &'s Scene<'s>,
        camera: &Camera,
        width: u32,
        height: u32,
        shade: bool,
    ) -> Result<Self, RasterError> {
        if width == 0 || height == 0 || width > MAX_IMAGE_SIZE || height > MAX_IMAGE_SIZE {
            return Err(RasterError::InvalidSize { width, height });
        }
        camera.validate()?;
        scene.validate()?;
        let vp = camera.view_projection(width as f32 / height as f32);
        let bands = height.div_ceil(BAND_ROWS) as usize;
        let mut chunks = Vec::new();
        for inst in &scene.instances {
            let mvp: Mat4 = vp * inst.transform;
            let ctx = InstanceCtx {
                inst,
                clip: inst.mesh.positions.par_iter().map(|p| mvp * p.extend(1.0)).collect(),
                normal_matrix: Mat3::from_mat4(inst.transform).inverse().transpose(),
                shade,
            };
            let tri_count = inst.mesh.triangle_count();
            let starts: Vec<usize> = (0..tri_count).step_by(CHUNK_TRIANGLES).collect();
            let mut new_chunks: Vec<Chunk> = starts
                .par_iter()
                .map(|&s| {
                    let e = (s + CHUNK_TRIANGLES).min(tri_count);
                    let mut tris = Vec::with_capacity(e - s);
                    for t in s..e {
                        assemble(scene, &ctx, t, width, height, &mut tris);
                    }
                    // Count first so each bin is allocated once.
                    let mut sizes = vec![0usize; bands];
                    for tri in &tris {
                        let b0 = u32::from(tri.bbox[1]) / BAND_ROWS;
                        let b1 = u32::from(tri.bbox[3]) / BAND_ROWS;
                        for n in &mut sizes[b0 as usize..=b1 as usize] {
                            *n += 1;
                        }
                    }
                    let mut bins: Vec<Vec<Tri>> = sizes.iter().map(|&n| Vec::with_capacity(n)).collect();
                    for tri in &tris {
                        let b0 = u32::from(tri.bbox[1]) / BAND_ROWS;
                        let b1 = u32::from(tri.bbox[3]) / BAND_ROWS;
                        for bin in &mut bins[b0 as usize..=b1 as usize] {
                            bin.push(*tri);
                        }
                    }
                    Chunk { bins }
                })
                .collect();
            chunks.append(&mut new_chunks);
        }
        Ok(Self { scene, chunks, height })
    }

    /// Number of bands.
    pub(crate) fn band_count(&self) -> u32 {
        self.height.div_ceil(BAND_ROWS)
    }

    /// First row and one-past-last row of band `b`.
    pub(crate) fn band_rows(&self, b: u32) -> (u32, u32) {
        let y0 = b * BAND_ROWS;
        (y0, (y0 + BAND_ROWS).min(self.height))
    }

    /// Calls `f(x, y, z, lambdas, tri, (chunk, index in band))` for every pixel centre in band `b`
    /// covered by a triangle (no depth or alpha test), triangles in submission order.
    pub(crate) fn raster_band(&self, b: u32, mut f: impl FnMut(u32, u32, f32, [f32; 3], &Tri, (u32, u32))) {
        let (y_lo, y_hi) = self.band_rows(b);
        for (ci, chunk) in self.chunks.iter().enumerate() {
            for (ti, t) in chunk.bins[b as usize].iter().enumerate() {
                covered(t, y_lo, y_hi, |x, y, l| {
                    let z = l[0] * t.z[0] + l[1] * t.z[1] + l[2] * t.z[2];
                    f(x, y, z, l, t, (ci as u32, ti as u32));
                });
            }
        }
    }

    /// The triangle with id `(chunk, index)` in band `b`.
    fn tri(&self, b: u32, id: (u32, u32)) -> &Tri {
        &self.chunks[id.0 as usize].bins[b as usize][id.1 as usize]
    }

    /// Screen-door coverage and alpha test of triangle `t` at pixel `(x, y)`, barycentrics
    /// `l`: `true` if the fragment survives.
    pub(crate) fn alpha_ok(&self, t: &Tri, l: [f32; 3], x: u32, y: u32) -> bool {
        if !t.alpha {
            return true;
        }
        let mat = &self.scene.materials[t.material as usize];
        if mat.coverage != FULL_COVERAGE {
            let d = dither_threshold(x, y);
            if !(d >= mat.coverage[0] && d < mat.coverage[1]) {
                return false;
            }
        }
        let Some(tex) = mat.texture.and_then(|k| self.scene.textures.get(k as usize)) else {
            return true;
        };
        mat.alpha_cutoff <= 0.0 || tex.alpha_test(t.uv_at(l), mat.alpha_cutoff)
    }

    /// Shaded sRGB colour of triangle `id` at pixel `(x, y)`.
    fn shade(&self, b: u32, id: (u32, u32), x: u32, y: u32, lighting: &Lighting) -> [u8; 4] {
        let t = self.tri(b, id);
        let l = t.lambdas_at(x, y);
        let mat = &self.scene.materials[t.material as usize];
        let mut base = Vec3::new(mat.color[0], mat.color[1], mat.color[2]);
        if let Some(tex) = mat.texture.and_then(|k| self.scene.textures.get(k as usize)) {
            base *= tex.sample(t.uv_at(l)).truncate();
        }
        let iw = l[0] * t.iw[0] + l[1] * t.iw[1] + l[2] * t.iw[2];
        let mut n = ((t.n[0] * l[0] + t.n[1] * l[1] + t.n[2] * l[2]) / iw).normalize_or_zero();
        if t.back {
            n = -n;
        }
        let sun = lighting.sun_direction.normalize_or_zero();
        let light = lighting.ambient + lighting.sun * n.dot(sun).max(0.0);
        let c = base * light;
        [linear_to_srgb(c.x), linear_to_srgb(c.y), linear_to_srgb(c.z), 255]
    }
}

impl Tri {
    /// Perspective-correct uv at barycentrics `l`.
    fn uv_at(&self, l: [f32; 3]) -> Vec2 {
        let iw = l[0] * self.iw[0] + l[1] * self.iw[1] + l[2] * self.iw[2];
        (self.uv[0] * l[0] + self.uv[1] * l[1] + self.uv[2] * l[2]) / iw
    }

    /// Barycentrics at the centre of pixel `(x, y)` (same arithmetic as the rasterizer).
    fn lambdas_at(&self, x: u32, y: u32) -> [f32; 3] {
        let px = i64::from(x) * ONE_PIXEL + HALF_PIXEL;
        let py = i64::from(y) * ONE_PIXEL + HALF_PIXEL;
        let e = edges(&self.v).map(|(a, b)| edge_at(a, b, px, py));
        to_lambdas(e, self.inv_area)
    }
}

/// Edges opposite v0, v1, v2: (v1→v2), (v2→v0), (v0→v1).
fn edges(v: &[[i32; 2]; 3]) -> [([i64; 2], [i64; 2]); 3] {
    let p = v.map(|q| [i64::from(q[0]), i64::from(q[1])]);
    [(p[1], p[2]), (p[2], p[0]), (p[0], p[1])]
}

/// Edge function of `a → b` at `(px, py)`: positive inside a positively oriented triangle.
fn edge_at(a: [i64; 2], b: [i64; 2], px: i64, py: i64) -> i64 {
    (b[0] - a[0]) * (py - a[1]) - (b[1] - a[1]) * (px - a[0])
}

fn to_lambdas(e: [i64; 3], inv_area: f32) -> [f32; 3] {
    e.map(|v| v as f32 * inv_area)
}

/// Calls `f(x, y, lambdas)` for every pixel centre in rows `y_lo..y_hi` covered by `t` under
/// the top-left rule.
fn covered(t: &Tri, y_lo: u32, y_hi: u32, mut f: impl FnMut(u32, u32, [f32; 3])) {
    let ys = u32::from(t.bbox[1]).max(y_lo);
    let ye = u32::from(t.bbox[3]).min(y_hi.saturating_sub(1));
    if ys > ye {
        return;
    }
    let (xs, xe) = (u32::from(t.bbox[0]), u32::from(t.bbox[2]));
    let es = edges(&t.v);
    // Top-left rule: a centre exactly on an edge counts only for top (horizontal, going right
    // in this y-down, positive-area orientation) and left (going up) edges.
    let bias = es.map(|(a, b)| {
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        if (dy == 0 && dx > 0) || dy < 0 { 0 } else { -1 }
    });
    let step_x = es.map(|(a, b)| -(b[1] - a[1]) * ONE_PIXEL);
    let px0 = i64::from(xs) * ONE_PIXEL + HALF_PIXEL;
    for y in ys..=ye {
        let py = i64::from(y) * ONE_PIXEL + HALF_PIXEL;
        let mut e = [0usize, 1, 2].map(|k| edge_at(es[k].0, es[k].1, px0, py));
        for x in xs..=xe {
            if e[0] + bias[0] >= 0 && e[1] + bias[1] >= 0 && e[2] + bias[2] >= 0 {
                f(x, y, to_lambdas(e, t.inv_area));
            }
            for k in 0..3 {
                e[k] += step_x[k];
            }
        }
    }
}

/// Assembles input triangle `t` of an instance: clip, snap, orient, bound, and push the
/// resulting screen triangles (0 if culled, several if clipped) onto `out`.
fn assemble(scene: &Scene<'_>, ctx: &InstanceCtx<'_>, t: usize, width: u32, height: u32, out: &mut Vec<Tri>) {
    let mesh = ctx.inst.mesh;
    let idx = [0, 1, 2].map(|k| mesh.indices[3 * t + k] as usize);
    let mat_id = mesh.material_of_triangle.get(t).copied().unwrap_or(0);
    let mat = &scene.materials[mat_id as usize];
    let item = ctx.inst.items.apply(mesh.item_of_triangle[t]);
    let pos = idx.map(|i| ctx.clip[i]);
    let codes = pos.map(outcode);
    if codes[0] & codes[1] & codes[2] != 0 {
        return;
    }
    let uv = idx.map(|i| mesh.uvs.get(i).map_or(Vec2::ZERO, |&u| Vec2::from(u)));
    let n = if ctx.shade {
        let p = idx.map(|i| mesh.positions[i]);
        let face = ctx.normal_matrix * (p[1] - p[0]).cross(p[2] - p[0]);
        idx.map(|i| {
            let vn = mesh.normals.get(i).map_or(Vec3::ZERO, |&v| ctx.normal_matrix * v);
            // Zero or missing vertex normals fall back to the face normal.
            if vn.length_squared() > 0.0 { vn } else { face }
        })
    } else {
        [Vec3::ZERO; 3]
    };
    let verts = [0, 1, 2].map(|k| ClipVert {
        pos: pos[k],
        uv: uv[k],
        n: n[k],
    });
    let alpha = (mat.texture.is_some() && mat.alpha_cutoff > 0.0) || mat.coverage != FULL_COVERAGE;
    let mut emit = |v: [ClipVert; 3]| {
        if let Some(tri) = setup(v, width, height, item, mat_id, alpha, mat.double_sided) {
            out.push(tri);
        }
    };
    if codes[0] | codes[1] | codes[2] == 0 {
        emit(verts);
    } else {
        let poly = clip_polygon(&verts);
        for k in 1..poly.len().saturating_sub(1) {
            emit([poly[0], poly[k], poly[k + 1]]);
        }
    }
}

/// Screen-space setup of one clipped triangle; `None` if degenerate, culled or covering no
/// pixel centre.
fn setup(
    mut v: [ClipVert; 3],
    width: u32,
    height: u32,
    item: u32,
    material: u16,
    alpha: bool,
    double_sided: bool,
) -> Option<Tri> {
    let snap = |c: &ClipVert| {
        let ndc = c.pos.truncate() / c.pos.w;
        let p = super::camera::ndc_to_pixel(ndc.x, ndc.y, width, height);
        [(p.x * SUBPIXEL).round() as i32, (p.y * SUBPIXEL).round() as i32]
    };
    let mut s = [snap(&v[0]), snap(&v[1]), snap(&v[2])];
    let e = edges(&s);
    let area = edge_at(e[0].0, e[0].1, i64::from(s[0][0]), i64::from(s[0][1]));
    if area == 0 {
        return None;
    }
    // Counter-clockwise on screen (a front face) has a negative area in these y-down
    // coordinates; rasterization wants a positive one.
    let back = area > 0;
    if back && !double_sided {
        return None;
    }
    if !back {
        s.swap(1, 2);
        v.swap(1, 2);
    }
    let min = |k: usize| s.iter().map(|q| i64::from(q[k])).min().unwrap_or(0);
    let max = |k: usize| s.iter().map(|q| i64::from(q[k])).max().unwrap_or(0);
    // Pixels whose centres can lie inside: centre k·256 + 128 within [min, max].
    let first = |lo: i64| (lo - HALF_PIXEL + ONE_PIXEL - 1).div_euclid(ONE_PIXEL);
    let last = |hi: i64| (hi - HALF_PIXEL).div_euclid(ONE_PIXEL);
    let x0 = first(min(0)).max(0);
    let y0 = first(min(1)).max(0);
    let x1 = last(max(0)).min(i64::from(width) - 1);
    let y1 = last(max(1)).min(i64::from(height) - 1);
    if x0 > x1 || y0 > y1 {
        return None;
    }
    let iw = v.map(|c| 1.0 / c.pos.w);
    Some(Tri {
        v: s,
        z: [0, 1, 2].map(|k| v[k].pos.z * iw[k]),
        iw,
        uv: [0, 1, 2].map(|k| v[k].uv * iw[k]),
        n: [0, 1, 2].map(|k| v[k].n * iw[k]),
        inv_area: (1.0 / area.unsigned_abs() as f64) as f32,
        bbox: [x0 as u16, y0 as u16, x1 as u16, y1 as u16],
        item,
        material,
        back,
        alpha,
    })
}

/// Renders `scene` like [`render`], in consecutive groups of whole instances of at most
/// `max_triangles` triangles each (an instance larger than that is a group of its own), merged
/// pixel by pixel.
///
/// Why: [`render`] prepares every triangle of the scene at once (clip-space vertices and
/// binning), which for a forest at full detail (10⁸ triangles) does not fit in memory. One group
/// at a time bounds that to `max_triangles`.
///
/// Contract: the frame is bit-identical to `render(scene, …)`. The merge keeps the smaller
/// `(depth, item)` and, on a full tie, the earlier group, which holds the earlier triangle; the
/// colour is shaded from the winning triangle alone (deferred), so it follows the winner.
/// Errors as [`render`] does.
pub fn render_in_passes(
    scene: &Scene<'_>,
    camera: &Camera,
    width: u32,
    height: u32,
    options: &RenderOptions,
    max_triangles: usize,
) -> Result<Frame, RasterError> {
    if scene.triangle_count() <= max_triangles {
        return render(scene, camera, width, height, options);
    }
    let mut merged: Option<Frame> = None;
    let mut start = 0;
    while start < scene.instances.len() {
        let mut end = start + 1;
        let mut triangles = scene.instances[start].mesh.triangle_count();
        while end < scene.instances.len() {
            let next = scene.instances[end].mesh.triangle_count();
            if triangles + next > max_triangles {
                break;
            }
            triangles += next;
            end += 1;
        }
        let group = Scene {
            instances: scene.instances[start..end].to_vec(),
            materials: scene.materials,
            textures: scene.textures,
        };
        let frame = render(&group, camera, width, height, options)?;
        match merged.as_mut() {
            None => merged = Some(frame),
            Some(acc) => {
                for k in 0..acc.depth.len() {
                    let (z, item) = (frame.depth[k], frame.item[k]);
                    if z < acc.depth[k] || (z == acc.depth[k] && item < acc.item[k]) {
                        acc.depth[k] = z;
                        acc.item[k] = item;
                        if let (Some(dst), Some(&src)) = (acc.color.get_mut(k), frame.color.get(k)) {
                            *dst = src;
                        }
                    }
                }
            }
        }
        start = end;
    }
    match merged {
        Some(frame) => Ok(frame),
        // Not reached: a scene over the limit has instances. One pass is the answer anyway.
        None => render(scene, camera, width, height, options),
    }
}

/// One band's depth, item and colour rows.
type BandOut = (Vec<f32>, Vec<u32>, Vec<[u8; 4]>);

/// Renders `scene` from `camera` into a `width × height` [`Frame`]: depth, item and (with
/// `options.shade`) colour.
///
/// Contract: a pixel shows the alpha-test-surviving fragment with the smallest
/// `(depth, item)`, earliest triangle on a full tie (see the module conventions); the result
/// is bit-identical for any rayon thread count. Errors on an invalid size, camera or scene.
pub fn render(
    scene: &Scene<'_>,
    camera: &Camera,
    width: u32,
    height: u32,
    options: &RenderOptions,
) -> Result<Frame, RasterError> {
    let prep = Prepared::new(scene, camera, width, height, options.shade)?;
    let w = width as usize;
    let bands: Vec<BandOut> = (0..prep.band_count())
        .into_par_iter()
        .map(|b| {
            let (y0, y1) = prep.band_rows(b);
            let n = (y1 - y0) as usize * w;
            let mut depth = vec![f32::INFINITY; n];
            let mut item = vec![EMPTY_ITEM; n];
            let mut win: Vec<(u32, u32)> = if options.shade {
                vec![(u32::MAX, 0); n]
            } else {
                Vec::new()
            };
            prep.raster_band(b, |x, y, z, l, t, id| {
                let k = (y - y0) as usize * w + x as usize;
                if (z < depth[k] || (z == depth[k] && t.item < item[k])) && prep.alpha_ok(t, l, x, y) {
                    depth[k] = z;
                    item[k] = t.item;
                    if let Some(slot) = win.get_mut(k) {
                        *slot = id;
                    }
                }
            });
            let color = if options.shade {
                // Deferred: shade each pixel once, with its winning triangle.
                win.iter()
                    .enumerate()
                    .map(|(k, &id)| {
                        if id.0 == u32::MAX {
                            options.clear_color
                        } else {
                            let (x, y) = ((k % w) as u32, y0 + (k / w) as u32);
                            prep.shade(b, id, x, y, &options.lighting)
                        }
                    })
                    .collect()
            } else {
                Vec::new()
            };
            (depth, item, color)
        })
        .collect();
    let mut frame = Frame {
        width,
        height,
        depth: Vec::with_capacity(w * height as usize),
        item: Vec::with_capacity(w * height as usize),
        color: Vec::with_capacity(if options.shade { w * height as usize } else { 0 }),
    };
    for (d, i, c) in bands {
        frame.depth.extend_from_slice(&d);
        frame.item.extend_from_slice(&i);
        frame.color.extend_from_slice(&c);
    }
    Ok(frame)
}
