//! Seed 004's leaf order by viewpoint mutual information (VMI).
//!
//! Each leaf node is its own object `O` (seed 004: nodes are independent). Views `V` are spread
//! evenly on a sphere around the node's bounding sphere (Fibonacci sphere, orthographic cameras
//! framing the sphere). With `a_o(v)` the visible pixels of leaf `o` from `v` and
//! `a_t(v) = Σ_o a_o(v)`:
//!
//! ```text
//! p(o|v) = a_o / a_t      p(o) = (1/N_v) Σ_v p(o|v)      I(v,O) = Σ_o p(o|v) ln(p(o|v) / p(o))
//! e_VMI(o) = Σ_v |I(v,O) − I(v,O∖{o})|
//! ```
//!
//! Greedy order (the paper's "less important leaves are removed first, VMI recomputed after every
//! removal"): repeatedly remove the leaf whose removal changes VMI least, apply the removal, and
//! recompute visibility; the importance order is the reverse of the removal order (the last leaf
//! left is the most important).
//!
//! Cost. Visibility is never re-rendered: one A-buffer per view holds every pixel's depth-sorted
//! fragments, so removing a leaf re-resolves only the pixels it fronted
//! (`FrontTracker::remove`). Each candidate's effect in each view (pixels it fronts, which of
//! them empty, which leaves behind gain how many) is cached and recomputed only for leaves that
//! have a fragment on a pixel of the removed leaf. Per step, scoring every candidate costs
//! O(n · N_v · g) with g the few leaves a candidate reveals; updating the baselines O(n · N_v). A
//! node of n leaves costs N_v renders plus O(n² · N_v · g) arithmetic.
//!
//! Ties: once two leaves are left, removing either leaves one object whose `I(v)` is 0, so
//! `e_VMI` ties by construction; ties go to the smaller visible area (the more visible leaf is
//! kept), then the smaller index.
//!
//! Approximation, stated: scoring a candidate exactly would recompute `p(o)` of every leaf (all
//! of them move when the candidate's pixels empty). Instead a revealed leaf's `p` gains what it
//! gains in every view, and the removed leaf's probability mass is spread over the rest by one
//! normaliser `Z` (see `Candidate`), not view by view. The chosen removal is then applied
//! exactly and every `p(o)`, `I(v)` recomputed. [`vmi_order_exact`] computes `e_VMI` exactly by
//! re-rendering every view for every candidate (the paper's literal method) and serves as the
//! baseline: 21× slower on a 32-leaf node (benchmarks/log.md); on a 10-leaf toy node the two orders'
//! top halves share 3 of 5 leaves.
//!
//! Batching: nodes are rendered 64 to an image (`BATCH_SIDE`²), each scaled into its own tile, so
//! each sees only its own leaves and the renders' fixed cost is shared.
//!
//! Occlusion by the rest of the tree. Seed 004 counts occluded parts of a leaf as zero area; a
//! node is one object, but it is seen inside its tree. So for every view direction the whole
//! tree (leaves and bark) is also rendered once, orthographic, at `context_resolution`², into
//! an A-buffer reduced to three values per pixel (`ContextView`): the leaf node owning the
//! nearest fragment, its depth, and the depth of the nearest fragment of anything else. Every
//! fragment of a node's tile behind the nearest fragment *not of that node* is cut from the
//! tile's A-buffer ([`ABuffer::retain`]) before the greedy loop, so leaves facing the trunk or
//! buried in the crown have little or no area and go first, and the last leaves kept are those
//! on the tree's outside. The other nodes count as fully present (a node's order cannot depend
//! on the rates other nodes get at run time). Leaves hidden from every view tie at `e_VMI` 0;
//! they go in order of their area when the node is seen alone, least first. Cost: `N_v` more
//! renders of the whole tree, and one pass over the tiles' fragments.

use canopy_shared::format::{NodeKind, NodeRecord};
use canopy_shared::model::TreeModel;
use canopy_shared::raster::{
    ABuffer, Camera, FrontTracker, Instance, ItemMap, Projection, RasterError, RasterMaterial, RasterMesh,
    RenderOptions, Scene, Texture, TreeMeshOptions, fibonacci_sphere, render, tree_materials,
};
use glam::{Mat4, Vec3, Vec4};
use rayon::prelude::*;

/// Options of the VMI bake.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VmiOptions {
    /// Viewpoints per node (seed 004 asks for views spread evenly; at least 32 by default).
    pub views: usize,
    /// Square image size per view, pixels.
    pub resolution: u32,
    /// Side, in pixels, of the whole-tree images from which the rest of the tree occludes each
    /// node (see "Occlusion by the rest of the tree" in the module doc); 0 ranks every node's
    /// leaves as if the node stood alone.
    pub context_resolution: u32,
}

impl Default for VmiOptions {
    fn default() -> Self {
        Self {
            views: 32,
            resolution: 48,
            context_resolution: 512,
        }
    }
}

/// The leaf texture used for VMI and evaluation renders: an alpha-tested lens-shaped blade, so a
/// leaf covers the pixels a real leaf would, not its whole quad.
pub fn leaf_texture() -> Texture {
    Texture::procedural_leaf(32)
}

/// Materials for `model` whose leaves all use texture 0 ([`leaf_texture`]).
pub fn leaf_materials(model: &TreeModel) -> Vec<RasterMaterial> {
    tree_materials(model, &vec![Some(0); model.materials.leaf.len()])
}

/// A mesh of the given leaves whose item ids are their positions in `leaves` (0..n).
fn local_mesh(model: &TreeModel, leaves: &[u32]) -> RasterMesh {
    let mut mesh = RasterMesh::from_tree(
        model,
        &TreeMeshOptions {
            leaves: true,
            bark: false,
            leaf_subset: Some(leaves),
            ..TreeMeshOptions::default()
        },
    );
    for (t, item) in mesh.item_of_triangle.iter_mut().enumerate() {
        *item = (t / 2) as u32;
    }
    mesh
}

/// Orders every leaf node's leaves (indices into `model.leaves`) by VMI, most important first.
/// `nodes` is the hierarchy in preorder; `node_leaves[k]` belongs to the k-th leaf node.
///
/// Nodes are rendered in batches of `BATCH_SIDE²`: every view renders the whole batch once, each
/// node scaled into its own square tile of the image (orthographic, framed on its bounding
/// sphere, which holds its leaves), so each node is its own object, as seed 004 requires, and
/// the renders' fixed cost is paid once per batch rather than once per node. With
/// `context_resolution > 0` the rest of the tree then occludes each tile (module doc); a model
/// whose bounds are not finite, or a hierarchy without leaf nodes, is ranked without context.
pub fn vmi_order(
    model: &TreeModel,
    nodes: &[NodeRecord],
    node_leaves: &mut [Vec<u32>],
    opts: &VmiOptions,
) -> Result<(), RasterError> {
    let spheres: Vec<(Vec3, f32)> = nodes
        .iter()
        .filter(|n| n.kind == NodeKind::Leaf)
        .map(|n| (n.sphere_center, n.sphere_radius))
        .collect();
    let dirs = fibonacci_sphere(opts.views.max(1));
    let materials = leaf_materials(model);
    let textures = [leaf_texture()];
    let per_batch = BATCH_SIDE * BATCH_SIDE;
    let logs = LogTable::new((opts.resolution * opts.resolution) as usize);
    let context = match tree_sphere(model) {
        Some((center, radius)) if opts.context_resolution > 0 && !node_leaves.is_empty() => {
            let mut leaf_node_of = vec![NO_NODE; model.leaves.len()];
            for (k, leaves) in node_leaves.iter().enumerate() {
                for &l in leaves {
                    if let Some(slot) = leaf_node_of.get_mut(l as usize) {
                        *slot = k as u32;
                    }
                }
            }
            let whole = RasterMesh::from_tree(model, &TreeMeshOptions::default());
            dirs.par_iter()
                .map(|&d| {
                    let scene = Scene::single(&whole, &materials, &textures);
                    ContextView::render(&scene, &leaf_node_of, center, radius, d, opts.context_resolution)
                })
                .collect::<Result<Vec<ContextView>, _>>()?
        }
        _ => Vec::new(),
    };
    let layouts: Vec<BatchLayout> = dirs.iter().map(|&d| BatchLayout::new(d, opts.resolution)).collect();
    node_leaves
        .par_chunks_mut(per_batch)
        .zip(spheres.par_chunks(per_batch))
        .enumerate()
        .try_for_each(|(b, (batch, spheres))| {
            let meshes: Vec<RasterMesh> = batch.iter().map(|l| local_mesh(model, l)).collect();
            let mut bases = Vec::with_capacity(batch.len());
            let mut next = 0u32;
            for l in batch.iter() {
                bases.push(next);
                next += l.len() as u32;
            }
            // Visible pixels of each leaf with its node alone, summed over views: the order of
            // the leaves that the rest of the tree hides from every view.
            let mut alone = vec![0u32; next as usize];
            let first_node = (b * per_batch) as u32;
            let abufs: Vec<ABuffer> = layouts
                .iter()
                .enumerate()
                .map(|(v, layout)| {
                    let abuf = render_batch(layout, &meshes, spheres, &bases, &materials, &textures)?;
                    let Some(ctx) = context.get(v) else {
                        return Ok(abuf);
                    };
                    let tracker = FrontTracker::new(&abuf);
                    for (&item, &count) in abuf.items().iter().zip(tracker.counts()) {
                        if let Some(a) = alone.get_mut(item as usize) {
                            *a += count;
                        }
                    }
                    Ok(clip_to_context(&abuf, layout, spheres, first_node, ctx))
                })
                .collect::<Result<_, RasterError>>()?;
            let mut trackers: Vec<FrontTracker> = abufs.iter().map(FrontTracker::new).collect();
            for (k, leaves) in batch.iter_mut().enumerate() {
                let start = bases[k] as usize;
                let tie = &alone[start..start + leaves.len()];
                let order = order_node(leaves.len(), bases[k], &abufs, &mut trackers, &logs, tie);
                *leaves = order.into_iter().map(|i| leaves[i as usize]).collect();
            }
            Ok(())
        })
}

/// The sphere around the model's bounds, for the whole-tree context views; `None` for an empty
/// model or bounds that are not finite.
fn tree_sphere(model: &TreeModel) -> Option<(Vec3, f32)> {
    let (lo, hi) = model.bounds()?;
    let (center, radius) = ((lo + hi) * 0.5, ((hi - lo).length() * 0.5).max(1e-3));
    (center.is_finite() && radius.is_finite()).then_some((center, radius))
}

/// Owner of fragments that belong to no leaf node (bark, leaves outside every node).
const NO_NODE: u32 = u32::MAX;

/// How far behind the nearest other fragment (in NDC depth of the context view, which spans
/// about twice the tree's radius) a node's fragment still counts as visible: coplanar surfaces
/// and rounding, not occlusion.
const CONTEXT_DEPTH_TOLERANCE: f32 = 1e-4;

/// The whole tree from one direction, reduced per pixel to the nearest fragment not of a given
/// leaf node (see the module doc).
struct ContextView {
    view_projection: Mat4,
    size: u32,
    /// Leaf node of the nearest fragment ([`NO_NODE`] for bark or an empty pixel).
    owner: Vec<u32>,
    /// NDC depth of the nearest fragment (infinite if none).
    first: Vec<f32>,
    /// NDC depth of the nearest fragment whose owner differs from `owner` (infinite if none).
    second: Vec<f32>,
}

impl ContextView {
    /// Renders `scene` (the whole tree; items are leaf indices, bark is `BARK_ITEM`)
    /// orthographic from direction `dir`, framing the sphere (`center`, `radius`).
    fn render(
        scene: &Scene<'_>,
        leaf_node_of: &[u32],
        center: Vec3,
        radius: f32,
        dir: Vec3,
        size: u32,
    ) -> Result<Self, RasterError> {
        let camera = Camera::orbit_orthographic(center, radius, dir);
        let abuf = ABuffer::render(scene, &camera, size, size)?;
        let owner_of = |item: u32| leaf_node_of.get(item as usize).copied().unwrap_or(NO_NODE);
        let pixels = (size as usize) * (size as usize);
        let mut owner = vec![NO_NODE; pixels];
        let mut first = vec![f32::INFINITY; pixels];
        let mut second = vec![f32::INFINITY; pixels];
        for p in 0..pixels {
            let frags = abuf.fragments(p);
            let Some(front) = frags.first() else { continue };
            let a = owner_of(front.item);
            owner[p] = a;
            first[p] = front.depth;
            if a != NO_NODE
                && let Some(f) = frags.iter().find(|f| owner_of(f.item) != a)
            {
                second[p] = f.depth;
            }
        }
        Ok(Self {
            view_projection: camera.view_projection(1.0),
            size,
            owner,
            first,
            second,
        })
    }

    /// NDC depth of the nearest fragment not of leaf node `node` on the view ray through
    /// `(x, y)` (NDC of this view); infinite if none or outside the image.
    fn wall(&self, node: u32, x: f32, y: f32) -> f32 {
        let s = self.size as f32;
        let (px, py) = ((x + 1.0) * 0.5 * s, (1.0 - y) * 0.5 * s);
        if !(px >= 0.0 && py >= 0.0 && px < s && py < s) {
            return f32::INFINITY;
        }
        let p = py as usize * self.size as usize + px as usize;
        if self.owner[p] == node {
            self.second[p]
        } else {
            self.first[p]
        }
    }
}

/// Cuts from a batch A-buffer every fragment that the rest of the tree hides in `ctx`. Node
/// `k` of the batch is leaf node `first_node + k`.
fn clip_to_context(
    abuf: &ABuffer,
    layout: &BatchLayout,
    spheres: &[(Vec3, f32)],
    first_node: u32,
    ctx: &ContextView,
) -> ABuffer {
    let side = layout.size as usize;
    let tile = side / BATCH_SIDE;
    // Batch NDC → context NDC, per node: back to the batch's local space, out of the tile to
    // world space, into the context view.
    let to_ctx: Vec<Mat4> = spheres
        .iter()
        .enumerate()
        .map(|(k, &s)| ctx.view_projection * layout.tile_transform(k, s).inverse() * layout.ndc_to_batch)
        .collect();
    // (pixel, wall): the wall is the same for every fragment of a pixel.
    let mut last: Option<(u32, f32)> = None;
    abuf.retain(|p, f| {
        let (x, y) = (p as usize % side, p as usize / side);
        let k = (y / tile) * BATCH_SIDE + x / tile;
        let Some(m) = to_ctx.get(k) else { return true };
        let ndc = |z: f32| {
            let q = *m
                * Vec4::new(
                    (x as f32 + 0.5) / side as f32 * 2.0 - 1.0,
                    1.0 - (y as f32 + 0.5) / side as f32 * 2.0,
                    z,
                    1.0,
                );
            q.truncate() / q.w
        };
        let wall = match last {
            Some((lp, w)) if lp == p => w,
            _ => {
                let q = ndc(0.0);
                let w = ctx.wall(first_node + k as u32, q.x, q.y);
                last = Some((p, w));
                w
            }
        };
        wall.is_infinite() || ndc(f.depth).z <= wall + CONTEXT_DEPTH_TOLERANCE
    })
}

/// Nodes per batch along each side of the batch image.
pub const BATCH_SIDE: usize = 8;

/// Where a batch's nodes land in its image for one view direction: node `k` (its sphere
/// scaled to the unit sphere) in tile `(k % BATCH_SIDE, k / BATCH_SIDE)` of `resolution`-pixel
/// tiles.
struct BatchLayout {
    camera: Camera,
    /// Inverse of the camera's view-projection: batch NDC → batch space.
    ndc_to_batch: Mat4,
    /// The camera's right and up in world space.
    right: Vec3,
    up: Vec3,
    /// Image side, pixels.
    size: u32,
}

impl BatchLayout {
    fn new(dir: Vec3, resolution: u32) -> Self {
        let d = dir.normalize_or(Vec3::Z);
        let up_hint = if d.y.abs() > 0.999_999 { Vec3::Z } else { Vec3::Y };
        let camera = Camera::look_at(
            d * 3.0,
            Vec3::ZERO,
            up_hint,
            Projection::Orthographic {
                half_height: BATCH_SIDE as f32,
                near: 1.999,
                far: 4.001,
            },
        );
        let view = camera.view();
        // Rows of the view rotation.
        let right = Vec3::new(view.x_axis.x, view.y_axis.x, view.z_axis.x);
        let up = Vec3::new(view.x_axis.y, view.y_axis.y, view.z_axis.y);
        Self {
            camera,
            ndc_to_batch: camera.view_projection(1.0).inverse(),
            right,
            up,
            size: resolution * BATCH_SIDE as u32,
        }
    }

    /// World → batch space of node `k` with bounding sphere `(c, r)`.
    fn tile_transform(&self, k: usize, (c, r): (Vec3, f32)) -> Mat4 {
        let side = BATCH_SIDE as f32;
        let (i, j) = ((k % BATCH_SIDE) as f32, (k / BATCH_SIDE) as f32);
        let offset = self.right * (2.0 * i + 1.0 - side) + self.up * (side - 1.0 - 2.0 * j);
        Mat4::from_translation(offset) * Mat4::from_scale(Vec3::splat(1.0 / r.max(1e-4))) * Mat4::from_translation(-c)
    }
}

/// Renders a batch of node meshes into `layout`, node `k`'s items offset by `bases[k]`.
fn render_batch(
    layout: &BatchLayout,
    meshes: &[RasterMesh],
    spheres: &[(Vec3, f32)],
    bases: &[u32],
    materials: &[RasterMaterial],
    textures: &[Texture],
) -> Result<ABuffer, RasterError> {
    let instances = meshes
        .iter()
        .zip(spheres)
        .zip(bases)
        .enumerate()
        .map(|(k, ((mesh, &sphere), &base))| Instance {
            mesh,
            transform: layout.tile_transform(k, sphere),
            items: ItemMap::Offset(base),
        })
        .collect();
    let scene = Scene {
        instances,
        materials,
        textures,
    };
    ABuffer::render(&scene, &layout.camera, layout.size, layout.size)
}

/// One candidate's effect in one view.
#[derive(Debug, Clone, Default)]
struct Effect {
    /// Pixels that become empty.
    empties: u32,
    /// Leaves behind that become visible, with the pixels each gains.
    gains: Vec<(u32, u32)>,
}

/// Per-view state: the fragment lists, the current fronts and the VMI baseline.
struct View<'a, 'b> {
    abuf: &'a ABuffer,
    tracker: &'b mut FrontTracker<'a>,
    /// Item id of local leaf 0.
    base: u32,
    /// Visible pixels per local leaf.
    area: Vec<u32>,
    total: u32,
    s1: f64,
    s2: f64,
    info: f64,
}

fn xlnx(x: f64) -> f64 {
    if x > 0.0 { x * x.ln() } else { 0.0 }
}

/// `x ln x` and `ln x` for the integer pixel counts of one tile, so the greedy loop's inner
/// arithmetic needs no logarithm except for the probabilities it perturbs.
struct LogTable {
    xlnx: Vec<f64>,
    ln: Vec<f64>,
}

impl LogTable {
    fn new(max: usize) -> Self {
        Self {
            xlnx: (0..=max).map(|x| xlnx(x as f64)).collect(),
            ln: (0..=max).map(|x| if x == 0 { 0.0 } else { (x as f64).ln() }).collect(),
        }
    }
    fn xlnx(&self, x: u32) -> f64 {
        self.xlnx.get(x as usize).copied().unwrap_or_else(|| xlnx(f64::from(x)))
    }
    fn ln(&self, x: u32) -> f64 {
        self.ln.get(x as usize).copied().unwrap_or_else(|| f64::from(x).ln())
    }
}

impl View<'_, '_> {
    /// The effect of removing local leaf `c`; fragments at its pixels all belong to this node.
    fn effect_of(&self, c: u32) -> Effect {
        let mut e = Effect::default();
        let id = self.base + c;
        let removed = self.tracker.removed();
        for &p in self.abuf.pixels_of(id) {
            if self.tracker.front(p as usize) != Some(id) {
                continue;
            }
            let behind = self
                .abuf
                .fragments(p as usize)
                .iter()
                .map(|f| f.item)
                .find(|&i| i != id && !removed.contains(i))
                .and_then(|i| i.checked_sub(self.base))
                .filter(|&g| (g as usize) < self.area.len());
            match behind {
                None => e.empties += 1,
                Some(g) => match e.gains.iter_mut().find(|(i, _)| *i == g) {
                    Some(slot) => slot.1 += 1,
                    None => e.gains.push((g, 1)),
                },
            }
        }
        e
    }

    /// Recomputes `s1`, `s2` and `info` from `area` and `ln p` (`lnp`).
    fn rebase(&mut self, lnp: &[f64], logs: &LogTable) {
        let t = f64::from(self.total);
        self.s1 = self.area.iter().map(|&a| logs.xlnx(a)).sum();
        self.s2 = self
            .area
            .iter()
            .zip(lnp)
            .filter(|(a, _)| **a > 0)
            .map(|(&a, &l)| f64::from(a) * l)
            .sum();
        self.info = if self.total > 0 {
            (self.s1 - self.s2) / t - logs.ln(self.total)
        } else {
            0.0
        };
    }

    /// `|I(v, O∖{c}) − I(v, O)|` for candidate `c` with effect `e` in this view. `pg` gives the
    /// perturbed probability of each revealed leaf (its gains over all views added) and `ln_z`
    /// the log of the normaliser of the perturbed distribution (see [`Candidate`]).
    fn delta(&self, c: u32, e: &Effect, lnp: &[f64], cand: &Candidate, logs: &LogTable) -> f64 {
        let ac = self.area[c as usize];
        if ac == 0 {
            return 0.0;
        }
        let t2 = self.total - e.empties;
        if t2 == 0 {
            return self.info.abs();
        }
        let t2f = f64::from(t2);
        let mut s1 = self.s1 - logs.xlnx(ac);
        let mut s2 = self.s2 - f64::from(ac) * lnp[c as usize];
        for &(g, d) in &e.gains {
            let a = self.area[g as usize];
            s1 += logs.xlnx(a + d) - logs.xlnx(a);
            s2 += f64::from(a + d) * cand.ln_p(g, lnp) - if a > 0 { f64::from(a) * lnp[g as usize] } else { 0.0 };
        }
        ((s1 - s2) / t2f - logs.ln(t2) + cand.ln_z - self.info).abs()
    }
}

/// The perturbed probabilities of one candidate's removal: `p'(g) = p(g) + Σ_v δ_g(v) / (N_v·t'(v))`
/// for every leaf `g` it reveals, and the normaliser `Z = 1 − p(c) + Σ_g (p'(g) − p(g))` that
/// spreads the removed leaf's probability mass over the rest (a uniform stand-in for the exact
/// per-view renormalisation), so that `p'` sums to 1 like the exact one.
struct Candidate {
    revealed: Vec<(u32, f64)>,
    ln_z: f64,
}

impl Candidate {
    fn new(c: u32, views: &[View], effects: &[Effect], p: &[f64], nv: f64) -> Self {
        let mut revealed: Vec<(u32, f64)> = Vec::new();
        for (v, e) in views.iter().zip(effects) {
            if v.area[c as usize] == 0 {
                continue;
            }
            let t2 = v.total - e.empties;
            if t2 == 0 {
                continue;
            }
            for &(g, d) in &e.gains {
                let add = f64::from(d) / (nv * f64::from(t2));
                match revealed.iter_mut().find(|(i, _)| *i == g) {
                    Some(slot) => slot.1 += add,
                    None => revealed.push((g, add)),
                }
            }
        }
        let z = 1.0 - p[c as usize] + revealed.iter().map(|(_, a)| a).sum::<f64>();
        let ln_z = if z > 0.0 { z.ln() } else { 0.0 };
        for (g, add) in &mut revealed {
            *add = (p[*g as usize] + *add).ln();
        }
        Self { revealed, ln_z }
    }

    /// `ln p'(g)` before normalisation.
    fn ln_p(&self, g: u32, lnp: &[f64]) -> f64 {
        self.revealed
            .iter()
            .find(|(i, _)| *i == g)
            .map_or(lnp[g as usize], |&(_, l)| l)
    }
}

fn probabilities(views: &[View], n: usize) -> Vec<f64> {
    let mut p = vec![0.0f64; n];
    for v in views.iter().filter(|v| v.total > 0) {
        let t = f64::from(v.total);
        for (o, &a) in v.area.iter().enumerate() {
            p[o] += f64::from(a) / t;
        }
    }
    let nv = views.len() as f64;
    for x in &mut p {
        *x /= nv;
    }
    p
}

/// The VMI order of one node's `n` leaves (item ids `base..base + n` in every view's A-buffer),
/// as local positions, most important first. Removes the node's leaves from `trackers` as it goes.
fn order_node<'a>(
    n: usize,
    base: u32,
    abufs: &'a [ABuffer],
    trackers: &mut [FrontTracker<'a>],
    logs: &LogTable,
    tie: &[u32],
) -> Vec<u32> {
    if n <= 1 {
        return (0..n as u32).collect();
    }
    let mut views: Vec<View> = abufs
        .iter()
        .zip(trackers.iter_mut())
        .map(|(abuf, tracker)| {
            let area: Vec<u32> = (0..n as u32).map(|o| tracker.count_of(base + o)).collect();
            let total = area.iter().sum();
            View {
                abuf,
                tracker,
                base,
                area,
                total,
                s1: 0.0,
                s2: 0.0,
                info: 0.0,
            }
        })
        .collect();
    let nv = views.len() as f64;
    let mut p = probabilities(&views, n);
    let mut lnp: Vec<f64> = p.iter().map(|x| x.ln()).collect();
    for v in &mut views {
        v.rebase(&lnp, logs);
    }

    let mut alive: Vec<u32> = (0..n as u32).collect();
    // effects[c * nvu + v], recomputed when dirty.
    let nvu = views.len();
    let mut effects: Vec<Effect> = Vec::with_capacity(n * nvu);
    for c in 0..n as u32 {
        for v in &views {
            effects.push(v.effect_of(c));
        }
    }
    let mut dirty = vec![false; n * nvu];
    let mut removal = Vec::with_capacity(n);
    while alive.len() > 1 {
        let mut best: Option<(f64, u32, u32, u32)> = None;
        for &c in &alive {
            let eff = &effects[c as usize * nvu..(c as usize + 1) * nvu];
            let cand = Candidate::new(c, &views, eff, &p, nv);
            let e: f64 = views
                .iter()
                .zip(eff)
                .map(|(v, ef)| v.delta(c, ef, &lnp, &cand, logs))
                .sum();
            let area: u32 = views.iter().map(|v| v.area[c as usize]).sum();
            let alone = tie.get(c as usize).copied().unwrap_or(0);
            if best.is_none_or(|b| better_removal((e, area, alone, c), b)) {
                best = Some((e, area, alone, c));
            }
        }
        let Some((_, _, _, r)) = best else { break };
        alive.retain(|&c| c != r);
        removal.push(r);
        for (vi, v) in views.iter_mut().enumerate() {
            let (area, base) = (&mut v.area, v.base);
            v.tracker.remove(base + r, |_, old, new| {
                if let Some(o) = old.checked_sub(base).filter(|&o| (o as usize) < area.len()) {
                    area[o as usize] -= 1;
                }
                if let Some(g) = new
                    .and_then(|g| g.checked_sub(base))
                    .filter(|&g| (g as usize) < area.len())
                {
                    area[g as usize] += 1;
                }
            });
            v.total = v.area.iter().sum();
            for &px in v.abuf.pixels_of(base + r) {
                for f in v.abuf.fragments(px as usize) {
                    if let Some(o) = f.item.checked_sub(base).filter(|&o| (o as usize) < n) {
                        dirty[o as usize * nvu + vi] = true;
                    }
                }
            }
        }
        p = probabilities(&views, n);
        lnp = p.iter().map(|x| x.ln()).collect();
        for v in &mut views {
            v.rebase(&lnp, logs);
        }
        for &c in &alive {
            for (vi, v) in views.iter().enumerate() {
                let k = c as usize * nvu + vi;
                if dirty[k] {
                    effects[k] = v.effect_of(c);
                    dirty[k] = false;
                }
            }
        }
    }
    removal.extend(alive);
    removal.reverse();
    removal
}

/// Relative tolerance under which two `e_VMI` values count as a tie.
const TIE_TOLERANCE: f64 = 1e-9;

/// Whether candidate `a = (e_VMI, visible area, area with the node alone, index)` should be
/// removed before `b`: smaller `e_VMI` first; ties (which VMI produces by construction once two
/// leaves are left: removing either leaves one object, whose I(v) is 0; and among leaves the
/// rest of the tree hides from every view) go to the smaller visible area, then the smaller
/// area with the node alone, then the smaller index, so the most visible leaf is kept and the
/// order is deterministic.
fn better_removal(a: (f64, u32, u32, u32), b: (f64, u32, u32, u32)) -> bool {
    let tol = TIE_TOLERANCE * a.0.abs().max(b.0.abs()).max(1e-12);
    if (a.0 - b.0).abs() > tol {
        return a.0 < b.0;
    }
    (a.1, a.2, a.3) < (b.1, b.2, b.3)
}

/// VMI of a leaf set from per-view visible areas (`areas[v][o]`), exactly as the module doc.
fn vmi_per_view(areas: &[Vec<u32>]) -> Vec<f64> {
    let n = areas.first().map_or(0, Vec::len);
    let nv = areas.len() as f64;
    let mut p = vec![0.0f64; n];
    let totals: Vec<f64> = areas.iter().map(|a| a.iter().map(|&x| f64::from(x)).sum()).collect();
    for (a, &t) in areas.iter().zip(&totals) {
        if t > 0.0 {
            for (o, &x) in a.iter().enumerate() {
                p[o] += f64::from(x) / t / nv;
            }
        }
    }
    areas
        .iter()
        .zip(&totals)
        .map(|(a, &t)| {
            if t <= 0.0 {
                return 0.0;
            }
            a.iter()
                .zip(&p)
                .filter(|(x, _)| **x > 0)
                .map(|(&x, &po)| {
                    let q = f64::from(x) / t;
                    q * (q / po).ln()
                })
                .sum()
        })
        .collect()
}

/// The paper's literal method, for comparison: after every removal, and for every candidate,
/// re-render every view without it and compute `e_VMI` exactly. O(n² · N_v) renders per node.
/// Returns positions into `leaves`, most important first.
pub fn vmi_order_exact(
    model: &TreeModel,
    leaves: &[u32],
    center: Vec3,
    radius: f32,
    opts: &VmiOptions,
) -> Result<Vec<u32>, RasterError> {
    let n = leaves.len();
    let dirs = fibonacci_sphere(opts.views.max(1));
    let materials = leaf_materials(model);
    let textures = [leaf_texture()];
    let cams: Vec<Camera> = dirs
        .iter()
        .map(|&d| Camera::orbit_orthographic(center, radius.max(1e-4), d))
        .collect();
    let ropts = RenderOptions {
        shade: false,
        ..RenderOptions::default()
    };
    let areas_of = |set: &[u32]| -> Result<Vec<Vec<u32>>, RasterError> {
        let sub: Vec<u32> = set.iter().map(|&i| leaves[i as usize]).collect();
        let mut mesh = local_mesh(model, &sub);
        // Map back to positions in `leaves`.
        for item in &mut mesh.item_of_triangle {
            *item = set[*item as usize];
        }
        let scene = Scene::single(&mesh, &materials, &textures);
        cams.iter()
            .map(|cam| {
                let f = render(&scene, cam, opts.resolution, opts.resolution, &ropts)?;
                let mut a = vec![0u32; n];
                for &it in &f.item {
                    if (it as usize) < n {
                        a[it as usize] += 1;
                    }
                }
                Ok(a)
            })
            .collect()
    };
    let mut alive: Vec<u32> = (0..n as u32).collect();
    let mut removal = Vec::with_capacity(n);
    while alive.len() > 1 {
        let base = vmi_per_view(&areas_of(&alive)?);
        let mut best: Option<(f64, u32)> = None;
        for &c in &alive {
            let rest: Vec<u32> = alive.iter().copied().filter(|&x| x != c).collect();
            let mut areas = areas_of(&rest)?;
            // Keep the candidate's slot (area 0) so p(o) is over the same objects.
            for a in &mut areas {
                a[c as usize] = 0;
            }
            let e: f64 = vmi_per_view(&areas).iter().zip(&base).map(|(a, b)| (a - b).abs()).sum();
            if best.is_none_or(|(b, _)| e < b) {
                best = Some((e, c));
            }
        }
        let Some((_, r)) = best else { break };
        alive.retain(|&c| c != r);
        removal.push(r);
    }
    removal.extend(alive);
    removal.reverse();
    Ok(removal)
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_shared::model::{Leaf, Materials, ModelSource};

    fn leaf(c: Vec3, size: f32) -> Leaf {
        Leaf {
            center: c,
            normal: Vec3::Z,
            axis: Vec3::Y,
            width: size,
            length: size,
            branch: None,
            iteration: 0,
            material: 0,
        }
    }

    /// A leaf node of `n` leaves in the sphere `(c, r)`.
    fn leaf_record(c: Vec3, r: f32, n: usize) -> NodeRecord {
        NodeRecord {
            parent: canopy_shared::format::NO_PARENT,
            subtree_end: 1,
            kind: NodeKind::Leaf,
            branch_level: 1,
            sphere_layer: 1,
            branch: canopy_shared::format::NO_BRANCH,
            leaf_count: n as u32,
            growth_direction: Vec3::Y,
            length: 1.0,
            sphere_center: c,
            sphere_radius: r,
            leaf_density: 1.0,
        }
    }

    /// The incremental order of one node, through the batch path.
    fn single_node(m: &TreeModel, leaves: &[u32], c: Vec3, r: f32, opts: &VmiOptions) -> Vec<u32> {
        let mut nl = vec![leaves.to_vec()];
        vmi_order(m, &[leaf_record(c, r, leaves.len())], &mut nl, opts).expect("vmi");
        nl.remove(0)
    }

    fn model(leaves: Vec<Leaf>) -> TreeModel {
        TreeModel {
            name: "t".into(),
            branches: Vec::new(),
            leaves,
            bark_mesh: canopy_shared::model::TriangleMesh::default(),
            materials: Materials::default(),
            iterations: 0,
            source: ModelSource::Gltf,
        }
    }

    /// A shell of leaves around a core of leaves: the core is hidden from every view, so VMI must
    /// rank every shell leaf above every core leaf.
    fn shell_and_core() -> TreeModel {
        let mut ls = Vec::new();
        for d in fibonacci_sphere(60) {
            let mut l = leaf(d * 1.0, 0.45);
            l.normal = d;
            l.axis = d.any_orthonormal_vector();
            ls.push(l);
        }
        for k in 0..8 {
            ls.push(leaf(Vec3::new(0.1 * (k as f32 - 4.0), 0.0, 0.0), 0.05));
        }
        model(ls)
    }

    #[test]
    fn hidden_core_leaves_come_last() {
        let m = shell_and_core();
        let leaves: Vec<u32> = (0..m.leaves.len() as u32).collect();
        let order = single_node(&m, &leaves, Vec3::ZERO, 1.3, &VmiOptions::default());
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, leaves, "a permutation");
        let core_ranks: Vec<usize> = order
            .iter()
            .enumerate()
            .filter(|(_, i)| **i >= 60)
            .map(|(r, _)| r)
            .collect();
        assert!(core_ranks.iter().all(|&r| r >= 60), "core leaves ranked {core_ranks:?}");
    }

    #[test]
    fn exact_and_incremental_both_rank_hidden_leaves_last() {
        // 24 shell leaves around 3 hidden core leaves; both methods must put the core last.
        let mut ls = Vec::new();
        for d in fibonacci_sphere(24) {
            let mut l = leaf(d, 0.7);
            l.normal = d;
            l.axis = d.any_orthonormal_vector();
            ls.push(l);
        }
        for k in 0..3 {
            ls.push(leaf(Vec3::new(0.1 * (k as f32 - 1.0), 0.0, 0.0), 0.05));
        }
        let m = model(ls);
        let leaves: Vec<u32> = (0..27).collect();
        let opts = VmiOptions {
            views: 12,
            resolution: 32,
            ..VmiOptions::default()
        };
        let exact = vmi_order_exact(&m, &leaves, Vec3::ZERO, 1.4, &opts).expect("exact");
        let fast = single_node(&m, &leaves, Vec3::ZERO, 1.4, &opts);
        for order in [&exact, &fast] {
            let core: Vec<usize> = order
                .iter()
                .enumerate()
                .filter(|(_, i)| **i >= 24)
                .map(|(r, _)| r)
                .collect();
            assert!(core.iter().all(|&r| r >= 24), "core ranked {core:?} in {order:?}");
        }
    }

    #[test]
    fn leaves_the_rest_of_the_tree_hides_go_first() {
        // Node A: a shell of 48 leaves around the origin. Node B: a dense wall on the +x
        // hemisphere at radius 3. With occlusion by the rest of the tree, A's +x leaves (hidden
        // from every +x view by B and from every −x view by A's own −x side) rank well below
        // its −x leaves; with each node alone the two sides rank alike.
        let mut ls = Vec::new();
        let dirs = fibonacci_sphere(48);
        for &d in &dirs {
            let mut l = leaf(d, 0.5);
            l.normal = d;
            l.axis = d.any_orthonormal_vector();
            ls.push(l);
        }
        for d in fibonacci_sphere(600).into_iter().filter(|d| d.x > 0.0) {
            let mut l = leaf(d * 3.0, 0.8);
            l.normal = d;
            l.axis = d.any_orthonormal_vector();
            ls.push(l);
        }
        let m = model(ls);
        let a: Vec<u32> = (0..48).collect();
        let b: Vec<u32> = (48..m.leaves.len() as u32).collect();
        let nodes = [
            leaf_record(Vec3::ZERO, 1.3, a.len()),
            leaf_record(Vec3::ZERO, 3.5, b.len()),
        ];
        // Mean rank (0 = most important) of A's +x leaves minus that of its −x leaves.
        let gap = |context_resolution: u32| {
            let mut lists = vec![a.clone(), b.clone()];
            let opts = VmiOptions {
                context_resolution,
                ..VmiOptions::default()
            };
            vmi_order(&m, &nodes, &mut lists, &opts).expect("vmi");
            let mut sorted = lists[0].clone();
            sorted.sort_unstable();
            assert_eq!(sorted, a, "a permutation");
            let mean_rank = |side: f32| {
                let ranks: Vec<f32> = lists[0]
                    .iter()
                    .enumerate()
                    .filter(|(_, l)| dirs[**l as usize].x * side > 0.3)
                    .map(|(r, _)| r as f32)
                    .collect();
                ranks.iter().sum::<f32>() / ranks.len() as f32
            };
            mean_rank(1.0) - mean_rank(-1.0)
        };
        let (with, alone) = (gap(256), gap(0));
        assert!(
            with > 15.0,
            "+x leaves should rank last with the rest of the tree: gap {with}"
        );
        assert!(alone.abs() < 10.0, "alone, the sides should rank alike: gap {alone}");
    }

    #[test]
    fn context_cuts_exactly_what_a_foreign_occluder_covers() {
        // Node 0: a 9 × 9 grid of leaves in the plane z = 0 facing +z. Bark: a quad at z = 2
        // over y > 0.2, facing +z. Seen from +z the bark hides the grid's rows above y = 0.2
        // and nothing below; seen from −z it is behind the grid and hides nothing.
        let mut ls = Vec::new();
        for i in 0..9 {
            for j in 0..9 {
                ls.push(leaf(Vec3::new(-0.8 + 0.2 * i as f32, -0.8 + 0.2 * j as f32, 0.0), 0.15));
            }
        }
        let mut m = model(ls);
        m.bark_mesh = canopy_shared::model::TriangleMesh {
            positions: vec![
                Vec3::new(-3.0, 0.2, 2.0),
                Vec3::new(3.0, 0.2, 2.0),
                Vec3::new(3.0, 3.0, 2.0),
                Vec3::new(-3.0, 3.0, 2.0),
            ],
            normals: Vec::new(),
            indices: vec![0, 1, 2, 0, 2, 3],
        };
        let leaves: Vec<u32> = (0..81).collect();
        let spheres = [(Vec3::ZERO, 1.3)];
        let materials = leaf_materials(&m);
        let textures = [leaf_texture()];
        let whole = RasterMesh::from_tree(&m, &TreeMeshOptions::default());
        let (center, radius) = tree_sphere(&m).expect("finite bounds");
        let meshes = [local_mesh(&m, &leaves)];
        for (dir, hidden_above) in [(Vec3::Z, true), (-Vec3::Z, false)] {
            let scene = Scene::single(&whole, &materials, &textures);
            let ctx = ContextView::render(&scene, &[0; 81], center, radius, dir, 256).expect("context");
            let layout = BatchLayout::new(dir, 48);
            let abuf = render_batch(&layout, &meshes, &spheres, &[0], &materials, &textures).expect("batch");
            let cut = clip_to_context(&abuf, &layout, &spheres, 0, &ctx);
            for (l, leaf) in m.leaves.iter().enumerate() {
                let (before, after) = (abuf.pixels_of(l as u32).len(), cut.pixels_of(l as u32).len());
                assert!(before > 0, "leaf {l} drawn");
                let y = leaf.center.y;
                if !hidden_above || y < 0.1 {
                    assert_eq!(after, before, "leaf {l} at y {y} seen from {dir}");
                } else if y > 0.3 {
                    assert_eq!(after, 0, "leaf {l} at y {y} seen from {dir}");
                }
            }
        }
    }

    #[test]
    fn vmi_of_uniform_views_is_zero() {
        // Every view sees the same distribution: p(o|v) = p(o), so I(v, O) = 0.
        let areas = vec![vec![3, 1, 0], vec![3, 1, 0]];
        assert!(vmi_per_view(&areas).iter().all(|&i| i.abs() < 1e-12));
        // A leaf seen only from one view carries information there.
        let areas = vec![vec![1, 0], vec![0, 1]];
        assert!(vmi_per_view(&areas).iter().all(|&i| (i - 2f64.ln()).abs() < 1e-12));
    }
}
