//! `canopy-server serve`: assets by byte range, scenes, live presence.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result};
use canopy_server::demo::{self, DemoConfig, DemoModels};
use canopy_server::http::{self, AppState, HttpConfig};
use canopy_server::store::{AssetStore, SqliteStore};
use indicatif::{ProgressBar, ProgressStyle};

/// Arguments of `serve`. Every flag can also be set by its environment variable.
#[derive(clap::Args, Debug)]
pub struct ServeArgs {
    /// Data folder: `assets/` (served under /assets/), `canopy.db` (scenes).
    #[arg(long, env = "CANOPY_DATA", default_value = "data")]
    data: PathBuf,
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
    /// Do not create the demo scene.
    #[arg(long, env = "CANOPY_NO_DEMO")]
    no_demo: bool,
    /// Messages a scene's live queue holds before a lagging viewer is dropped.
    #[arg(long, env = "CANOPY_LIVE_QUEUE", default_value_t = 256)]
    live_queue: usize,
    /// Shortest interval between forwarded poses of one viewer, milliseconds.
    #[arg(long, env = "CANOPY_POSE_INTERVAL_MS", default_value_t = 100)]
    pose_interval_ms: u64,
}

/// Runs the server until Ctrl-C or SIGTERM.
pub fn run(args: ServeArgs) -> Result<()> {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();

    let mut rt = tokio::runtime::Builder::new_multi_thread();
    rt.enable_all();
    if let Some(w) = args.workers {
        rt.worker_threads(w.max(1));
    }
    let rt = rt.build().context("starting the async runtime")?;

    std::fs::create_dir_all(&args.data).with_context(|| format!("creating {}", args.data.display()))?;
    let assets = Arc::new(AssetStore::open(&args.data.join("assets")).context("opening the asset folder")?);
    let db_path = args.data.join("canopy.db");
    let scenes = Arc::new(SqliteStore::open(&db_path).with_context(|| format!("opening {}", db_path.display()))?);
    let config = HttpConfig {
        live_queue: args.live_queue.max(1),
        pose_interval: Duration::from_millis(args.pose_interval_ms.max(1)),
        ..HttpConfig::default()
    };
    let (state, stop) = AppState::new(assets, scenes, config);

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
        pb.finish_and_clear();
        if created {
            tracing::info!(
                trees = cfg.trees,
                "demo scene ready (write token in DATA/demo-write-token)"
            );
        }
    }

    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(args.addr)
            .await
            .with_context(|| format!("binding {}", args.addr))?;
        let local = listener.local_addr().context("reading the bound address")?;
        // Tests and scripts read this line.
        println!("canopy-server listening on http://{local}");
        tracing::info!(addr = %local, data = %args.data.display(), "serving");
        http::serve(listener, state, stop, shutdown_signal())
            .await
            .context("serving")?;
        tracing::info!("stopped");
        Ok(())
    })
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
