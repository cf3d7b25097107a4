//! Storage: the content-addressed asset files, the scene database, the instance pack format and
//! packs stored per tile.

pub mod assets;
pub mod gc;
pub mod pack;
pub mod pack_draft;
pub mod recent;
pub mod scenes;
pub mod sqlite;
pub mod tiles;

pub use assets::{Asset, AssetError, AssetStore};
pub use scenes::{SceneStore, StoreError};
pub use sqlite::SqliteStore;
