//! The residency stage: what the client holds of each model, owned in one place. The block
//! cache, each model's held leaf-band prefixes (derived from the cache, kept current as blocks
//! arrive) and the segment counts of the skeleton iterations checked so far. Only this stage
//! writes them: fetched bytes enter through [`Residency::store`] and
//! [`Residency::keep_unasked`], each unit checked by `canopy_shared::format` first.
//!
//! Conventions: a model is its index into the manifest's models ([`ModelId`]); a leaf node's
//! held bands are the longest prefix of its bands in the cache.

use std::collections::HashSet;
use std::sync::Arc;

use bytes::Bytes;
use canopy_shared::format::skeleton::segment_counts_thicker;

use super::model::{ModelIndex, Models, SegmentsByRadius};
use super::schedule::Request;
use crate::cache::{BlockCache, BlockKey, CacheStats, FrameTouches, ModelId};
use crate::lod::bark::BARK_MIN_RADII;
use crate::net::ByteRange;

/// The leaf bands the cache holds of one model, as of a cache generation.
#[derive(Debug, Clone)]
pub(crate) struct HeldBands {
    generation: u64,
    /// Band prefix held, per leaf node.
    pub bands: Vec<usize>,
    /// Leaves those bands hold, per leaf node (`leaves_in_bands`).
    pub present: Vec<u32>,
}

/// Everything the client holds of the scene's models.
#[derive(Debug)]
pub(crate) struct Residency {
    cache: BlockCache,
    /// Per model: the cached band prefix of each leaf node, as of a cache generation.
    held_bands: Vec<Option<HeldBands>>,
    /// Per model, per skeleton iteration: its segments per bark variant, once its bytes have
    /// been checked.
    skeleton_segments: Vec<Vec<Option<SegmentsByRadius>>>,
}

impl Residency {
    /// An empty residency with a cache of `budget` bytes.
    pub fn new(budget: u64) -> Self {
        Self {
            cache: BlockCache::new(budget),
            held_bands: Vec::new(),
            skeleton_segments: Vec::new(),
        }
    }

    pub fn cache(&self) -> &BlockCache {
        &self.cache
    }

    pub fn stats(&self) -> CacheStats {
        self.cache.stats()
    }

    pub fn used_bytes(&self) -> u64 {
        self.cache.used_bytes()
    }

    /// Whether unit `key` of model `m` is cached.
    pub fn contains(&self, m: usize, key: BlockKey) -> bool {
        self.cache.contains(ModelId(m as u32), key)
    }

    /// The held band prefixes of model `m` as last refreshed ([`Self::refresh_held_bands`]).
    pub fn held_bands(&self, m: usize) -> Option<&HeldBands> {
        self.held_bands.get(m).and_then(Option::as_ref)
    }

    /// Bark triangles of model `m` in each bark variant ([`ModelIndex::bark_triangles`]).
    pub fn bark_triangles(&self, m: usize, idx: &ModelIndex) -> [u64; BARK_MIN_RADII.len()] {
        let segments = self.skeleton_segments.get(m).map_or(&[][..], Vec::as_slice);
        std::array::from_fn(|v| idx.bark_triangles(segments, v))
    }

    /// Bark triangles of model `m`'s skeleton iterations `0..=k` in bark variant `variant`
    /// ([`ModelIndex::bark_triangles_through`]).
    pub fn bark_triangles_through(&self, m: usize, idx: &ModelIndex, k: u8, variant: usize) -> u64 {
        idx.bark_triangles_through(self.skeleton_segments.get(m).map_or(&[], Vec::as_slice), k, variant)
    }

    /// Recomputes the band prefix the cache holds of each leaf node of model `m`, only when the
    /// cache changed since.
    pub fn refresh_held_bands(&mut self, models: &Models, m: usize) {
        let generation = self.cache.generation();
        if self.held_bands.len() < models.len() {
            self.held_bands.resize_with(models.len(), || None);
        }
        let Some(idx) = models.index(m) else {
            return;
        };
        if self.held_bands[m].as_ref().is_none_or(|h| h.generation != generation) {
            let bands: Vec<usize> = (0..idx.leaf_nodes.len())
                .map(|o| self.cache.held_leaf_bands(ModelId(m as u32), o as u32, &idx.layout))
                .collect();
            let present = idx
                .layout
                .leaf_counts()
                .iter()
                .zip(&bands)
                .map(|(&n, &b)| idx.layout.leaves_in_bands(n, b))
                .collect();
            self.held_bands[m] = Some(HeldBands {
                generation,
                bands,
                present,
            });
        }
    }

    /// Forgets model `m`'s held bands (its layout changed: the geometry part arrived).
    pub fn forget_bands(&mut self, m: usize) {
        if let Some(h) = self.held_bands.get_mut(m) {
            *h = None;
        }
    }

    /// Whether the bytes `a..b` of model `m` hold bytes the client already has, a unit the
    /// cache holds or bytes the opening requests read: such a gap is not merged over, or those
    /// bytes would cross the link again.
    pub fn gap_holds_cached(&self, models: &Models, m: usize, a: u64, b: u64) -> bool {
        let Some(idx) = models.index(m) else { return false };
        idx.opened.iter().any(|r| r.start < b && a < r.end)
            || idx.units_within(a, b).iter().any(|u| self.contains(m, u.key))
    }

    /// Keeps the units of a request that arrived (`bodies`, one per merged range), each checked
    /// first, then the whole units that came in its merged gaps; returns the units that failed
    /// their check (dropped, never drawn).
    pub fn store(&mut self, models: &Models, req: &Request, bodies: &[Bytes]) -> u64 {
        let m = req.model;
        let Some(idx) = models.index(m) else { return 0 };
        let ranges = &req.ranges;
        let mut corrupt = 0;
        // Both the wants and the merged ranges are sorted by start: walk them together.
        let mut k = 0;
        for w in &req.wants {
            while k < ranges.len() && ranges[k].end < w.range.end {
                k += 1;
            }
            let Some(r) = ranges.get(k).filter(|r| r.start <= w.range.start) else {
                continue;
            };
            let body = &bodies[k];
            let a = (w.range.start - r.start) as usize;
            let b = (w.range.end - r.start) as usize;
            let Some(bytes) = body.get(a..b) else {
                corrupt += 1;
                continue;
            };
            if w.check.verify(bytes, idx.unit_context()).is_ok() {
                self.accept(models, m, w.key, bytes);
            } else {
                corrupt += 1;
            }
        }
        let wanted: HashSet<BlockKey> = req.wants.iter().map(|w| w.key).collect();
        corrupt + self.keep_unasked(models, m, ranges, bodies, &wanted)
    }

    /// Whole units (leaf blocks, skeleton iterations, hull levels, atlas images, cloud levels)
    /// that arrived without being asked for: in the gaps merged between the `wanted` blocks
    /// ([`MERGE_GAP_BYTES`](crate::plan::MERGE_GAP_BYTES)), or in the requests that opened the
    /// model. Each is checked like a wanted one and cached, so that it does not cross the link
    /// again when it is needed. One is kept only while the cache has room for it without
    /// evicting (it must never push out a block this frame asked for); one that fails its
    /// check is dropped and counted as corrupt (the count is returned), like a wanted one. A
    /// leaf block may lie past a band the node does not hold yet: the cache's held prefix
    /// ([`BlockCache::held_leaf_bands`]) counts it once the bands before it arrive.
    pub fn keep_unasked(
        &mut self,
        models: &Models,
        m: usize,
        ranges: &[ByteRange],
        bodies: &[Bytes],
        wanted: &HashSet<BlockKey>,
    ) -> u64 {
        let Some(idx) = models.index(m) else { return 0 };
        let (mut found, mut corrupt): (Vec<(BlockKey, &[u8])>, u64) = (Vec::new(), 0);
        // Reads may overlap (an opening read and a table read after it): one look per unit.
        let mut seen: HashSet<BlockKey> = HashSet::new();
        for (r, body) in ranges.iter().zip(bodies) {
            for u in idx.units_within(r.start, r.end) {
                if wanted.contains(&u.key) || self.contains(m, u.key) || !seen.insert(u.key) {
                    continue;
                }
                let (Ok(a), Ok(b)) = (
                    usize::try_from(u.range.start - r.start),
                    usize::try_from(u.range.end - r.start),
                ) else {
                    continue;
                };
                let Some(bytes) = body.get(a..b) else { continue };
                if u.check.verify(bytes, idx.unit_context()).is_ok() {
                    found.push((u.key, bytes));
                } else {
                    corrupt += 1;
                }
            }
        }
        for (key, data) in found {
            if self.cache.used_bytes() + data.len() as u64 > self.cache.budget() {
                break;
            }
            self.accept(models, m, key, data);
        }
        corrupt
    }

    /// Caches a checked unit of model `m` (a skeleton iteration also records its segments).
    fn accept(&mut self, models: &Models, m: usize, key: BlockKey, bytes: &[u8]) {
        if let (BlockKey::Skeleton { iteration }, Some(idx)) = (key, models.index(m)) {
            if self.skeleton_segments.len() <= m {
                self.skeleton_segments.resize_with(m + 1, Vec::new);
            }
            let slots = &mut self.skeleton_segments[m];
            if slots.is_empty() {
                slots.resize(idx.directory.iteration_table.len(), None);
            }
            if let Some(slot) = slots.get_mut(usize::from(iteration)) {
                *slot = segment_counts_thicker(bytes, idx.directory.radius_max, &BARK_MIN_RADII)
                    .ok()
                    .and_then(|c| SegmentsByRadius::try_from(c).ok());
            }
        }
        let (g0, ev0) = (self.cache.generation(), self.cache.stats().evictions);
        if self.cache.insert(ModelId(m as u32), key, Arc::from(bytes)) && self.cache.stats().evictions == ev0 {
            self.note_insert(models, m, key, g0);
        }
    }

    /// Keeps the held band prefixes current after `key` of model `m` was inserted without
    /// evicting anything (the cache was at generation `g0` before): only that block changed.
    fn note_insert(&mut self, models: &Models, m: usize, key: BlockKey, g0: u64) {
        let g1 = self.cache.generation();
        for (k, slot) in self.held_bands.iter_mut().enumerate() {
            let Some(hb) = slot else { continue };
            if hb.generation != g0 {
                continue;
            }
            if let (true, BlockKey::Leaf { leaf_node, .. }, Some(idx)) = (k == m, key, models.index(k))
                && let Some(h) = hb.bands.get_mut(leaf_node as usize)
                && let Some(p) = hb.present.get_mut(leaf_node as usize)
            {
                *h = self.cache.held_leaf_bands(ModelId(k as u32), leaf_node, &idx.layout);
                *p = idx
                    .layout
                    .leaves_in_bands(idx.layout.leaf_counts()[leaf_node as usize], *h);
            }
            hb.generation = g1;
        }
    }

    /// Counts `n` wanted units that were not cached.
    pub fn record_misses(&mut self, n: u64) {
        self.cache.record_misses(n);
    }

    /// Marks the frame's units in use (the cache evicts the least used first).
    pub fn touch(&mut self, touches: &[FrameTouches]) {
        self.cache.touch_in_order(touches);
    }

    /// Ends frame `frame` (from 0): every 64 frames the use counts halve, so that old use fades.
    pub fn end_frame(&mut self, frame: u64) {
        if (frame + 1).is_multiple_of(64) {
            self.cache.halve_uses();
        }
    }
}
