//! `canopy-server serve`: assets by byte range, scenes, live presence.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result};
use canopy_server::demo::{self, DemoConfig, DemoModels};
use canopy_server::http::quota::{Creation, Rate};
use canopy_server::http::{self, AppState, HttpConfig};
use canopy_server::store::gc;
use canopy_server::store::scenes::StoreError;
use canopy_server::store::scenes::{Limits, MAX_EXTENT_M, MAX_INSTANCES};
use canopy_server::store::{AssetStore, PostgresStore, SceneStore, SqliteStore};
use indicatif::{ProgressBar, ProgressStyle};

/// Arguments of `serve`. Every flag can also be set by its environment variable.
#[derive(clap::Args, Debug)]
pub struct ServeArgs {
    /// Data folder: `assets/` (served under /assets/), `canopy.db` (scenes, with the default
    /// database).
    #[arg(long, env = "CANOPY_DATA", default_value = "data")]
    data: PathBuf,
    /// Scene database: `sqlite:PATH` (one server; default `sqlite:DATA/canopy.db`) or
    /// `postgres://USER[:PASSWORD]@HOST[:PORT]/DB` (several replicas sharing it and the data
    /// folder). A replica that cannot reach PostgreSQL starts anyway and answers 503 until it can.
    #[arg(long, env = "CANOPY_DATABASE")]
    database: Option<String>,
    /// Address to listen on (port 0 picks a free port; the bound address is printed).
    #[arg(long, env = "CANOPY_ADDR", default_value = "127.0.0.1:8080")]
    addr: SocketAddr,
    /// Worker threads (default: one per core).
    #[arg(long, env = "CANOPY_WORKERS")]
    workers: Option<usize>,
    /// Species specs the demo bakes on first start.
    #[arg(long, env = "CANOPY_SPECIES", default_value = "assets/species")]
    species: PathBuf,
    /// Only these species (comma-separated names) in the demo.
    #[arg(long, env = "CANOPY_DEMO_SPECIES", value_delimiter = ',')]
    demo_species: Vec<String>,
    /// Use this many small built-in synthetic trees instead of growing species (tests, quick
    /// starts).
    #[arg(long, env = "CANOPY_DEMO_SYNTHETIC")]
    demo_synthetic: Option<usize>,
    /// Trees in the demo scene.
    #[arg(long, env = "CANOPY_DEMO_TREES", default_value_t = 2500)]
    demo_trees: usize,
    /// Also bake N irregular billboard views per demo model (a generated photographer's set,
    /// seed 001), drawn by the ladder rung `views`.
    #[arg(long, env = "CANOPY_DEMO_PHOTO_VIEWS", value_parser = clap::value_parser!(u16).range(1..=16384))]
    demo_photo_views: Option<u16>,
    /// Demo extent along x, metres (seed 002's forest: 10000 by 10000).
    #[arg(long, env = "CANOPY_DEMO_WIDTH_M", default_value_t = DemoConfig::default().width_m, value_parser = parse_extent)]
    demo_width_m: f64,
    /// Demo extent along z, metres.
    #[arg(long, env = "CANOPY_DEMO_DEPTH_M", default_value_t = DemoConfig::default().depth_m, value_parser = parse_extent)]
    demo_depth_m: f64,
    /// Do not create the demo scene (nor the hills scene).
    #[arg(long, env = "CANOPY_NO_DEMO")]
    no_demo: bool,
    /// Do not create the scene `hills` beside the demo (the demo's models and placement rules on a
    /// generated terrain with 75 m of relief).
    #[arg(long, env = "CANOPY_NO_DEMO_HILLS")]
    no_demo_hills: bool,
    /// Bake and publish (the demo, the unique forest if asked) into the data folder and the
    /// database, then exit without serving: the bake job of a deployment whose replicas all start
    /// with `--no-demo` on the published data.
    #[arg(long, env = "CANOPY_PUBLISH_ONLY", conflicts_with = "no_demo")]
    publish_only: bool,
    /// The unique forest (opt-in: its first bake takes minutes).
    #[command(flatten)]
    unique: crate::unique_cmd::UniqueArgs,
    /// Presence publications a viewer may fall behind before it is closed as too slow.
    #[arg(long, env = "CANOPY_LIVE_QUEUE", default_value_t = 256)]
    live_queue: usize,
    /// Interval between a scene's presence publications (latest pose per viewer), milliseconds;
    /// stretched so a scene delivers at most 300,000 poses a second.
    #[arg(long, env = "CANOPY_POSE_INTERVAL_MS", default_value_t = 100)]
    pose_interval_ms: u64,
    /// Log format on stderr: `text` (human-readable) or `json` (one object per line).
    #[arg(long, env = "CANOPY_LOG_FORMAT", value_enum, default_value_t = LogFormat::Text)]
    log_format: LogFormat,
    /// Asset bytes held in memory, MiB (0: read every response from disk).
    #[arg(long, env = "CANOPY_ASSET_MEMORY_MB", default_value_t = 256)]
    asset_memory_mb: u64,
    /// Longest a request head may take, seconds: from accept on a new connection, from its first
    /// byte on a kept-alive one.
    #[arg(long, env = "CANOPY_HEADER_TIMEOUT_S", default_value = "10", value_parser = parse_timeout)]
    header_timeout_s: Duration,
    /// Longest an API request body may take to arrive whole, seconds (then 408).
    #[arg(long, env = "CANOPY_BODY_TIMEOUT_S", default_value = "30", value_parser = parse_timeout)]
    body_timeout_s: Duration,
    /// Longest a kept-alive connection may wait for its next request, seconds.
    #[arg(long, env = "CANOPY_IDLE_TIMEOUT_S", default_value = "60", value_parser = parse_timeout)]
    idle_timeout_s: Duration,
    /// Longest a response write may make no progress, seconds (a client that does not read).
    #[arg(long, env = "CANOPY_WRITE_TIMEOUT_S", default_value = "60", value_parser = parse_timeout)]
    write_timeout_s: Duration,
    /// Most open connections, WebSockets included (default: half the open-file limit, 64 to
    /// 16384). At the bound the connection idle longest is closed; with none idle, 503.
    #[arg(long, env = "CANOPY_MAX_CONNECTIONS", value_parser = clap::value_parser!(u64).range(1..))]
    max_connections: Option<u64>,
    /// Who may create scenes, quotas, rates, retention.
    #[command(flatten)]
    store: Box<StoreArgs>,
}

/// Flags of scene creation, quotas, rate limits and version retention (boxed in [`ServeArgs`]:
/// they would make it much larger than the other commands).
#[derive(clap::Args, Debug)]
pub struct StoreArgs {
    /// Scene creation needs this token (several: comma-separated, each with its own quotas).
    /// Without it or --open-creation, a token is generated once and kept in DATA/creation-token.
    #[arg(
        long,
        env = "CANOPY_CREATION_TOKEN",
        value_delimiter = ',',
        conflicts_with = "open_creation"
    )]
    creation_token: Vec<String>,
    /// Anyone may create scenes (quotas and rates then count per client address).
    #[arg(long, env = "CANOPY_OPEN_CREATION")]
    open_creation: bool,
    /// Most scenes per creation token (per client address in open mode).
    #[arg(long, env = "CANOPY_QUOTA_SCENES", default_value_t = Limits::default().max_scenes)]
    quota_scenes: u64,
    /// Most instances in one scene of a token's (at most 200000).
    #[arg(long, env = "CANOPY_QUOTA_INSTANCES", default_value_t = MAX_INSTANCES as u64,
          value_parser = clap::value_parser!(u64).range(1..=MAX_INSTANCES as u64))]
    quota_instances: u64,
    /// Most MiB the kept versions of a token's scenes take on disk.
    #[arg(long, env = "CANOPY_QUOTA_MB", default_value_t = 2048)]
    quota_mb: u64,
    /// Scene creations per minute, per token and per client address (a minute's worth at once).
    #[arg(long, env = "CANOPY_CREATIONS_PER_MIN", default_value_t = 10.0, value_parser = parse_rate)]
    creations_per_min: f64,
    /// Edits and pins per second, per scene and per client address (ten seconds' worth at once).
    #[arg(long, env = "CANOPY_EDITS_PER_S", default_value_t = 10.0, value_parser = parse_rate)]
    edits_per_s: f64,
    /// Versions kept per scene by count (besides pinned ones and those --keep-days keeps).
    #[arg(long, env = "CANOPY_KEEP_VERSIONS", default_value_t = Limits::default().keep_versions,
          value_parser = clap::value_parser!(u64).range(1..))]
    keep_versions: u64,
    /// Versions kept per scene by age, days (0: by count only).
    #[arg(long, env = "CANOPY_KEEP_DAYS", default_value_t = 0.0, value_parser = parse_days)]
    keep_days: f64,
    /// Seconds between garbage collections (retention by age, unreferenced scene files).
    #[arg(long, env = "CANOPY_GC_INTERVAL_S", default_value = "600", value_parser = parse_timeout)]
    gc_interval_s: Duration,
}

/// How log lines are written.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogFormat {
    /// `tracing`'s human-readable lines.
    Text,
    /// One JSON object per line: `timestamp`, `level`, `target`, `message`, `fields`.
    Json,
}

/// Formats each event as one JSON object per line (`--log-format json`), with `serde_json` (no
/// extra dependency): `{"timestamp":"…Z","level":"INFO","target":"…","message":"…","fields":{…}}`.
#[derive(Debug, Clone, Copy, Default)]
pub struct JsonFormat;

struct JsonFields<'a> {
    message: &'a mut Option<String>,
    fields: &'a mut serde_json::Map<String, serde_json::Value>,
}

impl tracing::field::Visit for JsonFields<'_> {
    fn record_str(&mut self, field: &tracing::field::Field, value: &str) {
        if field.name() == "message" {
            *self.message = Some(value.to_string());
        } else {
            self.fields.insert(field.name().to_string(), value.into());
        }
    }

    fn record_i64(&mut self, field: &tracing::field::Field, value: i64) {
        self.fields.insert(field.name().to_string(), value.into());
    }

    fn record_u64(&mut self, field: &tracing::field::Field, value: u64) {
        self.fields.insert(field.name().to_string(), value.into());
    }

    fn record_f64(&mut self, field: &tracing::field::Field, value: f64) {
        self.fields.insert(field.name().to_string(), value.into());
    }

    fn record_bool(&mut self, field: &tracing::field::Field, value: bool) {
        self.fields.insert(field.name().to_string(), value.into());
    }

    fn record_debug(&mut self, field: &tracing::field::Field, value: &dyn std::fmt::Debug) {
        self.record_str(field, &format!("{value:?}"));
    }
}

impl<S, N> tracing_subscriber::fmt::FormatEvent<S, N> for JsonFormat
where
    S: tracing::Subscriber + for<'a> tracing_subscriber::registry::LookupSpan<'a>,
    N: for<'a> tracing_subscriber::fmt::FormatFields<'a> + 'static,
{
    fn format_event(
        &self,
        _ctx: &tracing_subscriber::fmt::FmtContext<'_, S, N>,
        mut writer: tracing_subscriber::fmt::format::Writer<'_>,
        event: &tracing::Event<'_>,
    ) -> std::fmt::Result {
        use tracing_subscriber::fmt::time::FormatTime as _;
        let mut timestamp = String::new();
        tracing_subscriber::fmt::time::SystemTime
            .format_time(&mut tracing_subscriber::fmt::format::Writer::new(&mut timestamp))?;
        let (mut message, mut fields) = (None, serde_json::Map::new());
        event.record(&mut JsonFields {
            message: &mut message,
            fields: &mut fields,
        });
        let meta = event.metadata();
        let line = serde_json::json!({
            "timestamp": timestamp,
            "level": meta.level().as_str(),
            "target": meta.target(),
            "message": message.unwrap_or_default(),
            "fields": fields,
        });
        writeln!(writer, "{line}")
    }
}

/// A demo extent in metres: at least 1 m and at most what a scene's bounds allow.
pub(crate) fn parse_extent(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|_| format!("not a number of metres: {s:?}"))?;
    if (1.0..=MAX_EXTENT_M).contains(&v) {
        Ok(v)
    } else {
        Err(format!("must be between 1 and {MAX_EXTENT_M} m"))
    }
}

/// A timeout in seconds (fractions allowed): more than 0 and at most a day.
fn parse_timeout(s: &str) -> Result<Duration, String> {
    let v: f64 = s.parse().map_err(|_| format!("not a number of seconds: {s:?}"))?;
    if v > 0.0 && v <= 86_400.0 {
        Ok(Duration::from_secs_f64(v))
    } else {
        Err("must be more than 0 and at most 86400 s".into())
    }
}

/// A rate: finite, more than 0, at most a million.
fn parse_rate(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|_| format!("not a number: {s:?}"))?;
    if v > 0.0 && v <= 1e6 {
        Ok(v)
    } else {
        Err("must be more than 0 and at most 1000000".into())
    }
}

/// Days of versions kept: 0 (off) to 100 years.
fn parse_days(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|_| format!("not a number of days: {s:?}"))?;
    if (0.0..=36_500.0).contains(&v) {
        Ok(v)
    } else {
        Err("must be between 0 and 36500 days".into())
    }
}

/// The creation policy: the given tokens, open, or the token kept in `DATA/creation-token`
/// (made on first start, readable by the owner only).
fn creation(args: &StoreArgs, data: &std::path::Path) -> Result<Creation> {
    if args.open_creation {
        tracing::warn!("scene creation is open: anyone who can reach the server may create scenes");
        return Ok(Creation::Open);
    }
    let given: Vec<&String> = args.creation_token.iter().filter(|t| !t.trim().is_empty()).collect();
    if !given.is_empty() {
        return Ok(Creation::tokens(&given.iter().map(|t| t.trim()).collect::<Vec<_>>()));
    }
    let path = data.join("creation-token");
    let token = match std::fs::read_to_string(&path) {
        Ok(t) if !t.trim().is_empty() => t.trim().to_string(),
        _ => {
            let t = http::auth::new_token().context("making a creation token")?;
            let mut f = std::fs::OpenOptions::new();
            f.write(true).create(true).truncate(true);
            #[cfg(unix)]
            std::os::unix::fs::OpenOptionsExt::mode(&mut f, 0o600);
            let mut file = f.open(&path).with_context(|| format!("writing {}", path.display()))?;
            std::io::Write::write_all(&mut file, format!("{t}\n").as_bytes())
                .and_then(|()| file.sync_all())
                .with_context(|| format!("writing {}", path.display()))?;
            t
        }
    };
    tracing::info!(file = %path.display(), "scene creation needs the token in this file");
    Ok(Creation::tokens(&[token]))
}

/// The scene store `--database` names.
fn open_scenes(database: Option<&str>, data: &std::path::Path) -> Result<Arc<dyn SceneStore>> {
    match database {
        Some(url) if url.starts_with("postgres://") || url.starts_with("postgresql://") => {
            let store = PostgresStore::open(url).context("opening the PostgreSQL scene database")?;
            tracing::info!(available = store.available(), "scenes in PostgreSQL");
            Ok(Arc::new(store))
        }
        Some(other) => {
            let path = other
                .strip_prefix("sqlite:")
                .map(PathBuf::from)
                .with_context(|| format!("--database {other:?}: expected sqlite:PATH or postgres://…"))?;
            Ok(Arc::new(
                SqliteStore::open(&path).with_context(|| format!("opening {}", path.display()))?,
            ))
        }
        None => {
            let path = data.join("canopy.db");
            Ok(Arc::new(
                SqliteStore::open(&path).with_context(|| format!("opening {}", path.display()))?,
            ))
        }
    }
}

/// Runs the server until Ctrl-C or SIGTERM.
pub fn run(args: ServeArgs) -> Result<()> {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let logs = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    let _ = match args.log_format {
        LogFormat::Text => logs.try_init(),
        LogFormat::Json => logs.event_format(JsonFormat).try_init(),
    };

    // One worker: a current-thread runtime (no work-stealing queues or cross-thread wake-ups, the
    // shape of one nginx worker); more: the multi-threaded one.
    let mut rt = match args.workers {
        Some(1) => tokio::runtime::Builder::new_current_thread(),
        Some(w) => {
            let mut b = tokio::runtime::Builder::new_multi_thread();
            b.worker_threads(w.max(1));
            b
        }
        None => tokio::runtime::Builder::new_multi_thread(),
    };
    rt.enable_all();
    let rt = rt.build().context("starting the async runtime")?;

    std::fs::create_dir_all(&args.data).with_context(|| format!("creating {}", args.data.display()))?;
    let assets = Arc::new(
        AssetStore::open_with_memory(&args.data.join("assets"), args.asset_memory_mb.saturating_mul(1 << 20))
            .context("opening the asset folder")?,
    );
    let scenes = open_scenes(args.database.as_deref(), &args.data)?;
    assets.set_shared(scenes.shared());
    let limits = Limits {
        max_scenes: args.store.quota_scenes,
        max_instances: args.store.quota_instances as usize,
        max_bytes: args.store.quota_mb.saturating_mul(1 << 20),
        keep_versions: args.store.keep_versions,
        keep_secs: (args.store.keep_days * 86_400.0) as u64,
        ..Limits::default()
    };
    // Alone on its data, nothing is in flight yet: every unreferenced scene file can go (no
    // grace). Beside other replicas, their publishes may be.
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let grace = if scenes.shared() { gc::GRACE } else { Duration::ZERO };
    match gc::collect(&assets, scenes.as_ref(), &limits, now, grace) {
        Ok(c) => tracing::info!(
            versions = c.versions,
            files = c.files,
            bytes = c.bytes,
            "garbage collected at start"
        ),
        Err(e @ StoreError::Unavailable(_)) => tracing::warn!(error = %e, "no garbage collection at start"),
        Err(e) => return Err(e).context("collecting old versions"),
    }
    let config = HttpConfig {
        live_queue: args.live_queue.max(1),
        pose_interval: Duration::from_millis(args.pose_interval_ms.max(1)),
        header_timeout: args.header_timeout_s,
        body_timeout: args.body_timeout_s,
        idle_timeout: args.idle_timeout_s,
        write_timeout: args.write_timeout_s,
        max_connections: args
            .max_connections
            .map_or_else(http::conn::default_max_connections, |n| n as usize),
        creation: creation(&args.store, &args.data)?,
        limits,
        create_rate: Rate::per_minute(args.store.creations_per_min),
        edit_rate: Rate::per_second(args.store.edits_per_s),
        ..HttpConfig::default()
    };
    tracing::info!(
        max_connections = config.max_connections,
        open_file_limit = ?http::conn::descriptor_limit(),
        header_timeout_s = config.header_timeout.as_secs_f64(),
        body_timeout_s = config.body_timeout.as_secs_f64(),
        idle_timeout_s = config.idle_timeout.as_secs_f64(),
        write_timeout_s = config.write_timeout.as_secs_f64(),
        "connection limits"
    );
    // Made on the runtime: the live hubs keep its handle to start scene tickers from the store's
    // listener thread (presence relayed by other replicas). Only for this call: the store's
    // blocking client must not run inside it.
    let (state, stop) = {
        let _on_runtime = rt.enter();
        AppState::new(assets, scenes, config)
    };
    // Models baked before discrete LOD files existed get theirs now (new bakes write them).
    let made = canopy_server::discrete_files::ensure_level_files(&state.inner.assets, &|done, total| {
        if done == 1 || done == total {
            tracing::info!(done, total, "writing discrete LOD files of models baked without them");
        }
    })
    .context("writing discrete LOD files")?;
    if made.written > 0 {
        tracing::info!(models = made.written, "discrete LOD files written");
    }
    for (model, e) in &made.failed {
        tracing::warn!(model, error = %e, "no discrete LOD files for this model");
    }

    if !args.no_demo {
        let models = match args.demo_synthetic {
            Some(n) => DemoModels::Synthetic(n.max(1)),
            None => DemoModels::Species {
                dir: args.species.clone(),
                only: args.demo_species.clone(),
            },
        };
        let cfg = DemoConfig {
            models,
            trees: args.demo_trees,
            width_m: args.demo_width_m,
            depth_m: args.demo_depth_m,
            photo_views: args.demo_photo_views.map(usize::from),
            ..DemoConfig::default()
        };
        let pb = ProgressBar::new(1);
        pb.set_style(
            ProgressStyle::with_template("{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        let created = demo::ensure_demo(&state, &cfg, &mut |stage, done, total| {
            pb.set_length(total);
            pb.set_position(done);
            pb.set_message(stage.to_string());
        })
        .context("creating the demo scene")?;
        if created {
            tracing::info!(
                trees = cfg.trees,
                "demo scene ready (write token in DATA/demo-write-token)"
            );
        }
        if !args.no_demo_hills
            && demo::ensure_hills(&state, &cfg, &mut |stage, done, total| {
                pb.set_length(total);
                pb.set_position(done);
                pb.set_message(stage.to_string());
            })
            .context("creating the hills scene")?
        {
            tracing::info!(
                trees = cfg.trees,
                "hills scene ready (write token in DATA/hills-write-token)"
            );
        }
        pb.finish_and_clear();
    }

    crate::unique_cmd::ensure(&state, &args.unique, &args.species)?;
    if args.publish_only {
        // Tests and scripts read this line.
        println!("canopy-server published into {}", args.data.display());
        return Ok(());
    }

    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(args.addr)
            .await
            .with_context(|| format!("binding {}", args.addr))?;
        let local = listener.local_addr().context("reading the bound address")?;
        // Tests and scripts read this line.
        println!("canopy-server listening on http://{local}");
        tracing::info!(addr = %local, data = %args.data.display(), "serving");
        tokio::spawn(collect_periodically(state.clone(), args.store.gc_interval_s));
        http::serve(listener, state, stop, shutdown_signal())
            .await
            .context("serving")?;
        tracing::info!("stopped");
        Ok(())
    })
}

/// Applies the retention by age and sweeps unreferenced scene files every `every`.
async fn collect_periodically(state: AppState, every: Duration) {
    let mut tick = tokio::time::interval(every);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    tick.tick().await;
    loop {
        tick.tick().await;
        let st = state.clone();
        let done = tokio::task::spawn_blocking(move || {
            let now = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs());
            gc::collect(
                &st.inner.assets,
                st.inner.scenes.as_ref(),
                &st.inner.config.limits,
                now,
                gc::GRACE,
            )
        })
        .await;
        match done {
            Ok(Ok(c)) if c.files > 0 || c.versions > 0 => {
                tracing::info!(
                    versions = c.versions,
                    files = c.files,
                    bytes = c.bytes,
                    "garbage collected"
                );
            }
            Ok(Ok(_)) => {}
            Ok(Err(e)) => tracing::warn!(error = %e, "garbage collection failed"),
            Err(e) => tracing::warn!(error = %e, "garbage collection panicked"),
        }
    }
}

async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {},
        () = term => {},
    }
}

#[cfg(test)]
mod tests {
    use std::sync::{Arc, Mutex};

    use super::{JsonFormat, parse_extent, parse_timeout};

    #[derive(Clone, Default)]
    struct Buf(Arc<Mutex<Vec<u8>>>);

    impl std::io::Write for Buf {
        fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
            self.0.lock().expect("lock").extend_from_slice(b);
            Ok(b.len())
        }

        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn json_logs_are_one_object_per_line() {
        let buf = Buf::default();
        let out = buf.clone();
        let sub = tracing_subscriber::fmt()
            .event_format(JsonFormat)
            .with_writer(move || out.clone())
            .finish();
        tracing::subscriber::with_default(sub, || {
            tracing::info!(scene = "demo", viewer = 7u64, ok = true, "viewer \"joined\"");
            tracing::warn!(error = %"disk full", "cannot write");
        });
        let text = String::from_utf8(buf.0.lock().expect("lock").clone()).expect("utf8");
        let lines: Vec<serde_json::Value> = text
            .lines()
            .map(|l| serde_json::from_str(l).expect("one JSON object per line"))
            .collect();
        assert_eq!(lines.len(), 2, "{text}");
        assert_eq!(lines[0]["level"], "INFO");
        assert_eq!(lines[0]["message"], "viewer \"joined\"");
        assert_eq!(lines[0]["fields"]["scene"], "demo");
        assert_eq!(lines[0]["fields"]["viewer"], 7);
        assert_eq!(lines[0]["fields"]["ok"], true);
        assert!(lines[0]["timestamp"].as_str().is_some_and(|t| t.ends_with('Z')));
        assert_eq!(lines[1]["level"], "WARN");
        assert_eq!(lines[1]["fields"]["error"], "disk full");
    }

    #[test]
    fn timeouts_are_checked() {
        assert_eq!(parse_timeout("10"), Ok(std::time::Duration::from_secs(10)));
        assert_eq!(parse_timeout("0.5"), Ok(std::time::Duration::from_millis(500)));
        for bad in ["0", "-1", "86401", "NaN", "inf", "ten", ""] {
            assert!(parse_timeout(bad).is_err(), "{bad} accepted");
        }
    }

    #[test]
    fn demo_extents_are_checked() {
        assert_eq!(parse_extent("10000"), Ok(10_000.0));
        assert_eq!(parse_extent("1"), Ok(1.0));
        for bad in ["0", "0.5", "-5", "100001", "NaN", "inf", "1e9", "ten"] {
            assert!(parse_extent(bad).is_err(), "{bad} accepted");
        }
    }
}
