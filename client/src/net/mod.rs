//! Byte-range sources: the [`RangeSource`] trait with an HTTP backend ([`http::HttpSource`],
//! reqwest) and a file backend ([`file::FileSource`]).
//!
//! Paths are the server's URL paths (`/assets/trees/linden.<hash>.ctree`, `/api/scenes/demo/…`).
//! A source returns exactly the bytes asked for or an error: callers never see a short or
//! misplaced body (truncated responses are retried, then reported). Content checks (CRC-32 of
//! every block) are the caller's, because only the caller knows where blocks begin.

pub mod file;
pub mod http;
pub mod link;
pub mod linked;
pub mod multipart;

use std::future::Future;
use std::ops::Range;
use std::sync::atomic::{AtomicU64, Ordering};

use bytes::Bytes;

/// A byte range, `start..end` (end exclusive), absolute in its resource.
pub type ByteRange = Range<u64>;

/// Why a fetch failed.
#[derive(Debug, thiserror::Error)]
pub enum NetError {
    /// The server answered with an error status.
    #[error("HTTP {status} for {url}")]
    Status {
        /// Status code.
        status: u16,
        /// URL.
        url: String,
    },
    /// Connecting, sending or receiving failed (connection reset, timeout, …).
    #[error("transport error for {url}: {message}")]
    Transport {
        /// URL.
        url: String,
        /// What the HTTP client said.
        message: String,
    },
    /// The response is not what was asked for (wrong range, bad multipart, short body).
    #[error("bad response for {url}: {why}")]
    BadResponse {
        /// URL.
        url: String,
        /// What was wrong.
        why: String,
    },
    /// A file read failed.
    #[error("reading {path}: {source}")]
    Io {
        /// Path.
        path: String,
        /// The error.
        source: std::io::Error,
    },
    /// A range lies outside the resource.
    #[error("range {start}..{end} is outside {path} ({size} bytes)")]
    OutOfRange {
        /// Resource.
        path: String,
        /// Range start.
        start: u64,
        /// Range end.
        end: u64,
        /// Resource size.
        size: u64,
    },
    /// A path that the source refuses (escapes its root, not absolute).
    #[error("refused path {0:?}")]
    BadPath(String),
}

impl NetError {
    /// Whether trying again may succeed (transport errors, 5xx, 408, 429, bad bodies).
    pub fn is_retryable(&self) -> bool {
        match self {
            Self::Status { status, .. } => *status >= 500 || *status == 408 || *status == 429,
            Self::Transport { .. } | Self::BadResponse { .. } => true,
            Self::Io { .. } | Self::OutOfRange { .. } | Self::BadPath(_) => false,
        }
    }
}

/// Counters of one source, shared by all its requests.
#[derive(Debug, Default)]
pub struct NetStats {
    /// Requests sent (retries included).
    pub requests: AtomicU64,
    /// Response body bytes received (what crossed the network, wasted bytes included).
    pub bytes: AtomicU64,
    /// Retries after a failed attempt.
    pub retries: AtomicU64,
    /// Fetches that failed after every retry.
    pub failures: AtomicU64,
    /// Most requests in flight at once.
    pub peak_in_flight: AtomicU64,
    /// Requests in flight now (the viewer's live figure).
    pub in_flight: AtomicU64,
    /// Latency of each request, send to last body byte.
    pub latency: LatencyHistogram,
}

/// Buckets per power of two of [`LatencyHistogram`] (relative bucket width 2^(1/8) − 1 ≈ 9 %).
pub const LATENCY_SUB_BUCKETS: usize = 8;
/// Powers of two covered, from 1 µs: 2^32 µs ≈ 72 minutes.
const LATENCY_OCTAVES: usize = 32;

/// A fixed-size, lock-free latency histogram: logarithmic buckets from 1 µs with
/// [`LATENCY_SUB_BUCKETS`] per octave, so memory does not grow with the number of requests and a
/// percentile is accurate to about 9 %.
#[derive(Debug)]
pub struct LatencyHistogram {
    buckets: Vec<AtomicU64>,
}

impl Default for LatencyHistogram {
    fn default() -> Self {
        Self {
            buckets: (0..LATENCY_OCTAVES * LATENCY_SUB_BUCKETS)
                .map(|_| AtomicU64::new(0))
                .collect(),
        }
    }
}

impl LatencyHistogram {
    fn bucket(us: u64) -> usize {
        let v = us.max(1) as f64;
        let i = (v.log2() * LATENCY_SUB_BUCKETS as f64).floor() as usize;
        i.min(LATENCY_OCTAVES * LATENCY_SUB_BUCKETS - 1)
    }

    /// Records one latency.
    pub fn record(&self, d: std::time::Duration) {
        let us = u64::try_from(d.as_micros()).unwrap_or(u64::MAX);
        self.buckets[Self::bucket(us)].fetch_add(1, Ordering::Relaxed);
    }

    /// Adds another histogram's counts into this one.
    pub fn merge(&self, other: &Self) {
        for (a, b) in self.buckets.iter().zip(&other.buckets) {
            a.fetch_add(b.load(Ordering::Relaxed), Ordering::Relaxed);
        }
    }

    /// Samples recorded.
    pub fn count(&self) -> u64 {
        self.buckets.iter().map(|b| b.load(Ordering::Relaxed)).sum()
    }

    /// The `q` quantile (0..=1) in milliseconds: the upper edge of the bucket holding it; 0 when
    /// empty.
    pub fn quantile_ms(&self, q: f64) -> f64 {
        let n = self.count();
        if n == 0 {
            return 0.0;
        }
        let rank = ((q.clamp(0.0, 1.0) * n as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for (i, b) in self.buckets.iter().enumerate() {
            seen += b.load(Ordering::Relaxed);
            if seen >= rank {
                return 2f64.powf((i + 1) as f64 / LATENCY_SUB_BUCKETS as f64) / 1000.0;
            }
        }
        0.0
    }
}

/// A snapshot of [`NetStats`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct NetCounters {
    /// Requests sent.
    pub requests: u64,
    /// Body bytes received.
    pub bytes: u64,
    /// Retries.
    pub retries: u64,
    /// Failed fetches.
    pub failures: u64,
    /// Peak requests in flight.
    pub peak_in_flight: u64,
}

impl NetStats {
    /// Current values.
    pub fn snapshot(&self) -> NetCounters {
        NetCounters {
            requests: self.requests.load(Ordering::Relaxed),
            bytes: self.bytes.load(Ordering::Relaxed),
            retries: self.retries.load(Ordering::Relaxed),
            failures: self.failures.load(Ordering::Relaxed),
            peak_in_flight: self.peak_in_flight.load(Ordering::Relaxed),
        }
    }

    pub(crate) fn add_request(&self, body_bytes: u64) {
        self.requests.fetch_add(1, Ordering::Relaxed);
        self.bytes.fetch_add(body_bytes, Ordering::Relaxed);
    }
}

/// A source of bytes addressed by path and range.
pub trait RangeSource: Send + Sync + 'static {
    /// The whole resource (manifests, small files).
    fn get(&self, path: &str) -> impl Future<Output = Result<Bytes, NetError>> + Send;

    /// Exactly the given ranges of `path`, one buffer per range in the order given. Ranges must
    /// be non-empty; they may be in any order but must not overlap.
    fn fetch(&self, path: &str, ranges: &[ByteRange]) -> impl Future<Output = Result<Vec<Bytes>, NetError>> + Send;

    /// The source's counters.
    fn stats(&self) -> &NetStats;

    /// A token for a task that will send requests on this source, held for the task's life:
    /// a source on a virtual clock ([`linked::LinkedSource`]) moves its clock only while every
    /// such task waits on it. Take it before spawning the task.
    fn task(&self) -> TaskToken {
        TaskToken::default()
    }

    /// The source's own clock, seconds, where it has one (a virtual link's); `None`: wall time.
    fn clock(&self) -> Option<f64> {
        None
    }
}

/// A shared source is a source (so a [`linked::LinkedSource`] can wrap one that others use too).
impl<S: RangeSource> RangeSource for std::sync::Arc<S> {
    fn get(&self, path: &str) -> impl Future<Output = Result<Bytes, NetError>> + Send {
        S::get(self, path)
    }

    fn fetch(&self, path: &str, ranges: &[ByteRange]) -> impl Future<Output = Result<Vec<Bytes>, NetError>> + Send {
        S::fetch(self, path, ranges)
    }

    fn stats(&self) -> &NetStats {
        S::stats(self)
    }

    fn task(&self) -> TaskToken {
        S::task(self)
    }

    fn clock(&self) -> Option<f64> {
        S::clock(self)
    }
}

/// See [`RangeSource::task`]; dropping it ends the task's claim.
#[derive(Default)]
pub struct TaskToken(Option<Box<dyn std::any::Any + Send + Sync>>);

impl TaskToken {
    /// A token that runs `guard`'s `Drop` when dropped.
    pub fn new(guard: impl std::any::Any + Send + Sync) -> Self {
        Self(Some(Box::new(guard)))
    }
}

impl std::fmt::Debug for TaskToken {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(if self.0.is_some() {
            "TaskToken(held)"
        } else {
            "TaskToken(none)"
        })
    }
}

/// Counts a request in flight for as long as it lives.
#[derive(Debug)]
pub(crate) struct InFlight<'a> {
    stats: &'a NetStats,
    now: &'a AtomicU64,
}

impl<'a> InFlight<'a> {
    pub(crate) fn new(stats: &'a NetStats, now: &'a AtomicU64) -> Self {
        let n = now.fetch_add(1, Ordering::Relaxed) + 1;
        stats.peak_in_flight.fetch_max(n, Ordering::Relaxed);
        stats.in_flight.fetch_add(1, Ordering::Relaxed);
        Self { stats, now }
    }
}

impl Drop for InFlight<'_> {
    fn drop(&mut self) {
        self.stats.in_flight.fetch_sub(1, Ordering::Relaxed);
        self.now.fetch_sub(1, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn latency_quantiles_within_a_bucket() {
        let h = LatencyHistogram::default();
        assert_eq!(h.quantile_ms(0.5), 0.0);
        for ms in 1..=100u64 {
            h.record(Duration::from_millis(ms));
        }
        for (q, want) in [(0.5, 50.0), (0.99, 99.0), (1.0, 100.0)] {
            let got = h.quantile_ms(q);
            assert!(got >= want && got <= want * 1.1, "q{q}: {got} vs {want}");
        }
        let g = LatencyHistogram::default();
        g.merge(&h);
        assert_eq!(g.count(), 100);
        h.record(Duration::from_secs(1_000_000));
        assert_eq!(h.count(), 101);
    }
}
