//! The skeleton-radii section (spec: `docs/format.md#skeleton-radii-kind-9`, minor 4): per
//! skeleton iteration `k`, the thickest point radius of the branches born in it, quantized as the
//! skeleton stores radii (`u16` over `[0, radius max]`; 0 for an iteration with no branch).
//!
//! Why: a bark variant leaves out every branch that never reaches its radius (the client's
//! `lod::bark`), and an L-system's last iterations are mostly such twigs (the demo linden's
//! iterations 12–15 are 3.2 of its 3.7 MB of skeleton, none thicker than 2.2 cm). From this
//! table a reader knows, before fetching the skeleton, the last iteration a variant draws, so it
//! neither fetches nor waits for the rest. Optional: a file without it (minor < 4) is read as if
//! every iteration had a branch of radius max.

use super::FormatError;
use super::quant::dequantize_u16;
use super::skeleton::for_each_branch;
use super::{IterationEntry, bytes::Writer};

/// Bytes per entry.
pub const SKELETON_RADIUS_ENTRY_LEN: usize = 2;

/// The table of an encoded skeleton (`skeleton`: the whole section; `table`: its iteration
/// table): one quantized thickest radius per iteration entry.
pub fn thickest_per_iteration(skeleton: &[u8], table: &[IterationEntry]) -> Result<Vec<u16>, FormatError> {
    let mut out = Vec::with_capacity(table.len());
    let mut start = 0usize;
    for e in table {
        let end = e.skeleton_bytes_end as usize;
        let chunk = skeleton.get(start..end).ok_or(FormatError::Truncated {
            what: "skeleton",
            need: end as u64,
            have: skeleton.len() as u64,
        })?;
        out.push(thickest(chunk)?);
        start = end;
    }
    Ok(out)
}

/// Thickest quantized radius of whole branch records.
fn thickest(bytes: &[u8]) -> Result<u16, FormatError> {
    let mut q = 0u16;
    for_each_branch(bytes, |_, t| q = q.max(t))?;
    Ok(q)
}

/// Encodes the table.
pub fn encode_skeleton_radii(thickest: &[u16]) -> Vec<u8> {
    let mut w = Writer::default();
    for &q in thickest {
        w.u16(q);
    }
    w.buf
}

/// Decodes the table of a file with `entries` iteration entries and skeleton radius scale
/// `radius_max` into metres per iteration. The section must hold exactly one entry per
/// iteration.
pub fn decode_skeleton_radii(bytes: &[u8], entries: usize, radius_max: f32) -> Result<Vec<f32>, FormatError> {
    if bytes.len() != entries * SKELETON_RADIUS_ENTRY_LEN {
        return Err(FormatError::invalid(
            "skeleton radii",
            format!(
                "{} bytes for {entries} iteration entries (need {})",
                bytes.len(),
                entries * SKELETON_RADIUS_ENTRY_LEN
            ),
        ));
    }
    Ok(bytes
        .chunks_exact(SKELETON_RADIUS_ENTRY_LEN)
        .map(|c| dequantize_u16(u16::from_le_bytes([c[0], c[1]]), 0.0, radius_max))
        .collect())
}

/// The last iteration (index into the iteration table) with a branch reaching `min_radius`
/// metres, from a decoded table; `None` when no iteration does.
pub fn last_iteration_reaching(radii: &[f32], min_radius: f32) -> Option<usize> {
    radii.iter().rposition(|&r| r >= min_radius)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn record(points: &[u16]) -> Vec<u8> {
        let mut w = Writer::default();
        w.u32(u32::MAX);
        w.u8(1);
        w.u8(0);
        w.u16(points.len() as u16);
        for &r in points {
            for _ in 0..3 {
                w.u16(0);
            }
            w.u16(r);
        }
        w.buf
    }

    #[test]
    fn the_table_holds_each_iterations_thickest_point_and_round_trips() {
        let a = record(&[100, 900, 40]);
        let b = record(&[7]);
        let skeleton = [a.clone(), b.clone()].concat();
        let entry = |end: usize| IterationEntry {
            skeleton_bytes_end: end as u32,
            ..IterationEntry::default()
        };
        // Iteration 0 empty, 1 holds `a`, 2 holds `b`.
        let table = [entry(0), entry(a.len()), entry(skeleton.len())];
        let q = thickest_per_iteration(&skeleton, &table).unwrap();
        assert_eq!(q, vec![0, 900, 7]);
        let radii = decode_skeleton_radii(&encode_skeleton_radii(&q), 3, 65535.0).unwrap();
        assert_eq!(radii, vec![0.0, 900.0, 7.0]);
        assert_eq!(last_iteration_reaching(&radii, 7.0), Some(2));
        assert_eq!(last_iteration_reaching(&radii, 8.0), Some(1));
        assert_eq!(last_iteration_reaching(&radii, 901.0), None);
    }

    #[test]
    fn bad_tables_are_errors() {
        assert!(decode_skeleton_radii(&[0; 5], 3, 1.0).is_err());
        assert!(decode_skeleton_radii(&[0; 8], 3, 1.0).is_err());
        let a = record(&[1, 2]);
        let short = IterationEntry {
            skeleton_bytes_end: a.len() as u32 + 1,
            ..IterationEntry::default()
        };
        assert!(thickest_per_iteration(&a, &[short]).is_err());
        // A record cut inside its points.
        let cut = IterationEntry {
            skeleton_bytes_end: a.len() as u32 - 1,
            ..IterationEntry::default()
        };
        assert!(thickest_per_iteration(&a, &[cut]).is_err());
    }
}
