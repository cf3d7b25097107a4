//! Canopy client library: the streaming client (issue 5).
//!
//! - [`lod`]: level-of-detail policy — seed 000 screen-projection thresholds and representation
//!   choice, seed 004 per-node simplification rate, leaf enlargement and switch control, seed 002
//!   low-flight policy, frustum culling.
//! - [`plan`]: which leaf-block byte ranges to fetch for given per-node keep counts.
//! - [`cache`]: a memory-bounded, least-used block cache shared by every instance of a model.
//! - [`net`]: byte-range sources (HTTP with multi-range and parallel single ranges, files), and a
//!   modelled link on a virtual clock for headless runs ([`net::link`], [`net::linked`]).
//! - [`scene`]: the scene manifest and instance tiles.
//! - [`terrain`]: a scene's terrain tiles as held, the ground's lower bound, tile meshes.
//! - [`stream`]: the frame loop that ties them together; it never waits for the network.
//! - [`eval`]: renders what a client drew against the full-detail scene (SSIM, coverage, popping).
//! - [`paths`]: deterministic camera paths for headless runs.

pub mod cache;
pub mod eval;
pub mod lod;
pub mod net;
pub mod paths;
pub mod plan;
pub mod scene;
pub mod stream;
pub mod terrain;
pub mod view;
