//! A scene's flight table (seed 002's visual-redundancy table, `canopy_shared::flight_table`) as
//! both backends keep it: a scene property, not versioned, in a table of its own keyed by scene id
//! (`flight_tables`, deleted with the scene by `ON DELETE CASCADE`), so that writing it makes no
//! version and an edit's update of the scene row never copies it. The text is stored as given: the
//! HTTP layer checks the table and passes its compact JSON. Each function is one transaction; an
//! unknown scene is [`StoreError::NotFound`], told apart from a scene with no table (`None`).

use postgres::Transaction;
use rusqlite::{Connection, OptionalExtension, TransactionBehavior, params};

use super::postgres::col;
use super::scenes::StoreError;

fn not_found(id: &str) -> StoreError {
    StoreError::NotFound(id.to_string())
}

/// The table's text, `None` when the scene has none (SQLite; `c` is a read transaction).
pub(super) fn sqlite_get(c: &Connection, id: &str) -> Result<Option<String>, StoreError> {
    c.query_row(
        "SELECT f.json FROM scenes s LEFT JOIN flight_tables f ON f.scene = s.id WHERE s.id = ?1",
        [id],
        |r| r.get::<_, Option<String>>(0),
    )
    .optional()?
    .ok_or_else(|| not_found(id))
}

/// Sets (`Some`, replacing any) or removes (`None`) the table, on the writer; true when the
/// scene had one.
pub(super) fn sqlite_put(c: &mut Connection, id: &str, json: Option<&str>) -> Result<bool, StoreError> {
    let tx = c.transaction_with_behavior(TransactionBehavior::Immediate)?;
    if tx
        .query_row("SELECT 1 FROM scenes WHERE id = ?1", [id], |_| Ok(()))
        .optional()?
        .is_none()
    {
        return Err(not_found(id));
    }
    let had = tx.execute("DELETE FROM flight_tables WHERE scene = ?1", [id])? > 0;
    if let Some(j) = json {
        tx.execute(
            "INSERT INTO flight_tables (scene, json) VALUES (?1, ?2)",
            params![id, j],
        )?;
    }
    tx.commit()?;
    Ok(had)
}

/// The table's text, `None` when the scene has none (PostgreSQL; `tx` is a read snapshot).
pub(super) fn postgres_get(tx: &mut Transaction<'_>, id: &str) -> Result<Option<String>, StoreError> {
    let row = tx.query_opt(
        "SELECT f.json FROM scenes s LEFT JOIN flight_tables f ON f.scene = s.id WHERE s.id = $1",
        &[&id],
    )?;
    col(&row.ok_or_else(|| not_found(id))?, 0)
}

/// Sets (`Some`, replacing any) or removes (`None`) the table in `tx`; true when the scene had
/// one. The scene's row is share-locked first (`FOR KEY SHARE`, what the foreign key takes), so a
/// deletion on another replica waits for this transaction and then removes the table with the
/// scene; replicas setting it at once each replace it (`ON CONFLICT`), the last to commit kept.
pub(super) fn postgres_put(tx: &mut Transaction<'_>, id: &str, json: Option<&str>) -> Result<bool, StoreError> {
    let row = tx.query_opt(
        "SELECT EXISTS (SELECT 1 FROM flight_tables WHERE scene = s.id) FROM scenes s WHERE s.id = $1 \
         FOR KEY SHARE OF s",
        &[&id],
    )?;
    let had: bool = col(&row.ok_or_else(|| not_found(id))?, 0)?;
    match json {
        Some(j) => tx.execute(
            "INSERT INTO flight_tables (scene, json) VALUES ($1, $2) \
             ON CONFLICT (scene) DO UPDATE SET json = EXCLUDED.json",
            &[&id, &j],
        )?,
        None => tx.execute("DELETE FROM flight_tables WHERE scene = $1", &[&id])?,
    };
    Ok(had)
}
