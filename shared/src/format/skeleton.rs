//! The skeleton section (spec: `docs/format.md#skeleton-kind-2`): branches in iteration order.

use glam::Vec3;

use super::bytes::{Cursor, Writer};
use super::quant::{dequantize_point, dequantize_u16, quantize_point, quantize_u16};
use super::{FormatError, IterationEntry, NO_PARENT, crc32};
use crate::model::{Branch, SkeletonPoint};

/// Quantization frame of the skeleton: the tree bounds and the largest radius.
#[derive(Debug, Clone, Copy)]
pub struct SkeletonFrame {
    /// Bounds minimum.
    pub lo: Vec3,
    /// Bounds maximum.
    pub hi: Vec3,
    /// Largest radius.
    pub radius_max: f32,
}

/// Bytes of a branch record's header: parent (u32), level (u8), iteration (u8), points (u16).
pub const BRANCH_HEADER_LEN: usize = 8;
/// Byte offset of the point count inside a branch record's header.
const BRANCH_POINTS_AT: usize = 6;
/// Bytes per skeleton point: quantized x, y, z and radius (u16 each).
pub const BRANCH_POINT_LEN: usize = 8;

/// Segments (points − 1, summed over branches) of whole branch records: one skeleton
/// iteration's bytes, say. Only the record framing is read (no CRC, no field checks; those are
/// [`decode_skeleton`]'s); bytes that do not end on a record boundary are an error.
pub fn segment_count(bytes: &[u8]) -> Result<u64, FormatError> {
    // Every branch is at least 0 thick.
    segment_counts_thicker(bytes, 0.0, &[0.0]).map(|c| c[0])
}

/// Per radius threshold `thresholds[t]`, the segments (points − 1) of the whole branch records
/// in `bytes` that have a point at least that thick (radii dequantized over
/// `[0, radius_max]`): the segments of `branch_tubes_thicker_than(model, _, thresholds[t])`
/// (`crate::tessellate`), counted without decoding positions. Framing as [`segment_count`].
pub fn segment_counts_thicker(bytes: &[u8], radius_max: f32, thresholds: &[f32]) -> Result<Vec<u64>, FormatError> {
    let mut counts = vec![0u64; thresholds.len()];
    for_each_branch(bytes, |points, thickest_q| {
        let thickest = dequantize_u16(thickest_q, 0.0, radius_max);
        let segments = points.saturating_sub(1) as u64;
        for (c, &t) in counts.iter_mut().zip(thresholds) {
            if thickest >= t {
                *c += segments;
            }
        }
    })?;
    Ok(counts)
}

/// Calls `f(points, thickest)` for each whole branch record of `bytes`, with its point count
/// and its thickest quantized radius (0 for a branch without points). Only the record framing
/// is read; bytes that do not end on a record boundary are an error.
pub fn for_each_branch(bytes: &[u8], mut f: impl FnMut(usize, u16)) -> Result<(), FormatError> {
    let mut o = 0usize;
    while o < bytes.len() {
        let truncated = |need: usize| FormatError::Truncated {
            what: "skeleton branch",
            need: need as u64,
            have: bytes.len() as u64,
        };
        let h = bytes
            .get(o..o + BRANCH_HEADER_LEN)
            .ok_or_else(|| truncated(o + BRANCH_HEADER_LEN))?;
        let points = usize::from(u16::from_le_bytes([h[BRANCH_POINTS_AT], h[BRANCH_POINTS_AT + 1]]));
        let start = o + BRANCH_HEADER_LEN;
        let end = start + points * BRANCH_POINT_LEN;
        let records = bytes.get(start..end).ok_or_else(|| truncated(end))?;
        // The radius is the last u16 of each point record.
        let thickest = records
            .chunks_exact(BRANCH_POINT_LEN)
            .map(|p| u16::from_le_bytes([p[6], p[7]]))
            .max()
            .unwrap_or(0);
        f(points, thickest);
        o = end;
    }
    Ok(())
}

/// Encodes branches (already in iteration order) and builds the iteration table for
/// `iterations + 1` entries; `leaves_end[k]` is the number of leaves with iteration ≤ k.
/// Branches with more than 65,535 points are cut at that many.
pub fn encode_skeleton(
    branches: &[Branch],
    frame: &SkeletonFrame,
    iterations: u8,
    leaves_end: &[u32],
) -> (Vec<u8>, Vec<IterationEntry>) {
    let mut w = Writer::default();
    let mut table = Vec::with_capacity(iterations as usize + 1);
    let mut i = 0;
    let mut start = 0usize;
    for k in 0..=iterations {
        while i < branches.len() && branches[i].iteration <= k {
            let b = &branches[i];
            w.u32(b.parent.unwrap_or(NO_PARENT));
            w.u8(b.level);
            w.u8(b.iteration);
            let n = b.points.len().min(usize::from(u16::MAX));
            w.u16(n as u16);
            for p in &b.points[..n] {
                for q in quantize_point(p.position, frame.lo, frame.hi) {
                    w.u16(q);
                }
                w.u16(quantize_u16(p.radius, 0.0, frame.radius_max));
            }
            i += 1;
        }
        table.push(IterationEntry {
            branches_end: i as u32,
            skeleton_bytes_end: w.buf.len() as u32,
            leaves_end: leaves_end.get(k as usize).copied().unwrap_or(0),
            skeleton_crc: crc32(&w.buf[start..]),
        });
        start = w.buf.len();
    }
    (w.buf, table)
}

/// Decodes the skeleton prefix of the first `k + 1` iteration entries from `bytes`, which must
/// be exactly the section's bytes `[0, table[k].skeleton_bytes_end)`. Every iteration chunk's
/// CRC, parent index, level and iteration is checked.
pub fn decode_skeleton(
    bytes: &[u8],
    table: &[IterationEntry],
    frame: &SkeletonFrame,
) -> Result<Vec<Branch>, FormatError> {
    let mut branches: Vec<Branch> = Vec::new();
    let mut start = 0usize;
    for (k, e) in table.iter().enumerate() {
        let end = e.skeleton_bytes_end as usize;
        if end > bytes.len() || end < start {
            return Err(FormatError::Truncated {
                what: "skeleton",
                need: end as u64,
                have: bytes.len() as u64,
            });
        }
        let chunk = &bytes[start..end];
        super::check_crc("skeleton iteration", chunk, e.skeleton_crc)?;
        let mut c = Cursor::new(chunk, "skeleton");
        while c.remaining() > 0 {
            let idx = branches.len() as u32;
            let parent = c.u32()?;
            let level = c.u8()?;
            let iteration = c.u8()?;
            let n = c.u16()?;
            if parent != NO_PARENT && parent >= idx {
                return Err(FormatError::invalid(
                    "skeleton",
                    format!("branch {idx} parent {parent} does not precede it"),
                ));
            }
            if level == 0 || iteration as usize != k || n == 0 {
                return Err(FormatError::invalid(
                    "skeleton",
                    format!("branch {idx}: level {level}, iteration {iteration} in chunk {k}, {n} points"),
                ));
            }
            let mut points = Vec::with_capacity(n as usize);
            for _ in 0..n {
                let q = [c.u16()?, c.u16()?, c.u16()?];
                let r = c.u16()?;
                points.push(SkeletonPoint {
                    position: dequantize_point(q, frame.lo, frame.hi),
                    radius: dequantize_u16(r, 0.0, frame.radius_max),
                });
            }
            branches.push(Branch {
                points,
                parent: (parent != NO_PARENT).then_some(parent),
                level,
                iteration,
            });
        }
        if branches.len() as u32 != e.branches_end {
            return Err(FormatError::invalid(
                "skeleton",
                format!(
                    "iteration {k} holds {} branches, table says {}",
                    branches.len(),
                    e.branches_end
                ),
            ));
        }
        start = end;
    }
    if start != bytes.len() {
        return Err(FormatError::TrailingBytes {
            what: "skeleton",
            extra: (bytes.len() - start) as u64,
        });
    }
    Ok(branches)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn branch(points: usize, parent: Option<u32>, iteration: u8) -> Branch {
        let points = (0..points)
            .map(|k| SkeletonPoint {
                position: Vec3::new(0.0, k as f32, 0.0),
                radius: 0.1,
            })
            .collect();
        Branch {
            points,
            parent,
            level: 1 + u8::from(parent.is_some()),
            iteration,
        }
    }

    #[test]
    fn segment_count_reads_record_framing() {
        let frame = SkeletonFrame {
            lo: Vec3::ZERO,
            hi: Vec3::splat(4.0),
            radius_max: 0.1,
        };
        let branches = [branch(4, None, 0), branch(2, Some(0), 1), branch(1, Some(0), 1)];
        let (bytes, table) = encode_skeleton(&branches, &frame, 1, &[0, 0]);
        let first = table[0].skeleton_bytes_end as usize;
        assert_eq!(segment_count(&bytes[..first]), Ok(3));
        assert_eq!(segment_count(&bytes[first..]), Ok(1));
        assert_eq!(segment_count(&bytes), Ok(4));
        assert_eq!(segment_count(&[]), Ok(0));
        // A record cut anywhere, in its header or its points, is refused.
        for cut in [1, BRANCH_HEADER_LEN - 1, BRANCH_HEADER_LEN + 1, first - 1] {
            assert!(
                matches!(segment_count(&bytes[..cut]), Err(FormatError::Truncated { .. })),
                "cut at {cut}"
            );
        }
    }

    /// Counted by radius without decoding, the segments are those of the decoded branches
    /// thick enough for each threshold; the threshold 0 is [`segment_count`].
    #[test]
    fn segment_counts_thicker_follow_the_decoded_radii() {
        let frame = SkeletonFrame {
            lo: Vec3::ZERO,
            hi: Vec3::splat(4.0),
            radius_max: 0.1,
        };
        let mut branches = vec![branch(4, None, 0), branch(2, Some(0), 1), branch(3, Some(0), 1)];
        for (b, r) in branches.iter_mut().zip([0.1, 0.004, 0.02]) {
            for p in &mut b.points {
                p.radius = r;
            }
        }
        let (bytes, table) = encode_skeleton(&branches, &frame, 1, &[0, 0]);
        let thresholds = [0.0, 0.003, 0.01, 0.03, 0.1];
        let counts = segment_counts_thicker(&bytes, frame.radius_max, &thresholds).expect("counts");
        let decoded = decode_skeleton(&bytes, &table, &frame).expect("decode");
        for (t, &c) in thresholds.iter().zip(&counts) {
            let want: u64 = decoded
                .iter()
                .filter(|b| b.points.iter().any(|p| p.radius >= *t))
                .map(|b| b.points.len() as u64 - 1)
                .sum();
            assert_eq!(c, want, "threshold {t}");
        }
        assert_eq!(counts, vec![6, 6, 5, 3, 3]);
        assert_eq!(counts[0], segment_count(&bytes).expect("count"));
        assert!(segment_counts_thicker(&bytes[..bytes.len() - 1], 0.1, &thresholds).is_err());
    }
}
