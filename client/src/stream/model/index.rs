//! The model index: what a model's opening requests gave, decoded once and never written after
//! (the file's directory, node table, materials, hull, atlas and cloud tables), with the LOD
//! acceleration tables beside it and the units the cache keys by where they lie in the file.
//!
//! Conventions: offsets are absolute file offsets in bytes; ranges are half-open; node and leaf
//! ordinals are those of the node table (leaf ordinal `o` is the `o`-th leaf node).

use std::sync::Arc;

use canopy_shared::format::atlas::{AtlasLayoutKind, AtlasTable};
use canopy_shared::format::cloud::CloudTable;
use canopy_shared::format::directory::SectionKind;
use canopy_shared::format::hull::HullTable;
use canopy_shared::format::leaf::{BandLayout, LeafBlockRef};
use canopy_shared::format::skeleton_radii::last_iteration_reaching;
use canopy_shared::format::unit::{UnitCheck, UnitContext};
use canopy_shared::format::{Directory, IterationEntry, NodeRecord, leaf_node_iterations};
use glam::{Vec3, Vec4};

use crate::cache::BlockKey;
use crate::lod::LeafTable;
use crate::lod::bark::{BARK_MIN_RADII, BARK_VARIANT_SIDES};
use crate::net::ByteRange;

/// A piece of a model file the cache keys: where it is and how to check it.
#[derive(Debug, Clone)]
pub(crate) struct Unit {
    pub key: BlockKey,
    pub range: ByteRange,
    pub check: UnitCheck,
}

/// One opened model: what its first requests gave.
#[derive(Debug)]
pub(crate) struct ModelIndex {
    pub directory: Directory,
    pub nodes: Vec<NodeRecord>,
    pub layout: BandLayout,
    /// Node index of each leaf ordinal.
    pub leaf_nodes: Vec<usize>,
    pub leaves_offset: u64,
    pub leaf_material_count: usize,
    pub materials: canopy_shared::model::Materials,
    pub hull: Option<HullTable>,
    pub atlas: Option<AtlasTable>,
    /// Billboard-cloud table (`None`: no levels baked).
    pub cloud: Option<CloudTable>,
    /// Triangles of the imported bark mesh.
    pub bark_mesh_triangles: u64,
    pub height: f32,
    pub center: Vec3,
    pub radius: f32,
    /// Size of the model's largest leaf, `√(width_max · length_max)` (model units): the pixel
    /// budget's leaf size, an upper bound so that the budget errs towards more leaves.
    pub leaf_size: f32,
    /// The LOD acceleration tables, shared by every instance.
    pub lod: LodTables,
    /// The byte ranges the opening requests read, sorted: a fetch does not merge over them.
    pub opened: Vec<ByteRange>,
    /// [`ModelIndex::other_units`], built once at open.
    pub other_units: Vec<Unit>,
    /// [`ModelIndex::find_crossed_frames`], found once at open.
    pub crossed: Option<[u32; 2]>,
    /// [`ModelIndex::find_stand_in_units`], built once at open.
    pub stand_ins: Vec<Unit>,
    /// Thickest branch radius of each skeleton iteration, metres, from the geometry part
    /// (`None`: not opened yet, or a file without the skeleton-radii section).
    pub iteration_radii: Option<Vec<f32>>,
    /// The opening's first read (header and directory; all of a small file).
    pub head: bytes::Bytes,
}

/// What the per-node LOD reads of a model, derived from its node table at open.
#[derive(Debug)]
pub(crate) struct LodTables {
    /// Leaf-node data the rates read, shared by every instance.
    pub leaf_table: Arc<LeafTable>,
    /// Largest `|node centre − center| + node radius`: a sphere of this radius about `center`
    /// holds every node sphere (node spheres need not lie inside the tree's own sphere).
    pub node_reach: f32,
    /// Per node: radius about its centre holding its subtree's node spheres
    /// ([`crate::lod::tree::subtree_reach`]).
    pub subtree_reach: Vec<f32>,
    /// Per node, the leaf nodes before it ([`crate::lod::tree::leaves_before`]).
    pub leaves_before: Vec<u32>,
    /// Per node, its sphere (model frame): what node culling tests, shared by every instance.
    pub node_spheres: Vec<Vec4>,
    /// Per leaf ordinal, the iteration that created its node's branch (0 without a skeleton
    /// branch): a tree drawn with iterations `≤ k` keeps only the leaf nodes at or below `k`.
    pub leaf_iteration: Vec<u8>,
    /// Largest [`LodTables::leaf_iteration`] (0 without leaf nodes).
    pub max_leaf_iteration: u8,
}

impl LodTables {
    /// The tables of a node table whose root sphere is centred on `center`, with the skeleton's
    /// iteration table `iterations`.
    pub fn new(nodes: &[NodeRecord], center: Vec3, iterations: &[IterationEntry]) -> Self {
        let leaf_iteration = leaf_node_iterations(nodes, iterations);
        let node_reach = nodes
            .iter()
            .map(|n| n.sphere_center.distance(center) + n.sphere_radius.max(0.0))
            .fold(0f32, f32::max);
        Self {
            subtree_reach: crate::lod::tree::subtree_reach(nodes),
            leaves_before: crate::lod::tree::leaves_before(nodes),
            node_spheres: nodes.iter().map(|n| n.sphere_center.extend(n.sphere_radius)).collect(),
            leaf_table: Arc::new(LeafTable::new(nodes)),
            max_leaf_iteration: leaf_iteration.iter().copied().max().unwrap_or(0),
            leaf_iteration,
            node_reach: if node_reach.is_finite() {
                node_reach
            } else {
                f32::INFINITY
            },
        }
    }
}

impl ModelIndex {
    /// Whether the geometry part (node table, materials) is here: without it the model's trees
    /// are drawn as stand-ins.
    pub fn has_geometry(&self) -> bool {
        !self.nodes.is_empty()
    }

    /// What a unit's check reads of this model.
    pub fn unit_context(&self) -> UnitContext<'_> {
        UnitContext {
            leaf_materials: self.leaf_material_count,
            cloud: self.cloud.as_ref(),
        }
    }

    /// Leaf bands of the layout.
    pub fn band_count(&self) -> usize {
        self.layout.band_count()
    }

    /// Whole leaf blocks inside the file's bytes `a..b` ([`BandLayout::blocks_within`]).
    pub fn leaf_blocks_within(&self, a: u64, b: u64) -> Vec<LeafBlockRef> {
        let lo = self.leaves_offset;
        if b <= lo {
            return Vec::new();
        }
        self.layout.blocks_within(a.max(lo) - lo..b - lo)
    }

    /// Skeleton bytes of iteration `k` alone.
    pub fn skeleton_unit(&self, k: usize) -> Option<Unit> {
        let sk = self.directory.section(SectionKind::Skeleton)?;
        let t = &self.directory.iteration_table;
        let start = if k == 0 {
            0
        } else {
            u64::from(t.get(k - 1)?.skeleton_bytes_end)
        };
        let e = t.get(k)?;
        Some(Unit {
            key: BlockKey::Skeleton { iteration: k as u8 },
            range: sk.offset + start..sk.offset + u64::from(e.skeleton_bytes_end),
            check: UnitCheck::Crc(e.skeleton_crc),
        })
    }

    /// The imported bark mesh section.
    pub fn bark_unit(&self) -> Option<Unit> {
        let b = self.directory.section(SectionKind::BarkMesh)?;
        Some(Unit {
            key: BlockKey::Section { kind: b.kind.code() },
            range: b.range(),
            check: UnitCheck::Crc(b.crc),
        })
    }

    /// Crown-hull level `level`.
    pub fn hull_unit(&self, level: usize) -> Option<Unit> {
        let sec = self.directory.section(SectionKind::Hulls)?;
        let e = self.hull.as_ref()?.levels.get(level)?;
        let a = sec.offset + u64::from(e.offset);
        Some(Unit {
            key: BlockKey::Hull { level: level as u16 },
            range: a..a + u64::from(e.length),
            check: UnitCheck::Crc(e.crc),
        })
    }

    /// The two crossed-quad frames of the atlas, when both have an image at every resolution:
    /// the view-independent stand-in every tree of the model is drawn as before anything else
    /// (two small images, a billboard that reads as a tree, where a coarse hull reads as a rock).
    pub fn find_crossed_frames(&self) -> Option<[u32; 2]> {
        let a = self.atlas.as_ref()?;
        let l = a.layouts.iter().find(|l| l.kind == AtlasLayoutKind::CrossedQuads)?;
        let frames = [l.first_frame, l.first_frame + 1];
        let complete = |f: u32| (0..a.resolutions.len()).all(|r| a.image(f, r).is_some());
        (!a.resolutions.is_empty() && frames.iter().all(|&f| complete(f))).then_some(frames)
    }

    /// The stand-in units: the crossed frames ([`Self::crossed`], set first) at the coarsest
    /// resolution, else the coarsest hull level; none for a model with neither.
    pub fn find_stand_in_units(&self) -> Vec<Unit> {
        if let (Some(frames), Some(a)) = (self.crossed, self.atlas.as_ref()) {
            let coarsest = (a.resolutions.len() - 1) as u8;
            return frames.iter().filter_map(|&f| self.atlas_unit(f, coarsest)).collect();
        }
        self.hull
            .as_ref()
            .filter(|h| !h.levels.is_empty())
            .and_then(|h| self.hull_unit(h.levels.len() - 1))
            .into_iter()
            .collect()
    }

    /// Atlas image of `frame` at resolution `res`.
    pub fn atlas_unit(&self, frame: u32, res: u8) -> Option<Unit> {
        let sec = self.directory.section(SectionKind::BillboardAtlases)?;
        let e = self.atlas.as_ref()?.image(frame, usize::from(res))?;
        let a = sec.offset + u64::from(e.offset);
        Some(Unit {
            key: BlockKey::Atlas { frame, resolution: res },
            range: a..a + u64::from(e.length),
            check: UnitCheck::Crc(e.crc),
        })
    }

    /// Billboard-cloud level `level`.
    pub fn cloud_unit(&self, level: usize) -> Option<Unit> {
        let sec = self.directory.section(SectionKind::BillboardClouds)?;
        let r = self.cloud.as_ref()?.level_range(level)?;
        Some(Unit {
            key: BlockKey::Cloud { level: level as u8 },
            range: sec.offset + r.start..sec.offset + r.end,
            check: UnitCheck::CloudLevel(level as u8),
        })
    }

    /// Every unit other than leaf blocks (skeleton iterations, bark mesh, hull levels, atlas
    /// images, cloud levels), sorted by offset: built once at open.
    pub fn other_units(&self) -> Vec<Unit> {
        let mut units: Vec<Unit> = (0..self.directory.iteration_table.len())
            .filter_map(|k| self.skeleton_unit(k))
            .collect();
        units.extend(self.bark_unit());
        let hulls = self.hull.as_ref().map_or(0, |h| h.levels.len());
        units.extend((0..hulls).filter_map(|l| self.hull_unit(l)));
        if let Some(atlas) = &self.atlas {
            let nres = atlas.resolutions.len();
            for frame in 0..atlas.frames.len() as u32 {
                units.extend((0..nres).filter_map(|res| self.atlas_unit(frame, res as u8)));
            }
        }
        let clouds = self.cloud.as_ref().map_or(0, |c| c.levels.len());
        units.extend((0..clouds).filter_map(|l| self.cloud_unit(l)));
        units.retain(|u| u.range.end > u.range.start);
        units.sort_by_key(|u| u.range.start);
        units
    }

    /// Every unit the cache keys whose bytes lie wholly inside the file's bytes `a..b`.
    pub fn units_within(&self, a: u64, b: u64) -> Vec<Unit> {
        let mut units: Vec<Unit> = self
            .leaf_blocks_within(a, b)
            .iter()
            .map(|blk| self.leaf_unit(blk))
            .collect();
        let from = self.other_units.partition_point(|u| u.range.start < a);
        units.extend(
            self.other_units[from..]
                .iter()
                .take_while(|u| u.range.start < b)
                .filter(|u| u.range.end <= b)
                .cloned(),
        );
        units
    }

    /// Iterations whose skeleton bytes are not empty (each is one checked block).
    pub fn skeleton_iterations(&self) -> impl Iterator<Item = u8> + '_ {
        let t = &self.directory.iteration_table;
        (0..t.len()).filter_map(move |k| {
            let start = if k == 0 { 0 } else { t[k - 1].skeleton_bytes_end };
            (t[k].skeleton_bytes_end > start).then_some(k as u8)
        })
    }

    /// Bark triangles of bark variant `variant` ([`crate::lod::bark`]): the skeleton tubes thick
    /// enough for it at its [`BARK_VARIANT_SIDES`] sides, plus the bark mesh, from the segments
    /// of each skeleton iteration checked so far (`segments`, per iteration, per variant).
    /// Iterations not checked yet count nothing: which of their twigs a variant keeps depends on
    /// radii not read yet, and a guess of every twig overstated far trees' bark twentyfold. A
    /// lower bound until the skeleton is held (a tree is drawn as geometry only then).
    pub fn bark_triangles(&self, segments: &[Option<SegmentsByRadius>], variant: usize) -> u64 {
        let last = self.directory.iteration_table.len().saturating_sub(1) as u8;
        self.bark_triangles_through(segments, last, variant)
    }

    /// The last skeleton iteration bark variant `variant` draws a branch of
    /// ([`crate::lod::bark`]): later ones hold only twigs the variant leaves out, so a tree drawn
    /// at it needs no skeleton past this. The last iteration when the radii are not known.
    pub fn bark_iterations(&self, variant: usize) -> u8 {
        let last = self.directory.iteration_table.len().saturating_sub(1);
        let min_radius = BARK_MIN_RADII.get(variant).copied().unwrap_or(0.0);
        let k = match &self.iteration_radii {
            Some(r) if min_radius > 0.0 => last_iteration_reaching(r, min_radius).unwrap_or(0),
            _ => last,
        };
        k.min(last) as u8
    }

    /// Skeleton iterations `0..=k` drawn with `dropped` of them left out: `last − dropped`, but
    /// never below the first iteration that has branches (an L-system's axiom draws nothing).
    pub fn drawn_iterations(&self, dropped: u8) -> u8 {
        let table = &self.directory.iteration_table;
        let last = table.len().saturating_sub(1) as u8;
        let first = table.iter().position(|e| e.branches_end > 0).unwrap_or(0) as u8;
        last.saturating_sub(dropped).max(first.min(last))
    }

    /// Bark triangles of the skeleton iterations `0..=k` alone (seed 000's middle level) in bark
    /// variant `variant`: as [`Self::bark_triangles`] (iterations not checked yet count nothing).
    pub fn bark_triangles_through(&self, segments: &[Option<SegmentsByRadius>], k: u8, variant: usize) -> u64 {
        let t = &self.directory.iteration_table;
        let v = variant.min(BARK_VARIANT_SIDES.len() - 1);
        let last = usize::from(k).min(t.len().saturating_sub(1));
        let total: u64 = segments.iter().take(last + 1).flatten().map(|s| s[v]).sum();
        total * 2 * u64::from(BARK_VARIANT_SIDES[v]) + self.bark_mesh_triangles
    }

    /// The unit of a leaf block (offsets relative to the leaves section).
    pub fn leaf_unit(&self, blk: &LeafBlockRef) -> Unit {
        let start = self.leaves_offset + blk.offset;
        Unit {
            key: BlockKey::Leaf {
                band: blk.band,
                leaf_node: blk.leaf_node,
            },
            range: start..start + blk.len,
            check: UnitCheck::LeafBlock { count: blk.count },
        }
    }
}

/// Per bark variant ([`crate::lod::bark::BARK_MIN_RADII`]), the segments of one skeleton
/// iteration's branches thick enough for it.
pub type SegmentsByRadius = [u64; BARK_MIN_RADII.len()];
