//! `canopy-shared`: what the Canopy server and client must agree on.
//!
//! - [`model`]: the in-memory tree model (skeleton, leaves, materials).
//! - [`rng`]: the deterministic PRNG (SplitMix64) whose sequences both sides reproduce.
//! - [`tessellate`]: turning a skeleton and leaves into triangles.
//! - [`format`](mod@format): the progressive tree file (`.ctree`), spec in `docs/format.md`;
//!   its units and how each is checked ([`format::unit`]).
//! - [`manifest`]: the scene manifest the server writes and the client reads (`docs/scenes.md`).
//! - [`pack`]: the instance pack's tiles and records, and instance placement.
//! - [`terrain`]: a scene's tiled heightfield (`.cterrain`), the surface instances stand on.
//! - [`flight_table`]: seed 002's visual-redundancy table a scene stores.
//! - [`discrete`]: the discrete LOD files (whole `.glb` levels) the evaluation's baseline downloads.
//! - [`raster`], [`metrics`]: the CPU rasterizer and image metrics (bake and evaluation).

#[cfg(feature = "charts")]
pub mod chart;
pub mod discrete;
pub mod flight_table;
pub mod format;
pub mod manifest;
pub mod metrics;
pub mod model;
pub mod pack;
pub mod raster;
pub mod rng;
pub mod terrain;
pub mod tessellate;

pub use model::{Branch, Leaf, LeafMaterial, Materials, ModelSource, SkeletonPoint, TreeModel, TriangleMesh};
