//! The report stage: what one frame fetched and drew, for `fly --json`, `eval` and the viewer.
//!
//! Conventions: a node's rate is `1 − drawn/leaves` (0: every leaf drawn, 1: none); byte and
//! request counts are this frame's; times are wall-clock milliseconds.

use canopy_shared::pack::PackInstance;
use serde::Serialize;

use crate::lod::projection::BillboardKind;

/// What one frame fetched and drew.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct FrameReport {
    /// Frame number from 0.
    pub frame: u64,
    /// The stream's clock at the frame, seconds (virtual on a modelled link).
    pub time_s: f64,
    /// Whether every visible tree was drawn (at least as a stand-in), with no instance tile or
    /// model opening still on its way.
    pub complete: bool,
    /// Bytes the source fetched for requests sent this frame (bodies, wasted gap bytes
    /// included; a modelled link delivers them later).
    pub bytes: u64,
    /// Body bytes that arrived and were taken in this frame.
    pub bytes_arrived: u64,
    /// Instance tiles on their way.
    pub tiles_loading: usize,
    /// Models being opened (their stand-ins part: header, directory, hull, atlas and cloud
    /// tables).
    pub models_opening: usize,
    /// Models whose geometry part (node table, materials) is on its way.
    pub geometry_parts_loading: usize,
    /// Unit requests in flight after the frame.
    pub requests_in_flight: usize,
    /// Their bytes.
    pub bytes_in_flight: u64,
    /// Units needed and left for a later frame by the transfer window (or the byte budget).
    pub units_queued: usize,
    /// Their bytes.
    pub bytes_queued: u64,
    /// Detail level the stream asks for (1: as configured; lower while the link cannot keep up,
    /// see `stream/adapt.rs`).
    pub detail: f32,
    /// Throughput the client measured, bytes/s (`None`: not yet, or an instant link).
    pub rate_estimate: Option<f64>,
    /// Round trip the client measured, seconds.
    pub rtt_estimate: Option<f64>,
    /// Requests sent this frame (retries included).
    pub requests: u64,
    /// Retries this frame.
    pub retries: u64,
    /// Fetches that failed after retries this frame.
    pub failures: u64,
    /// Blocks that failed their CRC this frame (dropped).
    pub corrupt_blocks: u64,
    /// Cache payload bytes after the frame.
    pub cache_bytes: u64,
    /// Instances loaded so far (from tiles).
    pub instances_loaded: usize,
    /// Instances inside the view frustum and distance, and not hidden by the terrain.
    pub visible: usize,
    /// Instances inside the view frustum and distance that the terrain hides
    /// ([`crate::lod::occlusion`]): neither drawn nor fetched for.
    pub terrain_culled: usize,
    /// Terrain tiles held after the frame.
    pub terrain_tiles: usize,
    /// Terrain tiles on their way.
    pub terrain_loading: usize,
    /// Trees drawn as geometry.
    pub geometry_trees: usize,
    /// Trees drawn as crown hulls.
    pub hull_trees: usize,
    /// Trees drawn as billboards.
    pub billboard_trees: usize,
    /// Trees drawn as their model's crossed-quad stand-in because what they want is not held
    /// yet (counted among `billboard_trees` too).
    pub stand_in_trees: usize,
    /// Of them, trees wanted as geometry whose skeleton is held but fewer than
    /// [`super::resolve::STAND_IN_LEAF_SHARE`] of their wanted leaves.
    pub geometry_waiting: usize,
    /// Trees drawn as billboard clouds.
    pub cloud_trees: usize,
    /// Cloud planes drawn (a tree inside a cross-fade band counts both levels' planes).
    pub cloud_planes: u64,
    /// Cloud trees drawn as two levels cross-fading.
    pub cloud_blends: usize,
    /// Visible trees with nothing cached to draw yet.
    pub pending_trees: usize,
    /// Leaves drawn.
    pub leaves: u64,
    /// Triangles drawn (leaves 2 each, bark, hulls, billboard quads, cloud planes). Bark is
    /// counted as the viewer draws it: the variant for the tree's distance
    /// ([`crate::lod::bark`]), twigs under 0.1 px left out, fewer tube sides far away.
    pub triangles: u64,
    /// Triangles the visible trees have at full detail (every leaf; bark in the same variant).
    pub full_triangles: u64,
    /// Billboard quads drawn (crossed billboards count 2).
    pub billboard_quads: u64,
    /// Leaf nodes of geometry trees by drawn rate (1 − drawn/leaves), 10 bins of 0.1 (last bin
    /// includes 1.0; [`rate_bin`]).
    pub rate_histogram: [u64; 10],
    /// Leaf nodes whose rate switch control evaluated this frame (the others of the geometry
    /// trees were culled, or provably could not change): the planner's main per-frame work.
    pub nodes_evaluated: u64,
    /// Wall time of the frame's LOD and planning, milliseconds (fetch excluded).
    pub plan_ms: f64,
    /// Wall time of the whole frame, milliseconds.
    pub frame_ms: f64,
}

impl FrameReport {
    /// Every visible tree drawn (at least as a stand-in), no tile or model opening on its way.
    pub fn is_complete(&self) -> bool {
        self.visible > 0
            && self.pending_trees == 0
            && self.tiles_loading == 0
            && self.models_opening == 0
            && self.terrain_loading == 0
    }

    /// Nothing in flight, nothing waiting for the window, and the detail as configured.
    pub fn is_idle(&self) -> bool {
        self.requests_in_flight == 0
            && self.units_queued == 0
            && self.tiles_loading == 0
            && self.terrain_loading == 0
            && self.models_opening == 0
            && self.geometry_parts_loading == 0
            && self.detail >= 1.0
    }
}

/// What one tree instance was drawn as in the last frame, from cached data only.
#[derive(Debug, Clone, PartialEq)]
pub struct DrawnTree {
    /// The instance (id, model index into the manifest, position, rotation, scale).
    pub instance: PackInstance,
    /// What was drawn.
    pub what: Drawn,
}

/// A drawn representation.
#[derive(Debug, Clone, PartialEq)]
pub enum Drawn {
    /// Geometry: the first `leaves[o]` leaves of each leaf node (ordinal `o`) and the bark.
    Geometry {
        /// Leaves drawn per leaf node.
        leaves: Vec<u32>,
        /// Largest enlargement of the kept leaves the pixel-scale budget allows this frame
        /// (1: none; drawers also apply seed 004's capped enlargement when asked to).
        enlargement_cap: f32,
        /// Skeleton iterations drawn: the bark of branches born in iterations `0..=iterations`
        /// (every iteration when it is the model's last; `leaves` is 0 for the leaf nodes of
        /// branches born later).
        iterations: u8,
    },
    /// A crown hull level.
    Hull {
        /// Level index.
        level: u16,
    },
    /// Billboard-cloud levels with their weights (renormalised over the cached levels; two
    /// levels inside a cross-fade band, drawn with complementary coverage).
    Cloud {
        /// `(level, weight)`, heaviest first.
        levels: Vec<(u8, f32)>,
    },
    /// Billboard frames with their blend weights (renormalised over the cached frames).
    Billboard {
        /// Which kind.
        kind: BillboardKind,
        /// `(frame, resolution index, weight)`.
        frames: Vec<(u32, u8, f32)>,
    },
}

/// The [`FrameReport::rate_histogram`] bin of a node that draws `drawn` of its `leaves`: bin `k`
/// holds rates `1 − drawn/leaves` in `[k/10, (k + 1)/10)`, 1.0 in the last. Exact (integers):
/// in floating point rates of exactly 0.1 or 0.2 (9 or 8 of 10 leaves drawn) came out just below and
/// fell one bin low. Malformed counts read as before: `drawn > leaves` as rate 0, and a node of no
/// leaves as one of one leaf.
pub fn rate_bin(drawn: u32, leaves: u32) -> usize {
    let n = leaves.max(1);
    let left_out = u64::from(n.saturating_sub(drawn));
    ((left_out * 10 / u64::from(n)) as usize).min(9)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rate_bins_are_exact_tenths() {
        // 9 of 10 drawn is a rate of exactly 0.1: bin 1 (the float form gave 0.0999… → bin 0).
        assert_eq!(rate_bin(9, 10), 1);
        assert_eq!(rate_bin(10, 10), 0);
        assert_eq!(rate_bin(0, 10), 9);
        assert_eq!(rate_bin(1, 10), 9);
        assert_eq!(rate_bin(3, 10), 7);
        assert_eq!(rate_bin(7, 10), 3);
        assert_eq!(rate_bin(1, 3), 6); // 0.667
        assert_eq!(rate_bin(u32::MAX - 1, u32::MAX), 0);
        assert_eq!(rate_bin(0, u32::MAX), 9);
        // Malformed: more drawn than there are, or no leaves at all.
        assert_eq!(rate_bin(11, 10), 0);
        assert_eq!(rate_bin(0, 0), 9);
        assert_eq!(rate_bin(1, 0), 0);
        // Every tenth boundary lands in the bin it opens.
        for n in [10u32, 20, 50, 100, 1000, 4090] {
            for k in 0..10 {
                let drawn = n - n / 10 * k;
                assert_eq!(rate_bin(drawn, n), k as usize, "{drawn} of {n}");
            }
        }
    }
}
