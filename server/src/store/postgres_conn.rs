//! The PostgreSQL store's connections: the pool, the schema migrations, the availability check
//! and the change notifications between replicas (`LISTEN`/`NOTIFY`). The store's statements are
//! in [`super::postgres`].

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, Weak};
use std::time::Duration;

use postgres::error::SqlState;
use postgres::{Client, NoTls, Transaction};

use super::locks::lock;
use super::postgres::col;
use super::scenes::{SceneChange, StoreError};

/// Schema migrations, in order: `canopy_schema.version` is how many have run.
pub(super) const MIGRATIONS: &[&str] = &[
    "
CREATE TABLE scenes (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    public BOOLEAN NOT NULL,
    min_x DOUBLE PRECISION NOT NULL, min_z DOUBLE PRECISION NOT NULL,
    max_x DOUBLE PRECISION NOT NULL, max_z DOUBLE PRECISION NOT NULL,
    version BIGINT NOT NULL,
    next_id BIGINT NOT NULL,
    instance_count BIGINT NOT NULL,
    write_hash BYTEA NOT NULL,
    read_hash BYTEA,
    created_unix BIGINT NOT NULL,
    owner TEXT NOT NULL DEFAULT ''
);
CREATE INDEX scenes_owner ON scenes(owner);
CREATE TABLE instances (
    scene TEXT NOT NULL REFERENCES scenes(id) ON DELETE CASCADE,
    id BIGINT NOT NULL,
    model TEXT NOT NULL,
    x DOUBLE PRECISION NOT NULL, y DOUBLE PRECISION NOT NULL, z DOUBLE PRECISION NOT NULL,
    rotation DOUBLE PRECISION NOT NULL,
    scale DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (scene, id)
);
CREATE TABLE versions (
    scene TEXT NOT NULL REFERENCES scenes(id) ON DELETE CASCADE,
    version BIGINT NOT NULL,
    manifest TEXT NOT NULL,
    created_unix BIGINT NOT NULL,
    bytes BIGINT NOT NULL,
    pinned BOOLEAN NOT NULL DEFAULT FALSE,
    files TEXT NOT NULL,
    PRIMARY KEY (scene, version)
);
",
    // A random id per scene row, so that a scene deleted and created again with the same id in
    // the same second (on another replica) is never mistaken for the old one by a replica's cache
    // of instance lists.
    "ALTER TABLE scenes ADD COLUMN incarnation BIGINT NOT NULL DEFAULT (floor(random() * 9.2e18))::BIGINT;",
    // Seed 002's flight table, a scene property (not versioned): one row per scene that has one,
    // deleted with the scene (`flight_tables.rs`).
    "
CREATE TABLE flight_tables (
    scene TEXT PRIMARY KEY REFERENCES scenes(id) ON DELETE CASCADE,
    json TEXT NOT NULL
);
",
    // A scene's terrain (the manifest's `terrain` object): one row per scene that has one, deleted
    // with the scene; written with the version that sets it (`terrains.rs`).
    "
CREATE TABLE terrains (
    scene TEXT PRIMARY KEY REFERENCES scenes(id) ON DELETE CASCADE,
    json TEXT NOT NULL
);
",
];

const MIGRATION_LOCK: i64 = 0x0063_616e_6f70_7901;

/// Idle connections kept open per replica.
const MAX_IDLE: usize = 8;

/// How long a connection attempt may take before the database counts as unavailable.
pub(super) const CONNECT_TIMEOUT: Duration = Duration::from_secs(3);

/// How often the database is checked (and, when lost, tried again).
pub(super) const RETRY_EVERY: Duration = Duration::from_secs(1);

/// The channel replicas announce their scene changes on (`NOTIFY`, delivered at commit).
const CHANGES_CHANNEL: &str = "canopy_scene_changes";

/// The channel replicas relay presence on: `"REPLICA PAYLOAD"`, the payload the live module's.
const PRESENCE_CHANNEL: &str = "canopy_presence";

/// Presence payloads a replica keeps waiting for its sender before it drops new ones (presence is
/// latest-wins and re-sent in full every few seconds: a dropped one costs a late pose, never a
/// wrong roster for long).
const PRESENCE_QUEUE: usize = 1024;

/// Presence payloads sent in one statement (one round trip).
const PRESENCE_BATCH: usize = 64;

/// The pool and state shared by a store and its background threads.
pub(super) struct Inner {
    pub(super) config: postgres::Config,
    pub(super) idle: Mutex<Vec<Client>>,
    pub(super) migrated: AtomicBool,
    pub(super) available: AtomicBool,
}

impl std::fmt::Debug for Inner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Inner")
            .field("idle", &lock(&self.idle).len())
            .field("migrated", &self.migrated)
            .field("available", &self.available)
            .finish_non_exhaustive()
    }
}

/// Announces a change to the other replicas, in the transaction that makes it.
pub(super) fn announce(
    tx: &mut Transaction<'_>,
    replica: u64,
    scene: &str,
    version: Option<u64>,
) -> Result<(), StoreError> {
    let payload = serde_json::json!({"replica": replica.to_string(), "scene": scene, "version": version}).to_string();
    tx.execute("SELECT pg_notify($1, $2)", &[&CHANGES_CHANNEL, &payload])?;
    Ok(())
}

/// A notification's change, unless it is `own`'s or malformed.
pub(super) fn change_of(payload: &str, own: u64) -> Option<SceneChange> {
    let v: serde_json::Value = serde_json::from_str(payload).ok()?;
    if v["replica"].as_str()?.parse::<u64>().ok()? == own {
        return None;
    }
    let scene = v["scene"].as_str()?.to_string();
    Some(match v["version"].as_u64() {
        Some(version) => SceneChange::Version { scene, version },
        None => SceneChange::Deleted { scene },
    })
}

/// Presence another replica relayed, unless it is `own`'s or malformed.
pub(super) fn presence_of(payload: &str, own: u64) -> Option<SceneChange> {
    let (replica, body) = payload.split_once(' ')?;
    if replica.parse::<u64>().ok()? == own {
        return None;
    }
    Some(SceneChange::Presence {
        payload: body.to_string(),
    })
}

/// Sends this replica's presence payloads on [`PRESENCE_CHANNEL`] from a thread of its own, so
/// the live viewers never wait for the database.
#[derive(Debug)]
pub(super) struct PresenceSender {
    queue: std::sync::mpsc::SyncSender<String>,
}

impl PresenceSender {
    /// Starts the sender thread; it ends when the sender is dropped.
    pub(super) fn start(weak: Weak<Inner>, own: u64) -> std::io::Result<Self> {
        let (queue, rx) = std::sync::mpsc::sync_channel::<String>(PRESENCE_QUEUE);
        std::thread::Builder::new()
            .name("postgres-presence".into())
            .spawn(move || {
                while let Ok(first) = rx.recv() {
                    let mut batch = vec![format!("{own} {first}")];
                    while batch.len() < PRESENCE_BATCH {
                        match rx.try_recv() {
                            Ok(p) => batch.push(format!("{own} {p}")),
                            Err(_) => break,
                        }
                    }
                    let Some(inner) = weak.upgrade() else { return };
                    // While the database is away the check thread reconnects; until then each batch
                    // fails fast (no pooled connection, one connect attempt) and is dropped.
                    let sent = inner.with(|c| {
                        c.execute(
                            "SELECT pg_notify($1, p) FROM unnest($2::text[]) AS p",
                            &[&PRESENCE_CHANNEL, &batch],
                        )?;
                        Ok(())
                    });
                    if let Err(e) = sent {
                        tracing::debug!(error = %e, dropped = batch.len(), "presence not relayed");
                    }
                }
            })?;
        Ok(Self { queue })
    }

    /// Queues one payload; dropped when the queue is full.
    pub(super) fn send(&self, payload: String) {
        let _ = self.queue.try_send(payload);
    }
}

/// Whether a driver error means the database could not be reached (rather than refused a
/// statement).
fn unreachable(e: &postgres::Error) -> bool {
    e.is_closed()
        || e.as_db_error()
            .is_none_or(|d| d.code().code().starts_with("08") || d.code() == &SqlState::ADMIN_SHUTDOWN)
}

/// The driver's error with the server's message or the cause (its `Display` alone says only
/// "db error").
pub(super) fn describe(e: &postgres::Error) -> String {
    match (e.as_db_error(), std::error::Error::source(e)) {
        (Some(d), _) => d.to_string(),
        (None, Some(cause)) => format!("{e}: {cause}"),
        (None, None) => e.to_string(),
    }
}

fn db_err(e: &postgres::Error) -> StoreError {
    if unreachable(e) {
        StoreError::Unavailable(describe(e))
    } else {
        StoreError::Database(describe(e))
    }
}

impl From<postgres::Error> for StoreError {
    fn from(e: postgres::Error) -> Self {
        db_err(&e)
    }
}

fn migrate(client: &mut Client) -> Result<(), StoreError> {
    let mut tx = client.transaction()?;
    tx.execute("SELECT pg_advisory_xact_lock($1)", &[&MIGRATION_LOCK])?;
    tx.batch_execute("CREATE TABLE IF NOT EXISTS canopy_schema (version INTEGER NOT NULL)")?;
    let done = if let Some(r) = tx.query_opt("SELECT version FROM canopy_schema", &[])? {
        col::<i32>(&r, 0)?.max(0) as usize
    } else {
        tx.execute("INSERT INTO canopy_schema (version) VALUES (0)", &[])?;
        0
    };
    if done > MIGRATIONS.len() {
        return Err(StoreError::Database(format!(
            "the database has schema version {done}; this server knows up to {}",
            MIGRATIONS.len()
        )));
    }
    for (k, sql) in MIGRATIONS.iter().enumerate().skip(done) {
        tx.batch_execute(sql)?;
        tx.execute("UPDATE canopy_schema SET version = $1", &[&((k + 1) as i32)])?;
        tracing::info!(schema_version = k + 1, "scene database migrated");
    }
    tx.commit()?;
    let sync = client.query_one("SHOW synchronous_commit", &[])?;
    let sync: String = col(&sync, 0)?;
    if sync == "off" {
        tracing::warn!(synchronous_commit = %sync, "acknowledged edits may be lost in a power cut");
    }
    Ok(())
}

impl Inner {
    pub(super) fn connect(&self) -> Result<Client, StoreError> {
        let client = self.config.connect(NoTls).map_err(|e| {
            self.available.store(false, Ordering::Relaxed);
            StoreError::Unavailable(describe(&e))
        })?;
        Ok(client)
    }

    /// Connects and migrates once; false (and logged) while the database cannot be reached.
    pub(super) fn ensure_migrated(&self) -> Result<(), StoreError> {
        if self.migrated.load(Ordering::Acquire) {
            return Ok(());
        }
        let mut client = self.connect()?;
        migrate(&mut client)?;
        self.migrated.store(true, Ordering::Release);
        self.available.store(true, Ordering::Relaxed);
        let mut idle = lock(&self.idle);
        if idle.len() < MAX_IDLE {
            idle.push(client);
        }
        Ok(())
    }

    /// Runs `f` on a pooled connection.
    pub(super) fn with<T>(&self, f: impl FnOnce(&mut Client) -> Result<T, StoreError>) -> Result<T, StoreError> {
        self.ensure_migrated()?;
        let pooled = {
            let mut idle = lock(&self.idle);
            loop {
                match idle.pop() {
                    Some(c) if c.is_closed() => {}
                    other => break other,
                }
            }
        };
        let mut client = match pooled {
            Some(c) => c,
            None => self.connect()?,
        };
        let out = f(&mut client);
        let lost = client.is_closed() || matches!(out, Err(StoreError::Unavailable(_)));
        self.available.store(!lost, Ordering::Relaxed);
        if !lost {
            let mut idle = lock(&self.idle);
            if idle.len() < MAX_IDLE {
                idle.push(client);
            }
        }
        out
    }

    /// Checks the database once: connects (and migrates) when nothing is pooled or it was lost.
    pub(super) fn check(&self) {
        let ok = self.ensure_migrated().is_ok() && self.with(|c| Ok(c.simple_query("SELECT 1")?)).is_ok();
        let was = self.available.swap(ok, Ordering::Relaxed);
        if ok != was {
            if ok {
                tracing::info!("scene database reachable again");
            } else {
                tracing::warn!("scene database unreachable: scene API calls answer 503");
            }
        }
    }
}

/// Listens for other replicas' changes on its own connection (re-established once a second while
/// the database is away) until the store (`weak`) is dropped.
pub(super) fn listen(
    weak: Weak<Inner>,
    own: u64,
    on_change: Box<dyn Fn(SceneChange) + Send + Sync>,
) -> std::io::Result<std::thread::JoinHandle<()>> {
    use postgres::fallible_iterator::FallibleIterator;
    std::thread::Builder::new()
        .name("postgres-listen".into())
        .spawn(move || {
            let mut listened = false;
            while let Some(inner) = weak.upgrade() {
                let listening = inner.connect().and_then(|mut c| {
                    Ok(
                        c.batch_execute(&format!("LISTEN {CHANGES_CHANNEL}; LISTEN {PRESENCE_CHANNEL}"))
                            .map(|()| c)?,
                    )
                });
                drop(inner);
                let Ok(mut client) = listening else {
                    std::thread::sleep(RETRY_EVERY);
                    continue;
                };
                // Listening again: what was committed while it was not is read from the store.
                if std::mem::replace(&mut listened, true) {
                    on_change(SceneChange::Resync);
                }
                loop {
                    // A fresh iterator per wait: one's timer is not re-armed by a quiet second.
                    match client.notifications().timeout_iter(RETRY_EVERY).next() {
                        Ok(Some(n)) => {
                            let change = if n.channel() == PRESENCE_CHANNEL {
                                presence_of(n.payload(), own)
                            } else {
                                tracing::debug!(payload = n.payload(), "scene change notification");
                                change_of(n.payload(), own)
                            };
                            if let Some(change) = change {
                                on_change(change);
                            }
                        }
                        // A quiet second: still wanted?
                        Ok(None) if weak.strong_count() > 0 => {}
                        Ok(None) => return,
                        Err(e) => {
                            tracing::warn!(error = %describe(&e), "scene change notifications lost; listening again");
                            break;
                        }
                    }
                }
            }
        })
}
