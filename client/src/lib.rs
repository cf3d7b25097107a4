//! Canopy client library: the network-free layer of the streaming client (issue 5).
//!
//! - [`lod`]: level-of-detail policy — seed 000 screen-projection thresholds and representation
//!   choice, seed 004 per-node simplification rate, leaf enlargement and switch control, seed 002
//!   low-flight policy, frustum culling.
//! - [`plan`]: which leaf-block byte ranges to fetch for given per-node keep counts.
//! - [`cache`]: a memory-bounded, least-used block cache shared by every instance of a model.

pub mod cache;
pub mod lod;
pub mod plan;
