//! Storage: the content-addressed asset files, the scene database, the instance pack format and
//! packs stored per tile.

pub mod assets;
#[cfg(test)]
mod contract_tests;
mod flight_tables;
pub mod gc;
pub mod locks;
pub mod pack;
pub mod pack_draft;
pub mod postgres;
mod postgres_conn;
pub mod recent;
pub mod scenes;
pub mod sqlite;
mod sqlite_schema;
mod terrains;
pub mod tiles;

pub use assets::{Asset, AssetError, AssetStore};
pub use postgres::PostgresStore;
pub use scenes::{SceneStore, StoreError};
pub use sqlite::SqliteStore;
