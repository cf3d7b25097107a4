//! A model of a network link, and its simulation on a clock: what a transfer of so many bytes
//! costs on a thin client's link, without the link.
//!
//! Conventions: times in seconds from the simulation's start, rates in bytes per second (the
//! presets are stated in bits per second, as their sources state them), sizes in bytes on the
//! wire (body, HTTP headers, multipart part headers and TCP/IP packet headers).
//!
//! The model, per request: the request waits for one of `connections` connections (the first
//! use of a connection pays one more round trip, its TCP handshake); it goes up at the uplink
//! rate, its first byte comes back one round trip after it was sent; its body then shares the
//! downlink equally with every other body in transfer (processor sharing, what TCP flows on one
//! bottleneck converge to), capped per flow by the Mathis bound when the link loses packets.
//!
//! What it leaves out: TCP slow start (a new flow reaches its share after a few round trips, not
//! at once), HTTP/2 multiplexing (one connection, one congestion window), head-of-line blocking,
//! queueing delay in the bottleneck's buffer, and retransmission timeouts. `benchmarks/log.md`
//! has its error against the kernel-shaped link.

use std::fmt;
use std::str::FromStr;

/// Response status line and headers of a range response, bytes (the Canopy server's are 230 to
/// 290; nginx's about the same).
pub const RESPONSE_HEADER_BYTES: u64 = 280;
/// Part headers and boundary of each part of a `multipart/byteranges` body, bytes.
pub const MULTIPART_PART_BYTES: u64 = 110;
/// Request line and headers of a range request, bytes, before its ranges.
pub const REQUEST_HEADER_BYTES: u64 = 160;
/// Bytes per range spec in a `Range` header.
pub const RANGE_SPEC_BYTES: u64 = 22;
/// TCP segment payload on a 1,500-byte MTU with timestamps.
pub const SEGMENT_PAYLOAD: f64 = 1448.0;
/// Ethernet, IP and TCP headers per segment (what a token bucket on an interface counts).
pub const SEGMENT_HEADERS: f64 = 66.0;
/// Connections per host a browser opens for HTTP/1.1 (Chrome, Firefox and Safari: 6).
pub const DEFAULT_CONNECTIONS: usize = 6;

/// A link: rates, round trip, connection limit, loss; optionally a downlink rate that changes
/// at given times.
#[derive(Debug, Clone, PartialEq)]
pub struct LinkModel {
    /// Name (a preset's, or the spec it was parsed from).
    pub name: String,
    /// Downlink, bytes/s (`f64::INFINITY`: no limit).
    pub down: f64,
    /// Uplink, bytes/s.
    pub up: f64,
    /// Round-trip time, seconds.
    pub rtt: f64,
    /// Most connections (requests in transfer) at once.
    pub connections: usize,
    /// Packet loss probability, 0..1.
    pub loss: f64,
    /// From time `t` (seconds), the downlink is `rate` bytes/s; sorted by time.
    pub down_steps: Vec<(f64, f64)>,
}

/// The named links `--link` accepts, with the public definitions they follow.
pub const PRESETS: &[(&str, f64, f64, f64, &str)] = &[
    // name, down Mbit/s, up Mbit/s, RTT ms, source
    (
        "loopback",
        f64::INFINITY,
        f64::INFINITY,
        0.0,
        "no link: every transfer is instant",
    ),
    ("slow4g", 1.6, 0.75, 150.0, "Lighthouse's mobile throttling (Slow 4G)"),
    ("fast4g", 8.1, 1.35, 165.0, "Chrome DevTools' Fast 4G"),
    ("3g-slow", 0.4, 0.4, 400.0, "WebPageTest's 3G Slow"),
    ("dash10", 10.0, 10.0, 38.0, "DASH-3D's evaluation links"),
    ("dash5", 5.0, 5.0, 38.0, "DASH-3D's evaluation links"),
    ("dash2.5", 2.5, 2.5, 38.0, "DASH-3D's evaluation links"),
];

/// Bits per second in a megabit per second.
const MBIT: f64 = 1e6;

impl LinkModel {
    /// No link: instant transfers.
    pub fn loopback() -> Self {
        Self::preset("loopback").unwrap_or_else(|| Self::symmetric("loopback", f64::INFINITY, 0.0))
    }

    /// A named preset ([`PRESETS`]).
    pub fn preset(name: &str) -> Option<Self> {
        let &(n, down, up, rtt, _) = PRESETS.iter().find(|p| p.0 == name)?;
        Some(Self {
            name: n.to_string(),
            down: down * MBIT / 8.0,
            up: up * MBIT / 8.0,
            rtt: rtt / 1e3,
            connections: DEFAULT_CONNECTIONS,
            loss: 0.0,
            down_steps: Vec::new(),
        })
    }

    /// A link of `mbit` Mbit/s both ways and `rtt_ms` round trip.
    pub fn symmetric(name: &str, mbit: f64, rtt_ms: f64) -> Self {
        Self {
            name: name.to_string(),
            down: mbit * MBIT / 8.0,
            up: mbit * MBIT / 8.0,
            rtt: rtt_ms / 1e3,
            connections: DEFAULT_CONNECTIONS,
            loss: 0.0,
            down_steps: Vec::new(),
        }
    }

    /// Whether transfers are instant.
    pub fn is_instant(&self) -> bool {
        self.down.is_infinite() && self.rtt == 0.0 && self.down_steps.is_empty()
    }

    /// The downlink rate at time `t`.
    pub fn down_at(&self, t: f64) -> f64 {
        self.down_steps
            .iter()
            .rev()
            .find(|(at, _)| *at <= t)
            .map_or(self.down, |s| s.1)
    }

    /// The next time after `t` at which the downlink rate changes.
    fn next_step(&self, t: f64) -> Option<f64> {
        self.down_steps.iter().map(|s| s.0).find(|&at| at > t)
    }

    /// One flow's rate cap from loss (Mathis et al. 1997: MSS / (RTT·√(2p/3))); infinite
    /// without loss.
    fn flow_cap(&self) -> f64 {
        if self.loss <= 0.0 || self.rtt <= 0.0 {
            return f64::INFINITY;
        }
        SEGMENT_PAYLOAD / (self.rtt * (2.0 * self.loss / 3.0).sqrt())
    }
}

impl fmt::Display for LinkModel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.down.is_infinite() {
            return write!(f, "{} (no limit)", self.name);
        }
        write!(
            f,
            "{} ({:.2} Mbit/s down, {:.2} up, {:.0} ms RTT, {} connections",
            self.name,
            self.down * 8.0 / MBIT,
            self.up * 8.0 / MBIT,
            self.rtt * 1e3,
            self.connections
        )?;
        if self.loss > 0.0 {
            write!(f, ", {:.2} % loss", self.loss * 100.0)?;
        }
        for (t, r) in &self.down_steps {
            write!(f, ", {:.2} Mbit/s from {t} s", r * 8.0 / MBIT)?;
        }
        write!(f, ")")
    }
}

/// Why a `--link` spec was refused.
#[derive(Debug, thiserror::Error)]
#[error(
    "bad link {spec:?}: {why} (a preset: {presets}; or MBIT,RTT_MS[,UP_MBIT[,LOSS_PERCENT]], and optionally @T=MBIT;T=MBIT for downlink changes at T seconds)"
)]
pub struct LinkSpecError {
    spec: String,
    why: String,
    presets: String,
}

impl FromStr for LinkModel {
    type Err = LinkSpecError;

    /// A preset name or `MBIT,RTT_MS[,UP_MBIT[,LOSS_PERCENT]]`, then optionally
    /// `@T=MBIT;T=MBIT…` (the downlink from T seconds on).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let err = |why: &str| LinkSpecError {
            spec: s.to_string(),
            why: why.to_string(),
            presets: PRESETS.iter().map(|p| p.0).collect::<Vec<_>>().join(", "),
        };
        let (base, steps) = s.split_once('@').map_or((s, None), |(b, st)| (b, Some(st)));
        let mut link = if let Some(l) = Self::preset(base.trim()) {
            l
        } else {
            let nums: Vec<f64> = base
                .split(',')
                .map(|x| x.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .map_err(|_| err("not a preset and not numbers"))?;
            if !(2..=4).contains(&nums.len()) {
                return Err(err("want 2 to 4 numbers"));
            }
            if nums.iter().any(|x| !x.is_finite() || *x < 0.0) || nums[0] <= 0.0 {
                return Err(err("rates must be positive, times and loss not negative"));
            }
            let mut l = Self::symmetric(base.trim(), nums[0], nums[1]);
            if let Some(&up) = nums.get(2) {
                if up <= 0.0 {
                    return Err(err("uplink must be positive"));
                }
                l.up = up * MBIT / 8.0;
            }
            if let Some(&loss) = nums.get(3) {
                if loss >= 50.0 {
                    return Err(err("loss must be under 50 %"));
                }
                l.loss = loss / 100.0;
            }
            l
        };
        if let Some(steps) = steps {
            for st in steps.split(';').filter(|x| !x.trim().is_empty()) {
                let (t, r) = st.split_once('=').ok_or_else(|| err("a step is T=MBIT"))?;
                let (t, r): (f64, f64) = match (t.trim().parse(), r.trim().parse()) {
                    (Ok(t), Ok(r)) => (t, r),
                    _ => return Err(err("a step is T=MBIT, two numbers")),
                };
                if !(t.is_finite() && t >= 0.0 && r.is_finite() && r > 0.0) {
                    return Err(err("a step needs a time ≥ 0 and a positive rate"));
                }
                link.down_steps.push((t, r * MBIT / 8.0));
            }
            link.down_steps.sort_by(|a, b| a.0.total_cmp(&b.0));
            link.name = s.to_string();
        }
        Ok(link)
    }
}

/// Bytes a range response carrying `ranges` body ranges of `body` bytes puts on the wire.
pub fn response_wire_bytes(body: u64, ranges: usize) -> f64 {
    let parts = if ranges > 1 {
        ranges as u64 * MULTIPART_PART_BYTES
    } else {
        0
    };
    let payload = (body + RESPONSE_HEADER_BYTES + parts) as f64;
    payload * (1.0 + SEGMENT_HEADERS / SEGMENT_PAYLOAD)
}

/// Bytes the request for `ranges` ranges puts on the wire.
pub fn request_wire_bytes(ranges: usize) -> f64 {
    let payload = (REQUEST_HEADER_BYTES + ranges as u64 * RANGE_SPEC_BYTES) as f64;
    payload + SEGMENT_HEADERS
}

/// A transfer's id in a [`LinkSim`].
pub type TransferId = u64;

#[derive(Debug, Clone)]
struct Waiting {
    id: TransferId,
    submitted: f64,
    /// Tie-break among transfers submitted at the same time (deterministic order).
    order: u64,
    up: f64,
    down: f64,
}

#[derive(Debug, Clone)]
struct Moving {
    id: TransferId,
    /// When its first byte arrives; the body moves from then on.
    first_byte: f64,
    remaining: f64,
}

/// Counters of a [`LinkSim`].
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct LinkCounters {
    /// Bytes delivered down the link (wire bytes).
    pub wire_bytes: f64,
    /// Seconds during which some transfer was waiting or moving.
    pub pending_s: f64,
    /// What the downlink could have carried during `pending_s`, bytes.
    pub capacity_bytes: f64,
    /// Transfers completed.
    pub transfers: u64,
}

impl LinkCounters {
    /// Share of the downlink used while work was pending (1 on an instant link).
    pub fn utilisation(&self) -> f64 {
        if self.capacity_bytes.is_finite() && self.capacity_bytes > 0.0 {
            self.wire_bytes / self.capacity_bytes
        } else {
            1.0
        }
    }
}

/// The link's state on a clock: transfers submitted, waiting for a connection, moving, done.
/// Deterministic: the same submissions at the same times give the same completions, whatever
/// order they were submitted in within one instant (`order` breaks ties).
#[derive(Debug)]
pub struct LinkSim {
    model: LinkModel,
    now: f64,
    next_id: TransferId,
    waiting: Vec<Waiting>,
    moving: Vec<Moving>,
    /// Connections opened so far (a new one pays a handshake round trip).
    opened: usize,
    counters: LinkCounters,
}

/// Completion times closer than this are the same instant, seconds.
const EPS_S: f64 = 1e-9;

impl LinkSim {
    /// An idle link at time 0.
    pub fn new(model: LinkModel) -> Self {
        Self {
            model,
            now: 0.0,
            next_id: 0,
            waiting: Vec::new(),
            moving: Vec::new(),
            opened: 0,
            counters: LinkCounters::default(),
        }
    }

    /// The model.
    pub fn model(&self) -> &LinkModel {
        &self.model
    }

    /// The clock.
    pub fn now(&self) -> f64 {
        self.now
    }

    /// Counters so far.
    pub fn counters(&self) -> LinkCounters {
        self.counters
    }

    /// Transfers submitted and not completed.
    pub fn in_flight(&self) -> usize {
        self.waiting.len() + self.moving.len()
    }

    /// Submits a transfer now: `up` bytes up, `down` bytes down (wire bytes); `order` breaks
    /// ties with transfers submitted at the same instant. It starts at the next [`Self::advance`].
    pub fn submit(&mut self, up: f64, down: f64, order: u64) -> TransferId {
        let id = self.next_id;
        self.next_id += 1;
        self.waiting.push(Waiting {
            id,
            submitted: self.now,
            order,
            up,
            down,
        });
        id
    }

    /// Starts waiting transfers on free connections, oldest first.
    fn start_waiting(&mut self) {
        if self.waiting.is_empty() {
            return;
        }
        self.waiting
            .sort_by(|a, b| a.submitted.total_cmp(&b.submitted).then(a.order.cmp(&b.order)));
        let limit = self.model.connections.max(1);
        while self.moving.len() < limit && !self.waiting.is_empty() {
            let w = self.waiting.remove(0);
            // A connection not opened before pays its handshake.
            let handshake = if self.moving.len() >= self.opened {
                self.opened += 1;
                self.model.rtt
            } else {
                0.0
            };
            let up_s = if self.model.up.is_finite() {
                w.up / self.model.up
            } else {
                0.0
            };
            self.moving.push(Moving {
                id: w.id,
                first_byte: self.now + handshake + up_s + self.model.rtt,
                remaining: w.down,
            });
        }
    }

    /// The next time something happens (a first byte, a completion, a rate change), if any
    /// transfer is pending.
    pub fn next_event(&mut self) -> Option<f64> {
        self.start_waiting();
        if self.moving.is_empty() {
            return None;
        }
        let (share, _) = self.share();
        let mut next = f64::INFINITY;
        for m in &self.moving {
            if m.first_byte > self.now + EPS_S {
                next = next.min(m.first_byte);
            } else if share.is_infinite() || m.remaining <= 0.0 {
                next = next.min(self.now);
            } else {
                next = next.min(self.now + m.remaining / share);
            }
        }
        if let Some(step) = self.model.next_step(self.now) {
            next = next.min(step);
        }
        Some(next.max(self.now))
    }

    /// Each moving body's rate now, and how many bodies are moving.
    fn share(&self) -> (f64, usize) {
        let n = self.moving.iter().filter(|m| m.first_byte <= self.now + EPS_S).count();
        if n == 0 {
            return (0.0, 0);
        }
        let rate = self.model.down_at(self.now) / n as f64;
        (rate.min(self.model.flow_cap()), n)
    }

    /// Runs the clock to `t` (not backwards); returns the transfers completed on the way, each
    /// with its completion time, in completion order.
    pub fn advance(&mut self, t: f64) -> Vec<(TransferId, f64)> {
        let mut done = Vec::new();
        loop {
            let Some(next) = self.next_event() else {
                if t > self.now {
                    self.now = t;
                }
                break;
            };
            let step_to = next.min(t).max(self.now);
            let dt = step_to - self.now;
            let (share, moving) = self.share();
            if dt > 0.0 {
                self.counters.pending_s += dt;
                self.counters.capacity_bytes += self.model.down_at(self.now) * dt;
                if moving > 0 {
                    for m in self.moving.iter_mut().filter(|m| m.first_byte <= self.now + EPS_S) {
                        let moved = (share * dt).min(m.remaining);
                        m.remaining -= moved;
                        self.counters.wire_bytes += moved;
                    }
                }
            }
            self.now = step_to;
            // Bodies done: instantly on an unlimited link, else when nothing remains (within a
            // byte's rounding).
            let now = self.now;
            let mut k = 0;
            while k < self.moving.len() {
                let m = &self.moving[k];
                let started = m.first_byte <= now + EPS_S;
                // Within a byte's rounding, or less than the clock can resolve at this rate.
                let finished = started && (share.is_infinite() || m.remaining <= 1e-6 + share * 4.0 * EPS_S);
                if finished {
                    let m = self.moving.remove(k);
                    if share.is_infinite() {
                        self.counters.wire_bytes += m.remaining.max(0.0);
                    }
                    self.counters.transfers += 1;
                    done.push((m.id, now));
                } else {
                    k += 1;
                }
            }
            if next > t {
                break;
            }
        }
        done
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn link(mbit: f64, rtt_ms: f64) -> LinkModel {
        LinkModel::symmetric("t", mbit, rtt_ms)
    }

    fn run_all(sim: &mut LinkSim) -> Vec<(TransferId, f64)> {
        sim.advance(sim.now() + 1e4)
    }

    #[test]
    fn one_transfer_costs_handshake_round_trip_and_bytes_over_rate() {
        // 8 Mbit/s = 1 MB/s, 100 ms: handshake 0.1 + request up + 0.1 + 1 MB at 1 MB/s.
        let mut sim = LinkSim::new(link(8.0, 100.0));
        sim.submit(0.0, 1e6, 0);
        let done = run_all(&mut sim);
        assert_eq!(done.len(), 1);
        assert!((done[0].1 - 1.2).abs() < 1e-6, "{done:?}");
        // A second one on the now open connection: no handshake.
        sim.submit(0.0, 1e6, 0);
        let t0 = sim.now();
        let done = run_all(&mut sim);
        assert!((done[0].1 - t0 - 1.1).abs() < 1e-6, "{done:?}");
    }

    #[test]
    fn concurrent_bodies_share_the_downlink() {
        let mut sim = LinkSim::new(link(8.0, 0.0));
        sim.submit(0.0, 1e6, 0);
        sim.submit(0.0, 1e6, 1);
        let done = run_all(&mut sim);
        // Both move at 0.5 MB/s and end together at 2 s.
        assert_eq!(done.len(), 2);
        for (_, t) in done {
            assert!((t - 2.0).abs() < 1e-6);
        }
        assert!((sim.counters().utilisation() - 1.0).abs() < 1e-9);
    }

    #[test]
    fn connection_limit_queues_the_rest() {
        let mut l = link(8.0, 0.0);
        l.connections = 1;
        let mut sim = LinkSim::new(l);
        sim.submit(0.0, 1e6, 1);
        sim.submit(0.0, 1e6, 0);
        let done = run_all(&mut sim);
        // Order 0 goes first, whatever the submission order.
        assert_eq!(done[0].0, 1);
        assert!(
            (done[0].1 - 1.0).abs() < 1e-6 && (done[1].1 - 2.0).abs() < 1e-6,
            "{done:?}"
        );
    }

    #[test]
    fn loopback_is_instant_and_advance_stops_at_t() {
        let mut sim = LinkSim::new(LinkModel::loopback());
        sim.submit(100.0, 5e6, 0);
        let done = sim.advance(0.0);
        assert_eq!(done, vec![(0, 0.0)]);
        let mut sim = LinkSim::new(link(8.0, 0.0));
        sim.submit(0.0, 1e6, 0);
        assert!(sim.advance(0.5).is_empty());
        assert_eq!(sim.now(), 0.5);
        assert_eq!(sim.advance(1.0).len(), 1);
    }

    #[test]
    fn rate_steps_apply_from_their_time() {
        let mut l = link(8.0, 0.0);
        l.down_steps = vec![(0.5, 0.25e6)];
        let mut sim = LinkSim::new(l);
        sim.submit(0.0, 1e6, 0);
        // 0.5 MB in the first 0.5 s, the other 0.5 MB at 0.25 MB/s: 2 s more.
        let done = run_all(&mut sim);
        assert!((done[0].1 - 2.5).abs() < 1e-6, "{done:?}");
    }

    #[test]
    fn loss_caps_each_flow() {
        let mut l = link(1000.0, 100.0);
        l.loss = 0.01;
        let cap = l.flow_cap();
        // 1448 / (0.1 · √(0.02/3)) ≈ 177 kB/s, far under 125 MB/s.
        assert!((cap - 177_337.0).abs() < 100.0, "{cap}");
    }

    #[test]
    fn specs_parse_and_bad_ones_say_why() {
        let l: LinkModel = "slow4g".parse().expect("test setup");
        assert!((l.down - 200_000.0).abs() < 1e-6 && (l.up - 93_750.0).abs() < 1e-6 && l.rtt == 0.15);
        let l: LinkModel = "10,38".parse().expect("test setup");
        assert_eq!(l.down, 1.25e6);
        let l: LinkModel = "10,38,2,1".parse().expect("test setup");
        assert_eq!((l.up, l.loss), (0.25e6, 0.01));
        let l: LinkModel = "dash10@10=1.6;20=10".parse().expect("test setup");
        assert_eq!(l.down_steps, vec![(10.0, 200_000.0), (20.0, 1.25e6)]);
        assert_eq!(l.down_at(15.0), 200_000.0);
        for bad in [
            "",
            "fast",
            "0,10",
            "-1,10",
            "1",
            "1,2,3,4,5",
            "nan,3",
            "1,2,0",
            "1,2,3,60",
            "dash5@x",
            "dash5@3=0",
        ] {
            let e = bad.parse::<LinkModel>().expect_err("refused").to_string();
            assert!(e.contains("bad link") && e.contains("slow4g"), "{bad}: {e}");
        }
        assert!(LinkModel::loopback().is_instant());
    }

    #[test]
    fn wire_bytes_count_headers() {
        assert!(response_wire_bytes(0, 1) > RESPONSE_HEADER_BYTES as f64);
        let one = response_wire_bytes(10_000, 1);
        let three = response_wire_bytes(10_000, 3);
        assert!(
            (three - one - 3.0 * MULTIPART_PART_BYTES as f64 * (1.0 + SEGMENT_HEADERS / SEGMENT_PAYLOAD)).abs() < 1e-6
        );
        assert!(request_wire_bytes(2) > request_wire_bytes(1));
    }
}
