//! Read access to what the frame loop has cached, decoded for drawing.
//!
//! The viewer uploads geometry and images from here, never from whole files: what it can draw is
//! exactly what the streamer fetched and checked. Reads use [`BlockCache::peek`], so drawing
//! never changes what the cache evicts.

use std::sync::Arc;

use canopy_shared::format::FormatError;
use canopy_shared::format::atlas::{AtlasTable, decode_png_frame};
use canopy_shared::format::cloud::CloudTable;
use canopy_shared::format::directory::SectionKind;
use canopy_shared::format::hull::HullMesh;
use canopy_shared::format::leaf::{BandLayout, LeafFrame, decode_block};
use canopy_shared::format::mesh::decode_mesh;
use canopy_shared::format::skeleton::{SkeletonFrame, decode_skeleton};
use canopy_shared::format::{NO_BRANCH, NodeRecord};
use canopy_shared::model::{Branch, Leaf, Materials, TriangleMesh};
use glam::Vec3;

use super::Streamer;
use super::model::ModelIndex;
use crate::cache::{BlockCache, BlockKey, ModelId};
use crate::net::RangeSource;

/// One opened model as far as it is cached.
#[derive(Debug, Clone, Copy)]
pub struct CachedModel<'a> {
    idx: &'a ModelIndex,
    cache: &'a BlockCache,
    id: ModelId,
}

impl<S: RangeSource> Streamer<S> {
    /// Model `m` (index into the manifest's models) if it is open.
    pub fn cached_model(&self, m: usize) -> Option<CachedModel<'_>> {
        Some(CachedModel {
            idx: self.models.index(m)?,
            cache: self.residency.cache(),
            id: ModelId(u32::try_from(m).ok()?),
        })
    }
}

impl CachedModel<'_> {
    /// Leaf counts of the leaf nodes (ordinal order).
    pub fn leaf_counts(&self) -> &[u32] {
        self.idx.layout.leaf_counts()
    }

    /// The band layout of the leaf section.
    pub fn layout(&self) -> &BandLayout {
        &self.idx.layout
    }

    /// The node record of leaf node `ordinal`.
    pub fn leaf_node(&self, ordinal: usize) -> Option<&NodeRecord> {
        self.idx.nodes.get(*self.idx.leaf_nodes.get(ordinal)?)
    }

    /// Materials (fetched when the model was opened).
    pub fn materials(&self) -> &Materials {
        &self.idx.materials
    }

    /// Bounding sphere in model space (centre, radius).
    pub fn sphere(&self) -> (Vec3, f32) {
        (self.idx.center, self.idx.radius)
    }

    /// Model bounds (min, max).
    pub fn bounds(&self) -> (Vec3, Vec3) {
        (self.idx.directory.bounds_min, self.idx.directory.bounds_max)
    }

    fn peek(&self, key: BlockKey) -> Option<Arc<[u8]>> {
        self.cache.peek(self.id, key)
    }

    /// Leaves `from..to` of leaf node `ordinal` (file order, so a prefix is the node's best
    /// simplification), or `None` while a band they need is not cached. Every block was checked
    /// against its CRC when it entered the cache; decoding checks it again for structure.
    pub fn leaves(&self, ordinal: usize, from: u32, to: u32) -> Result<Option<Vec<Leaf>>, FormatError> {
        let layout = &self.idx.layout;
        let Some(&n) = layout.leaf_counts().get(ordinal) else {
            return Ok(None);
        };
        let to = to.min(n);
        if from >= to {
            return Ok(Some(Vec::new()));
        }
        let dir = &self.idx.directory;
        let frame = LeafFrame {
            lo: dir.bounds_min,
            hi: dir.bounds_max,
            width_max: dir.leaf_width_max,
            length_max: dir.leaf_length_max,
        };
        let branch = self.leaf_node(ordinal).map(|r| r.branch).filter(|&b| b != NO_BRANCH);
        let mut out = Vec::with_capacity((to - from) as usize);
        let mut start = 0u32;
        for band in 0..layout.band_count() {
            if start >= to {
                break;
            }
            let Some(blk) = layout.block(band, ordinal) else {
                continue;
            };
            let end = start + blk.count;
            if end > from {
                let Some(bytes) = self.peek(BlockKey::Leaf {
                    band: band as u8,
                    leaf_node: ordinal as u32,
                }) else {
                    return Ok(None);
                };
                let q = decode_block(&bytes, blk.count, self.idx.leaf_material_count)?;
                let lo = from.saturating_sub(start) as usize;
                let hi = (to.min(end) - start) as usize;
                out.extend(q[lo..hi].iter().map(|l| l.to_leaf(&frame, branch)));
            }
            start = end;
        }
        Ok((out.len() == (to - from) as usize).then_some(out))
    }

    /// The whole skeleton, once every iteration's bytes are cached.
    pub fn branches(&self) -> Result<Option<Vec<Branch>>, FormatError> {
        self.branches_through(u8::MAX)
    }

    /// The model's last iteration (its iteration table has one entry more).
    pub fn last_iteration(&self) -> u8 {
        self.idx.directory.iteration_table.len().saturating_sub(1) as u8
    }

    /// The skeleton of iterations `0..=k` (a prefix of the section; `k` past the last iteration
    /// is the whole skeleton), once those iterations' bytes are cached.
    pub fn branches_through(&self, k: u8) -> Result<Option<Vec<Branch>>, FormatError> {
        let dir = &self.idx.directory;
        let k = k.min(self.last_iteration());
        let mut bytes = Vec::new();
        for j in self.idx.skeleton_iterations().take_while(|&j| j <= k) {
            let Some(b) = self.peek(BlockKey::Skeleton { iteration: j }) else {
                return Ok(None);
            };
            bytes.extend_from_slice(&b);
        }
        let frame = SkeletonFrame {
            lo: dir.bounds_min,
            hi: dir.bounds_max,
            radius_max: dir.radius_max,
        };
        let table = &dir.iteration_table[..dir.iteration_table.len().min(usize::from(k) + 1)];
        decode_skeleton(&bytes, table, &frame).map(Some)
    }

    /// The imported bark mesh (empty for L-system trees) once cached.
    pub fn bark_mesh(&self) -> Result<Option<TriangleMesh>, FormatError> {
        let dir = &self.idx.directory;
        let Some(e) = dir.section(SectionKind::BarkMesh) else {
            return Ok(Some(TriangleMesh::default()));
        };
        if e.length == 0 {
            return Ok(Some(TriangleMesh::default()));
        }
        let Some(b) = self.peek(BlockKey::Section { kind: e.kind.code() }) else {
            return Ok(None);
        };
        decode_mesh(&b, dir.bounds_min, dir.bounds_max).map(Some)
    }

    /// Number of crown-hull levels.
    pub fn hull_levels(&self) -> usize {
        self.idx.hull.as_ref().map_or(0, |h| h.levels.len())
    }

    /// Hull level `level` once cached.
    pub fn hull(&self, level: u16) -> Result<Option<HullMesh>, FormatError> {
        let Some(table) = self.idx.hull.as_ref() else {
            return Ok(None);
        };
        let Some(b) = self.peek(BlockKey::Hull { level }) else {
            return Ok(None);
        };
        table.decode_level(usize::from(level), &b).map(Some)
    }

    /// The billboard atlas table, if the model has atlases.
    pub fn atlas(&self) -> Option<&AtlasTable> {
        self.idx.atlas.as_ref()
    }

    /// Billboard image `frame` at resolution index `res`, decoded, once cached.
    pub fn atlas_image(&self, frame: u32, res: u8) -> Result<Option<image::RgbaImage>, FormatError> {
        let Some(table) = self.idx.atlas.as_ref() else {
            return Ok(None);
        };
        let Some(&side) = table.resolutions.get(usize::from(res)) else {
            return Ok(None);
        };
        let Some(b) = self.peek(BlockKey::Atlas { frame, resolution: res }) else {
            return Ok(None);
        };
        decode_png_frame(&b, side).map(Some)
    }

    /// The billboard-cloud table, if the model has cloud levels.
    pub fn cloud(&self) -> Option<&CloudTable> {
        self.idx.cloud.as_ref()
    }

    /// Every plane texture of cloud level `level`, decoded, in plane order, once cached.
    pub fn cloud_level(&self, level: u8) -> Result<Option<Vec<image::RgbaImage>>, FormatError> {
        let Some(table) = self.idx.cloud.as_ref() else {
            return Ok(None);
        };
        let Some(b) = self.peek(BlockKey::Cloud { level }) else {
            return Ok(None);
        };
        table.decode_level(usize::from(level), &b).map(Some)
    }
}

impl CachedModel<'_> {
    /// The model without leaves (skeleton, bark mesh, materials), once the skeleton and bark
    /// mesh are cached: what bark tessellation needs.
    pub fn bark_model(&self) -> Result<Option<canopy_shared::model::TreeModel>, FormatError> {
        self.bark_model_through(u8::MAX)
    }

    /// [`Self::bark_model`] of the skeleton iterations `0..=k` ([`Self::branches_through`]).
    pub fn bark_model_through(&self, k: u8) -> Result<Option<canopy_shared::model::TreeModel>, FormatError> {
        let (Some(branches), Some(bark_mesh)) = (self.branches_through(k)?, self.bark_mesh()?) else {
            return Ok(None);
        };
        let dir = &self.idx.directory;
        Ok(Some(canopy_shared::model::TreeModel {
            name: dir.name.clone(),
            branches,
            leaves: Vec::new(),
            bark_mesh,
            materials: self.idx.materials.clone(),
            iterations: dir.iterations,
            source: dir.source,
        }))
    }
}

impl<S: RangeSource> Streamer<S> {
    /// The options in force.
    pub fn options(&self) -> &super::StreamOptions {
        &self.base_opts
    }

    /// Replaces the LOD options from the next frame on (the viewer's live controls). The cache
    /// budget stays what it was at construction.
    pub fn set_options(&mut self, opts: super::StreamOptions) {
        self.opts = super::adapt::at_level(&opts, self.detail.level);
        self.base_opts = opts;
    }
}
