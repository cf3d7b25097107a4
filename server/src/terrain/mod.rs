//! Scene terrains on the server: a DEM-like terrain generated from a seed ([`generate`]), a
//! heightmap imported from a 16-bit PNG or a GeoTIFF ([`import`]), and a terrain as a scene
//! version publishes it ([`ground`]: its `.cterrain` file under the scene's assets, the manifest's
//! `terrain` object, instances lifted onto it). The file format and the surface are
//! `canopy_shared::terrain` (byte layout: `docs/scenes.md`, "Terrain").
//!
//! Conventions (those of `canopy_shared::terrain`): y up; ground-plane coordinates `[x, z]` in
//! metres; sample `(i, j)` at `origin + (i·cell, j·cell)`, i along x, j along z; heights in metres.
//! An image's columns run along +x and its rows along +z (a north-up map has north at −z). With a
//! terrain, an instance's stored y is its height above the ground: the pack places it at
//! `height_at(x, z) + y`.

pub mod generate;
pub mod ground;
pub mod import;

pub use generate::generate;
pub use ground::Ground;
pub use import::{ImportError, ImportOptions, Imported, import};
