//! `canopy-shared`: what the Canopy server and client must agree on.
//!
//! - [`model`]: the in-memory tree model (skeleton, leaves, materials).
//! - [`lsystem`]: the stochastic parametric L-system engine and turtle (seed 000).
//! - [`species`]: species specs (TOML) that drive the L-system.
//! - [`tessellate`]: turning a skeleton and leaves into triangles.
//! - [`format`](mod@format): the progressive tree file (`.ctree`), spec in `docs/format.md`.
//! - [`reader`]: byte-range readers (`read(offset, len)`) over files and memory.

#[cfg(feature = "charts")]
pub mod chart;
pub mod format;
pub mod lsystem;
pub mod metrics;
pub mod model;
pub mod pack;
pub mod raster;
pub mod reader;
pub mod species;
pub mod tessellate;

pub use model::{Branch, Leaf, LeafMaterial, Materials, ModelSource, SkeletonPoint, TreeModel, TriangleMesh};
