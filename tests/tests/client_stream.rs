//! End-to-end tests of the streaming client: `canopy fly` against the real `canopy-server`, an
//! nginx asset host, and a fault-injecting proxy ([`canopy_e2e::faults`]).
//!
//! `fly` runs on a virtual clock (frames never wait; what a frame asks for arrives by the next on
//! the default instant link), so a run is deterministic: the same scene, path and options give
//! the same per-frame figures. The fault tests lean on that: a run through a faulty proxy is
//! compared frame by frame with a clean run of the same path (`client_faults.rs`; clouds and
//! `eval` in `client_clouds_eval.rs`; shared helpers in [`canopy_e2e::fly`]).

use std::path::Path;
use std::process::Command;

use canopy_e2e::faults::{Fault, FaultProxy, parse_range_spec};
use canopy_e2e::fly::*;
use canopy_e2e::net::{Nginx, Server};
use canopy_e2e::{scratch, server, workspace_root};
use serde_json::Value;

#[test]
fn fly_fetches_a_deterministic_fraction_of_the_scene() {
    let dir = scratch("client-fly");
    let s = Server::start(&dir.join("data"), SMALL_DEMO);
    let url = scene_url(&s);
    let a = fly(&url, &["--cache-mb", "64"]);

    let (bytes, full) = (a.sum("bytes"), a.sum("full_download_bytes"));
    assert!(bytes > 0, "nothing fetched: {}", a.summary);
    assert!(
        bytes < full,
        "LOD streaming fetched {bytes} bytes, not less than the full download {full}"
    );
    assert_eq!(a.sum("corrupt_blocks"), 0, "{}", a.summary);
    assert_eq!(a.sum("failures"), 0, "{}", a.summary);
    assert_eq!(
        a.sum("retries"),
        0,
        "a healthy local server needs no retries: {}",
        a.summary
    );
    assert!(a.sum("requests") > 0);
    assert!(
        a.per_frame("leaves").iter().any(|&l| l > 0),
        "no frame drew a leaf: {:?}",
        a.per_frame("leaves")
    );
    // The run fetches far less than the 64 MiB budget: the cache holds it all and evicts
    // nothing (a small budget's evictions have their own test).
    let (peak, budget) = (a.sum("cache_peak_bytes"), a.sum("cache_budget_bytes"));
    assert_eq!(budget, 64 << 20);
    assert!(peak > 0 && peak <= bytes, "cache peak {peak} vs {bytes} bytes fetched");
    assert_eq!(a.sum("cache_evictions"), 0, "{}", a.summary);
    assert_eq!(
        a.per_frame("cache_evictions").iter().sum::<u64>(),
        0,
        "a frame evicted blocks from a cache with room"
    );
    assert!(a.sum("cache_insertions") > 0, "{}", a.summary);
    let per_frame: u64 = a.per_frame("bytes").iter().sum();
    assert!(
        per_frame <= bytes,
        "frame bytes {per_frame} exceed the total {bytes} (which adds the manifest)"
    );

    let b = fly(&url, &["--cache-mb", "64"]);
    assert_eq!(
        a.per_frame("bytes"),
        b.per_frame("bytes"),
        "per-frame bytes differ between two runs"
    );
    assert_eq!(a.per_frame("requests"), b.per_frame("requests"));
    assert_eq!(a.drawn(), b.drawn(), "what is drawn differs between two runs");
}

/// Geometry trees are planned on the thread pool when a frame has four or more: what is fetched
/// and drawn must not depend on how many threads the pool has, nor on whether the pool is used
/// at all (`--no-plan-pool`, the sequential path).
#[test]
fn planning_does_not_depend_on_the_thread_count() {
    let dir = scratch("client-threads");
    let s = Server::start(&dir.join("data"), SMALL_DEMO);
    let url = scene_url(&s);
    let args = ["--ladder", "geometry:0", "--frames", "30"];
    let a = fly_env(&url, &args, &[("RAYON_NUM_THREADS", "4")]);
    // A frame after one with four or more geometry trees starts them on the pool as the
    // instance loop meets them.
    assert!(
        a.per_frame("geometry_trees").windows(2).any(|w| w[0] >= 4 && w[1] >= 4),
        "no two frames in a row planned enough geometry trees to use the thread pool: {:?}",
        a.per_frame("geometry_trees")
    );
    let b = fly_env(&url, &args, &[("RAYON_NUM_THREADS", "1")]);
    let mut sequential = args.to_vec();
    sequential.push("--no-plan-pool");
    let c = fly(&url, &sequential);
    for (other, what) in [(&b, "1 pool thread"), (&c, "no pool")] {
        assert_eq!(
            a.per_frame("bytes"),
            other.per_frame("bytes"),
            "4 pool threads against {what}"
        );
        assert_eq!(a.per_frame("requests"), other.per_frame("requests"), "{what}");
        assert_eq!(a.drawn(), other.drawn(), "what is drawn: 4 pool threads against {what}");
        assert_eq!(
            a.per_frame("nodes_evaluated"),
            other.per_frame("nodes_evaluated"),
            "switch-control evaluations: 4 pool threads against {what}"
        );
    }
    // Geometry trees are evaluated when they appear, and then mostly skipped.
    let evaluated = a.per_frame("nodes_evaluated");
    assert!(evaluated.iter().any(|&n| n > 0), "no node evaluated: {evaluated:?}");
}

/// Bytes of a model file the client reads in its first request (header and directory, and
/// whatever follows up to this length).
const FIRST_REQUEST_LEN: u64 = 64 * 1024;
/// Bytes of the atlas section's start the client reads with the tables.
const ATLAS_TABLE_PREFIX: u64 = 16 * 1024;

/// Bytes fetched by a run with LOD and one at full detail: leaf bytes (of the leaves sections)
/// and all bytes.
#[derive(Debug)]
struct LodTransfer {
    lod_leaves: u64,
    full_leaves: u64,
    lod_skeleton: u64,
    full_skeleton: u64,
    lod_bytes: u64,
    full_bytes: u64,
}

/// Flies `args` with LOD and at full detail over the demo of `s` and checks what each fetched
/// and drew: full detail every geometry byte and no billboard image past the crossed-quad
/// stand-in, the LOD billboard images and fewer leaves and triangles.
fn lod_and_full_detail(s: &Server, args: &[&str]) -> LodTransfer {
    let models = model_sections(s);
    // Per model: bytes of each geometry section fetched, and billboard image bytes fetched
    // (the atlas section past what the first request and the table prefix read).
    let run = |args: &[&str]| {
        // Through a pass-through proxy, which logs the ranges asked for.
        let proxy = FaultProxy::start(s.addr, Fault::None);
        let f = fly(&format!("http://{}/api/scenes/demo", proxy.addr), args);
        let per_model: Vec<(Vec<(u64, u64)>, u64)> = models
            .iter()
            .map(|(url, secs)| {
                let geometry = ["node_table", "materials", "skeleton", "bark_mesh", "leaves"]
                    .iter()
                    .map(|k| {
                        let r = section_of(secs, k);
                        (covered(&proxy, url, r), r.1 - r.0)
                    })
                    .collect();
                let (a, b) = section_of(secs, "billboard_atlases");
                let images = covered(
                    &proxy,
                    url,
                    (a.saturating_add(ATLAS_TABLE_PREFIX).max(FIRST_REQUEST_LEN), b),
                );
                // Less the model's crossed-quad stand-in, which every run fetches first.
                let file = s.data.join(url.trim_start_matches('/'));
                let stand_in = crossed_stand_in(&file).map_or(0, |(_, span)| covered(&proxy, url, span));
                (geometry, images.saturating_sub(stand_in))
            })
            .collect();
        (f, per_model)
    };
    let (lod, lod_models) = run(args);
    let (full, full_models) = run(&[args, &["--full-detail"]].concat());
    let (l, f) = (lod.sum("bytes"), full.sum("bytes"));
    let ratio = format!(
        "total bytes: full detail {f}, LOD {l}, {:.2}x",
        f as f64 / l.max(1) as f64
    );
    eprintln!("{ratio}\nLOD (geometry, images) {lod_models:?}\nfull {full_models:?}");

    for ((url, _), (geometry, images)) in models.iter().zip(&full_models) {
        // Full detail draws every visible tree at rate 0: every geometry byte, no billboard.
        for (got, len) in geometry {
            assert_eq!(
                got, len,
                "--full-detail fetched {got} of {len} bytes of a geometry section of {url}; {ratio}"
            );
        }
        assert_eq!(
            *images, 0,
            "--full-detail fetched {images} bytes of billboard images of {url}; {ratio}"
        );
    }
    // The LOD draws distant trees as billboards, so it fetches billboard images.
    let lod_images: u64 = lod_models.iter().map(|(_, i)| i).sum();
    let billboards: u64 = lod.per_frame("billboard_trees").iter().sum();
    assert!(
        billboards > 0 && lod_images > 0,
        "the LOD run drew {billboards} billboards from {lod_images} bytes of billboard images; {ratio}"
    );
    // The LOD draws less than full detail.
    let (ld, fd): (u64, u64) = (
        lod.per_frame("leaves").iter().sum(),
        full.per_frame("leaves").iter().sum(),
    );
    assert!(ld < fd, "full detail drew {fd} leaves over the run, LOD {ld}; {ratio}");
    let share = |x: &Fly| x.summary["triangle_share"].as_f64().expect("triangle_share");
    assert!(
        share(&lod) < 0.5 && share(&full) > 0.95,
        "triangle share: LOD {}, full detail {}; {ratio}",
        share(&lod),
        share(&full)
    );
    // Frames never wait for bytes: a tree is drawn as geometry from the frame after its bytes
    // were asked for, as its stand-in (crossed quads, else a hull) before. From the first
    // complete frame on, nothing is pending, and nearly every tree is geometry (those entering
    // the view are stand-ins for a frame).
    let first = full
        .frames
        .iter()
        .position(|f| f["complete"].as_bool() == Some(true))
        .expect("a complete frame");
    assert!(
        first <= 4,
        "first complete frame {first}: on loopback the stream catches up in 4"
    );
    let (mut geometry, mut visible_sum) = (0u64, 0u64);
    for (i, d) in full.drawn().iter().enumerate().skip(first) {
        let visible = full.frames[i]["visible"].as_u64().expect("visible");
        assert!(
            d[2] + d[3] + d[4] == visible && d[5] == 0,
            "full detail, frame {i}: {} of {visible} visible trees drawn as geometry, {} as hulls, {} as stand-in billboards, {} pending",
            d[2],
            d[3],
            d[4],
            d[5]
        );
        geometry += d[2];
        visible_sum += visible;
    }
    assert!(
        geometry as f64 >= 0.95 * visible_sum as f64,
        "full detail drew {geometry} of {visible_sum} visible trees as geometry"
    );
    let leaf_bytes = |per_model: &[(Vec<(u64, u64)>, u64)]| -> u64 { per_model.iter().map(|(g, _)| g[4].0).sum() };
    let skeleton_bytes = |per_model: &[(Vec<(u64, u64)>, u64)]| -> u64 { per_model.iter().map(|(g, _)| g[2].0).sum() };
    LodTransfer {
        lod_leaves: leaf_bytes(&lod_models),
        full_leaves: leaf_bytes(&full_models),
        lod_skeleton: skeleton_bytes(&lod_models),
        full_skeleton: skeleton_bytes(&full_models),
        lod_bytes: l,
        full_bytes: f,
    }
}

#[test]
fn transfer_follows_lod_geometry_at_full_detail_billboards_with_lod() {
    let dir = scratch("client-full-detail");
    let s = Server::start(&dir.join("data"), SMALL_DEMO);
    let t = lod_and_full_detail(&s, &[]);
    // The synthetic trees' files are smaller than the opening read, which holds their whole
    // leaves section: both runs fetch every leaf byte (measured 5,056 each). Leaf bytes that
    // follow the LOD need a larger model (the next test).
    assert!(t.lod_leaves <= t.full_leaves, "{t:?}");
}

/// On maples, a low flight with LOD fetches a fraction of the leaf bytes that full detail
/// fetches, and fewer bytes in all.
fn transfer_follows_lod_leaf_bytes(s: &Server) {
    // The crown-hull ladder: a hull level is a few kilobytes where the default ladder's
    // billboard frames are tens (the default measured 2,066,403 bytes in all, 0.89).
    let t = lod_and_full_detail(
        s,
        &[
            "--path",
            "lowflight",
            "--frames",
            "90",
            "--ladder",
            "geometry:150,hull0:60,hull1:30,hemioct:0",
        ],
    );
    eprintln!("{t:?}");
    // Measured (twice, the run is deterministic): LOD 795,272 leaf bytes of full detail's
    // 1,448,596 (0.55), and 1,876,531 bytes in all against 2,321,562 (0.81).
    assert!(
        t.lod_leaves * 10 < t.full_leaves * 6,
        "leaf bytes fetched: LOD {}, full detail {}: not under 0.6 of it",
        t.lod_leaves,
        t.full_leaves
    );
    assert!(t.lod_bytes * 100 < t.full_bytes * 85, "{t:?}");
    // A low flight passes close enough that some tree draws every twig: the whole skeleton.
    assert!(t.lod_skeleton <= t.full_skeleton, "{t:?}");
}

/// A budget smaller than what the run needs: the cache evicts (its own counters say so), never
/// holds more than the budget after a frame, and evicted blocks are fetched again. The synthetic
/// demo's two small models fit in the smallest budget (1 MiB), so this flies low over maples
/// ([`maple_server`]), whose blocks a low flight needs 1.7 MB of.
fn small_cache_evicts_and_stays_within_its_budget(s: &Server) {
    let args = |mb| ["--path", "lowflight", "--frames", "90", "--cache-mb", mb];
    let roomy = fly(&scene_url(s), &args("64"));
    let small = fly(&scene_url(s), &args("1"));
    let budget = small.sum("cache_budget_bytes");
    assert_eq!(budget, 1 << 20);
    // With room, the cache holds more than the small budget (measured 1,658,208 bytes) and
    // evicts nothing.
    assert!(
        roomy.sum("cache_peak_bytes") > budget,
        "the run needs only {} bytes of cache: a {budget}-byte budget does not constrain it",
        roomy.sum("cache_peak_bytes")
    );
    assert_eq!(roomy.sum("cache_evictions"), 0, "{}", roomy.summary);
    let held = small.per_frame("cache_bytes");
    for (i, &c) in held.iter().enumerate() {
        assert!(
            c <= budget,
            "frame {i}: the cache holds {c} bytes, over its budget of {budget}"
        );
    }
    let evictions = small.per_frame("cache_evictions");
    assert!(
        evictions.iter().sum::<u64>() > 0,
        "a {budget}-byte cache evicted nothing where the run needs {} bytes",
        roomy.sum("cache_peak_bytes")
    );
    assert_eq!(
        evictions.iter().sum::<u64>(),
        small.sum("cache_evictions"),
        "{}",
        small.summary
    );
    // The budget is what limits it: the cache fills up to it (measured 1,048,573 bytes, twice).
    let peak = small.sum("cache_peak_bytes");
    assert_eq!(peak, held.iter().copied().max().unwrap_or(0));
    assert!(peak >= budget / 20 * 19, "cache peak {peak} of a {budget}-byte budget");
    // Evicted blocks that are needed again are fetched again (measured 5,876,764 bytes against
    // 1,876,531 with room).
    assert!(
        small.sum("bytes") > roomy.sum("bytes"),
        "a cache that evicts fetched {} bytes, one with room {}",
        small.sum("bytes"),
        roomy.sum("bytes")
    );
    assert_eq!(small.sum("failures"), 0, "{}", small.summary);
}

#[test]
fn maples_transfer_follows_lod_and_a_small_cache_evicts() {
    let dir = scratch("client-maples-fly");
    let s = maple_server(&dir);
    transfer_follows_lod_leaf_bytes(&s);
    small_cache_evicts_and_stays_within_its_budget(&s);
}

#[test]
fn species_trees_are_drawn_as_geometry_at_full_detail() {
    // A species grown by its L-system (not the synthetic trees): its iteration 0 (the axiom)
    // has no branches, so the file's iteration table starts with an empty skeleton iteration.
    let dir = scratch("client-species");
    let species = workspace_root().join("assets/species");
    let s = Server::start(
        &dir.join("data"),
        &[
            "--species",
            species.to_str().expect("UTF-8 path"),
            "--demo-species",
            "small_shrub",
            "--demo-trees",
            "200",
        ],
    );
    // The stream catches up in a few frames (tiles, openings, then units, each drawn the frame
    // after it arrived); from the first frame drawing geometry on, every visible tree is
    // geometry.
    let full = fly(&scene_url(&s), &["--full-detail", "--frames", "10"]);
    let first = full
        .frames
        .iter()
        .position(|f| f["geometry_trees"].as_u64().unwrap_or(0) > 0)
        .expect("geometry drawn");
    assert!(first <= 4, "geometry first drawn at frame {first}");
    for (i, f) in full.frames.iter().enumerate().skip(first) {
        let g = |k: &str| f[k].as_u64().unwrap_or_else(|| panic!("frame.{k}: {f}"));
        assert!(
            g("visible") > 0 && g("geometry_trees") == g("visible") && g("pending_trees") == 0,
            "frame {i} at full detail: {} visible, {} drawn as geometry, {} pending ({} bytes fetched in all, \
             {} cached); a tree whose blocks are all fetched must be drawn",
            g("visible"),
            g("geometry_trees"),
            g("pending_trees"),
            full.sum("bytes"),
            g("cache_bytes")
        );
    }
}

/// A model file's iteration table (`canopy-server inspect --json`): per iteration, the end of
/// its skeleton bytes (relative to the section) and its leaf nodes.
fn iteration_table(file: &Path) -> Vec<(u64, u64)> {
    let out = run_bounded(Command::new(server()).arg("inspect").arg("--json").arg(file), RUN_LIMIT);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: Value = serde_json::from_slice(&out.stdout).expect("inspect JSON");
    v["iteration_table"]
        .as_array()
        .expect("iteration_table")
        .iter()
        .map(|e| {
            (
                e["skeleton_bytes_end"].as_u64().expect("skeleton_bytes_end"),
                e["leaf_nodes"].as_u64().expect("leaf_nodes"),
            )
        })
        .collect()
}

#[test]
fn fewer_iterations_fetch_a_skeleton_prefix_and_fewer_leaves() {
    // Seed 000's middle level: a tree drawn with its last two iterations left out asks for
    // the skeleton of the earlier iterations only (a prefix of the section) and no leaf node
    // of a branch born later.
    let dir = scratch("client-iterations");
    let species = workspace_root().join("assets/species");
    let s = Server::start(
        &dir.join("data"),
        &[
            "--species",
            species.to_str().expect("UTF-8 path"),
            "--demo-species",
            "small_shrub",
            "--demo-trees",
            "200",
        ],
    );
    let (url, secs) = model_sections(&s).into_iter().next().expect("one model");
    let table = iteration_table(&s.data.join(url.trim_start_matches('/')));
    let last = table.len() - 1;
    assert!(last >= 3, "small_shrub grows {last} iterations");
    let skeleton = section_of(&secs, "skeleton");
    let leaves = section_of(&secs, "leaves");
    let run = |ladder: &str| {
        let proxy = FaultProxy::start(s.addr, Fault::None);
        let f = fly(
            &format!("http://{}/api/scenes/demo", proxy.addr),
            &["--ladder", ladder, "--frames", "12"],
        );
        let sk = covered(&proxy, &url, skeleton);
        let lv = covered(&proxy, &url, leaves);
        (f, sk, lv)
    };
    let (fewer, fewer_skeleton, fewer_leaves) = run("iter2:0");
    let (all, all_skeleton, all_leaves) = run("geometry:0");
    // Every iteration a tree's bark variant draws a branch of; the last twigs, thinner than the
    // variant of any tree on this path (the file's skeleton-radii table), are not fetched
    // (measured 44,240 of 58,504 bytes).
    assert!(
        all_skeleton < skeleton.1 - skeleton.0 && all_skeleton >= fewer_skeleton,
        "skeleton bytes: {all_skeleton} of {}, {fewer_skeleton} with two iterations fewer",
        skeleton.1 - skeleton.0
    );
    let prefix = table[last - 2].0;
    // The prefix, and past it at most what one merged read spans (the merge gap).
    assert!(
        fewer_skeleton >= prefix && fewer_skeleton < prefix + 4096,
        "skeleton bytes fetched with 2 iterations left out: {fewer_skeleton}; the prefix of iterations \
         0..={} is {prefix} of {}",
        last - 2,
        all_skeleton
    );
    let later_nodes: u64 = table[last - 1..].iter().map(|e| e.1).sum();
    assert!(
        later_nodes == 0 || fewer_leaves < all_leaves,
        "leaf bytes: {fewer_leaves} with 2 iterations left out, {all_leaves} with all ({later_nodes} leaf nodes \
         born in the last two)"
    );
    // Every visible tree is drawn as geometry once its units are in, the same as with all.
    for f in [&fewer, &all] {
        let last_frame = f.frames.last().expect("frames");
        let g = |k: &str| last_frame[k].as_u64().unwrap_or_else(|| panic!("frame.{k}"));
        assert!(g("visible") > 0 && g("geometry_trees") == g("visible"), "{last_frame}");
    }
    let tri = |f: &Fly| f.frames.last().and_then(|x| x["triangles"].as_u64()).unwrap_or(0);
    // Never more triangles. Not fewer here: the shrubs' last two iterations are twigs under
    // 0.1 px from the path, which the bark variant leaves out with every iteration drawn too
    // (as the viewer does), and they carry no leaf node.
    assert!(
        tri(&fewer) <= tri(&all),
        "fewer iterations draw more triangles: {} against {}; last frames {} and {}",
        tri(&fewer),
        tri(&all),
        fewer.frames.last().expect("frames"),
        all.frames.last().expect("frames")
    );
}

#[test]
fn nginx_as_asset_host_draws_the_same_as_canopy() {
    let dir = scratch("client-nginx");
    let data = dir.join("data");
    let s = Server::start(&data, SMALL_DEMO);
    let Some(ng) = Nginx::start(&data.join("assets"), &dir.join("nginx")) else {
        return;
    };
    let url = scene_url(&s);
    let direct = fly(&url, &[]);
    // Through a pass-through proxy in front of nginx, which logs the `Range` headers sent.
    let mut requests = Vec::new();
    for mode in ["auto", "single"] {
        let proxy = FaultProxy::start(ng.addr, Fault::None);
        let base = format!("http://{}", proxy.addr);
        let via = fly(&url, &["--assets-base", &base, "--range-mode", mode]);
        assert_eq!(
            direct.drawn(),
            via.drawn(),
            "through nginx with --range-mode {mode}, the frames draw differently"
        );
        assert_eq!(via.sum("corrupt_blocks"), 0, "{mode}: {}", via.summary);
        assert_eq!(via.sum("failures"), 0, "{mode}: {}", via.summary);
        assert_eq!(via.sum("retries"), 0, "{mode}: {}", via.summary);
        // Every asset request went through the proxy (the manifest comes from the server).
        assert_eq!(
            proxy.requests(),
            via.sum("requests"),
            "{mode}: requests the proxy saw against those the client counted"
        );
        let multi = proxy.seen().iter().filter(|r| multi_range(r)).count();
        match mode {
            // nginx answers multi-range requests, so auto mode keeps sending them.
            "auto" => assert!(multi > 0, "auto mode sent nginx no multi-range request"),
            _ => assert_eq!(multi, 0, "single mode sent {multi} multi-range requests"),
        }
        requests.push(via.sum("requests"));
    }
    assert!(
        requests[1] > requests[0],
        "single ranges took {} requests, multi-range {}: not more",
        requests[1],
        requests[0]
    );
}

/// A billboard image is not fetched at a resolution when a larger one of the same frame was
/// asked for before (or in the same request): the larger one serves the smaller tree too,
/// minified. On the maple flyover both resolutions are asked for, the larger ones first for the
/// near trees; their frames' smaller images would follow for the trees behind. Only images at a
/// merged range's ends count as asked for: those inside may be the gaps the merge rule spans.
#[test]
fn a_smaller_billboard_image_is_not_fetched_after_a_larger_one() {
    let dir = scratch("client-atlas-finer");
    let s = maple_server(&dir);
    let proxy = FaultProxy::start(s.addr, Fault::None);
    let f = fly(
        &format!("http://{}/api/scenes/demo", proxy.addr),
        &["--path", "flyover", "--frames", "240"],
    );
    assert_eq!(f.sum("failures"), 0, "{}", f.summary);
    let seen = proxy.seen();
    let (mut larger_asked, mut smaller_asked, mut after) = (0, 0, Vec::new());
    for (url, _) in model_sections(&s) {
        let images = atlas_images(&s.data.join(url.trim_start_matches('/')));
        let mut larger: std::collections::HashSet<u64> = std::collections::HashSet::new();
        for r in seen.iter().filter(|r| r.target == url) {
            let spans = r.range.as_deref().map(parse_range_spec).unwrap_or_default();
            let at_ends: Vec<&AtlasImage> = images
                .iter()
                .filter(|im| spans.iter().any(|&(a, b)| im.range.0 == a || im.range.1 == b + 1))
                .collect();
            let now: Vec<u64> = at_ends
                .iter()
                .filter(|im| im.resolution == 0)
                .map(|im| im.frame)
                .collect();
            larger_asked += now.len();
            larger.extend(now);
            for im in at_ends.iter().filter(|im| im.resolution > 0) {
                smaller_asked += 1;
                if larger.contains(&im.frame) {
                    after.push((url.clone(), r.seq, im.frame, im.resolution));
                }
            }
        }
    }
    assert!(
        larger_asked > 0 && smaller_asked > 0,
        "both resolutions asked for: larger {larger_asked}, smaller {smaller_asked}"
    );
    assert!(
        after.is_empty(),
        "smaller images asked for after a larger one (model, request, frame, resolution): {after:?}"
    );
}

/// The views layout of a model file: its first frame and frame count (`inspect --json`).
fn views_layout(file: &Path) -> (u64, u64) {
    let out = run_bounded(Command::new(server()).arg("inspect").arg("--json").arg(file), RUN_LIMIT);
    assert!(out.status.success(), "canopy-server inspect {}", file.display());
    let v: Value = serde_json::from_slice(&out.stdout).expect("inspect JSON");
    let l = v["atlas"]["layouts"]
        .as_array()
        .expect("atlas layouts")
        .iter()
        .find(|l| l["layout"] == "views")
        .unwrap_or_else(|| panic!("{}: no views layout", file.display()));
    (
        l["first_frame"].as_u64().expect("first_frame"),
        l["frames"].as_u64().expect("frames"),
    )
}

/// Seed 001's irregular views: a demo baked with a photographer's set of 24 views draws its far
/// trees with the `views` rung, from frames of the views layout only, each fetched by range.
#[test]
fn irregular_views_are_drawn_from_their_own_frames() {
    let dir = scratch("client-views");
    let mut args = SMALL_DEMO.to_vec();
    args.extend(["--demo-photo-views", "24"]);
    let s = Server::start(&dir.join("data"), &args);
    let proxy = FaultProxy::start(s.addr, Fault::None);
    let f = fly(
        &format!("http://{}/api/scenes/demo", proxy.addr),
        &["--ladder", "geometry:150,views:0"],
    );
    assert_eq!(f.sum("failures"), 0, "{}", f.summary);
    let billboards: u64 = f.per_frame("billboard_trees").iter().sum();
    assert!(billboards > 0, "no tree drawn as a billboard: {}", f.summary);
    let seen = proxy.seen();
    let mut asked = 0;
    for (url, _) in model_sections(&s) {
        let file = s.data.join(url.trim_start_matches('/'));
        let (first, count) = views_layout(&file);
        assert_eq!(count, 24, "{url}");
        // The crossed-quad stand-in, fetched for every model before anything else.
        let (stand_in, _) = crossed_stand_in(&file).unwrap_or_else(|| panic!("{url}: no crossed quads"));
        let images = atlas_images(&file);
        for r in seen.iter().filter(|r| r.target == url) {
            let spans = r.range.as_deref().map(parse_range_spec).unwrap_or_default();
            // Images at a merged range's ends were asked for; those inside may be its gaps.
            for im in images
                .iter()
                .filter(|im| spans.iter().any(|&(a, b)| im.range.0 == a || im.range.1 == b + 1))
            {
                if stand_in.contains(&im.frame) {
                    continue;
                }
                asked += 1;
                assert!(
                    (first..first + count).contains(&im.frame),
                    "{url}: frame {} of another layout asked for (views are {first}..{})",
                    im.frame,
                    first + count
                );
            }
        }
    }
    assert!(asked > 0, "no views image fetched");
}
