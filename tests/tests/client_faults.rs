//! End-to-end tests of the streaming client under faults: `canopy fly` through a fault-injecting
//! proxy ([`canopy_e2e::faults`]): refused multi-range requests, truncated and unavailable
//! responses, a slow server, flipped bytes, and servers that are unknown, garbage or gone.
//!
//! `fly` runs on a virtual clock (frames never wait; what a frame asks for arrives by the next on
//! the default instant link), so a run is deterministic: a run through a faulty proxy is compared
//! frame by frame with a clean run of the same path. Shared helpers: [`canopy_e2e::fly`].

use canopy_e2e::faults::{CannedServer, Fault, FaultProxy, Refusal, Window};
use canopy_e2e::fly::*;
use canopy_e2e::net::Server;
use canopy_e2e::scratch;

/// The frame (from 0) of each request a proxy saw, by sequence number, from the run's per-frame
/// request counts: the frame loop waits for each frame's fetches, so the proxy sees the frames'
/// requests in frame order. The first `before` requests (the manifest) belong to no frame.
fn frames_of_requests(f: &Fly, proxy: &FaultProxy, before: u64) -> Vec<(u64, Option<usize>)> {
    let per_frame = f.per_frame("requests");
    assert_eq!(
        proxy.requests(),
        before + per_frame.iter().sum::<u64>(),
        "requests the proxy saw against those the client counted: {}",
        f.summary
    );
    let mut ends = Vec::with_capacity(per_frame.len());
    let mut end = before;
    for n in per_frame {
        end += n;
        ends.push(end);
    }
    proxy
        .seen()
        .iter()
        .map(|r| (r.seq, (r.seq > before).then(|| ends.partition_point(|&e| e < r.seq))))
        .collect()
}

/// A server (or CDN) that does not do multi-range answers a request for several ranges with the
/// whole file (`200`) or with one part. The client then takes what came back and fetches the
/// rest as single ranges (`client/src/net/http.rs`): the same frames are drawn, with more
/// requests. In auto mode it stops sending multi-range requests after the first refusal; in
/// multi mode it keeps asking, and falls back request by request.
#[test]
fn refused_multi_range_falls_back_to_single_ranges_and_draws_the_same() {
    let dir = scratch("client-no-multi");
    let s = Server::start(&dir.join("data"), SMALL_DEMO);
    let through = |fault: Fault, mode: &str| {
        let proxy = FaultProxy::start(s.addr, fault);
        let args = [LOWFLIGHT, &["--range-mode", mode]].concat();
        let f = fly(&format!("http://{}/api/scenes/demo", proxy.addr), &args);
        assert_eq!(f.sum("failures"), 0, "{mode}: {}", f.summary);
        assert_eq!(f.sum("retries"), 0, "{mode}: {}", f.summary);
        assert_eq!(f.sum("corrupt_blocks"), 0, "{mode}: {}", f.summary);
        (f, proxy)
    };
    // The canopy server answers multi-range requests: auto mode sends them in several frames
    // of a low flight (measured: frames 0, 21, 31 and 46 of 60).
    let (clean, clean_proxy) = through(Fault::None, "auto");
    let multi_frames = |f: &Fly, proxy: &FaultProxy| -> Vec<usize> {
        let frames = frames_of_requests(f, proxy, 1);
        let mut out: Vec<usize> = proxy
            .seen()
            .iter()
            .zip(&frames)
            .filter(|(r, _)| multi_range(r))
            .map(|(r, &(seq, frame))| {
                assert_eq!(r.seq, seq);
                frame.unwrap_or_else(|| panic!("multi-range request {seq} before the first frame"))
            })
            .collect();
        out.sort_unstable();
        out.dedup();
        out
    };
    let clean_frames = multi_frames(&clean, &clean_proxy);
    assert!(
        clean_frames.len() > 1,
        "auto mode sent multi-range requests in frames {clean_frames:?} only, to a server that answers them"
    );
    for (how, mode) in [
        (Refusal::Whole, "auto"),
        (Refusal::FirstRange, "auto"),
        (Refusal::FirstRange, "multi"),
    ] {
        let what = format!("{how:?}, --range-mode {mode}");
        let (f, proxy) = through(Fault::NoMultiRange(how), mode);
        assert!(proxy.faults() > 0, "{what}: no multi-range request was refused");
        assert_eq!(
            clean.drawn(),
            f.drawn(),
            "{what}: multi-range refused, the frames draw differently"
        );
        assert!(
            f.sum("requests") > clean.sum("requests"),
            "{what}: {} requests, no more than the {} of multi-range",
            f.sum("requests"),
            clean.sum("requests")
        );
        let frames = multi_frames(&f, &proxy);
        if mode == "auto" {
            // Refused once, auto mode sends single ranges from then on: multi-range requests
            // only in the frame of the first refusal (several models fetch at once there).
            assert_eq!(
                frames.len(),
                1,
                "{what}: multi-range requests in frames {frames:?} after the server refused one"
            );
        } else {
            assert_eq!(
                frames, clean_frames,
                "{what}: multi mode stopped asking for multi-range"
            );
        }
    }
}

/// Path and frames of the transport fault runs: a fast low flight, which fetches in many frames.
const LOWFLIGHT: &[&str] = &["--path", "lowflight", "--frames", "60"];

/// For each range mode, a clean run and a run through a proxy with the fault `fault(server)`,
/// on one server, with `args`; `check(mode, clean, faulty, proxy)` judges each pair.
fn clean_and_faulty(
    name: &str,
    args: &[&str],
    fault: impl Fn(&Server) -> Fault,
    check: impl Fn(&str, &Fly, &Fly, &FaultProxy),
) {
    let dir = scratch(name);
    let s = Server::start(&dir.join("data"), SMALL_DEMO);
    for mode in ["auto", "single"] {
        let args = [args, &["--range-mode", mode]].concat();
        let clean = fly(&scene_url(&s), &args);
        let proxy = FaultProxy::start(s.addr, fault(&s));
        let faulty = fly(&format!("http://{}/api/scenes/demo", proxy.addr), &args);
        assert!(
            proxy.requests() > 0,
            "{name} {mode}: the client did not go through the proxy"
        );
        eprintln!(
            "{name} {mode}: {} requests through the proxy, {} faults; retries {}, failures {}, corrupt blocks {}",
            proxy.requests(),
            proxy.faults(),
            faulty.sum("retries"),
            faulty.sum("failures"),
            faulty.sum("corrupt_blocks")
        );
        check(mode, &clean, &faulty, &proxy);
    }
}

/// Checks that no frame of `faulty` draws more than the same frame of `clean`.
fn never_more(clean: &Fly, faulty: &Fly, what: &str) {
    for (i, (c, f)) in clean.drawn().iter().zip(faulty.drawn()).enumerate() {
        assert!(
            f[0] <= c[0] && f[2] <= c[2],
            "{what}: frame {i} drew {} leaves on {} geometry trees, more than the clean run's {} on {}",
            f[0],
            f[2],
            c[0],
            c[2]
        );
    }
}

/// Shared checks of the transport faults (truncation, 503): retried, and the run goes on.
fn retried_fault(name: &str, fault: &Fault) {
    clean_and_faulty(
        name,
        LOWFLIGHT,
        |_| fault.clone(),
        |mode, clean, faulty, proxy| {
            let what = format!("{name} {mode}");
            assert!(proxy.faults() > 0, "{what}: the proxy injected nothing");
            // Each fault is retried once (the proxy never faults a request twice; the manifest,
            // request 1, is never faulted).
            assert_eq!(
                faulty.sum("retries"),
                proxy.faults(),
                "{what}: {} faults injected, retries reported: {}",
                proxy.faults(),
                faulty.summary
            );
            assert_eq!(faulty.sum("corrupt_blocks"), 0, "{what}: {}", faulty.summary);
            let (c, f) = (clean.drawing_frames(), faulty.drawing_frames());
            assert!(
                f * 10 >= c * 9,
                "{what}: only {f} frames drew a tree, the clean run {c}"
            );
            // The proxy never faults the same request twice, so with retries every fetch
            // succeeds within its frame (a client that gave up would count a failure here),
            // and the picture is the clean one.
            assert_eq!(faulty.sum("failures"), 0, "{what}: {}", faulty.summary);
            assert_eq!(
                clean.drawn(),
                faulty.drawn(),
                "{what}: every fetch succeeded after retries, yet the frames drew differently"
            );
        },
    );
}

#[test]
fn truncated_responses_are_retried() {
    retried_fault("client-fault-truncate", &Fault::Truncate { every: 4 });
}

#[test]
fn unavailable_responses_are_retried() {
    retried_fault("client-fault-503", &Fault::Unavailable { every: 3 });
}

/// Delay of every response in the slow-server test, milliseconds.
const DELAY_MS: u64 = 40;

#[test]
fn slow_server_changes_nothing_but_time() {
    clean_and_faulty(
        "client-fault-slow",
        LOWFLIGHT,
        |_| Fault::Delay { ms: DELAY_MS },
        |mode, clean, slow, proxy| {
            // Every response was held back (the manifest's too).
            assert_eq!(
                proxy.faults(),
                proxy.requests(),
                "{mode}: not every response was delayed"
            );
            assert_eq!(proxy.requests(), 1 + slow.sum("requests"), "{mode}: {}", slow.summary);
            assert_eq!(slow.sum("retries"), 0, "{mode}: {}", slow.summary);
            assert_eq!(
                clean.per_frame("bytes"),
                slow.per_frame("bytes"),
                "{mode}: per-frame bytes"
            );
            assert_eq!(
                clean.per_frame("requests"),
                slow.per_frame("requests"),
                "{mode}: per-frame requests"
            );
            assert_eq!(
                clean.drawn(),
                slow.drawn(),
                "{mode}: a slow server changed what is drawn"
            );
            // A frame waits for its fetches, so each frame that sent a request took at least
            // one delay. (A lower bound on time: a loaded machine only adds to it.)
            let waiting = slow.per_frame("requests").iter().filter(|&&n| n > 0).count();
            assert!(waiting > 10, "{mode}: only {waiting} frames fetched");
            let secs = slow.summary["seconds"].as_f64().expect("seconds");
            let least = waiting as f64 * DELAY_MS as f64 / 1e3;
            assert!(
                secs >= least,
                "{mode}: {waiting} frames waited for {DELAY_MS} ms responses, yet the run took {secs} s"
            );
        },
    );
}

#[test]
fn flipped_leaf_blocks_are_dropped_counted_and_refetched() {
    // Flips land only on the first byte of a requested range inside a model's leaves section:
    // always a leaf block, which carries a CRC-32. The model index, tables and tiles are intact,
    // so the LOD (which does not depend on the cache) is the clean run's, frame by frame.
    let windows = |s: &Server| {
        let within = leaf_sections(s)
            .into_iter()
            .map(|(target, (start, end))| Window { target, start, end })
            .collect();
        // The opening requests of these small files hold the whole leaves section: flip its
        // first byte there too (a leaf block the client did not ask for, kept only if it checks).
        Fault::FlipRangeByte {
            every: 1,
            limit: 2,
            within,
            window_starts: true,
        }
    };
    clean_and_faulty(
        "client-fault-flip-leaves",
        &["--path", "walk", "--frames", "90"],
        windows,
        |mode, clean, bad, proxy| {
            let n = every_flip_refetched(proxy, bad, mode) as u64;
            assert_eq!(
                bad.sum("corrupt_blocks"),
                n,
                "{mode}: {n} leaf blocks were corrupted in transit; each must be dropped and counted"
            );
            assert_eq!(bad.sum("retries"), 0, "{mode}: the HTTP framing was intact");
            // Corrupt data is never drawn: with blocks missing, a frame draws less, never more.
            never_more(clean, bad, &format!("flipped leaf blocks, {mode}"));
            // Dropped blocks are fetched again next frame: the picture recovers.
            assert_eq!(
                clean.drawn().last(),
                bad.drawn().last(),
                "{mode}: the last frame did not recover from {n} corrupt leaf blocks"
            );
        },
    );
}

#[test]
fn flipped_bytes_anywhere_are_detected_and_refetched() {
    // Every 2nd range response, first data byte of its first part: tiles, model indexes, node
    // tables and blocks alike, all CRC-checked. A corrupt block or tile is dropped and counted
    // in corrupt_blocks; a corrupt model index or table is not a block: the model is opened
    // again next frame (neither corrupt_blocks nor retries count it). What must hold either
    // way: the byte is fetched again, and the run recovers.
    // The crown-hull ladder, under which every unit a flip lands on is still wanted afterwards.
    // Under a ladder without hull rungs, as the default is, a flipped block may be one the client
    // never wants again (seen once with `geometry:30,hemioct:0`: a block at byte 4096 of a
    // synthetic model, dropped, not asked for again), and a byte nobody wants need not come back.
    clean_and_faulty(
        "client-fault-flip",
        &[
            "--path",
            "walk",
            "--frames",
            "90",
            "--ladder",
            "geometry:150,hull0:60,hull1:30,hemioct:0",
        ],
        |_| Fault::FlipRangeByte {
            every: 2,
            limit: 3,
            within: Vec::new(),
            window_starts: false,
        },
        |mode, clean, bad, proxy| {
            let n = every_flip_refetched(proxy, bad, mode);
            // Some flips land on blocks or tiles, which the CRC check catches and counts
            // (measured: 2 of 3 flips in auto mode, 3 of 3 in single mode, in three runs each);
            // one counted per flip at most.
            let corrupt = bad.sum("corrupt_blocks");
            assert!(
                corrupt > 0 && corrupt <= n as u64,
                "{mode}: {n} bytes flipped, {corrupt} corrupt blocks detected"
            );
            // A model or tile that arrives a frame late starts seed 004's switch control a
            // frame late, so leaf counts may differ (either way) for a while; which trees are
            // drawn, and how, must not.
            let reps = |f: &Fly| f.drawn().last().map(|d| [d[2], d[3], d[4], d[5]]);
            assert_eq!(
                reps(clean),
                reps(bad),
                "{mode}: the last frame did not recover from {n} flipped bytes \
                 ([geometry, hull, billboard, pending] trees)"
            );
        },
    );
}

#[test]
fn unknown_scene_fails_with_a_message() {
    let dir = scratch("client-unknown-scene");
    let s = Server::start(&dir.join("data"), SMALL_DEMO);
    let err = fly_fails(&format!("http://{}/api/scenes/nope", s.addr), &["--retries", "1"]);
    assert!(
        err.contains("manifest") && err.contains("404") && err.contains("nope"),
        "no clear message for an unknown scene:\n{err}"
    );
}

#[test]
fn garbage_manifest_fails_with_a_message() {
    for body in [
        &b"{\"scene\": \"demo\", \"models\": [tr"[..],
        b"<html>not json</html>",
        b"{\"hello\": 1}",
    ] {
        let canned = CannedServer::start(CannedServer::json_200(body));
        let err = fly_fails(&format!("http://{}/api/scenes/demo", canned.addr), &["--retries", "1"]);
        assert!(canned.requests() > 0, "the client did not ask the canned server");
        assert!(
            err.contains("manifest") && err.contains("JSON"),
            "no clear message for the manifest {:?}:\n{err}",
            String::from_utf8_lossy(body)
        );
    }
}

#[test]
fn unreachable_server_fails_with_a_message() {
    // A port that was free a moment ago: nothing listens there.
    // (It gives up after its retries; `RUN_LIMIT` bounds the run in case it hangs instead. No
    // tighter wall-clock bound: on a loaded machine that measures the machine.)
    let port = canopy_e2e::net::free_port();
    let err = fly_fails(&format!("http://127.0.0.1:{port}/api/scenes/demo"), &["--retries", "2"]);
    assert!(err.contains("manifest"), "no clear message for a dead server:\n{err}");
}
