//! Presence that sheds (issue 23, item 6), on the real `canopy-server serve` over loopback.
//!
//! The load: well-behaved viewers on one scene, most at 10 Hz and some at 95 Hz (under the 100
//! frames a second limit), about 10,000 poses a second in all: ten times the rate at which the
//! old per-pose fan-out collapsed (about 1,000 poses a second: 120 viewers at 10 Hz lost 24 in
//! 20 s, 150 lost nearly all). Beside them, viewers that never read and one of each kind of
//! abuse (a ping flood, a pose flood over the limit, a frame over 4 KiB, invalid UTF-8, an
//! unmasked frame, a binary frame). Every well-behaved viewer must stay connected and keep
//! hearing from the others; every abuser must get a 1008 close with its reason.
//!
//! Viewer counts: one scene takes at most 256 viewers (`max_viewers_per_scene`), and one thread
//! per viewer on a 2-core machine parses what the server sends (capped at
//! `MAX_FANOUT_PER_S` = 300,000 poses a second), so 240 well-behaved viewers plus the abusers is
//! what fits. `CANOPY_PRESENCE_*` variables change the load for the figures run (see
//! `benchmarks/runs/2026-12-04-presence/run.sh`), which also points it at another server binary.

use std::collections::HashMap;
use std::io::{ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use canopy_e2e::net::{Server, http};
use canopy_e2e::scratch;
use serde_json::{Value, json};

const PATH: &str = "/api/scenes/demo/live";

/// The load of one run.
#[derive(Debug, Clone)]
struct Load {
    /// Viewers at 10 Hz.
    steady: usize,
    /// Viewers at 95 Hz.
    fast: usize,
    /// Viewers that read their welcome and nothing after.
    never_read: usize,
    /// Whether to add one of each abuse.
    abuse: bool,
    /// Length of the run.
    run: Duration,
}

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// The server under test: the workspace's binary, or `CANOPY_PRESENCE_SERVER` (an older build
/// for the baseline figures).
enum Running {
    Ours(Server),
    Other(Child, SocketAddr),
}

impl Running {
    fn start(name: &str) -> Self {
        let dir = scratch(name);
        let args = ["--demo-synthetic", "2", "--demo-trees", "400"];
        let Ok(bin) = std::env::var("CANOPY_PRESENCE_SERVER") else {
            return Self::Ours(Server::start(&dir.join("data"), &args));
        };
        let mut child = Command::new(bin)
            .arg("serve")
            .arg("--data")
            .arg(dir.join("data"))
            .args(["--addr", "127.0.0.1:0"])
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("spawn the server");
        let stdout = child.stdout.take().expect("stdout");
        let mut lines = std::io::BufRead::lines(std::io::BufReader::new(stdout));
        let addr = lines
            .find_map(|l| {
                l.ok()?
                    .strip_prefix("canopy-server listening on http://")
                    .map(|a| a.trim().parse().expect("address"))
            })
            .expect("the server's listening line");
        // Keep draining stdout so the server never blocks on it.
        std::thread::spawn(move || lines.for_each(drop));
        Self::Other(child, addr)
    }

    fn addr(&self) -> SocketAddr {
        match self {
            Self::Ours(s) => s.addr,
            Self::Other(_, a) => *a,
        }
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        if let Self::Other(c, _) = self {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// One client frame (masked unless `unmasked`).
fn frame(opcode: u8, payload: &[u8], unmasked: bool) -> Vec<u8> {
    let mut f = vec![0x80 | opcode];
    let mask_bit = if unmasked { 0 } else { 0x80 };
    if payload.len() < 126 {
        f.push(mask_bit | payload.len() as u8);
    } else {
        f.push(mask_bit | 0x7e);
        f.extend_from_slice(&(payload.len() as u16).to_be_bytes());
    }
    if unmasked {
        f.extend_from_slice(payload);
    } else {
        let mask = [0x5au8, 0x13, 0xc7, 0x2e];
        f.extend_from_slice(&mask);
        f.extend(payload.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
    }
    f
}

/// A server frame.
#[derive(Debug)]
enum In {
    Text(Vec<u8>),
    Close(u16, String),
}

/// A raw WebSocket client over a blocking socket with a receive buffer.
struct Ws {
    s: TcpStream,
    buf: Vec<u8>,
}

impl Ws {
    fn connect(addr: SocketAddr) -> Result<Self, u16> {
        let mut s = TcpStream::connect(addr).expect("connect");
        s.set_nodelay(true).expect("nodelay");
        s.set_read_timeout(Some(Duration::from_secs(20))).expect("timeout");
        let req = format!(
            "GET {PATH} HTTP/1.1\r\nHost: {addr}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
             Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
        );
        s.write_all(req.as_bytes()).expect("send upgrade");
        let mut head = Vec::new();
        let mut b = [0u8; 1];
        while !head.ends_with(b"\r\n\r\n") {
            s.read_exact(&mut b).expect("upgrade response");
            head.push(b[0]);
        }
        let code = String::from_utf8_lossy(&head)
            .split(' ')
            .nth(1)
            .and_then(|c| c.parse().ok())
            .unwrap_or(0);
        if code == 101 {
            Ok(Self { s, buf: Vec::new() })
        } else {
            Err(code)
        }
    }

    /// The next complete frame in the buffer.
    fn take(&mut self) -> Option<In> {
        loop {
            let b = &self.buf;
            if b.len() < 2 {
                return None;
            }
            let (len, at) = match b[1] & 0x7f {
                126 if b.len() >= 4 => (usize::from(u16::from_be_bytes([b[2], b[3]])), 4),
                127 if b.len() >= 10 => (u64::from_be_bytes(b[2..10].try_into().ok()?) as usize, 10),
                126 | 127 => return None,
                n => (usize::from(n), 2),
            };
            if b.len() < at + len {
                return None;
            }
            let opcode = b[0] & 0x0f;
            let payload = b[at..at + len].to_vec();
            self.buf.drain(..at + len);
            match opcode {
                1 => return Some(In::Text(payload)),
                8 => {
                    let code = payload.get(..2).map_or(1005, |c| u16::from_be_bytes([c[0], c[1]]));
                    let reason = String::from_utf8_lossy(payload.get(2..).unwrap_or_default()).into_owned();
                    return Some(In::Close(code, reason));
                }
                _ => {}
            }
        }
    }

    /// Reads until `deadline` or until at least one frame is complete; `false` at the end of
    /// the stream (EOF or reset).
    fn fill(&mut self, deadline: Instant) -> bool {
        let wait = deadline.saturating_duration_since(Instant::now());
        if wait.is_zero() {
            return true;
        }
        self.s.set_read_timeout(Some(wait)).expect("timeout");
        let mut chunk = vec![0u8; 64 << 10];
        match self.s.read(&mut chunk) {
            Ok(0) => false,
            Ok(n) => {
                self.buf.extend_from_slice(&chunk[..n]);
                true
            }
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted
                ) =>
            {
                true
            }
            Err(_) => false,
        }
    }

    /// The next frame, waiting up to `within`.
    fn next(&mut self, within: Duration) -> Option<In> {
        let deadline = Instant::now() + within;
        loop {
            if let Some(f) = self.take() {
                return Some(f);
            }
            if Instant::now() >= deadline || !self.fill(deadline) {
                return None;
            }
        }
    }

    /// Reads frames until a close frame (its code and reason) or the end of the stream (`None`).
    fn until_close(&mut self, within: Duration) -> Option<(u16, String)> {
        let deadline = Instant::now() + within;
        while Instant::now() < deadline {
            match self.next(deadline.saturating_duration_since(Instant::now())) {
                Some(In::Close(code, reason)) => return Some((code, reason)),
                Some(In::Text(_)) => {}
                None => return None,
            }
        }
        None
    }

    /// The welcome's viewer id.
    fn welcome(&mut self) -> u64 {
        match self.next(Duration::from_secs(20)) {
            Some(In::Text(t)) => {
                let v: Value = serde_json::from_slice(&t).expect("JSON");
                assert_eq!(v["type"], "welcome", "{v}");
                v["viewer"].as_u64().expect("viewer id")
            }
            other => panic!("expected a welcome, got {other:?}"),
        }
    }
}

/// The number after `key` in `text`.
fn number_after(text: &[u8], key: &[u8]) -> Option<f64> {
    let at = text.windows(key.len()).position(|w| w == key)? + key.len();
    let rest = &text[at..];
    let end = rest
        .iter()
        .position(|c| !(c.is_ascii_digit() || matches!(c, b'-' | b'.' | b'e' | b'E' | b'+')))
        .unwrap_or(rest.len());
    std::str::from_utf8(&rest[..end]).ok()?.parse().ok()
}

fn contains(text: &[u8], key: &[u8]) -> bool {
    text.windows(key.len()).any(|w| w == key)
}

/// A pose's send time: its position's y (see [`behave`]).
fn sent_ms(text: &[u8]) -> Option<f64> {
    let key = br#""position":["#;
    let at = text.windows(key.len()).position(|w| w == key)? + key.len();
    let rest = &text[at..];
    let comma = rest.iter().position(|&c| c == b',')?;
    number_after(&rest[comma..], b",")
}

/// What one well-behaved viewer saw.
#[derive(Debug, Default)]
struct Seen {
    id: u64,
    hz: f64,
    presence: u64,
    /// When each other viewer was last heard from.
    last_from: HashMap<u64, Instant>,
    /// Pose age on arrival (send to receipt), ms.
    ages_ms: Vec<f32>,
    /// How the connection ended before the run did: a close frame, or `None` for EOF/reset.
    #[allow(clippy::option_option)]
    ended: Option<Option<(u16, String)>>,
}

/// A well-behaved viewer: poses at `hz` (position y carries the send time, ms since `epoch`),
/// reading everything, until `end`.
fn behave(mut ws: Ws, id: u64, hz: f64, epoch: Instant, end: Instant) -> Seen {
    let mut seen = Seen {
        id,
        hz,
        ..Seen::default()
    };
    let period = Duration::from_secs_f64(1.0 / hz);
    // Spread the first sends over one period, so the viewers do not pose in lockstep.
    let mut next_send = Instant::now() + period.mul_f64((id % 97) as f64 / 97.0);
    let mut k = 0u32;
    loop {
        let now = Instant::now();
        if now >= end {
            return seen;
        }
        if now >= next_send {
            let t = now.duration_since(epoch).as_millis() as f32;
            let pose = format!(r#"{{"type":"pose","position":[{id},{t},{k}],"orientation":[0,0,0,1]}}"#);
            k += 1;
            if ws.s.write_all(&frame(1, pose.as_bytes(), false)).is_err() {
                seen.ended = Some(ws.until_close(Duration::from_secs(2)));
                return seen;
            }
            next_send += period;
        }
        while let Some(f) = ws.take() {
            match f {
                In::Text(t) => {
                    if contains(&t, br#""type":"presence""#) {
                        seen.presence += 1;
                        let at = Instant::now();
                        if let Some(from) = number_after(&t, br#""viewer":"#) {
                            seen.last_from.insert(from as u64, at);
                        }
                        if let Some(sent) = sent_ms(&t) {
                            seen.ages_ms
                                .push(at.duration_since(epoch).as_secs_f32() * 1000.0 - sent as f32);
                        }
                    }
                }
                In::Close(code, reason) => {
                    seen.ended = Some(Some((code, reason)));
                    return seen;
                }
            }
        }
        if !ws.fill(next_send.min(end)) {
            seen.ended = Some(None);
            return seen;
        }
    }
}

/// One abuse: what it sends after its welcome.
fn abuses() -> Vec<(&'static str, Vec<u8>, &'static str)> {
    let pose = br#"{"type":"pose","position":[0,0,0],"orientation":[0,0,0,1]}"#;
    vec![
        (
            "ping flood",
            (0..300).flat_map(|_| frame(9, b"hi", false)).collect(),
            "too many messages",
        ),
        (
            "pose flood",
            (0..300).flat_map(|_| frame(1, pose, false)).collect(),
            "too many messages",
        ),
        ("frame over 4 KiB", frame(1, &[b' '; 5000], false), "Message too long"),
        ("invalid UTF-8", frame(1, &[0xff, 0xfe, 0xfd], false), "UTF-8"),
        ("unmasked frame", frame(1, pose, true), "unmasked"),
        ("binary frame", frame(2, b"\x01\x02", false), "binary"),
    ]
}

fn percentile(v: &mut [f32], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f32::total_cmp);
    let i = ((v.len() as f64 * p).ceil() as usize).clamp(1, v.len()) - 1;
    f64::from(v[i])
}

fn metric(addr: SocketAddr, name: &str) -> i64 {
    let text = String::from_utf8(http(addr, "GET", "/metrics", &[], None).body).expect("utf8");
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or(-1)
}

/// An abuse, its close (code, reason) if any, and the reason it should have.
type Abused = (&'static str, Option<(u16, String)>, &'static str);

/// Runs one load and returns its figures and what each viewer saw.
fn run(load: &Load, name: &str) -> (Value, Vec<Seen>, Vec<Abused>) {
    let server = Running::start(name);
    let addr = server.addr();
    let epoch = Instant::now();
    // Connect everyone first (sequentially: the upgrade is cheap), then start the clock.
    let mut good = Vec::new();
    for k in 0..load.steady + load.fast {
        let mut ws = Ws::connect(addr).unwrap_or_else(|c| panic!("viewer {k}: upgrade answered {c}"));
        let id = ws.welcome();
        good.push((ws, id, if k < load.steady { 10.0 } else { 95.0 }));
    }
    let mut silent = Vec::new();
    for _ in 0..load.never_read {
        let mut ws = Ws::connect(addr).expect("upgrade");
        ws.welcome();
        silent.push(ws);
    }
    let connected = epoch.elapsed();
    let end = Instant::now() + load.run;
    let threads: Vec<_> = good
        .into_iter()
        .map(|(ws, id, hz)| std::thread::spawn(move || behave(ws, id, hz, epoch, end)))
        .collect();
    // The abusers start a second in, when the load is up.
    std::thread::sleep(Duration::from_secs(1));
    let abusers: Vec<_> = if load.abuse {
        abuses()
            .into_iter()
            .map(|(what, bytes, expect)| {
                let mut ws = Ws::connect(addr).expect("upgrade");
                ws.welcome();
                std::thread::spawn(move || {
                    let _ = ws.s.write_all(&bytes);
                    (what, ws.until_close(Duration::from_secs(10)), expect)
                })
            })
            .collect()
    } else {
        Vec::new()
    };
    // The API keeps answering: /healthz every 200 ms through the run.
    let mut healthz = Vec::new();
    while Instant::now() + Duration::from_millis(300) < end {
        let t0 = Instant::now();
        assert_eq!(http(addr, "GET", "/healthz", &[], None).status, 200);
        healthz.push(t0.elapsed().as_secs_f32() * 1000.0);
        std::thread::sleep(Duration::from_millis(200));
    }
    let seen: Vec<Seen> = threads.into_iter().map(|t| t.join().expect("viewer thread")).collect();
    let abused: Vec<_> = abusers.into_iter().map(|t| t.join().expect("abuser thread")).collect();
    let viewers_after = metric(addr, "canopy_live_viewers");
    let dropped_slow = metric(addr, "canopy_live_dropped_slow_total");
    // Never-readers: did the server let them go (their sockets take a while to fill)?
    let silent_closed = silent
        .iter_mut()
        .map(|ws| {
            ws.s.set_nonblocking(true).expect("nonblocking");
            let mut b = vec![0u8; 64 << 10];
            loop {
                match ws.s.read(&mut b) {
                    Ok(0) => break true,
                    Ok(_) => {}
                    Err(e) if e.kind() == ErrorKind::WouldBlock => break false,
                    Err(_) => break true,
                }
            }
        })
        .filter(|&closed| closed)
        .count();

    let window = Duration::from_secs(3);
    let ids: Vec<u64> = seen.iter().map(|s| s.id).collect();
    let mut fresh_share: Vec<f32> = seen
        .iter()
        .map(|s| {
            let heard = ids
                .iter()
                .filter(|&&o| o != s.id && s.last_from.get(&o).is_some_and(|&t| end.duration_since(t) < window))
                .count();
            heard as f32 / (ids.len() - 1).max(1) as f32
        })
        .collect();
    let mut ages: Vec<f32> = seen.iter().flat_map(|s| s.ages_ms.iter().copied()).collect();
    let received: u64 = seen.iter().map(|s| s.presence).sum();
    let dropped_good = seen.iter().filter(|s| s.ended.is_some()).count();
    let secs = load.run.as_secs_f64();
    let poses_in = (load.steady as f64 * 10.0 + load.fast as f64 * 95.0) * secs;
    let figures = json!({
        "steady_10hz": load.steady,
        "fast_95hz": load.fast,
        "never_read": load.never_read,
        "abusers": abused.len(),
        "run_s": secs,
        "connect_s": connected.as_secs_f64(),
        "poses_sent_per_s": poses_in / secs,
        "presence_received_per_s": received as f64 / secs,
        "well_behaved_dropped": dropped_good,
        "well_behaved_end_reasons": seen.iter().filter_map(|s| s.ended.clone()).map(|e| format!("{e:?}")).take(5).collect::<Vec<_>>(),
        "fresh_share_last_3s_min": fresh_share.iter().copied().fold(f32::INFINITY, f32::min),
        "fresh_share_last_3s_p50": percentile(&mut fresh_share, 0.5),
        "pose_age_ms_p50": percentile(&mut ages, 0.5),
        "pose_age_ms_p99": percentile(&mut ages, 0.99),
        "healthz_ms_p50": percentile(&mut healthz, 0.5),
        "healthz_ms_p99": percentile(&mut healthz, 0.99),
        "healthz_ms_max": healthz.iter().copied().fold(0.0f32, f32::max),
        "never_read_closed": silent_closed,
        "abusers_closed": abused.iter().map(|(w, c, _)| json!({"abuse": w, "close": c.as_ref().map(|(code, r)| json!({"code": code, "reason": r}))})).collect::<Vec<_>>(),
        "metric_live_viewers_after": viewers_after,
        "metric_dropped_slow_total": dropped_slow,
    });
    eprintln!("PRESENCE_FIGURES {figures}");
    drop(server);
    (figures, seen, abused)
}

#[test]
fn presence_at_ten_times_the_breaking_load_keeps_every_well_behaved_viewer() {
    let load = Load {
        steady: env_or("CANOPY_PRESENCE_STEADY", 150),
        fast: env_or("CANOPY_PRESENCE_FAST", 90),
        never_read: env_or("CANOPY_PRESENCE_NEVER_READ", 3),
        abuse: true,
        run: Duration::from_secs_f64(env_or("CANOPY_PRESENCE_SECONDS", 12.0)),
    };
    let t0 = Instant::now();
    let (figures, seen, abused) = run(&load, "presence-shedding");
    eprintln!("whole run: {:?}", t0.elapsed());
    if let Ok(path) = std::env::var("CANOPY_PRESENCE_FIGURES") {
        std::fs::write(path, figures.to_string()).expect("write figures");
    }
    for s in &seen {
        assert!(
            s.ended.is_none(),
            "well-behaved viewer {} ({} Hz) was dropped: {:?}",
            s.id,
            s.hz,
            s.ended
        );
    }
    let share = figures["fresh_share_last_3s_min"].as_f64().expect("share");
    assert!(
        share >= 0.9,
        "a well-behaved viewer heard from only {share:.2} of the others in the last 3 s"
    );
    for (what, close, expect) in &abused {
        match close {
            Some((code, reason)) => {
                assert_eq!(*code, 1008, "{what}: {reason}");
                assert!(reason.contains(expect), "{what}: reason {reason:?} lacks {expect:?}");
            }
            None => panic!("{what}: no close frame"),
        }
    }
}
