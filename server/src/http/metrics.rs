//! Prometheus metrics, kept in atomics and written in the text exposition format.

use std::fmt::Write as _;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering::Relaxed};
use std::time::Duration;

/// Route classes counted separately.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Route {
    /// `/assets/…`.
    Assets = 0,
    /// `/api/…` except the WebSocket.
    Api = 1,
    /// `/api/scenes/{id}/live`.
    Live = 2,
    /// Anything else (`/healthz`, `/metrics`, 404s).
    Other = 3,
}

const ROUTES: [&str; 4] = ["assets", "api", "live", "other"];

/// The stage at which a connection ran out of time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Reading a request head (from accept, or from its first byte on a kept-alive connection).
    Header = 0,
    /// Reading a request body.
    Body = 1,
    /// Waiting for the next request on a kept-alive connection.
    Idle = 2,
    /// Writing a response the client does not take.
    Write = 3,
}

const STAGES: [&str; 4] = ["header", "body", "idle", "write"];

/// What the connection bound did to make room.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shed {
    /// Closed a connection that had no request in flight, to admit a new one.
    Evicted = 0,
    /// Answered a new connection 503 and closed it: no connection could be evicted.
    Refused = 1,
}

const SHEDS: [&str; 2] = ["evicted", "refused"];
const LATENCY_BUCKETS_S: [f64; 12] = [
    0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5, 2.5,
];
const RANGE_BUCKETS: [f64; 9] = [0.0, 1.0, 2.0, 4.0, 8.0, 16.0, 64.0, 256.0, 1024.0];

#[derive(Debug)]
struct Histogram<const N: usize> {
    bounds: [f64; N],
    counts: [AtomicU64; N],
    count: AtomicU64,
    /// Sum in micro-units (microseconds, or ranges × 1e6) to stay integral.
    sum_micro: AtomicU64,
}

impl<const N: usize> Histogram<N> {
    fn new(bounds: [f64; N]) -> Self {
        Self {
            bounds,
            counts: std::array::from_fn(|_| AtomicU64::new(0)),
            count: AtomicU64::new(0),
            sum_micro: AtomicU64::new(0),
        }
    }

    fn observe(&self, v: f64) {
        if let Some(k) = self.bounds.iter().position(|&b| v <= b) {
            self.counts[k].fetch_add(1, Relaxed);
        }
        self.count.fetch_add(1, Relaxed);
        self.sum_micro.fetch_add((v * 1e6) as u64, Relaxed);
    }

    fn write(&self, out: &mut String, name: &str, labels: &str) {
        let sep = if labels.is_empty() { "" } else { "," };
        let mut cum = 0;
        for (b, c) in self.bounds.iter().zip(&self.counts) {
            cum += c.load(Relaxed);
            let _ = writeln!(out, "{name}_bucket{{{labels}{sep}le=\"{b}\"}} {cum}");
        }
        let count = self.count.load(Relaxed);
        let _ = writeln!(out, "{name}_bucket{{{labels}{sep}le=\"+Inf\"}} {count}");
        let _ = writeln!(
            out,
            "{name}_sum{{{labels}}} {}",
            self.sum_micro.load(Relaxed) as f64 / 1e6
        );
        let _ = writeln!(out, "{name}_count{{{labels}}} {count}");
    }
}

/// The server's metrics.
#[derive(Debug)]
pub struct Metrics {
    requests: [[AtomicU64; 5]; 4],
    bytes: [AtomicU64; 4],
    latency: [Histogram<12>; 4],
    ranges: Histogram<9>,
    viewers: AtomicI64,
    dropped_slow: AtomicU64,
    edits: AtomicU64,
    connections: AtomicI64,
    in_flight: AtomicI64,
    timeouts: [AtomicU64; 4],
    shed: [AtomicU64; 2],
}

impl Default for Metrics {
    fn default() -> Self {
        Self {
            requests: std::array::from_fn(|_| std::array::from_fn(|_| AtomicU64::new(0))),
            bytes: std::array::from_fn(|_| AtomicU64::new(0)),
            latency: std::array::from_fn(|_| Histogram::new(LATENCY_BUCKETS_S)),
            ranges: Histogram::new(RANGE_BUCKETS),
            viewers: AtomicI64::new(0),
            dropped_slow: AtomicU64::new(0),
            edits: AtomicU64::new(0),
            connections: AtomicI64::new(0),
            in_flight: AtomicI64::new(0),
            timeouts: std::array::from_fn(|_| AtomicU64::new(0)),
            shed: std::array::from_fn(|_| AtomicU64::new(0)),
        }
    }
}

impl Metrics {
    /// Records one finished request (latency up to the response head).
    pub fn request(&self, route: Route, status: u16, body_bytes: u64, latency: Duration) {
        let class = usize::from(status / 100).clamp(1, 5) - 1;
        self.requests[route as usize][class].fetch_add(1, Relaxed);
        self.bytes[route as usize].fetch_add(body_bytes, Relaxed);
        self.latency[route as usize].observe(latency.as_secs_f64());
    }

    /// Records how many ranges an asset request asked for (after coalescing; 0 for none).
    pub fn ranges(&self, n: usize) {
        self.ranges.observe(n as f64);
    }

    /// A viewer joined (+1) or left (−1).
    pub fn viewers(&self, delta: i64) {
        self.viewers.fetch_add(delta, Relaxed);
    }

    /// Current viewers.
    pub fn viewer_count(&self) -> i64 {
        self.viewers.load(Relaxed)
    }

    /// A slow viewer was dropped.
    pub fn dropped_slow(&self) {
        self.dropped_slow.fetch_add(1, Relaxed);
    }

    /// A scene edit was published.
    pub fn edit(&self) {
        self.edits.fetch_add(1, Relaxed);
    }

    /// A connection opened (+1) or closed (−1).
    pub fn connections(&self, delta: i64) {
        self.connections.fetch_add(delta, Relaxed);
    }

    /// A request began (+1: its head was read) or ended (−1: its response was written, or it
    /// was upgraded to a WebSocket).
    pub fn in_flight(&self, delta: i64) {
        self.in_flight.fetch_add(delta, Relaxed);
    }

    /// A connection timed out at `stage`.
    pub fn timeout(&self, stage: Stage) {
        self.timeouts[stage as usize].fetch_add(1, Relaxed);
    }

    /// The connection bound shed one connection.
    pub fn shed(&self, how: Shed) {
        self.shed[how as usize].fetch_add(1, Relaxed);
    }

    /// The Prometheus text exposition.
    pub fn render(&self) -> String {
        let mut o = String::with_capacity(4096);
        o.push_str("# HELP canopy_http_requests_total HTTP requests by route class and status class.\n");
        o.push_str("# TYPE canopy_http_requests_total counter\n");
        for (r, name) in ROUTES.iter().enumerate() {
            for (c, n) in self.requests[r].iter().enumerate() {
                let _ = writeln!(
                    o,
                    "canopy_http_requests_total{{route=\"{name}\",status=\"{}xx\"}} {}",
                    c + 1,
                    n.load(Relaxed)
                );
            }
        }
        o.push_str("# HELP canopy_http_response_body_bytes_total Response body bytes by route class (as declared in Content-Length).\n");
        o.push_str("# TYPE canopy_http_response_body_bytes_total counter\n");
        for (r, name) in ROUTES.iter().enumerate() {
            let _ = writeln!(
                o,
                "canopy_http_response_body_bytes_total{{route=\"{name}\"}} {}",
                self.bytes[r].load(Relaxed)
            );
        }
        o.push_str("# HELP canopy_http_request_duration_seconds Time from request to response head.\n");
        o.push_str("# TYPE canopy_http_request_duration_seconds histogram\n");
        for (r, name) in ROUTES.iter().enumerate() {
            self.latency[r].write(
                &mut o,
                "canopy_http_request_duration_seconds",
                &format!("route=\"{name}\""),
            );
        }
        o.push_str(
            "# HELP canopy_asset_ranges_per_request Ranges served per asset GET after coalescing (0: whole file).\n",
        );
        o.push_str("# TYPE canopy_asset_ranges_per_request histogram\n");
        self.ranges.write(&mut o, "canopy_asset_ranges_per_request", "");
        o.push_str(
            "# HELP canopy_live_viewers Connected scene viewers (WebSockets).\n# TYPE canopy_live_viewers gauge\n",
        );
        let _ = writeln!(o, "canopy_live_viewers {}", self.viewers.load(Relaxed));
        o.push_str("# HELP canopy_live_dropped_slow_total Viewers dropped because they fell behind.\n# TYPE canopy_live_dropped_slow_total counter\n");
        let _ = writeln!(o, "canopy_live_dropped_slow_total {}", self.dropped_slow.load(Relaxed));
        o.push_str("# HELP canopy_scene_edits_total Scene versions published by edits.\n# TYPE canopy_scene_edits_total counter\n");
        let _ = writeln!(o, "canopy_scene_edits_total {}", self.edits.load(Relaxed));
        o.push_str("# HELP canopy_http_connections Open client connections (WebSockets included).\n# TYPE canopy_http_connections gauge\n");
        let _ = writeln!(o, "canopy_http_connections {}", self.connections.load(Relaxed));
        o.push_str("# HELP canopy_http_requests_in_flight Requests whose head was read and whose response is not yet written (WebSockets not counted).\n# TYPE canopy_http_requests_in_flight gauge\n");
        let _ = writeln!(o, "canopy_http_requests_in_flight {}", self.in_flight.load(Relaxed));
        o.push_str("# HELP canopy_http_timeouts_total Connections closed for running out of time, by stage.\n# TYPE canopy_http_timeouts_total counter\n");
        for (k, name) in STAGES.iter().enumerate() {
            let _ = writeln!(
                o,
                "canopy_http_timeouts_total{{stage=\"{name}\"}} {}",
                self.timeouts[k].load(Relaxed)
            );
        }
        o.push_str("# HELP canopy_http_connections_shed_total Connections shed at the connection bound: evicted (idle, closed to admit a new one) or refused (answered 503).\n# TYPE canopy_http_connections_shed_total counter\n");
        for (k, name) in SHEDS.iter().enumerate() {
            let _ = writeln!(
                o,
                "canopy_http_connections_shed_total{{action=\"{name}\"}} {}",
                self.shed[k].load(Relaxed)
            );
        }
        o
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histogram_buckets_are_cumulative() {
        let m = Metrics::default();
        m.request(Route::Assets, 206, 100, Duration::from_micros(300));
        m.request(Route::Assets, 404, 0, Duration::from_secs(9));
        m.ranges(8);
        let t = m.render();
        assert!(
            t.contains("canopy_http_requests_total{route=\"assets\",status=\"2xx\"} 1"),
            "{t}"
        );
        assert!(t.contains("canopy_http_requests_total{route=\"assets\",status=\"4xx\"} 1"));
        assert!(t.contains("canopy_http_request_duration_seconds_bucket{route=\"assets\",le=\"0.0005\"} 1"));
        assert!(t.contains("canopy_http_request_duration_seconds_bucket{route=\"assets\",le=\"2.5\"} 1"));
        assert!(t.contains("canopy_http_request_duration_seconds_bucket{route=\"assets\",le=\"+Inf\"} 2"));
        assert!(t.contains("canopy_asset_ranges_per_request_bucket{le=\"4\"} 0"));
        assert!(t.contains("canopy_asset_ranges_per_request_bucket{le=\"8\"} 1"));
        assert!(t.contains("canopy_http_response_body_bytes_total{route=\"assets\"} 100"));
    }
}
