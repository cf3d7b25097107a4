//! A scene's terrain as both backends keep it: the manifest's `terrain` object (JSON text, its
//! file named inside) in a table of its own keyed by scene id (`terrains`, deleted with the scene
//! by `ON DELETE CASCADE`; migration 4), so that an edit's update of the scene row never copies
//! it. Unlike the flight table, setting it makes a version: it is written in the transaction that
//! commits that version ([`super::scenes::SceneStore::set_terrain`]), and every edit reads it with
//! the version it builds on ([`super::scenes::Changes::terrain`]). The text is stored as given:
//! the HTTP layer checks the file and writes the object.

use postgres::Transaction;
use rusqlite::{Connection, OptionalExtension, params};

use super::postgres::col;
use super::scenes::StoreError;

/// What a version does to the scene's terrain.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum TerrainChange<'a> {
    /// Keeps it (an edit): read with the version the edit builds on.
    Keep,
    /// Sets it (`Some`) or removes it (`None`), in the version's transaction.
    Set(Option<&'a str>),
}

fn not_found(id: &str) -> StoreError {
    StoreError::NotFound(id.to_string())
}

/// The terrain's text, `None` when the scene has none (SQLite; `c` is a read transaction).
pub(super) fn sqlite_get(c: &Connection, id: &str) -> Result<Option<String>, StoreError> {
    c.query_row(
        "SELECT t.json FROM scenes s LEFT JOIN terrains t ON t.scene = s.id WHERE s.id = ?1",
        [id],
        |r| r.get::<_, Option<String>>(0),
    )
    .optional()?
    .ok_or_else(|| not_found(id))
}

/// Sets (`Some`, replacing any) or removes (`None`) the terrain inside the writer's transaction
/// `tx`, whose scene row exists.
pub(super) fn sqlite_put(tx: &Connection, id: &str, json: Option<&str>) -> Result<(), StoreError> {
    tx.execute("DELETE FROM terrains WHERE scene = ?1", [id])?;
    if let Some(j) = json {
        tx.execute("INSERT INTO terrains (scene, json) VALUES (?1, ?2)", params![id, j])?;
    }
    Ok(())
}

/// The terrain's text, `None` when the scene has none (PostgreSQL; `tx` is a read snapshot).
pub(super) fn postgres_get(tx: &mut Transaction<'_>, id: &str) -> Result<Option<String>, StoreError> {
    let row = tx.query_opt(
        "SELECT t.json FROM scenes s LEFT JOIN terrains t ON t.scene = s.id WHERE s.id = $1",
        &[&id],
    )?;
    col(&row.ok_or_else(|| not_found(id))?, 0)
}

/// Sets (`Some`, replacing any) or removes (`None`) the terrain in `tx`, which holds the scene's
/// row lock (`FOR UPDATE`: the version's commit).
pub(super) fn postgres_put(tx: &mut Transaction<'_>, id: &str, json: Option<&str>) -> Result<(), StoreError> {
    match json {
        Some(j) => tx.execute(
            "INSERT INTO terrains (scene, json) VALUES ($1, $2) ON CONFLICT (scene) DO UPDATE SET json = EXCLUDED.json",
            &[&id, &j],
        )?,
        None => tx.execute("DELETE FROM terrains WHERE scene = $1", &[&id])?,
    };
    Ok(())
}
