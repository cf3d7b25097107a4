//! `canopy eval`: transfer against visual quality along a camera path, for several methods in
//! the same run.
//!
//! Methods:
//! - `canopy`: the streaming client (per-node VMI prefixes, hulls and billboards by projected
//!   size), its real bytes;
//! - `canopy-random`: the same fetches, drawing for each node a random subset of the same size,
//!   which is what a file baked in random order (stochastic pruning) gives for the same bytes;
//! - `discrete`: discrete LOD files downloaded whole ([`canopy_client::eval::DiscreteFiles`]);
//! - `full`: every visible tree at full detail (a streamer with LOD off), its real bytes;
//! - `whole-glb`, `whole-ctree`: each visible model's file downloaded whole (its finest meshopt
//!   `.glb`, or its `.ctree`), a tree drawn at full detail once its model's file has arrived
//!   ([`DiscreteFiles::whole`]), as a glTF viewer does;
//! - `canopy-clouds`: the streaming client with billboard-cloud levels where the ladder has
//!   hulls ([`with_clouds`]), its real bytes;
//! - `canopy-weights-xS`, one per `--detail-scales` factor S: the streaming client with seed 004's
//!   weights scaled by S (S = 0 keeps every leaf of a geometry tree), its real bytes: the points
//!   of a quality-against-bytes curve, from which the bytes to reach an SSIM can be read;
//! - `canopy-ladder-…`, one per `--ladders` ladder: the streaming client with that ladder, its
//!   real bytes: the points of a sweep that picks the ladder by quality per byte.
//!
//! At every sampled frame `t` (and `t − 1`, for popping) each method and the full-detail
//! reference are rendered with the shared CPU rasterizer at the viewport's size, and scored:
//! SSIM and the perceptual FLIP error, over the image and per distance band (near / mid / far
//! trees by projected height); the chosen methods' image strips (method | full detail | error)
//! and an HTML report are written beside the CSV and JSON (`output.rs`).

use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use canopy_client::eval::{
    BandMap, BandScore, DiscreteFiles, EvalScene, LeafChoice, RenderMode, View, WholeFile, perceptual, popping,
    render_view, render_view_with_trees,
};
use canopy_client::lod::projection::with_clouds;
use canopy_client::net::RangeSource;
use canopy_client::net::file::FileSource;
use canopy_client::net::http::HttpSource;
use canopy_client::net::link::LinkModel;
use canopy_client::net::linked::LinkedSource;
use canopy_client::scene::Manifest;
use canopy_client::stream::{Camera, DrawnTree, StreamOptions, Streamer};
use clap::Args;

mod charts;
mod methods;
mod output;
use charts::{write_charts, write_detail_curve};
use indicatif::{ProgressBar, ProgressStyle};
use methods::{
    FULL_DETAIL_METHODS, METHODS, all_geometry, detail_scales, draws_all, ladder_variants, sample_frames, scaled_method,
};
use output::{Resolution, band_means, print_tables, write_html_report};
use serde::Serialize;

use crate::cli::{
    LinkArgs, SceneArgs, SceneLocation, ViewArgs, fetch_manifest, http_options, locate, resolve_flight_table,
    stream_options,
};

/// Options of `canopy eval`.
#[derive(Args, Debug)]
pub struct EvalArgs {
    #[command(flatten)]
    pub scene: SceneArgs,
    #[command(flatten)]
    pub view: ViewArgs,
    #[command(flatten)]
    pub link: LinkArgs,
    /// Render and score every N-th frame (and the frame before it, for popping).
    #[arg(long, default_value_t = 30)]
    pub every: u32,
    /// Score at these times instead (seconds on the run's clock, comma-separated; each at the
    /// frame nearest to it, at least frame 1): dense where things change, sparse where they
    /// have settled.
    #[arg(long, value_delimiter = ',', value_name = "SECONDS")]
    pub sample_at: Vec<f64>,
    /// Enlarge the kept leaves of simplified nodes (seed 004, s = √(1/(1 − R)), capped at 2).
    #[arg(long)]
    pub enlarge: bool,
    /// Output folder for the CSV files, the JSON summary and the charts.
    #[arg(long, default_value = "eval-report")]
    pub out: PathBuf,
    /// Also write each method's rendered image at every sampled frame.
    #[arg(long)]
    pub save_images: bool,
    /// Print the JSON summary to stdout.
    #[arg(long)]
    pub json: bool,
    /// Folder for the image strips (method | full detail | FLIP error, one PNG per sampled frame
    /// and method of `--strip-methods`); default: `strips` in `--out`.
    #[arg(long, value_name = "DIR")]
    pub strips_dir: Option<PathBuf>,
    /// Methods whose image strips are written, comma-separated (none: `--strip-methods ''`).
    #[arg(long, value_delimiter = ',', default_value = "canopy")]
    pub strip_methods: Vec<String>,
    /// Also evaluate Canopy with seed 004's weights (`--lod-weights`) scaled by each of these
    /// factors in [0, 1], comma-separated: lower keeps more leaves (0: every leaf of a tree
    /// drawn as geometry). Each is one more method, `canopy-weights-xS`, with its own cache and
    /// its real bytes: together the points of a quality-against-bytes curve.
    #[arg(long, value_delimiter = ',', value_name = "S")]
    pub detail_scales: Vec<f32>,
    /// Also evaluate Canopy with each of these ladders (`--ladder`'s syntax), separated by `;`:
    /// `--ladders 'geometry:60,hemioct:0;geometry:150,hemioct:0'`. Each is one more method,
    /// `canopy-ladder-RUNGS` (rungs `NAME@PX` joined by `+`), with its own cache and real bytes;
    /// with any given, `ladder_sweep.svg` charts FLIP (whole image and mid band) against bytes.
    #[arg(long, value_delimiter = ';', value_name = "LADDER")]
    pub ladders: Vec<String>,
}

/// The previous frame: camera and the canopy, discrete, full-detail, clouds, whole-file (glb,
/// ctree), scaled-weights and reference draw lists.
type PrevFrame = (
    Camera,
    Vec<DrawnTree>,
    Vec<DrawnTree>,
    Vec<DrawnTree>,
    Vec<DrawnTree>,
    [Vec<DrawnTree>; 2],
    Vec<Vec<DrawnTree>>,
    Vec<DrawnTree>,
);
/// A method to score: name, previous and current draw lists, how to render, byte counter.
type Case<'a> = (&'a str, &'a [DrawnTree], &'a [DrawnTree], RenderMode, usize);

/// One scored sample.
#[derive(Debug, Clone, Serialize)]
struct Sample {
    method: String,
    frame: u32,
    /// The frame's time on the run's clock, seconds.
    time_s: f64,
    cumulative_bytes: u64,
    ssim: f64,
    precision: f64,
    recall: f64,
    popping: f64,
    triangles: u64,
    full_triangles: u64,
    /// Mean FLIP error (lower is better).
    flip: f64,
    /// Near, mid and far bands.
    bands: [BandScore; 3],
}

/// One sampled frame's check of the terrain's culling against the full-detail reference.
#[derive(Debug, Clone, Serialize)]
struct TerrainCheck {
    frame: u32,
    /// Trees in view the terrain hid (canopy's streamer).
    culled: usize,
    /// Of them, trees the reference shows on some pixel (0 when the culling is conservative).
    culled_seen: usize,
    /// Their pixels in the reference.
    culled_seen_pixels: usize,
}

/// Per-method totals.
#[derive(Debug, Clone, Serialize)]
struct MethodSummary {
    method: String,
    bytes: u64,
    mean_ssim: f64,
    min_ssim: f64,
    mean_precision: f64,
    mean_recall: f64,
    mean_popping: f64,
    mean_triangle_share: f64,
    /// Mean over samples of the mean FLIP error.
    mean_flip: f64,
    /// Per band (near, mid, far): mean SSIM, FLIP and pixel share over the samples where the
    /// band has pixels.
    bands: Vec<output::BandSummary>,
    /// Cumulative bytes at the first sample from which every later sample has SSIM ≥ 0.95.
    bytes_to_ssim_095: Option<u64>,
    /// This method's bytes over Canopy's (`bytes_to_ssim_095` when both reach it, else totals).
    bytes_ratio_to_canopy: f64,
    /// Time of the first sample from which every later sample has SSIM ≥ 0.90 (0.95), seconds
    /// on the run's clock: with `--link`, what a viewer on that link waits.
    time_to_ssim_090: Option<f64>,
    time_to_ssim_095: Option<f64>,
    /// Time of the first complete frame, seconds on the run's clock: a streamer's own report
    /// (every visible tree drawn, at least as a stand-in, as `fly` counts it); a file method's
    /// list holding every tree the reference draws, once the reference has opened every tile
    /// and model in view.
    time_to_complete: Option<f64>,
    /// Time of the first sample from which every later sample has SSIM ≥ the run's quality
    /// target (see the summary's `quality_target`).
    time_to_quality_target: Option<f64>,
}

/// Runs the evaluation.
pub async fn run(mut a: EvalArgs) -> Result<()> {
    // Bad arguments fail before the network is touched.
    a.detail_scales = detail_scales(&a.detail_scales)?;
    let ladders = ladder_variants(&a.ladders)?;
    a.strip_methods.retain(|m| !m.is_empty());
    for name in &a.strip_methods {
        let known = METHODS.contains(&name.as_str())
            || a.detail_scales.iter().any(|&s| &scaled_method(s) == name)
            || ladders.iter().any(|(n, _)| n == name);
        if !known {
            anyhow::bail!(
                "--strip-methods: no method {name:?} (methods: {}, canopy-weights-xS per --detail-scales \
                 and canopy-ladder-RUNGS per --ladders)",
                METHODS.join(", ")
            );
        }
    }
    let loc = locate(&a.scene)?;
    let mut opts = StreamOptions {
        lod_enabled: true,
        ..stream_options(&a.view)?
    };
    resolve_flight_table(&mut opts, &a.view, &loc, &a.scene).await?;
    match loc {
        SceneLocation::Http {
            api_origin,
            manifest_path,
            assets_origin,
        } => {
            let (m, _) = fetch_manifest(&api_origin, &manifest_path, &a.scene).await?;
            let mk = || Ok(HttpSource::new(&assets_origin, http_options(&a.scene))?);
            Box::pin(evaluate(&mk, Arc::new(mk()?), m, &a, opts)).await
        }
        SceneLocation::Files { root, manifest_path } => {
            let src = FileSource::new(&root);
            let m = Manifest::parse(&src.get(&manifest_path).await?).context("reading the manifest")?;
            let mk = || Ok(FileSource::new(&root));
            Box::pin(evaluate(&mk, Arc::new(mk()?), m, &a, opts)).await
        }
    }
}

pub(crate) async fn load_models<S: RangeSource>(
    src: &S,
    m: &Manifest,
    scene: &mut EvalScene,
    trees: &[DrawnTree],
) -> Result<()> {
    for t in trees {
        let k = usize::from(t.instance.model);
        if !scene.has(k)
            && let Some(mm) = m.models.get(k)
        {
            let bytes = src
                .get(&mm.url)
                .await
                .with_context(|| format!("fetching {} for the reference", mm.url))?;
            scene.load(k, &mm.name, &bytes)?;
        }
    }
    Ok(())
}

/// The views at `t − 1` and `t`, with the tree seen at each pixel at `t`.
fn render_pair(
    scene: &mut EvalScene,
    lists: (&[DrawnTree], &[DrawnTree]),
    mode: RenderMode,
    cams: (&Camera, &Camera),
    opts: &StreamOptions,
) -> Result<(View, (View, Vec<u32>))> {
    let vp = &opts.viewport;
    let prev = render_view(scene, lists.0, mode, cams.0, vp, vp.width, vp.height)?;
    let now = render_view_with_trees(scene, lists.1, mode, cams.1, vp, vp.width, vp.height)?;
    Ok((prev, now))
}

#[allow(clippy::too_many_arguments)]
async fn evaluate<S: RangeSource>(
    mk: &impl Fn() -> Result<S>,
    ref_src: Arc<S>,
    m: Manifest,
    a: &EvalArgs,
    opts: StreamOptions,
) -> Result<()> {
    // Every streamer on its own link, all on one virtual clock.
    let linked = || -> Result<Arc<LinkedSource<S>>> { Ok(Arc::new(LinkedSource::new(mk()?, a.link.link.clone()))) };
    // Checked in `run`.
    let scales = &a.detail_scales;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    // Variants of Canopy, each its own method: scaled weights, then other ladders.
    let mut variants: Vec<(String, StreamOptions)> = Vec::new();
    for &sc in scales {
        let mut o = opts.clone();
        o.lod.weights = o.lod.weights.map(|w| w * sc);
        variants.push((scaled_method(sc), o));
    }
    for (name, ladder) in ladder_variants(&a.ladders)? {
        variants.push((name, StreamOptions { ladder, ..opts.clone() }));
    }
    let methods: Vec<String> = METHODS
        .iter()
        .map(ToString::to_string)
        .chain(variants.iter().map(|(n, _)| n.clone()))
        .collect();
    let mut scaled: Vec<Streamer<LinkedSource<S>>> = Vec::new();
    for (_, o) in variants {
        scaled.push(Streamer::with_manifest(linked()?, m.clone(), o));
    }
    let full_opts = StreamOptions {
        lod_enabled: false,
        ..opts.clone()
    };
    let clouds_opts = StreamOptions {
        ladder: with_clouds(&opts.ladder),
        ..opts.clone()
    };
    let mut canopy = Streamer::with_manifest(linked()?, m.clone(), opts.clone());
    let mut clouds = Streamer::with_manifest(linked()?, m.clone(), clouds_opts);
    let mut full = Streamer::with_manifest(linked()?, m.clone(), full_opts.clone());
    // The reference: full detail as it looks with every byte here. On an instant link that is
    // the full-detail method itself; on a modelled one a second full-detail stream on no link.
    let mut reference = if a.link.link.is_instant() {
        None
    } else {
        Some(Streamer::with_manifest(
            Arc::new(LinkedSource::new(mk()?, LinkModel::loopback())),
            m.clone(),
            full_opts,
        ))
    };
    // Where the ladder stops drawing geometry (iteration rungs included).
    let geometry_px = opts
        .ladder
        .iter()
        .rfind(|s| s.rep.is_geometry())
        .map_or(150.0, |s| s.min_projected_px);
    let mut discrete = DiscreteFiles::new(linked()?, &m, geometry_px);
    let mut whole = [
        DiscreteFiles::whole(linked()?, &m, WholeFile::Glb),
        DiscreteFiles::whole(linked()?, &m, WholeFile::Ctree),
    ];
    let without_levels = discrete.models_without_levels();
    if without_levels > 0 {
        eprintln!(
            "note: {without_levels} of the scene's {} models have no discrete LOD files in its manifest \
             (a version published before the server wrote them): the discrete and whole-glb methods draw none of \
             their trees",
            m.models.len()
        );
    }
    let mut scene = EvalScene::new(m.models.len());
    let ground = crate::cli::path_ground(ref_src.as_ref(), &m).await?;
    scene.set_terrain(ground.as_ref());
    let bounds = m.bounds.as_f32();
    let every = a.every.max(1);
    let sample_frames = sample_frames(&a.sample_at, a.view.frame_time)?;
    let is_sample = |f: u32| {
        if sample_frames.is_empty() {
            f.is_multiple_of(every)
        } else {
            sample_frames.contains(&f)
        }
    };
    let frames = a.view.frames.max(2);
    let resolution = Resolution::new(opts.viewport.width, opts.viewport.height);
    let strips_dir = a.strips_dir.clone().unwrap_or_else(|| a.out.join("strips"));
    let mut strips: Vec<(String, PathBuf)> = Vec::new();

    let bar = ProgressBar::new(u64::from(frames));
    bar.set_style(
        ProgressStyle::with_template("{spinner} eval {pos}/{len} frames [{bar:30}] {msg} ({eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let t0 = Instant::now();
    let mut cum = vec![0u64; methods.len()];
    let mut per_frame = std::iter::once("frame".to_string())
        .chain(methods.iter().map(|n| format!("{}_bytes", n.replace('-', "_"))))
        .collect::<Vec<_>>()
        .join(",");
    per_frame.push('\n');
    let mut samples: Vec<Sample> = Vec::new();
    let mut prev: Option<PrevFrame> = None;
    // The whole-file baseline: every model a full-detail frame draws, its file downloaded whole
    // (what a glTF viewer fetches before it draws the tree at all).
    let mut whole_models = std::collections::BTreeSet::new();
    let mut terrain_checks: Vec<TerrainCheck> = Vec::new();
    let mut complete_at: Vec<Option<f64>> = vec![None; methods.len()];
    // Whether Canopy's last frame had nothing to fetch, at its configured detail.
    let mut canopy_idle = false;
    for f in 0..frames {
        let cam = a.view.camera(bounds, f, ground.as_ref());
        let dt = a.view.frame_time as f32;
        // Each link moves to the next frame's time: what arrives by then is drawn next.
        let t_next = f64::from(f + 1) * a.view.frame_time;
        let rc = canopy.frame_until(&cam, dt, t_next).await;
        canopy_idle = rc.is_idle();
        let rf = full.frame_until(&cam, dt, t_next).await;
        let rl = clouds.frame_until(&cam, dt, t_next).await;
        // Whether the reference drew every visible tree, with no tile or model still opening.
        let reference_complete = match reference.as_mut() {
            Some(r) => r.frame_until(&cam, dt, t_next).await.complete,
            None => rf.complete,
        };
        let mut rs = Vec::with_capacity(scaled.len());
        let mut rs_complete = Vec::with_capacity(scaled.len());
        for st in &mut scaled {
            let r = st.frame_until(&cam, dt, t_next).await;
            rs.push(r.bytes);
            rs_complete.push(r.complete);
        }
        // Discrete LOD needs the models' contents to size its files: load them for the reference.
        load_models(ref_src.as_ref(), &m, &mut scene, full.drawn()).await?;
        if let Some(r) = &reference {
            load_models(ref_src.as_ref(), &m, &mut scene, r.drawn()).await?;
        }
        load_models(ref_src.as_ref(), &m, &mut scene, canopy.drawn()).await?;
        load_models(ref_src.as_ref(), &m, &mut scene, clouds.drawn()).await?;
        for st in &scaled {
            load_models(ref_src.as_ref(), &m, &mut scene, st.drawn()).await?;
        }
        let before = discrete.bytes;
        let d_list = discrete.update(&scene, full.drawn(), &cam, &opts.viewport);
        discrete.source().advance_to(t_next).await;
        discrete.receive();
        let mut w_lists: [Vec<DrawnTree>; 2] = Default::default();
        let mut w_bytes = [0u64; 2];
        for ((w, list), b) in whole.iter_mut().zip(&mut w_lists).zip(&mut w_bytes) {
            let before = w.bytes;
            // The reference's list: every visible tree at full detail, with no tile or opening
            // of its own to wait for (which favours the baseline).
            let trees = reference.as_ref().map_or(full.drawn(), |r| r.drawn());
            *list = w.update(&scene, trees, &cam, &opts.viewport);
            w.source().advance_to(t_next).await;
            w.receive();
            *b = w.bytes - before;
        }
        let frame_bytes: Vec<u64> = [
            rc.bytes,
            rc.bytes,
            discrete.bytes - before,
            rf.bytes,
            rl.bytes,
            w_bytes[0],
            w_bytes[1],
        ]
        .into_iter()
        .chain(rs)
        .collect();
        for (c, b) in cum.iter_mut().zip(&frame_bytes) {
            *c += b;
        }
        let _ = write!(per_frame, "{f}");
        for b in &frame_bytes {
            let _ = write!(per_frame, ",{b}");
        }
        per_frame.push('\n');
        whole_models.extend(full.drawn().iter().map(|t| usize::from(t.instance.model)));
        let c_list = canopy.drawn().to_vec();
        let f_list = full.drawn().to_vec();
        let r_list = reference
            .as_ref()
            .map_or_else(|| f_list.clone(), |r| r.drawn().to_vec());
        let l_list = clouds.drawn().to_vec();
        let s_lists: Vec<Vec<DrawnTree>> = scaled.iter().map(|st| st.drawn().to_vec()).collect();
        // A streamer's own report says whether it drew every visible tree (as `fly` counts it);
        // the file methods (discrete and whole files) are held to the reference's trees.
        let mut complete: Vec<bool> = [rc.complete, rc.complete, false, rf.complete, rl.complete, false, false]
            .into_iter()
            .chain(rs_complete)
            .collect();
        // The file methods against the reference's trees, until each has been complete once.
        let file_lists: [(usize, &[DrawnTree]); 3] = [(2, &d_list), (5, &w_lists[0]), (6, &w_lists[1])];
        if reference_complete && file_lists.iter().any(|(k, _)| complete_at[*k].is_none()) {
            let wanted: std::collections::HashSet<u32> = r_list.iter().map(|t| t.instance.id).collect();
            for (k, list) in file_lists {
                complete[k] = complete_at[k].is_none() && !wanted.is_empty() && draws_all(list, &wanted);
            }
        }
        for (at, done) in complete_at.iter_mut().zip(complete) {
            if at.is_none() && done {
                *at = Some(f64::from(f) * a.view.frame_time);
            }
        }
        if is_sample(f)
            && f > 0
            && let Some((pcam, pc, pd, pf, pl, pw, ps, pr)) = &prev
        {
            let (ref_prev, (ref_now, ref_trees)) =
                render_pair(&mut scene, (pr, &r_list), RenderMode::Full, (pcam, &cam), &opts)?;
            let full_tris = ref_now.triangles;
            // The terrain's culling is conservative: no tree it hid shows in the reference.
            if canopy.terrain().is_some() {
                let culled: std::collections::HashSet<u32> = canopy.terrain_culled_ids().iter().copied().collect();
                let seen: std::collections::HashSet<u32> =
                    ref_trees.iter().copied().filter(|id| culled.contains(id)).collect();
                terrain_checks.push(TerrainCheck {
                    frame: f,
                    culled: culled.len(),
                    culled_seen: seen.len(),
                    culled_seen_pixels: ref_trees.iter().filter(|id| culled.contains(id)).count(),
                });
            }
            let vp = &opts.viewport;
            let band_lists: Vec<&[DrawnTree]> = [&r_list, &c_list, &d_list, &l_list]
                .into_iter()
                .map(Vec::as_slice)
                .chain(s_lists.iter().map(Vec::as_slice))
                .collect();
            let bands = BandMap::new(&scene, &band_lists, &cam, vp, vp.height);
            let as_drawn = RenderMode::AsDrawn {
                choice: LeafChoice::Prefix,
                enlarge: a.enlarge,
            };
            let mut cases: Vec<Case<'_>> = vec![
                (
                    METHODS[0],
                    pc,
                    &c_list,
                    RenderMode::AsDrawn {
                        choice: LeafChoice::Prefix,
                        enlarge: a.enlarge,
                    },
                    0,
                ),
                (
                    METHODS[1],
                    pc,
                    &c_list,
                    RenderMode::AsDrawn {
                        choice: LeafChoice::Random,
                        enlarge: a.enlarge,
                    },
                    1,
                ),
                (
                    METHODS[2],
                    pd,
                    &d_list,
                    RenderMode::AsDrawn {
                        choice: LeafChoice::Prefix,
                        enlarge: false,
                    },
                    2,
                ),
                (
                    METHODS[3],
                    pf,
                    &f_list,
                    RenderMode::AsDrawn {
                        choice: LeafChoice::Prefix,
                        enlarge: false,
                    },
                    3,
                ),
                (METHODS[4], pl, &l_list, as_drawn, 4),
            ];
            let full_mode = RenderMode::AsDrawn {
                choice: LeafChoice::Prefix,
                enlarge: false,
            };
            for (k, (lp, ln)) in pw.iter().zip(&w_lists).enumerate() {
                cases.push((METHODS[5 + k], lp, ln, full_mode, 5 + k));
            }
            for (k, (lp, ln)) in ps.iter().zip(&s_lists).enumerate() {
                cases.push((&methods[METHODS.len() + k], lp, ln, as_drawn, METHODS.len() + k));
            }
            for (name, lp, ln, mode, k) in cases {
                // A full-detail method drawing the reference's own lists (full detail on an instant
                // link, a whole-file method once every file is in) is not rendered twice.
                let rendered;
                let (vp_prev, (vp_now, vp_trees)) = if FULL_DETAIL_METHODS.contains(&name)
                    && lp == pr.as_slice()
                    && ln == r_list
                    && all_geometry(lp)
                    && all_geometry(ln)
                {
                    (&ref_prev, (&ref_now, &ref_trees))
                } else {
                    rendered = render_pair(&mut scene, (lp, ln), mode, (pcam, &cam), &opts)?;
                    (&rendered.0, (&rendered.1.0, &rendered.1.1))
                };
                let (q, flip_map) = perceptual(&ref_now, &ref_trees, vp_now, vp_trees, &bands)?;
                let pop = popping(&ref_prev, &ref_now, vp_prev, vp_now);
                if a.strip_methods.iter().any(|s| s == name) {
                    let p = strips_dir.join(format!("frame{f:05}-{name}.png"));
                    canopy_client::eval::strip::write_strip(&p, vp_now, &ref_now, &flip_map)?;
                    strips.push((format!("frame {f}: {name} | full detail | FLIP error"), p));
                }
                if a.save_images {
                    let p = a.out.join(format!("frame{f:05}-{name}.png"));
                    canopy_shared::metrics::write_png(&p, vp_now.width, vp_now.height, &vp_now.color)?;
                }
                samples.push(Sample {
                    method: name.to_string(),
                    frame: f,
                    time_s: f64::from(f) * a.view.frame_time,
                    cumulative_bytes: cum[k],
                    ssim: q.quality.ssim,
                    precision: q.quality.precision,
                    recall: q.quality.recall,
                    popping: pop,
                    triangles: vp_now.triangles,
                    full_triangles: full_tris,
                    flip: q.flip,
                    bands: q.bands,
                });
            }
            if a.save_images {
                let p = a.out.join(format!("frame{f:05}-reference.png"));
                canopy_shared::metrics::write_png(&p, ref_now.width, ref_now.height, &ref_now.color)?;
            }
            if let Some(s) = samples.iter().rev().find(|s| s.method == "canopy") {
                bar.set_message(format!("canopy SSIM {:.3}", s.ssim));
            }
        }
        prev = Some((cam, c_list, d_list, f_list, l_list, w_lists, s_lists, r_list));
        bar.inc(1);
    }
    bar.finish_and_clear();

    // Summaries.
    let first_good = |name: &str, q: f64| -> Option<&Sample> {
        let s: Vec<&Sample> = samples.iter().filter(|s| s.method == name).collect();
        let i = (0..s.len()).find(|&i| s[i..].iter().all(|x| x.ssim >= q))?;
        Some(s[i])
    };
    let reach = |name: &str| first_good(name, 0.95).map(|s| s.cumulative_bytes);
    // Issue 20's Q: 0.01 under the lower of Canopy's and the discrete files' last SSIM (their
    // settled SSIM when the run lasts until both have settled; `settled` says whether they did).
    let last_ssim = |name: &str| samples.iter().rfind(|s| s.method == name).map(|s| s.ssim);
    let quality_target = match (last_ssim(METHODS[0]), last_ssim(METHODS[2])) {
        (Some(c), Some(d)) => Some(c.min(d) - 0.01),
        _ => None,
    };
    let canopy_reach = reach("canopy");
    let summaries: Vec<MethodSummary> = methods
        .iter()
        .enumerate()
        .map(|(k, name)| {
            let s: Vec<&Sample> = samples.iter().filter(|s| &s.method == name).collect();
            let n = s.len().max(1) as f64;
            let mean = |g: &dyn Fn(&Sample) -> f64| s.iter().map(|x| g(x)).sum::<f64>() / n;
            let r = reach(name);
            let ratio = match (r, canopy_reach) {
                (Some(x), Some(c)) if c > 0 => x as f64 / c as f64,
                _ => cum[k] as f64 / cum[0].max(1) as f64,
            };
            MethodSummary {
                method: name.clone(),
                bytes: cum[k],
                mean_ssim: mean(&|x| x.ssim),
                min_ssim: s.iter().map(|x| x.ssim).fold(f64::INFINITY, f64::min),
                mean_precision: mean(&|x| x.precision),
                mean_recall: mean(&|x| x.recall),
                mean_popping: mean(&|x| x.popping),
                mean_triangle_share: mean(&|x| x.triangles as f64 / x.full_triangles.max(1) as f64),
                mean_flip: mean(&|x| x.flip),
                bands: band_means(&s.iter().map(|x| &x.bands).collect::<Vec<_>>()),
                bytes_to_ssim_095: r,
                bytes_ratio_to_canopy: ratio,
                time_to_ssim_090: first_good(name, 0.90).map(|s| s.time_s),
                time_to_ssim_095: first_good(name, 0.95).map(|s| s.time_s),
                time_to_complete: complete_at[k],
                time_to_quality_target: quality_target.and_then(|q| first_good(name, q)).map(|s| s.time_s),
            }
        })
        .collect();

    // Files.
    std::fs::write(a.out.join("frames.csv"), per_frame)?;
    let mut csv = String::from(
        "method,frame,time_s,cumulative_bytes,ssim,precision,recall,popping,triangles,full_triangles,flip,\
         near_share,near_ssim,near_flip,mid_share,mid_ssim,mid_flip,far_share,far_ssim,far_flip\n",
    );
    for s in &samples {
        let _ = write!(
            csv,
            "{},{},{:.4},{},{:.5},{:.5},{:.5},{:.6},{},{},{:.5}",
            s.method,
            s.frame,
            s.time_s,
            s.cumulative_bytes,
            s.ssim,
            s.precision,
            s.recall,
            s.popping,
            s.triangles,
            s.full_triangles,
            s.flip
        );
        let opt = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.5}"));
        for b in &s.bands {
            let _ = write!(csv, ",{:.5},{},{}", b.pixel_share, opt(b.ssim), opt(b.flip));
        }
        csv.push('\n');
    }
    std::fs::write(a.out.join("samples.csv"), csv)?;
    let mut charts = write_charts(&a.out, &methods, &samples, &a.out.join("frames.csv"))?;
    if !scales.is_empty() {
        charts.extend(write_detail_curve(&a.out, scales, &summaries)?);
    }
    if !a.ladders.is_empty() {
        charts.extend(output::write_ladder_sweep(&a.out, &summaries)?);
    }
    let whole_file_bytes: u64 = whole_models
        .iter()
        .filter_map(|&k| m.models.get(k))
        .map(|x| x.size)
        .sum();
    // The same models as a glTF viewer gets them: each one's finest level file (a quantized,
    // meshopt-compressed .glb) whole.
    let whole_glb_bytes: Option<u64> = whole_models
        .iter()
        .filter_map(|&k| m.models.get(k))
        .map(|x| x.levels.first().map(|l| l.size))
        .sum();
    let sampled = samples.len() / methods.len().max(1);
    let report = write_html_report(
        &a.out,
        &format!("{} v{}: {:?}, {frames} frames", m.scene, m.version, a.view.path),
        &resolution,
        sampled,
        quality_target,
        &summaries,
        &charts,
        &strips,
    )?;
    let summary = serde_json::json!({
        "whole_file_bytes": whole_file_bytes, "whole_file_models": whole_models.len(),
        "whole_glb_bytes": whole_glb_bytes,
        "discrete_files": { "requests": discrete.requests, "failures": discrete.failures,
            "pending_at_end": discrete.pending(), "models_without_levels": without_levels },
        "whole_files": whole.iter().zip(["glb", "ctree"]).map(|(w, kind)| serde_json::json!({
            "file": kind, "requests": w.requests, "failures": w.failures, "pending_at_end": w.pending(),
        })).collect::<Vec<_>>(),
        "quality_target": quality_target,
        "settled": { "canopy": canopy_idle, "discrete": discrete.pending() == 0,
            "whole_glb": whole[0].pending() == 0, "whole_ctree": whole[1].pending() == 0 },
        "scene": m.scene, "version": m.version, "path": a.view.path, "frames": frames, "every": every,
        "viewport": opts.viewport, "enlarge": a.enlarge, "detail_scales": scales,
        "resolution": resolution,
        "band_edges_px": [canopy_client::eval::MID_MIN_PX, canopy_client::eval::NEAR_MIN_PX],
        "seconds": t0.elapsed().as_secs_f64(),
        "methods": summaries, "samples": samples,
        "terrain_culling": (!terrain_checks.is_empty()).then(|| serde_json::json!({
            "frames_checked": terrain_checks.len(),
            "mean_culled": terrain_checks.iter().map(|c| c.culled as f64).sum::<f64>() / terrain_checks.len() as f64,
            "culled_seen_in_reference": terrain_checks.iter().map(|c| c.culled_seen).sum::<usize>(),
            "culled_seen_pixels": terrain_checks.iter().map(|c| c.culled_seen_pixels).sum::<usize>(),
            "per_frame": terrain_checks,
        })),
        "charts": charts.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
        "strips": strips.iter().map(|(_, p)| p.display().to_string()).collect::<Vec<_>>(),
        "strips_dir": strips_dir.display().to_string(),
        "report": report.display().to_string(),
    });
    std::fs::write(a.out.join("summary.json"), serde_json::to_string_pretty(&summary)?)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        println!(
            "{} v{}: {frames} frames of {:?}, {sampled} samples, {:.0} s",
            m.scene,
            m.version,
            a.view.path,
            t0.elapsed().as_secs_f64()
        );
        println!("{}", resolution.note);
        if sampled < output::CURVE_SAMPLES {
            println!(
                "{sampled} sampled frames per method: fewer than {} make the charts points, not curves",
                output::CURVE_SAMPLES
            );
        }
        print_tables(&summaries);
        println!(
            "every drawn model's file whole: {whole_file_bytes} B as .ctree{} ({} models)",
            whole_glb_bytes.map_or(String::new(), |g| format!(", {g} B as meshopt .glb")),
            whole_models.len()
        );
        println!("wrote {} (CSV, summary.json, charts)", a.out.display());
        for c in &charts {
            println!("  {}", c.display());
        }
        println!("image strips ({}): {}", strips.len(), strips_dir.display());
        println!("report: {}", report.display());
    }
    Ok(())
}
