//! The leaves section (spec: `docs/format.md#leaves-kind-3`): 16-byte quantized leaf records in
//! band-major leaf blocks, each block followed by its CRC-32.

use glam::{Mat3, Quat, Vec3};

use super::bytes::{Cursor, Writer};
use super::quant::{dequantize_point, dequantize_u16, pack_quat, quantize_point, quantize_u16, unpack_quat};
use super::{FormatError, LEAF_BLOCK_CRC_LEN, LEAF_RECORD_LEN, crc32};
use crate::model::Leaf;

/// Default band edges: keep fractions 1/64, 1/32, 1/16, 1/8, 1/4, 1/2, 3/4, 1, each
/// `⌊65535·f⌋` so that `rank_end(k/f, e) = k` (a node of 64 leaves has exactly one in band 0).
pub const DEFAULT_BAND_EDGES: [u16; 8] = [1023, 2047, 4095, 8191, 16383, 32767, 49151, 65535];

/// Quantization frame of leaf records.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LeafFrame {
    /// Bounds minimum.
    pub lo: Vec3,
    /// Bounds maximum.
    pub hi: Vec3,
    /// Width scale.
    pub width_max: f32,
    /// Length scale.
    pub length_max: f32,
}

/// A leaf as stored: 16 bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct QuantizedLeaf {
    /// Centre, quantized over the bounds.
    pub center: [u16; 3],
    /// Smallest-three quaternion (local x = across, y = along, z = normal).
    pub orientation: u32,
    /// Width over `[0, width_max]`.
    pub width: u16,
    /// Length over `[0, length_max]`.
    pub length: u16,
    /// Iteration that created the leaf.
    pub iteration: u8,
    /// Material index.
    pub material: u8,
}

impl QuantizedLeaf {
    /// Quantizes a leaf. `axis` is made perpendicular to `normal` first.
    pub fn from_leaf(l: &Leaf, f: &LeafFrame) -> Self {
        let normal = l.normal.try_normalize().unwrap_or(Vec3::Z);
        let axis = (l.axis - normal * l.axis.dot(normal))
            .try_normalize()
            .unwrap_or_else(|| normal.any_orthonormal_vector());
        let side = axis.cross(normal);
        let q = Quat::from_mat3(&Mat3::from_cols(side, axis, normal));
        Self {
            center: quantize_point(l.center, f.lo, f.hi),
            orientation: pack_quat(q),
            width: quantize_u16(l.width, 0.0, f.width_max),
            length: quantize_u16(l.length, 0.0, f.length_max),
            iteration: l.iteration,
            material: l.material,
        }
    }

    /// Decodes to a model leaf carried by `branch`.
    pub fn to_leaf(&self, f: &LeafFrame, branch: Option<u32>) -> Leaf {
        let q = unpack_quat(self.orientation);
        Leaf {
            center: dequantize_point(self.center, f.lo, f.hi),
            normal: q * Vec3::Z,
            axis: q * Vec3::Y,
            width: dequantize_u16(self.width, 0.0, f.width_max),
            length: dequantize_u16(self.length, 0.0, f.length_max),
            branch,
            iteration: self.iteration,
            material: self.material,
        }
    }

    fn encode(&self, w: &mut Writer) {
        for v in self.center {
            w.u16(v);
        }
        w.u32(self.orientation);
        w.u16(self.width);
        w.u16(self.length);
        w.u8(self.iteration);
        w.u8(self.material);
    }

    fn decode(c: &mut Cursor) -> Result<Self, FormatError> {
        Ok(Self {
            center: [c.u16()?, c.u16()?, c.u16()?],
            orientation: c.u32()?,
            width: c.u16()?,
            length: c.u16()?,
            iteration: c.u8()?,
            material: c.u8()?,
        })
    }
}

/// Appends one leaf block: the records then their CRC-32.
pub fn encode_block(leaves: &[QuantizedLeaf], out: &mut Vec<u8>) {
    let mut w = Writer::default();
    for l in leaves {
        l.encode(&mut w);
    }
    let crc = crc32(&w.buf);
    out.extend_from_slice(&w.buf);
    out.extend_from_slice(&crc.to_le_bytes());
}

/// Decodes one leaf block of `count` records (`bytes` = records + CRC, exactly). Checks the CRC
/// and that every material index is below `material_count`.
pub fn decode_block(bytes: &[u8], count: u32, material_count: usize) -> Result<Vec<QuantizedLeaf>, FormatError> {
    let need = u64::from(count) * LEAF_RECORD_LEN as u64 + LEAF_BLOCK_CRC_LEN as u64;
    if bytes.len() as u64 != need {
        return Err(FormatError::Truncated {
            what: "leaf block",
            need,
            have: bytes.len() as u64,
        });
    }
    let (records, crc) = bytes.split_at(bytes.len() - LEAF_BLOCK_CRC_LEN);
    super::check_crc(
        "leaf block",
        records,
        u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]),
    )?;
    let mut c = Cursor::new(records, "leaf block");
    let mut out = Vec::with_capacity(count as usize);
    for _ in 0..count {
        let l = QuantizedLeaf::decode(&mut c)?;
        if l.material as usize >= material_count {
            return Err(FormatError::invalid(
                "leaf",
                format!("material {} of {material_count}", l.material),
            ));
        }
        out.push(l);
    }
    Ok(out)
}

/// Where one leaf block lies: band `band` of leaf node `leaf_node` (index among leaf nodes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LeafBlockRef {
    /// Band index.
    pub band: u8,
    /// Leaf-node ordinal (position among leaf nodes in preorder).
    pub leaf_node: u32,
    /// First rank (position in the node's importance order) in this block.
    pub first_rank: u32,
    /// Records in the block (> 0).
    pub count: u32,
    /// Offset relative to the start of the leaves section.
    pub offset: u64,
    /// Bytes, CRC trailer included.
    pub len: u64,
}

/// Leaf-block offsets computed from the band edges and the leaf nodes' leaf counts alone.
#[derive(Debug, Clone, PartialEq)]
pub struct BandLayout {
    edges: Vec<u16>,
    leaf_counts: Vec<u32>,
    /// `offsets[b * (n + 1) + i]`: offset of leaf node i's block in band b (n + 1 entries per band).
    offsets: Vec<u64>,
}

/// Leaves of an `n`-leaf node that lie in bands `0..=b` with edge `e`: `⌈n·e / 65535⌉`.
pub fn rank_end(n: u32, edge: u16) -> u32 {
    ((u64::from(n) * u64::from(edge)).div_ceil(65535)) as u32
}

impl BandLayout {
    /// Builds the layout. `edges` must be valid band edges (as a decoded directory guarantees).
    pub fn new(edges: &[u16], leaf_counts: &[u32]) -> Self {
        let n = leaf_counts.len();
        let mut offsets = Vec::with_capacity(edges.len() * (n + 1));
        let mut off = 0u64;
        for b in 0..edges.len() {
            for &count in leaf_counts {
                offsets.push(off);
                let c = Self::count_in_band(edges, count, b);
                if c > 0 {
                    off += u64::from(c) * LEAF_RECORD_LEN as u64 + LEAF_BLOCK_CRC_LEN as u64;
                }
            }
            offsets.push(off);
        }
        Self {
            edges: edges.to_vec(),
            leaf_counts: leaf_counts.to_vec(),
            offsets,
        }
    }

    fn count_in_band(edges: &[u16], n: u32, b: usize) -> u32 {
        let hi = rank_end(n, edges[b]);
        let lo = if b == 0 { 0 } else { rank_end(n, edges[b - 1]) };
        hi - lo
    }

    /// Number of bands.
    pub fn band_count(&self) -> usize {
        self.edges.len()
    }

    /// Band edges.
    pub fn edges(&self) -> &[u16] {
        &self.edges
    }

    /// Leaf counts of the leaf nodes.
    pub fn leaf_counts(&self) -> &[u32] {
        &self.leaf_counts
    }

    /// Total bytes of the leaves section.
    pub fn total_len(&self) -> u64 {
        self.offsets.last().copied().unwrap_or(0)
    }

    /// Byte range of a whole band, relative to the section.
    pub fn band_range(&self, band: usize) -> std::ops::Range<u64> {
        let n = self.leaf_counts.len();
        self.offsets[band * (n + 1)]..self.offsets[band * (n + 1) + n]
    }

    /// The block of `leaf_node` in `band`, or `None` when that slice is empty or out of range.
    pub fn block(&self, band: usize, leaf_node: usize) -> Option<LeafBlockRef> {
        let n = self.leaf_counts.len();
        if band >= self.edges.len() || leaf_node >= n {
            return None;
        }
        let total = self.leaf_counts[leaf_node];
        let count = Self::count_in_band(&self.edges, total, band);
        if count == 0 {
            return None;
        }
        let first_rank = if band == 0 {
            0
        } else {
            rank_end(total, self.edges[band - 1])
        };
        let i = band * (n + 1) + leaf_node;
        Some(LeafBlockRef {
            band: band as u8,
            leaf_node: leaf_node as u32,
            first_rank,
            count,
            offset: self.offsets[i],
            len: self.offsets[i + 1] - self.offsets[i],
        })
    }

    /// Every non-empty block that lies wholly inside `range` (relative to the leaves section), in
    /// offset order (band-major). A block cut by either end of the range is left out.
    pub fn blocks_within(&self, range: std::ops::Range<u64>) -> Vec<LeafBlockRef> {
        let n = self.leaf_counts.len();
        let mut out = Vec::new();
        if range.start >= range.end {
            return out;
        }
        for band in 0..self.edges.len() {
            let offsets = &self.offsets[band * (n + 1)..(band + 1) * (n + 1)];
            // Blocks of this band start at offsets[i] and end at offsets[i + 1].
            let first = offsets.partition_point(|&o| o < range.start);
            for i in first..n {
                if offsets[i + 1] > range.end {
                    break;
                }
                if let Some(b) = self.block(band, i) {
                    out.push(b);
                }
            }
        }
        out
    }

    /// Bands a node of `n` leaves needs so that its first `keep` leaves are present: the
    /// smallest `b + 1` with `rank_end(n, e_b) ≥ keep` (0 when `keep` is 0).
    pub fn bands_for_keep(&self, n: u32, keep: u32) -> usize {
        if keep == 0 {
            return 0;
        }
        self.edges
            .iter()
            .position(|&e| rank_end(n, e) >= keep)
            .map_or(self.edges.len(), |b| b + 1)
    }

    /// Leaves of an `n`-leaf node present when its first `bands` bands are.
    pub fn leaves_in_bands(&self, n: u32, bands: usize) -> u32 {
        if bands == 0 {
            0
        } else {
            rank_end(n, self.edges[bands.min(self.edges.len()) - 1])
        }
    }
}

/// Leaves kept at simplification rate `rate` (0 = all, 1 = none) of an `n`-leaf node: the
/// nearest integer to `n·(1 − rate)`, with the rate clamped to [0, 1].
pub fn keep_count(n: u32, rate: f32) -> u32 {
    let r = if rate.is_nan() { 0.0 } else { rate.clamp(0.0, 1.0) };
    ((n as f32) * (1.0 - r)).round().min(n as f32) as u32
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn blocks_within_takes_whole_blocks_only() {
        // Nodes of 64, 0, 3 and 200 leaves: empty slices in some bands.
        let layout = BandLayout::new(&DEFAULT_BAND_EDGES, &[64, 0, 3, 200]);
        let mut all: Vec<LeafBlockRef> = Vec::new();
        for b in 0..layout.band_count() {
            all.extend((0..4).filter_map(|o| layout.block(b, o)));
        }
        assert_eq!(layout.blocks_within(0..layout.total_len()), all);
        assert!(layout.blocks_within(5..5).is_empty());
        let (hi, lo) = (9, 3);
        assert!(layout.blocks_within(hi..lo).is_empty());
        // Every block exactly, and a byte less at either end loses it.
        for b in &all {
            assert_eq!(layout.blocks_within(b.offset..b.offset + b.len), vec![*b]);
            assert!(!layout.blocks_within(b.offset + 1..b.offset + b.len).contains(b));
            assert!(!layout.blocks_within(b.offset..b.offset + b.len - 1).contains(b));
        }
        // A range from the middle of one block to the middle of a later one holds just those between.
        let (a, c) = (&all[1], &all[4]);
        let mid = layout.blocks_within(a.offset + 1..c.offset + c.len - 1);
        assert_eq!(mid, all[2..4].to_vec());
    }

    #[test]
    fn rank_end_extremes() {
        assert_eq!(rank_end(0, 65535), 0);
        assert_eq!(rank_end(100, 65535), 100);
        assert_eq!(rank_end(5, DEFAULT_BAND_EDGES[0]), 1);
        assert_eq!(rank_end(64, DEFAULT_BAND_EDGES[0]), 1);
        assert_eq!(rank_end(65, DEFAULT_BAND_EDGES[0]), 2);
        assert_eq!(rank_end(2, DEFAULT_BAND_EDGES[5]), 1);
        assert_eq!(rank_end(100, DEFAULT_BAND_EDGES[5]), 50);
    }

    proptest! {
        #[test]
        fn blocks_within_is_every_block_inside(
            counts in proptest::collection::vec(0u32..300, 1..30),
            a in 0u64..20_000,
            len in 0u64..20_000,
        ) {
            let layout = BandLayout::new(&DEFAULT_BAND_EDGES, &counts);
            let (start, end) = (a.min(layout.total_len() + 10), a.saturating_add(len));
            let mut inside = Vec::new();
            for b in 0..layout.band_count() {
                for o in 0..counts.len() {
                    if let Some(blk) = layout.block(b, o)
                        && blk.offset >= start
                        && blk.offset + blk.len <= end
                    {
                        inside.push(blk);
                    }
                }
            }
            prop_assert_eq!(layout.blocks_within(start..end), inside);
        }

        #[test]
        fn layout_partitions_every_node(counts in proptest::collection::vec(1u32..500, 1..40)) {
            let layout = BandLayout::new(&DEFAULT_BAND_EDGES, &counts);
            let mut next = 0u64;
            for b in 0..layout.band_count() {
                let mut per_band = 0;
                for (i, &n) in counts.iter().enumerate() {
                    if let Some(blk) = layout.block(b, i) {
                        prop_assert_eq!(blk.offset, next);
                        next += blk.len;
                        per_band += blk.count;
                        prop_assert_eq!(blk.first_rank, layout.leaves_in_bands(n, b));
                    }
                }
                let r = layout.band_range(b);
                prop_assert_eq!(r.end - r.start, u64::from(per_band) * 16 + 4 * (0..counts.len()).filter(|&i| layout.block(b, i).is_some()).count() as u64);
            }
            prop_assert_eq!(next, layout.total_len());
            for &n in &counts {
                prop_assert_eq!(layout.leaves_in_bands(n, layout.band_count()), n);
                for keep in 0..=n {
                    let bands = layout.bands_for_keep(n, keep);
                    prop_assert!(layout.leaves_in_bands(n, bands) >= keep);
                    if bands > 0 { prop_assert!(layout.leaves_in_bands(n, bands - 1) < keep); }
                }
            }
        }
    }
}
