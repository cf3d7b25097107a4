//! `canopy-server` library: model import/export and baking, shared by the binary and tests.

pub mod bake;
pub mod demo;
pub mod discrete_files;
pub mod eval;
pub mod eval_clouds;
pub mod eval_iterations;
pub mod eval_views;
pub mod export_glb_meshopt;
pub mod export_gltf;
pub mod http;
pub mod import_gltf;
pub mod lsystem;
pub mod species;
pub mod store;
pub mod terrain;
pub mod unique;
