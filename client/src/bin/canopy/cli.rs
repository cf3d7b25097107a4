//! Arguments and helpers shared by the subcommands.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use canopy_client::lod::projection::{DEFAULT_LADDER_SPEC, SWITCH_BLEND_BAND, parse_ladder};
use canopy_client::lod::{FlightParams, LodParams};
use canopy_client::net::http::{HttpOptions, HttpSource, RangeMode};
use canopy_client::net::link::LinkModel;
use canopy_client::net::{NetError, RangeSource};
use canopy_client::paths::{FRAME_DT, PathKind};
use canopy_client::scene::Manifest;
use canopy_client::stream::{StreamOptions, Viewport};
use canopy_shared::flight_table::FlightTable;
use clap::Args;

/// Where a scene comes from and how to reach its assets.
#[derive(Args, Debug, Clone)]
pub struct SceneArgs {
    /// The scene: `http://HOST:PORT/api/scenes/ID`, or a manifest file inside a server's data
    /// folder (a scene's first version, `DATA/assets/scenes/ID/v1.HASH.json`, read with the file
    /// backend; later versions are served by the server only).
    pub url: String,
    /// Base URL of the assets (a CDN or nginx serving the server's `assets/` folder at
    /// `/assets/`); default: the scene's own server.
    #[arg(long)]
    pub assets_base: Option<String>,
    /// How several ranges are requested: auto (multi-range until refused), multi, single.
    #[arg(long, value_enum, default_value_t = RangeMode::Auto)]
    pub range_mode: RangeMode,
    /// Most requests in flight.
    #[arg(long, default_value_t = 16)]
    pub max_in_flight: usize,
    /// Retries per request after the first attempt (exponential backoff from 25 ms).
    #[arg(long, default_value_t = 4)]
    pub retries: u32,
}

/// LOD and view options.
#[derive(Args, Debug, Clone)]
#[allow(clippy::struct_excessive_bools)] // Independent command-line switches.
pub struct ViewArgs {
    /// Camera path.
    #[arg(long, value_enum, default_value_t = PathKind::Flyover)]
    pub path: PathKind,
    /// Frames, each `--frame-time` of path time apart.
    #[arg(long, default_value_t = 300)]
    pub frames: u32,
    /// Seconds between frames on the headless clock (the transport advances on the same
    /// clock, so figures do not depend on how loaded the machine is).
    #[arg(long, default_value_t = f64::from(FRAME_DT), value_parser = parse_frame_time)]
    pub frame_time: f64,
    /// Speed along the path, m/s, instead of the path's own (orbit 20, flyover 25, walk 3,
    /// lowflight 60, turns 20); 0 holds the camera at the path's start.
    #[arg(long, value_parser = parse_speed)]
    pub speed: Option<f32>,
    /// Fly the path at this eye height instead of its own, metres above the ground (its
    /// direction of view unchanged): seed 002's flight height H.
    #[arg(long, value_name = "M", value_parser = parse_eye_height)]
    pub eye_height: Option<f32>,
    /// Viewport width, pixels.
    #[arg(long, default_value_t = 1280)]
    pub width: u32,
    /// Viewport height, pixels (seed 000's L).
    #[arg(long, default_value_t = 720)]
    pub height: u32,
    /// Vertical field of view, degrees.
    #[arg(long, default_value_t = 60.0)]
    pub fov_deg: f32,
    /// View distance, metres: farther trees are neither fetched nor drawn.
    #[arg(long, default_value_t = 1500.0)]
    pub view_distance: f32,
    /// Cache budget, MiB (at least 1).
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u64).range(1..))]
    pub cache_mb: u64,
    /// Most bytes fetched per frame, KiB (best visual gain per byte first); 0 = no limit.
    #[arg(long, default_value_t = 0)]
    pub frame_budget_kb: u64,
    /// Draw every visible tree at full detail (the baseline LOD is compared with).
    #[arg(long)]
    pub full_detail: bool,
    /// Seed 000 representation ladder, finest first: `NAME:ε` rungs where ε is the projected
    /// tree height in pixels down to which the rung is used. Names: geometry, iterN (geometry
    /// grown N iterations fewer, seed 000's middle level), hullN, cloudN, hemioct, latlong,
    /// crossed, views (seed 001's irregular views, where the bake made them; else hemioct). The
    /// default won a sweep on perceptual quality per byte at the crown-hull ladder's
    /// triangle count; that ladder, fewest bytes, is `geometry:150,hull0:60,hull1:30,hemioct:0`;
    /// `geometry:30,hemioct:0` looks better still at 11× the triangles.
    #[arg(long, default_value = DEFAULT_LADDER_SPEC)]
    pub ladder: String,
    /// Cross-fade band between adjacent billboard-cloud rungs, as a fraction of the switch's ε
    /// (0 turns the cross-fade off).
    #[arg(long, default_value_t = SWITCH_BLEND_BAND)]
    pub cloud_blend: f32,
    /// Seed 004: distance at or below which a node's distance factors (f2, f4) are 0, metres.
    /// The other factors still simplify it: `--lod-weights 0,0,0,0,0` keeps every leaf.
    #[arg(long, default_value_t = LodParams::default().near)]
    pub lod_near: f32,
    /// Seed 004: distance at or beyond which f2 = 0.5 and f4 = 1, metres.
    #[arg(long, default_value_t = LodParams::default().far)]
    pub lod_far: f32,
    /// Seed 004 weights α1..α5 of the factors (bounding-sphere layer, branch level with distance,
    /// leaf density, distance, view direction), comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = LodParams::default().weights)]
    pub lod_weights: Vec<f32>,
    /// Seed 004: apply every proposed rate change at once (no switch control, eq. 13): the
    /// baseline of its switch-control experiment.
    #[arg(long)]
    pub no_switch_control: bool,
    /// Pixel-scale leaf budget: a far tree drawn as geometry keeps at most the fraction
    /// `(ℓ/PX)²` of each node's leaves (at least one), where ℓ is its leaf size in pixels, and
    /// the kept leaves are enlarged up to PX pixels so the crown keeps its leaf area. Trees whose
    /// leaves are PX pixels or larger are left to seed 004's rate alone. Off when not given.
    #[arg(long, value_name = "PX")]
    pub leaf_pixels: Option<f32>,
    /// With `--leaf-pixels`: draw the kept leaves at their own size instead of enlarging them to
    /// PX pixels. What is drawn is then a subset of the full tree's pixels (coverage precision
    /// 1, unless `eval --enlarge` enlarges them anyway), at the cost of recall and SSIM.
    #[arg(long, requires = "leaf_pixels")]
    pub no_leaf_pixels_enlarge: bool,
    /// Use seed 002's low-flight policy (distance bands 100/250/500/1000 m, 120° field,
    /// threat zone of 2 s) instead of seed 000's projected-size ladder. Its level k draws the
    /// ladder's rung k (the last rung past the ladder's end). With it, the scene's
    /// visual-redundancy table (`GET /api/scenes/ID/flight-table`, made by `canopy redundancy`)
    /// raises levels by flight height and speed, and its policy's bands replace the defaults;
    /// a scene without one flies the policy alone.
    #[arg(long)]
    pub flight_policy: bool,
    /// With `--flight-policy`: this redundancy table (JSON, as `canopy redundancy` writes it)
    /// instead of the scene's. Implies `--flight-policy`.
    #[arg(long, value_name = "FILE", conflicts_with = "no_flight_table")]
    pub flight_table: Option<PathBuf>,
    /// With `--flight-policy`: ignore the scene's redundancy table (the policy alone).
    #[arg(long)]
    pub no_flight_table: bool,
    /// Draw and fetch for trees the scene's terrain hides too (no occlusion culling): the
    /// baseline of the culling's figures.
    #[arg(long)]
    pub no_terrain_culling: bool,
    /// Plan every tree on the frame loop's own thread instead of spreading the geometry trees
    /// over rayon's pool (`RAYON_NUM_THREADS` sets its size). What is fetched and drawn is the
    /// same either way.
    #[arg(long)]
    pub no_plan_pool: bool,
}

fn parse_frame_time(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(t) if t.is_finite() && t > 0.0 && t <= 10.0 => Ok(t),
        _ => Err("a frame time is seconds, over 0 and at most 10".into()),
    }
}

fn parse_eye_height(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(h) if h.is_finite() && (0.1..=10_000.0).contains(&h) => Ok(h),
        _ => Err("an eye height is metres, from 0.1 to 10000".into()),
    }
}

fn parse_speed(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v.is_finite() && (0.0..=1000.0).contains(&v) => Ok(v),
        _ => Err("a speed is m/s, from 0 to 1000".into()),
    }
}

impl ViewArgs {
    /// The camera at frame `f`, over `ground` when the scene has a terrain (its whole
    /// heightfield: the pilot knows the ground; [`canopy_client::terrain::fetch_whole`]).
    pub fn camera(
        &self,
        bounds: canopy_client::paths::Rect,
        f: u32,
        ground: Option<&canopy_shared::terrain::Heightfield>,
    ) -> canopy_client::stream::Camera {
        let t = (f64::from(f) * self.frame_time) as f32;
        let speed = self.speed.unwrap_or_else(|| self.path.speed());
        if let Some(g) = ground {
            return canopy_client::paths::camera_over(self.path, bounds, t, speed, self.eye_height, &|x, z| {
                g.height_at(x, z)
            });
        }
        let mut cam = canopy_client::paths::camera_at_speed(self.path, bounds, t, speed);
        if let Some(h) = self.eye_height {
            cam.eye.y = h;
        }
        cam
    }
}

/// The link headless runs stream over, on their virtual clock.
#[derive(Args, Debug, Clone)]
pub struct LinkArgs {
    /// The link between client and server, modelled on the run's virtual clock: a preset,
    /// `loopback` (no link: transfers are instant), `slow4g` (Lighthouse's mobile throttling:
    /// 1.6 Mbit/s down, 750 kbit/s up, 150 ms), `fast4g` (Chrome DevTools: 8.1 Mbit/s down,
    /// 1.35 up, 165 ms), `3g-slow` (WebPageTest: 400 kbit/s, 400 ms), `dash10`, `dash5`,
    /// `dash2.5` (DASH-3D's links: 10, 5, 2.5 Mbit/s, 38 ms); or `MBIT,RTT_MS[,UP_MBIT[,LOSS_%]]`;
    /// then optionally `@T=MBIT;T=MBIT` for downlink changes at T seconds (`dash10@10=1.6;20=10`).
    /// 6 connections, as a browser opens per host. Left out: TCP slow start, HTTP/2.
    #[arg(long, default_value = "loopback")]
    pub link: LinkModel,
}

pub fn stream_options(v: &ViewArgs) -> Result<StreamOptions> {
    let ladder = parse_ladder(&v.ladder).map_err(|e| anyhow::anyhow!("--ladder: {e}"))?;
    let defaults = LodParams::default();
    let weights: [f32; 5] = v
        .lod_weights
        .as_slice()
        .try_into()
        .map_err(|_| anyhow::anyhow!("--lod-weights takes exactly 5 numbers"))?;
    if !(weights.iter().all(|w| w.is_finite() && *w >= 0.0)
        && v.lod_near.is_finite()
        && v.lod_far.is_finite()
        && v.lod_near >= 0.0
        && v.lod_far > v.lod_near.max(1.0))
    {
        bail!("--lod-weights must be finite and ≥ 0, and --lod-far > max(--lod-near, 1) ≥ 0");
    }
    if v.leaf_pixels.is_some_and(|px| !(px.is_finite() && px > 0.0)) {
        bail!("--leaf-pixels must be a positive number of pixels");
    }
    if !(v.cloud_blend.is_finite() && (0.0..=1.0).contains(&v.cloud_blend)) {
        bail!("--cloud-blend must be between 0 and 1");
    }
    Ok(StreamOptions {
        lod: LodParams {
            near: v.lod_near,
            far: v.lod_far,
            weights,
            leaf_pixels: v.leaf_pixels,
            leaf_pixels_enlarge: !v.no_leaf_pixels_enlarge,
            switch_control: !v.no_switch_control,
            ..defaults
        },
        ladder,
        cloud_blend: v.cloud_blend,
        viewport: Viewport {
            width: v.width.max(1),
            height: v.height.max(1),
            fov_y: v.fov_deg.clamp(1.0, 170.0).to_radians(),
            near: 0.1,
            far: v.view_distance.max(1.0),
        },
        cache_budget: v.cache_mb.saturating_mul(1 << 20),
        frame_byte_budget: (v.frame_budget_kb > 0).then(|| v.frame_budget_kb.saturating_mul(1024)),
        lod_enabled: !v.full_detail,
        terrain_culling: !v.no_terrain_culling,
        plan_on_pool: !v.no_plan_pool,
        flight: (v.flight_policy || v.flight_table.is_some()).then(FlightParams::standard),
        stand_in_from_px: None,
    })
}

/// The ground a headless run's camera path flies over: the scene's whole terrain (its bytes go
/// over `src` before the run, outside the run's figures), or `None` for a flat scene.
pub async fn path_ground<S: canopy_client::net::RangeSource>(
    src: &S,
    m: &canopy_shared::manifest::Manifest,
) -> Result<Option<canopy_shared::terrain::Heightfield>> {
    match &m.terrain {
        Some(t) => Ok(Some(canopy_client::terrain::fetch_whole(src, t).await?)),
        None => Ok(None),
    }
}

/// Reads a redundancy table file.
pub fn read_flight_table(path: &Path) -> Result<FlightTable> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    FlightTable::parse(&bytes).with_context(|| format!("reading the flight table {}", path.display()))
}

/// The scene's redundancy table's API path (`…/ID/manifest` → `…/ID/flight-table`); `None` for
/// a static manifest file, which has none beside it.
pub fn flight_table_path(manifest_path: &str) -> Option<String> {
    manifest_path
        .strip_suffix("/manifest")
        .map(|scene| format!("{scene}/flight-table"))
}

/// Gives `opts`' low-flight policy its redundancy table, when the policy is on: `--flight-table`'s
/// file, else the scene's own from its server unless `--no-flight-table` (a scene without one,
/// 404, flies the policy alone, and says so on stderr). Returns where the table came from.
pub async fn resolve_flight_table(
    opts: &mut StreamOptions,
    v: &ViewArgs,
    loc: &SceneLocation,
    scene: &SceneArgs,
) -> Result<Option<String>> {
    if opts.flight.is_none() || v.no_flight_table {
        return Ok(None);
    }
    if let Some(path) = &v.flight_table {
        opts.flight = Some(FlightParams::from_table(read_flight_table(path)?));
        return Ok(Some(path.display().to_string()));
    }
    let SceneLocation::Http {
        api_origin,
        manifest_path,
        ..
    } = loc
    else {
        return Ok(None);
    };
    let Some(path) = flight_table_path(manifest_path) else {
        return Ok(None);
    };
    let api = HttpSource::new(api_origin, http_options(scene))?;
    match api.get(&path).await {
        Ok(bytes) => {
            let t =
                FlightTable::parse(&bytes).with_context(|| format!("reading the flight table {api_origin}{path}"))?;
            opts.flight = Some(FlightParams::from_table(t));
            Ok(Some(format!("{api_origin}{path}")))
        }
        Err(NetError::Status { status: 404, .. }) => {
            eprintln!("note: the scene has no flight table ({api_origin}{path}); seed 002's policy without redundancy");
            Ok(None)
        }
        Err(e) => Err(e).with_context(|| format!("fetching the flight table {api_origin}{path}")),
    }
}

/// A resolved scene location.
pub enum SceneLocation {
    Http {
        api_origin: String,
        manifest_path: String,
        assets_origin: String,
    },
    Files {
        root: PathBuf,
        manifest_path: String,
    },
}

pub fn origin_of(url: &str) -> Result<(String, String)> {
    let rest = url
        .strip_prefix("http://")
        .map(|r| ("http://", r))
        .or_else(|| url.strip_prefix("https://").map(|r| ("https://", r)));
    let Some((scheme, rest)) = rest else {
        bail!("{url:?} is not an http(s) URL");
    };
    let (host, path) = rest.split_at(rest.find('/').unwrap_or(rest.len()));
    if host.is_empty() {
        bail!("{url:?} has no host");
    }
    Ok((format!("{scheme}{host}"), path.to_string()))
}

pub fn locate(a: &SceneArgs) -> Result<SceneLocation> {
    if a.url.starts_with("http://") || a.url.starts_with("https://") {
        let (origin, path) = origin_of(&a.url)?;
        let path = path.trim_end_matches('/');
        let manifest_path = if path.ends_with("/manifest")
            || Path::new(path)
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("json"))
        {
            path.to_string()
        } else {
            format!("{path}/manifest")
        };
        let assets_origin = match &a.assets_base {
            Some(b) => origin_of(b)?.0,
            None => origin.clone(),
        };
        return Ok(SceneLocation::Http {
            api_origin: origin,
            manifest_path,
            assets_origin,
        });
    }
    let p = Path::new(&a.url)
        .canonicalize()
        .with_context(|| format!("{} does not exist", a.url))?;
    // DATA/assets/scenes/ID/vN.json: the root is the folder holding `assets`.
    let root = p
        .ancestors()
        .find(|d| d.file_name().is_some_and(|n| n == "assets"))
        .and_then(Path::parent)
        .with_context(|| format!("{} is not inside a data folder's assets/", p.display()))?
        .to_path_buf();
    let rel = p.strip_prefix(&root).context("manifest outside the root")?;
    Ok(SceneLocation::Files {
        manifest_path: format!("/{}", rel.display()),
        root,
    })
}

pub fn http_options(a: &SceneArgs) -> HttpOptions {
    HttpOptions {
        mode: a.range_mode,
        max_in_flight: a.max_in_flight.max(1),
        retries: a.retries,
        ..HttpOptions::default()
    }
}

/// Peak resident set size of this process (`VmHWM`), bytes; 0 where unknown.
pub fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

pub fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// Fetches and checks a scene's manifest from its server; returns it with its size in bytes.
pub async fn fetch_manifest(api_origin: &str, manifest_path: &str, a: &SceneArgs) -> Result<(Manifest, u64)> {
    let api = HttpSource::new(api_origin, http_options(a))?;
    let bytes = api
        .get(manifest_path)
        .await
        .with_context(|| format!("fetching the manifest {api_origin}{manifest_path}"))?;
    let m = Manifest::parse(&bytes).context("reading the manifest")?;
    Ok((m, bytes.len() as u64))
}
