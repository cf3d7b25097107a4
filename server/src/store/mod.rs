//! Storage: the content-addressed asset files, the scene database, and the instance pack format.

pub mod assets;
pub mod gc;
pub mod pack;
pub mod scenes;
pub mod sqlite;

pub use assets::{Asset, AssetError, AssetStore};
pub use scenes::{SceneStore, StoreError};
pub use sqlite::SqliteStore;
