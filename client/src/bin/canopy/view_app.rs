//! The egui viewer window: streaming on a background thread, rendering with wgpu each UI frame.
//!
//! Threads: the stream thread owns a tokio runtime and runs the streamer's frame loop for the
//! LOD camera; the UI thread renders the last prepared plan from the current camera every frame
//! and uploads from the streamer's cache when a new stream frame is ready (`try_lock`, so the UI
//! never waits for the network). A presence thread keeps the scene's WebSocket: it sends this
//! viewer's pose and collects the others'.

use std::collections::{HashMap, VecDeque};
use std::sync::mpsc::{Receiver, Sender, channel};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Result, anyhow};
use canopy_client::lod::Representation;
use canopy_client::lod::projection::{CLOUD_LADDER_SPEC, DEFAULT_LADDER_SPEC, HULL_LADDER_SPEC, parse_ladder};
use canopy_client::net::RangeSource;
use canopy_client::paths::{PathKind, camera_at, camera_over};
use canopy_client::scene::Manifest;
use canopy_client::stream::{Camera, FrameReport, StreamOptions, Streamer};
use canopy_client::view::gpu::{Renderer, Target, supports_ui_view};
use canopy_client::view::upload::{DrawStats, FramePlan, GpuScene, LOD_COLORS, ViewOptions, frame_camera};
use canopy_shared::terrain::Heightfield;
use eframe::egui;
use glam::Vec3;

use crate::view_cmd::{ViewCmdArgs, start_camera};

mod presence;
use presence::{POSE_INTERVAL, Presence, spawn_presence};

/// Samples kept for the live plots (about 20 s at 30 stream frames a second).
const PLOT_HISTORY: usize = 600;
/// Fly speed, metres per second (shift: ×5).
const FLY_SPEED: f32 = 20.0;
/// Mouse look, radians per point dragged.
const LOOK_RATE: f32 = 0.004;
/// A window capture waits at most this long past its time for streaming to settle, seconds.
const CAPTURE_SETTLE_S: f64 = 60.0;

struct Shared {
    lod_camera: Camera,
    opts: StreamOptions,
    opts_changed: bool,
    quit: bool,
}

pub fn open<S: RangeSource + 'static>(
    src: Arc<S>,
    m: Manifest,
    opts: StreamOptions,
    a: &ViewCmdArgs,
    api_origin: Option<String>,
    ground: Option<Heightfield>,
) -> Result<()> {
    let cam = start_camera(a, &m)?;
    let source = Arc::clone(&src);
    let streamer = Arc::new(Mutex::new(Streamer::with_manifest(src, m.clone(), opts.clone())));
    let shared = Arc::new(Mutex::new(Shared {
        lod_camera: cam,
        opts: opts.clone(),
        opts_changed: false,
        quit: false,
    }));
    let (tx, rx) = channel::<FrameReport>();
    let presence: Presence = Arc::new(Mutex::new(HashMap::new()));
    let (pose_tx, pose_rx) = channel::<Camera>();
    let live_url = api_origin.map(|o| format!("{}/api/scenes/{}/live", o.replace("http://", "ws://"), m.scene));
    let native = eframe::NativeOptions {
        renderer: eframe::Renderer::Wgpu,
        viewport: egui::ViewportBuilder::default()
            .with_inner_size([1280.0, 800.0])
            .with_title(format!("Canopy: {}", m.scene)),
        ..eframe::NativeOptions::default()
    };
    let view_opts = ViewOptions {
        enlarge: a.enlarge,
        color_by_lod: a.color_by_lod,
        ground: !a.no_ground,
    };
    let path = a.view.path;
    let capture = match (a.capture_after, a.capture.clone()) {
        (Some(t), Some(p)) => Some(Capture {
            after_s: t.max(0.0),
            path: p,
            requested: false,
            done: Arc::new(Mutex::new(None)),
        }),
        _ => None,
    };
    eframe::run_native(
        "canopy",
        native,
        Box::new(move |cc| {
            let rs = cc
                .wgpu_render_state
                .clone()
                .ok_or_else(|| anyhow!("eframe started without wgpu"))?;
            if !supports_ui_view(&rs.adapter) {
                let info = rs.adapter.get_info();
                return Err(anyhow!(
                    "the GPU adapter {} ({:?}) cannot show the view in a window (no VIEW_FORMATS); \
                     `canopy view --screenshot` renders without it",
                    info.name,
                    info.backend
                )
                .into());
            }
            spawn_stream(Arc::clone(&streamer), Arc::clone(&shared), tx, cc.egui_ctx.clone());
            if let Some(url) = live_url {
                spawn_presence(url, Arc::clone(&presence), pose_rx);
            }
            let renderer = Renderer::new(&rs.device, &rs.queue);
            let gpu = GpuScene::new(&rs.device, m.models.len());
            let info = rs.adapter.get_info();
            Ok(Box::new(ViewerApp {
                rs,
                renderer,
                gpu,
                target: None,
                texture: None,
                plan: FramePlan::default(),
                draw_stats: DrawStats::default(),
                streamer,
                shared,
                reports: rx,
                history: VecDeque::new(),
                last_report: None,
                cam,
                orbit: false,
                orbit_target: Vec3::new(cam.eye.x, 0.0, cam.eye.z - 100.0),
                freeze: false,
                play: None,
                path,
                bounds: m.bounds.as_f32(),
                view_opts,
                flight_policy: opts
                    .flight
                    .clone()
                    .unwrap_or_else(canopy_client::lod::FlightParams::standard),
                opts,
                presence,
                pose_tx,
                last_pose: Instant::now(),
                frame_ms: 0.0,
                adapter: format!("{} ({:?})", info.name, info.backend),
                prepared_frames: 0,
                reports_received: 0,
                source,
                capture,
                recording: None,
                recorded: Vec::new(),
                replay: None,
                ground,
            }))
        }),
    )
    .map_err(|e| anyhow!("viewer: {e}"))
}

#[allow(clippy::await_holding_lock)] // The UI only ever try_locks; nothing else waits on it.
fn spawn_stream<S: RangeSource + 'static>(
    streamer: Arc<Mutex<Streamer<S>>>,
    shared: Arc<Mutex<Shared>>,
    tx: Sender<FrameReport>,
    ctx: egui::Context,
) {
    std::thread::spawn(move || {
        // Worker threads: the stream's transfers run there while this thread plans frames.
        let Ok(rt) = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
        else {
            return;
        };
        // Frames spawn their transfers on this runtime.
        let _runtime = rt.enter();
        let mut last = Instant::now();
        loop {
            let (cam, opts) = {
                let Ok(mut sh) = shared.lock() else { return };
                if sh.quit {
                    return;
                }
                let opts = sh.opts_changed.then(|| sh.opts.clone());
                sh.opts_changed = false;
                (sh.lod_camera, opts)
            };
            let dt = last.elapsed().as_secs_f32().min(0.5);
            last = Instant::now();
            let report = {
                let Ok(mut s) = streamer.lock() else { return };
                if let Some(o) = opts {
                    s.set_options(o);
                }
                s.frame(&cam, dt)
            };
            let idle = report.is_idle();
            if tx.send(report).is_err() {
                return;
            }
            ctx.request_repaint();
            // Frames never wait for the network: plan about 60 times a second while bytes are
            // coming, 30 when nothing is.
            std::thread::sleep(if idle {
                Duration::from_millis(30)
            } else {
                Duration::from_millis(16)
            });
        }
    });
}

/// A window capture: when, where, and the result once written.
struct Capture {
    after_s: f64,
    path: std::path::PathBuf,
    requested: bool,
    done: Arc<Mutex<Option<Result<(), String>>>>,
}

struct ViewerApp<S: RangeSource> {
    rs: eframe::egui_wgpu::RenderState,
    renderer: Renderer,
    gpu: GpuScene,
    target: Option<Target>,
    texture: Option<egui::TextureId>,
    plan: FramePlan,
    draw_stats: DrawStats,
    streamer: Arc<Mutex<Streamer<S>>>,
    shared: Arc<Mutex<Shared>>,
    reports: Receiver<FrameReport>,
    history: VecDeque<(f64, FrameReport)>,
    last_report: Option<FrameReport>,
    cam: Camera,
    orbit: bool,
    orbit_target: Vec3,
    freeze: bool,
    play: Option<f32>,
    path: PathKind,
    bounds: [f32; 4],
    view_opts: ViewOptions,
    opts: StreamOptions,
    /// Seed 002's policy as the checkbox turns it on (with the scene's table, if it had one).
    flight_policy: canopy_client::lod::FlightParams,
    presence: Presence,
    pose_tx: Sender<Camera>,
    last_pose: Instant,
    frame_ms: f64,
    adapter: String,
    prepared_frames: u64,
    /// Stream frames received so far (the history keeps only the last [`PLOT_HISTORY`]).
    reports_received: u64,
    /// The streamer's source, read without the streamer's lock (counters only).
    source: Arc<S>,
    capture: Option<Capture>,
    /// Camera samples recorded while flying (seconds since the start of the recording).
    recording: Option<Vec<(f32, Camera)>>,
    recorded: Vec<(f32, Camera)>,
    replay: Option<f32>,
    /// The scene's whole terrain, which a played path flies over.
    ground: Option<Heightfield>,
}

impl<S: RangeSource> Drop for ViewerApp<S> {
    fn drop(&mut self) {
        if let Ok(mut sh) = self.shared.lock() {
            sh.quit = true;
        }
    }
}

impl<S: RangeSource> ViewerApp<S> {
    fn controls(&mut self, ctx: &egui::Context, response: &egui::Response) {
        let dt = ctx.input(|i| i.stable_dt).min(0.1);
        if let Some(t) = self.replay.as_mut() {
            *t += dt;
            match self.recorded.iter().find(|(at, _)| *at >= *t) {
                Some((_, c)) => self.cam = *c,
                None => self.replay = None,
            }
            return;
        }
        if let Some(rec) = self.recording.as_mut() {
            let t = rec.last().map_or(0.0, |(at, _)| at + dt);
            rec.push((t, self.cam));
        }
        if let Some(t) = self.play.as_mut() {
            *t += dt;
            self.cam = match &self.ground {
                Some(g) => camera_over(self.path, self.bounds, *t, self.path.speed(), None, &|x, z| {
                    g.height_at(x, z)
                }),
                None => camera_at(self.path, self.bounds, *t),
            };
            return;
        }
        let drag = response.drag_delta();
        let (fwd, right) = {
            let f = self.cam.forward();
            (f, f.cross(Vec3::Y).normalize_or_zero())
        };
        if self.orbit {
            if drag != egui::Vec2::ZERO {
                let offset = self.cam.eye - self.orbit_target;
                let r = offset.length().max(1.0);
                let yaw = offset.x.atan2(offset.z) - drag.x * LOOK_RATE;
                let pitch = (offset.y / r).asin() + drag.y * LOOK_RATE;
                let pitch = pitch.clamp(-0.1, 1.5);
                self.cam.eye =
                    self.orbit_target + r * Vec3::new(yaw.sin() * pitch.cos(), pitch.sin(), yaw.cos() * pitch.cos());
            }
            let scroll = ctx.input(|i| i.smooth_scroll_delta.y);
            if scroll != 0.0 {
                let d = self.cam.eye - self.orbit_target;
                self.cam.eye = self.orbit_target + d * (1.0 - scroll * 0.002).clamp(0.5, 2.0);
            }
            let d = (self.orbit_target - self.cam.eye).normalize_or_zero();
            self.cam.yaw = d.x.atan2(-d.z);
            self.cam.pitch = d.y.asin();
        } else {
            self.cam.yaw += drag.x * LOOK_RATE;
            self.cam.pitch = (self.cam.pitch - drag.y * LOOK_RATE).clamp(-1.55, 1.55);
        }
        if !ctx.egui_wants_keyboard_input() {
            let speed = FLY_SPEED * if ctx.input(|i| i.modifiers.shift) { 5.0 } else { 1.0 } * dt;
            let mut mv = Vec3::ZERO;
            ctx.input(|i| {
                if i.key_down(egui::Key::W) {
                    mv += fwd;
                }
                if i.key_down(egui::Key::S) {
                    mv -= fwd;
                }
                if i.key_down(egui::Key::D) {
                    mv += right;
                }
                if i.key_down(egui::Key::A) {
                    mv -= right;
                }
                if i.key_down(egui::Key::E) {
                    mv += Vec3::Y;
                }
                if i.key_down(egui::Key::Q) {
                    mv -= Vec3::Y;
                }
            });
            self.cam.eye += mv * speed;
            if self.orbit {
                self.orbit_target += mv * speed;
            }
        }
    }

    fn side_panel(&mut self, ui: &mut egui::Ui) {
        let mut changed = false;
        ui.heading("Camera");
        ui.horizontal(|ui| {
            ui.selectable_value(&mut self.orbit, false, "fly");
            ui.selectable_value(&mut self.orbit, true, "orbit");
        });
        ui.horizontal(|ui| {
            egui::ComboBox::from_id_salt("path")
                .selected_text(format!("{:?}", self.path))
                .show_ui(ui, |ui| {
                    for p in [
                        PathKind::Orbit,
                        PathKind::Flyover,
                        PathKind::Walk,
                        PathKind::Lowflight,
                        PathKind::Turns,
                    ] {
                        ui.selectable_value(&mut self.path, p, format!("{p:?}"));
                    }
                });
            let playing = self.play.is_some();
            if ui.button(if playing { "stop path" } else { "play path" }).clicked() {
                self.play = if playing { None } else { Some(0.0) };
            }
        });
        ui.horizontal(|ui| {
            let rec = self.recording.is_some();
            if ui.button(if rec { "stop recording" } else { "record" }).clicked() {
                if let Some(r) = self.recording.take() {
                    self.recorded = r;
                } else {
                    self.recording = Some(Vec::new());
                }
            }
            let can = !self.recorded.is_empty() && !rec;
            if ui
                .add_enabled(
                    can,
                    egui::Button::new(format!("replay ({} samples)", self.recorded.len())),
                )
                .clicked()
            {
                self.replay = Some(0.0);
            }
        });
        ui.checkbox(&mut self.freeze, "freeze LOD camera (inspect culling)");
        ui.label(format!(
            "eye {:.0} {:.0} {:.0}, yaw {:.0}°, pitch {:.0}°",
            self.cam.eye.x,
            self.cam.eye.y,
            self.cam.eye.z,
            self.cam.yaw.to_degrees(),
            self.cam.pitch.to_degrees()
        ));
        ui.label("WASD move, Q/E down/up, shift ×5, drag to look (orbit: drag rotates, wheel zooms)");
        ui.separator();
        ui.heading("LOD");
        // The label on its own line, so the extra button does not widen the panel.
        ui.label("seed 000 ladder ε (projected px):");
        ui.horizontal(|ui| {
            for (name, spec) in [
                ("default", DEFAULT_LADDER_SPEC),
                ("hulls", HULL_LADDER_SPEC),
                ("clouds", CLOUD_LADDER_SPEC),
            ] {
                if ui.button(name).clicked()
                    && let Ok(l) = parse_ladder(spec)
                {
                    self.opts.ladder = l;
                    changed = true;
                }
            }
        });
        for step in &mut self.opts.ladder {
            changed |= ui
                .add(egui::Slider::new(&mut step.min_projected_px, 0.0..=400.0).text(rep_name(step.rep)))
                .changed();
        }
        ui.label("seed 004 rates");
        changed |= ui
            .add(egui::Slider::new(&mut self.opts.lod.near, 0.0..=500.0).text("near m"))
            .changed();
        changed |= ui
            .add(egui::Slider::new(&mut self.opts.lod.far, 10.0..=5000.0).text("far m"))
            .changed();
        for (k, w) in self.opts.lod.weights.iter_mut().enumerate() {
            changed |= ui
                .add(egui::Slider::new(w, 0.0..=1.0).text(format!("α{}", k + 1)))
                .changed();
        }
        let mut flight = self.opts.flight.is_some();
        if ui.checkbox(&mut flight, "seed 002 low-flight policy").changed() {
            self.opts.flight = flight.then(|| self.flight_policy.clone());
            changed = true;
        }
        changed |= ui
            .checkbox(&mut self.opts.lod_enabled, "LOD on (off: full detail)")
            .changed();
        ui.checkbox(&mut self.view_opts.enlarge, "seed 004 leaf enlargement");
        ui.checkbox(&mut self.view_opts.color_by_lod, "colour by LOD");
        if self.view_opts.color_by_lod {
            ui.horizontal_wrapped(|ui| {
                for (name, c) in LOD_COLORS {
                    let rgb = egui::Rgba::from_rgb(c[0], c[1], c[2]);
                    ui.colored_label(egui::Color32::from(rgb), format!("■ {name}"));
                }
            });
        }
        ui.checkbox(&mut self.view_opts.ground, "ground");
        if changed {
            self.opts.lod.far = self.opts.lod.far.max(self.opts.lod.near + 1.0);
            if let Ok(mut sh) = self.shared.lock() {
                sh.opts = self.opts.clone();
                sh.opts_changed = true;
            }
        }
        ui.separator();
        ui.heading("Live");
        let secs = 2.0;
        let recent: Vec<&FrameReport> = self
            .history
            .iter()
            .rev()
            .take_while(|(t, _)| self.history.back().is_some_and(|(l, _)| l - t <= secs))
            .map(|(_, r)| r)
            .collect();
        let bytes_s = recent.iter().map(|r| r.bytes).sum::<u64>() as f64 / secs;
        let req_s = recent.iter().map(|r| r.requests).sum::<u64>() as f64 / secs;
        let cs = self.streamer.try_lock().ok().map(|s| s.cache_stats());
        let net = self.source.stats();
        ui.label(format!(
            "{:.2} MB/s, {:.1} requests/s, {} in flight (peak {})",
            bytes_s / 1e6,
            req_s,
            net.in_flight.load(std::sync::atomic::Ordering::Relaxed),
            net.peak_in_flight.load(std::sync::atomic::Ordering::Relaxed)
        ));
        if let Some(r) = &self.last_report {
            ui.label(format!(
                "cache {:.1} MB, visible {}, geometry {} / hull {} / cloud {} / billboard {}",
                r.cache_bytes as f64 / 1e6,
                r.visible,
                r.geometry_trees,
                r.hull_trees,
                r.cloud_trees,
                r.billboard_trees
            ));
            ui.label(format!("plan {:.1} ms, stream frame {:.1} ms", r.plan_ms, r.frame_ms));
        }
        if let Some(cs) = cs {
            ui.label(format!(
                "cache hit rate {:.3}",
                cs.hits as f64 / (cs.hits + cs.misses).max(1) as f64
            ));
        }
        let d = self.draw_stats;
        ui.label(format!(
            "drawn: {} leaves, {} triangles, {} instances",
            d.leaves, d.triangles, d.instances
        ));
        ui.label(format!("frame {:.1} ms on {}", self.frame_ms, self.adapter));
        let others = self.presence.lock().map_or(0, |p| p.len());
        ui.label(format!("other viewers: {others}"));
        let t0 = self.history.front().map_or(0.0, |(t, _)| *t);
        let bytes: egui_plot::PlotPoints<'_> = self
            .history
            .iter()
            .map(|(t, r)| [t - t0, r.bytes as f64 / 1e3])
            .collect();
        let tris: egui_plot::PlotPoints<'_> = self
            .history
            .iter()
            .map(|(t, r)| [t - t0, r.triangles as f64 / 1e3])
            .collect();
        ui.label("kB per stream frame");
        egui_plot::Plot::new("bytes").height(90.0).show(ui, |p| {
            p.line(egui_plot::Line::new("kB", bytes));
        });
        ui.label("drawn triangles (thousands)");
        egui_plot::Plot::new("tris").height(90.0).show(ui, |p| {
            p.line(egui_plot::Line::new("k triangles", tris));
        });
    }
}

fn rep_name(r: Representation) -> String {
    format!("{r:?}").to_lowercase()
}

impl<S: RangeSource> eframe::App for ViewerApp<S> {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        let start = Instant::now();
        let ctx = ui.ctx().clone();
        while let Ok(r) = self.reports.try_recv() {
            self.reports_received += 1;
            let t = ctx.input(|i| i.time);
            self.history.push_back((t, r.clone()));
            while self.history.len() > PLOT_HISTORY {
                self.history.pop_front();
            }
            self.last_report = Some(r);
        }
        egui::Panel::right("controls").min_size(320.0).show(ui, |ui| {
            egui::ScrollArea::vertical().show(ui, |ui| self.side_panel(ui));
        });
        egui::CentralPanel::default().show(ui, |ui| {
            let size = ui.available_size();
            let (w, h) = (
                (size.x * ctx.pixels_per_point()) as u32,
                (size.y * ctx.pixels_per_point()) as u32,
            );
            let (rect, response) = ui.allocate_exact_size(size, egui::Sense::click_and_drag());
            self.controls(&ctx, &response);
            let vp = canopy_client::stream::Viewport {
                width: w.max(1),
                height: h.max(1),
                ..self.opts.viewport
            };
            if !self.freeze
                && let Ok(mut sh) = self.shared.lock()
            {
                sh.lod_camera = self.cam;
                if sh.opts.viewport.width != vp.width || sh.opts.viewport.height != vp.height {
                    sh.opts.viewport = vp;
                    self.opts.viewport = vp;
                    sh.opts_changed = true;
                }
            }
            if self.last_pose.elapsed() >= POSE_INTERVAL {
                let _ = self.pose_tx.send(self.cam);
                self.last_pose = Instant::now();
            }
            // New stream frame: upload what it drew (never wait for the stream thread).
            let n = self.reports_received;
            if n != self.prepared_frames
                && let Ok(s) = self.streamer.try_lock()
            {
                let lod_cam = self.shared.lock().map_or(self.cam, |sh| sh.lod_camera);
                let (plan, stats) = self.gpu.prepare(
                    &self.rs.device,
                    &self.rs.queue,
                    &self.renderer,
                    &s,
                    &lod_cam,
                    &vp,
                    &self.view_opts,
                );
                self.plan = plan;
                self.draw_stats = stats;
                self.prepared_frames = n;
            }
            if self.target.as_ref().is_none_or(|t| t.size != (vp.width, vp.height)) {
                let t = Target::with_ui_view(&self.rs.device, vp.width, vp.height);
                if let Some(ui_view) = t.ui_view.as_ref() {
                    let mut r = self.rs.renderer.write();
                    match self.texture {
                        Some(id) => {
                            r.update_egui_texture_from_wgpu_texture(
                                &self.rs.device,
                                ui_view,
                                wgpu::FilterMode::Linear,
                                id,
                            );
                        }
                        None => {
                            self.texture =
                                Some(r.register_native_texture(&self.rs.device, ui_view, wgpu::FilterMode::Linear));
                        }
                    }
                }
                self.target = Some(t);
            }
            if let Some(target) = &self.target {
                let draws = self.gpu.draws(&self.plan);
                self.renderer.render(
                    &self.rs.device,
                    &self.rs.queue,
                    target,
                    &frame_camera(&self.cam, &vp),
                    &draws,
                );
            }
            if let Some(id) = self.texture {
                ui.painter().image(
                    id,
                    rect,
                    egui::Rect::from_min_max(egui::pos2(0.0, 0.0), egui::pos2(1.0, 1.0)),
                    egui::Color32::WHITE,
                );
            }
            // Other viewers as markers.
            let view_proj = vp.projection() * self.cam.view();
            if let Ok(p) = self.presence.lock() {
                for (id, (pos, _)) in p.iter() {
                    let c = view_proj * pos.extend(1.0);
                    if c.w > 0.0 {
                        let ndc = c.truncate() / c.w;
                        if ndc.x.abs() <= 1.0 && ndc.y.abs() <= 1.0 {
                            let at = egui::pos2(
                                rect.left() + (ndc.x * 0.5 + 0.5) * rect.width(),
                                rect.top() + (0.5 - ndc.y * 0.5) * rect.height(),
                            );
                            ui.painter()
                                .circle_filled(at, 6.0, egui::Color32::from_rgb(255, 220, 0));
                            ui.painter().text(
                                at + egui::vec2(8.0, -8.0),
                                egui::Align2::LEFT_BOTTOM,
                                id,
                                egui::FontId::monospace(11.0),
                                egui::Color32::WHITE,
                            );
                        }
                    }
                }
            }
        });
        self.frame_ms = start.elapsed().as_secs_f64() * 1e3;
        if let Some(c) = &mut self.capture {
            let now = ctx.input(|i| i.time);
            // Capture once streaming has settled (an idle stream frame, uploaded), or at the
            // latest CAPTURE_SETTLE_S after the requested time.
            let settled = self
                .last_report
                .as_ref()
                .is_some_and(|r| r.bytes == 0 && r.requests == 0 && r.visible > 0)
                && self.prepared_frames == self.reports_received;
            if !c.requested && now >= c.after_s && (settled || now >= c.after_s + CAPTURE_SETTLE_S) {
                c.requested = true;
                let (path, done) = (c.path.clone(), Arc::clone(&c.done));
                ctx.request_screenshot(move |img| {
                    let bytes: Vec<u8> = img.pixels.iter().flat_map(egui::Color32::to_array).collect();
                    let r = image::RgbaImage::from_raw(img.size[0] as u32, img.size[1] as u32, bytes)
                        .ok_or_else(|| "screenshot size".to_string())
                        .and_then(|i| i.save(&path).map_err(|e| e.to_string()));
                    if let Ok(mut d) = done.lock() {
                        *d = Some(r);
                    }
                });
            }
            let finished = c.done.lock().ok().and_then(|d| d.clone());
            if let Some(r) = finished {
                match r {
                    Ok(()) => eprintln!("window captured to {}", c.path.display()),
                    Err(e) => eprintln!("window capture failed: {e}"),
                }
                ctx.send_viewport_cmd(egui::ViewportCommand::Close);
            }
        }
        ctx.request_repaint();
    }
}
