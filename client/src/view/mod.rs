//! The viewer: streamed forests on the GPU (wgpu), in a window (eframe) or offscreen.
//!
//! - [`gpu`]: pipelines, offscreen targets, read-back.
//! - [`upload`]: keeps GPU copies of what the streamer cached (leaves per model, bark per
//!   distance variant, hull levels, billboard frames) and turns the streamer's drawn list into
//!   one frame's draws.
//!
//! Conventions are the client's ([`crate::lod`]): Y up, right-handed, metres, radians.

pub mod gpu;
pub mod upload;
