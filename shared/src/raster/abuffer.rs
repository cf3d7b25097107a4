//! A-buffer: every pixel's fragments sorted front to back, an item → pixels index, and
//! visibility under removals (the VMI leaf-ordering bake, seed 004).
//!
//! # Memory
//!
//! Fragments are stored once in CSR layout: per fragment 8 bytes ([`Fragment`]: `f32` depth +
//! `u32` item) plus 4 bytes in the item → pixels index; per pixel 4 bytes of offsets; per
//! distinct item 8 bytes. Only the nearest fragment of each item per pixel is kept (a closed
//! bark tube's back face or a folded leaf adds nothing). So a view costs about
//! `12 × fragments + 4 × pixels` bytes, where `fragments = pixels × mean depth complexity`;
//! [`ABuffer::memory_bytes`] reports it. Building needs about twice that transiently (band
//! sort buffers and the index sort). For a bake over many views, build one view at a time and
//! keep the [`ABuffer`]s (or only their [`FrontTracker`] counts) that the greedy loop needs;
//! `benchmarks/log.md` lists measured fragment counts.

use rayon::prelude::*;

use super::pipeline::Prepared;
use super::scene::Scene;
use super::{Camera, RasterError};

/// One fragment of a pixel: NDC depth (smaller is nearer) and item id.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fragment {
    /// NDC depth, 0 near … 1 far.
    pub depth: f32,
    /// Item id.
    pub item: u32,
}

/// A growable set of `u32` ids, one bit each.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct BitSet {
    words: Vec<u64>,
}

impl BitSet {
    /// An empty set.
    pub fn new() -> Self {
        Self::default()
    }

    /// An empty set with room for ids `< n` without reallocating.
    pub fn with_capacity(n: usize) -> Self {
        Self {
            words: Vec::with_capacity(n.div_ceil(64)),
        }
    }

    /// Adds `id`; returns `true` if it was not present. Grows to `id + 1` bits (so huge ids such
    /// as [`super::BARK_ITEM`] cost 512 MiB: do not insert them).
    pub fn insert(&mut self, id: u32) -> bool {
        let (w, b) = ((id / 64) as usize, id % 64);
        if w >= self.words.len() {
            self.words.resize(w + 1, 0);
        }
        let had = self.words[w] >> b & 1 == 1;
        self.words[w] |= 1 << b;
        !had
    }

    /// Removes `id`; returns `true` if it was present.
    pub fn remove(&mut self, id: u32) -> bool {
        let (w, b) = ((id / 64) as usize, id % 64);
        match self.words.get_mut(w) {
            Some(word) if *word >> b & 1 == 1 => {
                *word &= !(1 << b);
                true
            }
            _ => false,
        }
    }

    /// Whether `id` is in the set.
    pub fn contains(&self, id: u32) -> bool {
        self.words
            .get((id / 64) as usize)
            .is_some_and(|w| w >> (id % 64) & 1 == 1)
    }

    /// Number of ids in the set.
    pub fn len(&self) -> usize {
        self.words.iter().map(|w| w.count_ones() as usize).sum()
    }

    /// Whether the set is empty.
    pub fn is_empty(&self) -> bool {
        self.words.iter().all(|&w| w == 0)
    }
}

/// Per-pixel depth-sorted fragment lists for one view, with an item → pixels index.
#[derive(Debug, Clone, PartialEq)]
pub struct ABuffer {
    width: u32,
    height: u32,
    /// Pixel `p`'s fragments are `fragments[offsets[p]..offsets[p + 1]]`.
    offsets: Vec<u32>,
    /// Sorted by `(depth, item)` within each pixel; one per (pixel, item).
    fragments: Vec<Fragment>,
    /// Distinct item ids present, ascending.
    items: Vec<u32>,
    /// Item `items[k]`'s pixels are `item_pixels[item_offsets[k]..item_offsets[k + 1]]`.
    item_offsets: Vec<u32>,
    /// Pixel indices, ascending within each item.
    item_pixels: Vec<u32>,
}

/// Depth as sortable bits: depths are ≥ 0 after clipping, so IEEE order is integer order
/// (−0 folded into +0).
fn depth_key(z: f32) -> u32 {
    if z <= 0.0 { 0 } else { z.to_bits() }
}

impl ABuffer {
    /// Renders every fragment of `scene` that survives the alpha test (no depth test) from
    /// `camera` at `width × height`.
    ///
    /// Contract: pixel lists are sorted by `(depth, item)`, keep the nearest fragment of each
    /// item, and their first entry equals [`super::Frame::item`] of [`super::render`] for the
    /// same inputs; bit-identical for any rayon thread count. Errors as [`super::render`], or
    /// [`RasterError::TooManyFragments`] beyond `u32::MAX` fragments.
    pub fn render(scene: &Scene<'_>, camera: &Camera, width: u32, height: u32) -> Result<Self, RasterError> {
        let prep = Prepared::new(scene, camera, width, height, false)?;
        let w = width as usize;
        let bands: Vec<(Vec<u32>, Vec<Fragment>)> = (0..prep.band_count())
            .into_par_iter()
            .map(|b| {
                let (y0, y1) = prep.band_rows(b);
                let mut raw: Vec<(u32, u32, u32)> = Vec::new();
                prep.raster_band(b, |x, y, z, l, t, _| {
                    if prep.alpha_ok(t, l, x, y) {
                        let k = (y - y0) * width + x;
                        raw.push((k, t.item, depth_key(z)));
                    }
                });
                // Keep each item's nearest fragment per pixel, then order by (depth, item).
                raw.sort_unstable();
                raw.dedup_by_key(|f| (f.0, f.1));
                raw.sort_unstable_by_key(|&(k, item, z)| (k, z, item));
                let mut counts = vec![0u32; (y1 - y0) as usize * w];
                for f in &raw {
                    counts[f.0 as usize] += 1;
                }
                let frags = raw
                    .iter()
                    .map(|&(_, item, z)| Fragment {
                        depth: f32::from_bits(z),
                        item,
                    })
                    .collect();
                (counts, frags)
            })
            .collect();
        let total: usize = bands.iter().map(|b| b.1.len()).sum();
        if u32::try_from(total).is_err() {
            return Err(RasterError::TooManyFragments(total));
        }
        let mut offsets = Vec::with_capacity(w * height as usize + 1);
        let mut fragments = Vec::with_capacity(total);
        offsets.push(0u32);
        let mut acc = 0u32;
        for (counts, frags) in bands {
            for c in counts {
                acc += c;
                offsets.push(acc);
            }
            fragments.extend_from_slice(&frags);
        }
        Ok(Self::from_lists(width, height, offsets, fragments))
    }

    /// A copy keeping only the fragments for which `keep(pixel, fragment)` holds, in the same
    /// order: lists stay sorted by `(depth, item)` with one fragment per (pixel, item), but where
    /// fragments were cut the first entry no longer matches [`super::render`]'s item buffer.
    /// Used to cut each pixel's list at an occluder that is not part of the scene rendered.
    #[must_use]
    pub fn retain(&self, mut keep: impl FnMut(u32, &Fragment) -> bool) -> Self {
        let pixels = self.offsets.len().saturating_sub(1);
        let mut offsets = Vec::with_capacity(pixels + 1);
        let mut fragments = Vec::with_capacity(self.fragments.len());
        offsets.push(0u32);
        for p in 0..pixels {
            for f in self.fragments(p) {
                if keep(p as u32, f) {
                    fragments.push(*f);
                }
            }
            // Never more fragments than the source, which fitted in u32.
            offsets.push(fragments.len() as u32);
        }
        Self::from_lists(self.width, self.height, offsets, fragments)
    }

    /// Builds the item → pixels index over CSR pixel lists.
    fn from_lists(width: u32, height: u32, offsets: Vec<u32>, fragments: Vec<Fragment>) -> Self {
        // Item → pixels index: sort (item, pixel) pairs.
        let mut pairs: Vec<u64> = offsets
            .par_windows(2)
            .enumerate()
            .flat_map_iter(|(p, r)| {
                fragments[r[0] as usize..r[1] as usize]
                    .iter()
                    .map(move |f| (u64::from(f.item) << 32) | p as u64)
            })
            .collect();
        pairs.par_sort_unstable();
        let mut items = Vec::new();
        let mut item_offsets = Vec::new();
        let mut item_pixels = Vec::with_capacity(pairs.len());
        for (k, &pair) in pairs.iter().enumerate() {
            let item = (pair >> 32) as u32;
            if items.last() != Some(&item) {
                items.push(item);
                item_offsets.push(k as u32);
            }
            item_pixels.push(pair as u32);
        }
        item_offsets.push(pairs.len() as u32);
        Self {
            width,
            height,
            offsets,
            fragments,
            items,
            item_offsets,
            item_pixels,
        }
    }

    /// Image width.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Image height.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Total fragments stored.
    pub fn fragment_count(&self) -> usize {
        self.fragments.len()
    }

    /// Bytes held by this A-buffer (heap arrays).
    pub fn memory_bytes(&self) -> usize {
        self.offsets.len() * 4
            + self.fragments.len() * std::mem::size_of::<Fragment>()
            + self.items.len() * 4
            + self.item_offsets.len() * 4
            + self.item_pixels.len() * 4
    }

    /// Fragments of pixel `pixel` (= `y × width + x`), nearest first; empty if out of range.
    pub fn fragments(&self, pixel: usize) -> &[Fragment] {
        match (self.offsets.get(pixel), self.offsets.get(pixel + 1)) {
            (Some(&a), Some(&b)) => &self.fragments[a as usize..b as usize],
            _ => &[],
        }
    }

    /// The nearest item at `pixel` that is not in `removed` (`None`: nothing left there).
    pub fn front(&self, pixel: usize, removed: &BitSet) -> Option<u32> {
        self.fragments(pixel)
            .iter()
            .map(|f| f.item)
            .find(|&i| !removed.contains(i))
    }

    /// Distinct item ids with at least one fragment, ascending.
    pub fn items(&self) -> &[u32] {
        &self.items
    }

    /// Position of `item` in [`ABuffer::items`].
    pub fn item_index(&self, item: u32) -> Option<usize> {
        self.items.binary_search(&item).ok()
    }

    /// Pixels where `item` has a fragment (ascending); empty if none.
    pub fn pixels_of(&self, item: u32) -> &[u32] {
        self.item_index(item).map_or(&[], |k| {
            &self.item_pixels[self.item_offsets[k] as usize..self.item_offsets[k + 1] as usize]
        })
    }

    /// Visible pixel count of each item of [`ABuffer::items`] (same order) when `removed`
    /// items are taken away.
    pub fn front_counts(&self, removed: &BitSet) -> Vec<u32> {
        let mut counts = vec![0u32; self.items.len()];
        for p in 0..self.offsets.len().saturating_sub(1) {
            if let Some(k) = self.front(p, removed).and_then(|i| self.item_index(i)) {
                counts[k] += 1;
            }
        }
        counts
    }
}

/// Incremental visibility over an [`ABuffer`] as items are removed one at a time: keeps each
/// pixel's current front fragment and every item's visible pixel count.
#[derive(Debug, Clone)]
pub struct FrontTracker<'a> {
    abuf: &'a ABuffer,
    /// Per pixel, index into the A-buffer's fragments of the current front (== end if none).
    head: Vec<u32>,
    removed: BitSet,
    /// Visible pixels per item, indexed like [`ABuffer::items`].
    counts: Vec<u32>,
}

impl<'a> FrontTracker<'a> {
    /// A tracker with nothing removed.
    pub fn new(abuf: &'a ABuffer) -> Self {
        Self::with_removed(abuf, BitSet::new())
    }

    /// A tracker starting with `removed` already taken away.
    pub fn with_removed(abuf: &'a ABuffer, removed: BitSet) -> Self {
        let pixels = abuf.offsets.len().saturating_sub(1);
        let mut head = Vec::with_capacity(pixels);
        let mut counts = vec![0u32; abuf.items.len()];
        for p in 0..pixels {
            let (a, b) = (abuf.offsets[p], abuf.offsets[p + 1]);
            let h = (a..b)
                .find(|&k| !removed.contains(abuf.fragments[k as usize].item))
                .unwrap_or(b);
            if h < b
                && let Some(k) = abuf.item_index(abuf.fragments[h as usize].item)
            {
                counts[k] += 1;
            }
            head.push(h);
        }
        Self {
            abuf,
            head,
            removed,
            counts,
        }
    }

    /// Current front item at `pixel` (`None`: empty or everything there removed).
    pub fn front(&self, pixel: usize) -> Option<u32> {
        let h = *self.head.get(pixel)?;
        (h < self.abuf.offsets[pixel + 1]).then(|| self.abuf.fragments[h as usize].item)
    }

    /// Visible pixel counts, indexed like [`ABuffer::items`].
    pub fn counts(&self) -> &[u32] {
        &self.counts
    }

    /// Visible pixel count of `item` (0 if it has no fragment).
    pub fn count_of(&self, item: u32) -> u32 {
        self.abuf.item_index(item).map_or(0, |k| self.counts[k])
    }

    /// The removed set.
    pub fn removed(&self) -> &BitSet {
        &self.removed
    }

    /// Removes `item`: every pixel it fronted is re-resolved to the next fragment behind it
    /// that is not removed, counts are updated, and `on_change(pixel, item, new_front)` is
    /// called for each such pixel (ascending pixel order). Cost: O(pixels where `item` has a
    /// fragment + fragments skipped). Returns `false` (and does nothing) if already removed.
    pub fn remove(&mut self, item: u32, mut on_change: impl FnMut(u32, u32, Option<u32>)) -> bool {
        if !self.removed.insert(item) {
            return false;
        }
        let abuf = self.abuf;
        for &p in abuf.pixels_of(item) {
            let pu = p as usize;
            let end = abuf.offsets[pu + 1];
            let mut h = self.head[pu];
            if h >= end || abuf.fragments[h as usize].item != item {
                continue;
            }
            while h < end && self.removed.contains(abuf.fragments[h as usize].item) {
                h += 1;
            }
            self.head[pu] = h;
            if let Some(k) = abuf.item_index(item) {
                self.counts[k] -= 1;
            }
            let new = (h < end).then(|| abuf.fragments[h as usize].item);
            if let Some(k) = new.and_then(|i| abuf.item_index(i)) {
                self.counts[k] += 1;
            }
            on_change(p, item, new);
        }
        true
    }
}
