//! Range planning: which leaf-block byte ranges a client must fetch.
//!
//! Input: the tree's [`BandLayout`] (from the node table alone), the absolute offset of the
//! leaves section, and per leaf node (in leaf-node ordinal order, i.e. preorder among leaf nodes):
//! how many leaves to keep, how many bands the cache already holds, and the visual gain per leaf.
//!
//! 1. A node keeping `k` of its `n` leaves needs bands `0..layout.bands_for_keep(n, k)`.
//! 2. Bands `0..held` of a node are in the cache and are not requested: `held` is the prefix of
//!    a node's bands the cache holds, because leaves are drawn as a prefix of the importance
//!    order. (The cache may also hold a later band whose block arrived in a merged gap; the
//!    streamer does not ask for cached blocks again, and this planner counts them only once
//!    the prefix reaches them.)
//! 3. The remaining blocks, sorted by offset, are merged into ranges: a block joins the current
//!    range when the gap between them is **strictly less than** [`MERGE_GAP_BYTES`] (a gap of
//!    `MERGE_GAP_BYTES − 1` merges, `MERGE_GAP_BYTES` does not; adjacent blocks, gap 0, always
//!    merge) **and** the gap contains no block the cache holds. Gap bytes are fetched anyway:
//!    one request costs more than a few KiB on any real link. The streamer keeps the whole
//!    leaf blocks among them (checked like wanted ones), so they do not cross the link again.
//! 4. Ranges are ordered by visual gain per byte, descending (`Σ gain·count` of their blocks over
//!    their length, gap bytes included); ties by start offset. Blocks are independent (each has
//!    its own CRC and first rank), but drawing needs a prefix of bands: a client applies a block
//!    once its node's earlier bands are present.
//!
//! Ranges are absolute file offsets, `start..end` with `end` exclusive; the blocks'
//! [`LeafBlockRef::offset`] stays relative to the leaves section, as in the format.

use canopy_shared::format::leaf::{BandLayout, LeafBlockRef, keep_count};

/// Two needed blocks closer than this (bytes between them) are fetched in one range.
pub const MERGE_GAP_BYTES: u64 = 4096;

/// Planning errors.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum PlanError {
    /// A per-node slice does not have one entry per leaf node.
    #[error("{what}: {got} entries for {expected} leaf nodes")]
    LengthMismatch {
        /// Which argument.
        what: &'static str,
        /// Leaf nodes.
        expected: usize,
        /// Entries given.
        got: usize,
    },
}

/// One byte range to request and the leaf blocks it carries.
#[derive(Debug, Clone, PartialEq)]
pub struct PlannedRange {
    /// First byte (absolute).
    pub start: u64,
    /// One past the last byte (absolute).
    pub end: u64,
    /// Needed blocks inside, by offset.
    pub blocks: Vec<LeafBlockRef>,
    /// Visual gain of the blocks (`Σ gain·count`).
    pub gain: f64,
}

impl PlannedRange {
    /// Bytes requested.
    pub fn len(&self) -> u64 {
        self.end - self.start
    }

    /// Whether the range is empty (never, for a planned range).
    pub fn is_empty(&self) -> bool {
        self.end <= self.start
    }

    /// Gain per byte requested.
    pub fn gain_per_byte(&self) -> f64 {
        if self.is_empty() {
            0.0
        } else {
            self.gain / self.len() as f64
        }
    }
}

/// The ranges to request, best first.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RangePlan {
    /// Ranges ordered by gain per byte (descending), non-overlapping.
    pub ranges: Vec<PlannedRange>,
    /// Σ range lengths (gap bytes included).
    pub bytes: u64,
    /// Σ needed block lengths (`bytes − block_bytes` is the merge overhead).
    pub block_bytes: u64,
}

/// Bands each leaf node needs to keep `keep[i]` leaves.
pub fn needed_bands(layout: &BandLayout, keep: &[u32]) -> Vec<usize> {
    layout
        .leaf_counts()
        .iter()
        .zip(keep)
        .map(|(&n, &k)| layout.bands_for_keep(n, k.min(n)))
        .collect()
}

/// Whether a block starting at `next_start` joins a range ending at `prev_end` (gap only).
pub fn gap_merges(prev_end: u64, next_start: u64) -> bool {
    next_start.saturating_sub(prev_end) < MERGE_GAP_BYTES
}

/// Merges ranges sorted by start where [`gap_merges`] allows, except over a gap `end..start`
/// for which `keep_apart(end, start)` holds (a gap holding bytes the client already has).
/// Overlapping or touching ranges always merge. The leaf planner applies the same rule block by
/// block ([`plan_leaf_ranges`]); the scheduler applies it to a model's units of every kind.
pub fn merge_ranges_unless(
    sorted: impl Iterator<Item = std::ops::Range<u64>>,
    keep_apart: impl Fn(u64, u64) -> bool,
) -> Vec<std::ops::Range<u64>> {
    let mut out: Vec<std::ops::Range<u64>> = Vec::new();
    for r in sorted {
        if let Some(last) = out.last_mut()
            && r.start >= last.start
            && gap_merges(last.end, r.start)
            && (r.start <= last.end || !keep_apart(last.end, r.start))
        {
            last.end = last.end.max(r.end);
            continue;
        }
        out.push(r);
    }
    out
}

/// [`merge_ranges_unless`] with no gap kept apart.
pub fn merge_ranges(sorted: impl Iterator<Item = std::ops::Range<u64>>) -> Vec<std::ops::Range<u64>> {
    merge_ranges_unless(sorted, |_, _| false)
}

/// Best gain per byte first (`gain / len`, descending): the one order of fetching, for the leaf
/// planner's ranges and the scheduler's units alike. Ties are the caller's to break.
pub fn by_gain_per_byte(gain_a: f64, len_a: u64, gain_b: f64, len_b: u64) -> std::cmp::Ordering {
    let per_byte = |g: f64, len: u64| if len == 0 { 0.0 } else { g / len as f64 };
    per_byte(gain_b, len_b).total_cmp(&per_byte(gain_a, len_a))
}

fn check_len(what: &'static str, expected: usize, got: usize) -> Result<(), PlanError> {
    if expected == got {
        Ok(())
    } else {
        Err(PlanError::LengthMismatch { what, expected, got })
    }
}

fn gain_of(gain: f32) -> f64 {
    if gain.is_finite() && gain > 0.0 {
        f64::from(gain)
    } else {
        0.0
    }
}

/// Plans the leaf ranges (see the module doc). `leaves_offset` is the leaves section's absolute
/// offset; `keep`, `held_bands` and `gain_per_leaf` have one entry per leaf node. Non-finite or
/// negative gains count as 0.
pub fn plan_leaf_ranges(
    layout: &BandLayout,
    leaves_offset: u64,
    keep: &[u32],
    held_bands: &[usize],
    gain_per_leaf: &[f32],
) -> Result<RangePlan, PlanError> {
    let n = layout.leaf_counts().len();
    check_len("keep", n, keep.len())?;
    check_len("held_bands", n, held_bands.len())?;
    check_len("gain_per_leaf", n, gain_per_leaf.len())?;
    let bands = layout.band_count();
    let need = needed_bands(layout, keep);
    // Band-major layout: iterating band then node yields blocks in offset order.
    let mut blocks = Vec::new();
    let mut held = Vec::new();
    for b in 0..bands {
        for i in 0..n {
            if let Some(blk) = layout.block(b, i) {
                if b < held_bands[i] {
                    held.push(blk.offset..blk.offset + blk.len);
                } else if b < need[i] {
                    blocks.push(blk);
                }
            }
        }
    }
    let mut ranges: Vec<PlannedRange> = Vec::new();
    let mut block_bytes = 0u64;
    for blk in blocks {
        block_bytes += blk.len;
        let start = blk.offset;
        let end = blk.offset + blk.len;
        let g = gain_of(gain_per_leaf[blk.leaf_node as usize]) * f64::from(blk.count);
        if let Some(last) = ranges.last_mut() {
            let prev_end = last.end - leaves_offset;
            // First held block ending after the range: does it start inside the gap?
            let h = held.partition_point(|r| r.end <= prev_end);
            let gap_has_held = held.get(h).is_some_and(|r| r.start < start);
            if gap_merges(prev_end, start) && !gap_has_held {
                last.end = leaves_offset + end;
                last.blocks.push(blk);
                last.gain += g;
                continue;
            }
        }
        ranges.push(PlannedRange {
            start: leaves_offset + start,
            end: leaves_offset + end,
            blocks: vec![blk],
            gain: g,
        });
    }
    ranges.sort_by(|a, b| by_gain_per_byte(a.gain, a.len(), b.gain, b.len()).then(a.start.cmp(&b.start)));
    let bytes = ranges.iter().map(PlannedRange::len).sum();
    Ok(RangePlan {
        ranges,
        bytes,
        block_bytes,
    })
}

/// One contiguous range for a uniform rate: every node gets the bands the neediest node needs
/// (`max_i bands_for_keep(n_i, keep_count(n_i, rate))`), which in a band-major layout is the
/// single range from the start of band 0 to the end of the last band needed. `None` when nothing
/// is needed. Every block inside is listed; `gain` is the leaves carried.
pub fn uniform_range(layout: &BandLayout, leaves_offset: u64, rate: f32) -> Option<PlannedRange> {
    let bands = layout
        .leaf_counts()
        .iter()
        .map(|&n| layout.bands_for_keep(n, keep_count(n, rate)))
        .max()
        .unwrap_or(0);
    if bands == 0 {
        return None;
    }
    let n = layout.leaf_counts().len();
    let blocks: Vec<LeafBlockRef> = (0..bands)
        .flat_map(|b| (0..n).filter_map(move |i| layout.block(b, i)))
        .collect();
    let gain = blocks.iter().map(|b| f64::from(b.count)).sum();
    let r = layout.band_range(0).start..layout.band_range(bands - 1).end;
    (r.end > r.start).then(|| PlannedRange {
        start: leaves_offset + r.start,
        end: leaves_offset + r.end,
        blocks,
        gain,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
pub(crate) mod tests {
    use super::*;

    #[test]
    fn merge_ranges_uses_the_gap_constant() {
        let g = MERGE_GAP_BYTES;
        assert_eq!(merge_ranges([0..10, 10 + g - 1..20 + g].into_iter()), vec![0..20 + g]);
        assert_eq!(
            merge_ranges([0..10, 10 + g..20 + g].into_iter()),
            vec![0..10, 10 + g..20 + g]
        );
        assert_eq!(merge_ranges([0..10, 5..8].into_iter()), vec![0..10]);
    }

    #[test]
    fn merge_ranges_keeps_apart_gaps_it_is_told_to() {
        let apart = |a: u64, b: u64| a <= 15 && b >= 15;
        // The gap 10..20 holds byte 15: not merged; 30..40 does not: merged.
        assert_eq!(
            merge_ranges_unless([0..10, 20..30, 40..50].into_iter(), apart),
            vec![0..10, 20..50]
        );
        // Touching and overlapping ranges have no gap to keep apart.
        assert_eq!(
            merge_ranges_unless([0..15, 15..20, 18..25].into_iter(), apart),
            vec![0..25]
        );
    }
    use canopy_shared::format::leaf::DEFAULT_BAND_EDGES;
    use proptest::prelude::*;
    use std::collections::HashSet;

    const ONE_BAND: [u16; 1] = [65535];

    #[test]
    fn gap_boundary() {
        assert!(gap_merges(100, 100));
        assert!(gap_merges(100, 100 + MERGE_GAP_BYTES - 1));
        assert!(!gap_merges(100, 100 + MERGE_GAP_BYTES));
    }

    #[test]
    fn layout_gap_boundary() {
        // One band: each node is one block of 16·n + 4 bytes. Three skipped blocks of 85 leaves:
        // gap 16·255 + 12 = 4092 < 4096 → one range. Four skipped blocks of 255 leaves in all:
        // gap 16·255 + 16 = 4096 → two ranges.
        let layout = BandLayout::new(&ONE_BAND, &[1, 85, 85, 85, 1]);
        let p = plan_leaf_ranges(&layout, 1000, &[1, 0, 0, 0, 1], &[0; 5], &[1.0; 5]).unwrap();
        assert_eq!(p.ranges.len(), 1);
        assert_eq!(p.ranges[0].start, 1000);
        assert_eq!(p.ranges[0].end, 1000 + 20 + 4092 + 20);
        assert_eq!(p.bytes, 4132);
        assert_eq!(p.block_bytes, 40);
        let layout = BandLayout::new(&ONE_BAND, &[1, 64, 64, 64, 63, 1]);
        let p = plan_leaf_ranges(&layout, 0, &[1, 0, 0, 0, 0, 1], &[0; 6], &[1.0; 6]).unwrap();
        assert_eq!(p.ranges.len(), 2);
        assert_eq!(p.ranges[1].start - (p.ranges[0].end), MERGE_GAP_BYTES);
        assert_eq!(p.bytes, 40);
        // A held block in a small gap prevents the merge.
        let layout = BandLayout::new(&ONE_BAND, &[1, 1, 1]);
        let p = plan_leaf_ranges(&layout, 0, &[1, 1, 1], &[0, 1, 0], &[1.0; 3]).unwrap();
        assert_eq!(p.ranges.len(), 2);
    }

    #[test]
    fn ordered_by_gain_per_byte() {
        let layout = BandLayout::new(&ONE_BAND, &[10, 1000, 10]);
        let p = plan_leaf_ranges(&layout, 0, &[10, 0, 10], &[0; 3], &[1.0, 0.0, 5.0]).unwrap();
        assert_eq!(p.ranges.len(), 2);
        assert_eq!(p.ranges[0].blocks[0].leaf_node, 2);
        assert_eq!(p.ranges[1].blocks[0].leaf_node, 0);
        assert!((p.ranges[0].gain - 50.0).abs() < 1e-9);
    }

    #[test]
    fn length_mismatch_and_nothing_needed() {
        let layout = BandLayout::new(&DEFAULT_BAND_EDGES, &[10, 20]);
        assert_eq!(
            plan_leaf_ranges(&layout, 0, &[1], &[0, 0], &[1.0, 1.0]),
            Err(PlanError::LengthMismatch {
                what: "keep",
                expected: 2,
                got: 1
            })
        );
        let p = plan_leaf_ranges(&layout, 0, &[0, 0], &[0, 0], &[1.0, 1.0]).unwrap();
        assert!(p.ranges.is_empty());
        assert_eq!(p.bytes, 0);
        // All held.
        let p = plan_leaf_ranges(&layout, 0, &[10, 20], &[8, 8], &[1.0, 1.0]).unwrap();
        assert!(p.ranges.is_empty());
    }

    #[test]
    fn uniform_range_matches_bands() {
        let layout = BandLayout::new(&DEFAULT_BAND_EDGES, &[64, 100, 7]);
        assert_eq!(uniform_range(&layout, 0, 1.0), None);
        let all = uniform_range(&layout, 500, 0.0).unwrap();
        assert_eq!(all.start, 500);
        assert_eq!(all.end, 500 + layout.total_len());
        assert_eq!(all.gain, 171.0);
        // Rate 0.5: 100 leaves keep 50 → bands 0..6 (edge 1/2), the neediest.
        let half = uniform_range(&layout, 0, 0.5).unwrap();
        assert_eq!(half.end, layout.band_range(5).end);
        assert!(half.blocks.iter().all(|b| b.band < 6));
    }

    /// A real `.ctree`: one trunk, leaf nodes of the given sizes.
    pub(crate) fn encoded_tree(counts: &[u32]) -> Vec<u8> {
        use canopy_shared::format::tree::{BakedTree, SectionBody, encode_tree};
        use canopy_shared::format::{LeafOrder, NO_BRANCH, NO_PARENT, NodeRecord, node::NodeKind};
        use canopy_shared::{Branch, Leaf, Materials, ModelSource, SkeletonPoint, TriangleMesh};
        use glam::Vec3;
        let k = counts.len() as u32;
        let record = |parent, subtree_end, kind, leaf_count| NodeRecord {
            parent,
            subtree_end,
            kind,
            branch_level: 1,
            sphere_layer: 1,
            branch: if kind == NodeKind::Branch { 0 } else { NO_BRANCH },
            leaf_count,
            growth_direction: Vec3::Y,
            length: 5.0,
            sphere_center: Vec3::new(0.0, 3.0, 0.0),
            sphere_radius: 4.0,
            leaf_density: 2.0,
        };
        let mut nodes = vec![record(NO_PARENT, k + 1, NodeKind::Branch, 0)];
        nodes.extend(
            counts
                .iter()
                .enumerate()
                .map(|(i, &n)| record(0, i as u32 + 2, NodeKind::Leaf, n)),
        );
        let leaf = |j: u32| Leaf {
            center: Vec3::new((j % 7) as f32 * 0.3, 2.0 + (j % 5) as f32 * 0.4, 0.1),
            normal: Vec3::Z,
            axis: Vec3::Y,
            width: 0.05,
            length: 0.1,
            branch: Some(0),
            iteration: 0,
            material: 0,
        };
        let node_leaves = counts.iter().map(|&n| (0..n).map(leaf).collect()).collect();
        let t = BakedTree {
            name: "plan-test".into(),
            source: ModelSource::LSystem,
            leaf_order: LeafOrder::Generation,
            iterations: 0,
            band_edges: DEFAULT_BAND_EDGES.to_vec(),
            branches: vec![Branch {
                points: vec![
                    SkeletonPoint {
                        position: Vec3::ZERO,
                        radius: 0.2,
                    },
                    SkeletonPoint {
                        position: Vec3::new(0.0, 5.0, 0.0),
                        radius: 0.1,
                    },
                ],
                parent: None,
                level: 1,
                iteration: 0,
            }],
            materials: Materials::default(),
            bark_mesh: TriangleMesh::default(),
            nodes,
            node_leaves,
            hulls: SectionBody::default(),
            atlases: SectionBody::default(),
            clouds: SectionBody::default(),
        };
        encode_tree(&t).unwrap()
    }

    #[test]
    fn plan_reads_and_decodes_from_a_real_file() {
        use canopy_shared::format::directory::SectionKind;
        use canopy_shared::format::leaf::decode_block;
        use canopy_shared::format::tree::{decode_index, decode_node_index, section_bytes};
        let counts = [300, 40, 7, 120];
        let bytes = encoded_tree(&counts);
        let (_, directory) = decode_index(&bytes, Some(bytes.len() as u64)).unwrap();
        let table = section_bytes(&bytes, directory.section(SectionKind::NodeTable).unwrap()).unwrap();
        let idx = decode_node_index(&directory, table).unwrap();
        let keep = [150, 40, 0, 12];
        let plan = plan_leaf_ranges(
            &idx.layout,
            idx.leaves_offset,
            &keep,
            &[1, 0, 0, 0],
            &[1.0, 2.0, 3.0, 4.0],
        )
        .unwrap();
        let mut present = [0u32; 4];
        present[0] = idx.layout.leaves_in_bands(300, 1);
        let mut blocks: Vec<LeafBlockRef> = plan.ranges.iter().flat_map(|r| r.blocks.clone()).collect();
        blocks.sort_by_key(|b| b.offset);
        for r in &plan.ranges {
            let data = &bytes[r.start as usize..r.end as usize];
            for b in &r.blocks {
                let at = (idx.leaves_offset + b.offset - r.start) as usize;
                let got = decode_block(&data[at..at + b.len as usize], b.count, 1).unwrap();
                assert_eq!(got.len() as u32, b.count);
            }
        }
        // Blocks arrive as band prefixes: each node ends up with at least its keep count.
        for b in &blocks {
            let i = b.leaf_node as usize;
            assert_eq!(b.first_rank, present[i], "node {i} band {}", b.band);
            present[i] += b.count;
        }
        for (i, &k) in keep.iter().enumerate() {
            assert!(present[i] >= k, "node {i}: {} < {k}", present[i]);
        }
        let u = uniform_range(&idx.layout, idx.leaves_offset, 0.0).unwrap();
        assert_eq!(u.len(), idx.layout.total_len());
    }

    fn check_plan(counts: &[u32], keep: &[u32], held: &[usize], gain: &[f32]) -> Result<(), TestCaseError> {
        let layout = BandLayout::new(&DEFAULT_BAND_EDGES, counts);
        let base = 4321;
        let p = plan_leaf_ranges(&layout, base, keep, held, gain).unwrap();
        let need = needed_bands(&layout, keep);
        let mut expected = HashSet::new();
        let mut held_set = Vec::new();
        for (i, (&nb, &hb)) in need.iter().zip(held).enumerate() {
            for b in 0..layout.band_count() {
                if let Some(blk) = layout.block(b, i) {
                    if b < hb {
                        held_set.push((base + blk.offset, base + blk.offset + blk.len));
                    } else if b < nb {
                        expected.insert((b, i));
                    }
                }
            }
        }
        let mut seen = HashSet::new();
        for r in &p.ranges {
            prop_assert!(r.start < r.end);
            for blk in &r.blocks {
                prop_assert!(seen.insert((blk.band as usize, blk.leaf_node as usize)), "block twice");
                prop_assert!(r.start <= base + blk.offset && base + blk.offset + blk.len <= r.end);
            }
            // Nothing held is requested, not even as gap bytes.
            for &(s, e) in &held_set {
                prop_assert!(e <= r.start || s >= r.end, "held block inside a range");
            }
        }
        prop_assert_eq!(&seen, &expected);
        let mut sorted: Vec<_> = p.ranges.iter().map(|r| (r.start, r.end)).collect();
        sorted.sort_unstable();
        for w in sorted.windows(2) {
            prop_assert!(w[0].1 <= w[1].0, "overlap");
        }
        for w in p.ranges.windows(2) {
            prop_assert!(w[0].gain_per_byte() >= w[1].gain_per_byte());
        }
        prop_assert_eq!(p.bytes, p.ranges.iter().map(PlannedRange::len).sum::<u64>());
        prop_assert!(p.block_bytes <= p.bytes);
        Ok(())
    }

    proptest! {
        #[test]
        fn plan_covers_exactly_what_is_needed(
            nodes in proptest::collection::vec((1u32..600, 0.0f64..=1.0, 0usize..=9, 0.0f32..10.0), 1..40)
        ) {
            let counts: Vec<u32> = nodes.iter().map(|n| n.0).collect();
            let keep: Vec<u32> = nodes.iter().map(|n| (f64::from(n.0) * n.1).round() as u32).collect();
            let held: Vec<usize> = nodes.iter().map(|n| n.2).collect();
            let gain: Vec<f32> = nodes.iter().map(|n| n.3).collect();
            check_plan(&counts, &keep, &held, &gain)?;
        }
    }
}
