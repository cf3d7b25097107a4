//! HTTP backend (reqwest): multi-range requests where the server answers them with
//! `multipart/byteranges`, parallel single-range requests where it does not, a bound on requests
//! in flight, and retries with exponential backoff.
//!
//! Range mode [`RangeMode::Auto`] sends several ranges in one request until a server shows it
//! does not support that (it answers `200` with the whole file, or one part that covers only some
//! of the ranges); from then on the source sends one request per range, in parallel. The bytes of
//! such a probe are not wasted: whatever came back is used.

use std::fmt::Write as _;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use bytes::Bytes;
use futures_util::future::join_all;
use reqwest::StatusCode;
use reqwest::header::{CONTENT_RANGE, CONTENT_TYPE, RANGE};
use tokio::sync::Semaphore;

use super::multipart::{multipart_boundary, parse_content_range, parse_multipart, slice_wanted};
use super::{ByteRange, InFlight, NetError, NetStats, RangeSource};

/// How several ranges of one resource are requested.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum RangeMode {
    /// Multi-range until the server shows it cannot, then parallel single ranges.
    #[default]
    Auto,
    /// Always one request with every range (falls back per request if refused).
    Multi,
    /// Always one request per range.
    Single,
}

/// Most range specs sent in one `Range` header (the Canopy server accepts 1,024; a short header
/// keeps every proxy happy and lets big plans run as parallel requests).
pub const MAX_RANGES_PER_REQUEST: usize = 64;

/// Options of an [`HttpSource`].
#[derive(Debug, Clone)]
pub struct HttpOptions {
    /// Range mode.
    pub mode: RangeMode,
    /// Most requests in flight at once.
    pub max_in_flight: usize,
    /// Retries after the first attempt.
    pub retries: u32,
    /// First backoff; doubled per retry, capped at 2 s.
    pub backoff: Duration,
    /// Timeout of one request, body included.
    pub timeout: Duration,
}

impl Default for HttpOptions {
    fn default() -> Self {
        Self {
            mode: RangeMode::Auto,
            max_in_flight: 16,
            retries: 4,
            backoff: Duration::from_millis(25),
            timeout: Duration::from_secs(20),
        }
    }
}

/// An HTTP origin (`http://host:port`) serving paths by range.
#[derive(Debug)]
pub struct HttpSource {
    client: reqwest::Client,
    origin: String,
    opts: HttpOptions,
    gate: Semaphore,
    multi_refused: AtomicBool,
    stats: NetStats,
    in_flight: AtomicU64,
}

enum Answer {
    /// Exactly the wanted ranges.
    All(Vec<Bytes>),
    /// Some wanted ranges (the others are `None`); the server does not do multi-range.
    Some(Vec<Option<Bytes>>),
}

impl HttpSource {
    /// A source for `origin` (scheme, host and port; a trailing `/` is dropped).
    pub fn new(origin: &str, opts: HttpOptions) -> Result<Self, NetError> {
        let client = reqwest::Client::builder()
            .timeout(opts.timeout)
            .pool_max_idle_per_host(opts.max_in_flight.max(1))
            // Assets are immutable URLs: a redirect is not expected, and following one could
            // take a load test off the loopback host it was pointed at.
            .redirect(reqwest::redirect::Policy::none())
            .build()
            .map_err(|e| NetError::Transport {
                url: origin.into(),
                message: e.to_string(),
            })?;
        Ok(Self {
            client,
            origin: origin.trim_end_matches('/').to_string(),
            gate: Semaphore::new(opts.max_in_flight.max(1)),
            opts,
            multi_refused: AtomicBool::new(false),
            stats: NetStats::default(),
            in_flight: AtomicU64::new(0),
        })
    }

    /// Whether the server was seen refusing multi-range requests.
    pub fn multi_refused(&self) -> bool {
        self.multi_refused.load(Ordering::Relaxed)
    }

    fn url(&self, path: &str) -> String {
        if path.starts_with("http://") || path.starts_with("https://") {
            path.to_string()
        } else {
            format!("{}{}", self.origin, path)
        }
    }

    fn transport(url: &str, e: &reqwest::Error) -> NetError {
        NetError::Transport {
            url: url.into(),
            message: e.to_string(),
        }
    }

    fn bad(url: &str, why: impl Into<String>) -> NetError {
        NetError::BadResponse {
            url: url.into(),
            why: why.into(),
        }
    }

    async fn send(
        &self,
        url: &str,
        range: Option<&str>,
    ) -> Result<(StatusCode, reqwest::header::HeaderMap, Bytes), NetError> {
        let _permit = self.gate.acquire().await.map_err(|_| Self::bad(url, "source closed"))?;
        let _g = InFlight::new(&self.stats, &self.in_flight);
        let t0 = std::time::Instant::now();
        let mut req = self.client.get(url);
        if let Some(r) = range {
            req = req.header(RANGE, r);
        }
        let resp = req.send().await.map_err(|e| Self::transport(url, &e))?;
        let status = resp.status();
        let headers = resp.headers().clone();
        let body = resp.bytes().await.map_err(|e| Self::transport(url, &e))?;
        self.stats.add_request(body.len() as u64);
        self.stats.latency.record(t0.elapsed());
        Ok((status, headers, body))
    }

    async fn retrying<T, F, Fut>(&self, mut attempt: F) -> Result<T, NetError>
    where
        F: FnMut() -> Fut,
        Fut: Future<Output = Result<T, NetError>>,
    {
        let mut delay = self.opts.backoff;
        let mut tries = 0;
        loop {
            match attempt().await {
                Ok(v) => return Ok(v),
                Err(e) if e.is_retryable() && tries < self.opts.retries => {
                    tries += 1;
                    self.stats.retries.fetch_add(1, Ordering::Relaxed);
                    tokio::time::sleep(delay).await;
                    delay = (delay * 2).min(Duration::from_secs(2));
                }
                Err(e) => {
                    self.stats.failures.fetch_add(1, Ordering::Relaxed);
                    return Err(e);
                }
            }
        }
    }

    fn header_str(h: &reqwest::header::HeaderMap, k: reqwest::header::HeaderName) -> Option<&str> {
        h.get(k).and_then(|v| v.to_str().ok())
    }

    async fn single_once(&self, url: &str, r: &ByteRange) -> Result<Bytes, NetError> {
        let spec = format!("bytes={}-{}", r.start, r.end - 1);
        let (status, headers, body) = self.send(url, Some(&spec)).await?;
        let want = r.end - r.start;
        match status {
            StatusCode::PARTIAL_CONTENT => {
                let cr = Self::header_str(&headers, CONTENT_RANGE)
                    .ok_or_else(|| Self::bad(url, "206 without Content-Range"))?;
                let (a, b, _) = parse_content_range(cr).map_err(|e| Self::bad(url, e.to_string()))?;
                if a > r.start || b < r.end || body.len() as u64 != b - a {
                    return Err(Self::bad(
                        url,
                        format!("asked {}..{}, got {a}..{b} with {} bytes", r.start, r.end, body.len()),
                    ));
                }
                Ok(body.slice((r.start - a) as usize..(r.end - a) as usize))
            }
            StatusCode::OK => {
                if (body.len() as u64) < r.end {
                    return Err(Self::bad(
                        url,
                        format!("200 with {} bytes, range ends at {}", body.len(), r.end),
                    ));
                }
                Ok(body.slice(r.start as usize..r.end as usize))
            }
            s => Err(NetError::Status {
                status: s.as_u16(),
                url: url.into(),
            }),
        }
        .and_then(|b: Bytes| {
            if b.len() as u64 == want {
                Ok(b)
            } else {
                Err(Self::bad(url, "short body"))
            }
        })
    }

    async fn multi_once(&self, url: &str, ranges: &[ByteRange]) -> Result<Answer, NetError> {
        let mut spec = String::from("bytes=");
        for (i, r) in ranges.iter().enumerate() {
            if i > 0 {
                spec.push(',');
            }
            let _ = write!(spec, "{}-{}", r.start, r.end - 1);
        }
        let (status, headers, body) = self.send(url, Some(&spec)).await?;
        match status {
            StatusCode::PARTIAL_CONTENT => {
                let ct = Self::header_str(&headers, CONTENT_TYPE).unwrap_or("");
                let parts = if let Some(b) = multipart_boundary(ct) {
                    let b = b.map_err(|e| Self::bad(url, e.to_string()))?;
                    parse_multipart(&body, &b).map_err(|e| Self::bad(url, e.to_string()))?
                } else {
                    {
                        // One part: the server coalesced the ranges, or served only some.
                        let cr = Self::header_str(&headers, CONTENT_RANGE)
                            .ok_or_else(|| Self::bad(url, "206 without Content-Range"))?;
                        let (a, b, len) = parse_content_range(cr).map_err(|e| Self::bad(url, e.to_string()))?;
                        if body.len() as u64 != b - a {
                            return Err(Self::bad(url, "206 body length disagrees with Content-Range"));
                        }
                        vec![super::multipart::RangePart {
                            start: a,
                            end: b,
                            complete_len: len,
                            body,
                        }]
                    }
                };
                let got = slice_wanted(&parts, ranges);
                if got.iter().all(Option::is_some) {
                    Ok(Answer::All(got.into_iter().flatten().collect()))
                } else if got.iter().any(Option::is_some) && parts.len() == 1 {
                    Ok(Answer::Some(got))
                } else {
                    Err(Self::bad(url, "multipart answer misses requested ranges"))
                }
            }
            StatusCode::OK => {
                let got = ranges
                    .iter()
                    .map(|r| (r.end <= body.len() as u64).then(|| body.slice(r.start as usize..r.end as usize)))
                    .collect();
                Ok(Answer::Some(got))
            }
            s => Err(NetError::Status {
                status: s.as_u16(),
                url: url.into(),
            }),
        }
    }

    async fn singles(&self, url: &str, ranges: &[ByteRange]) -> Result<Vec<Bytes>, NetError> {
        join_all(ranges.iter().map(|r| self.retrying(|| self.single_once(url, r))))
            .await
            .into_iter()
            .collect()
    }

    async fn multi_chunk(&self, url: &str, ranges: &[ByteRange]) -> Result<Vec<Bytes>, NetError> {
        match self.retrying(|| self.multi_once(url, ranges)).await? {
            Answer::All(v) => Ok(v),
            Answer::Some(got) => {
                self.multi_refused.store(true, Ordering::Relaxed);
                let missing: Vec<ByteRange> = ranges
                    .iter()
                    .zip(&got)
                    .filter(|(_, g)| g.is_none())
                    .map(|(r, _)| r.clone())
                    .collect();
                let mut rest = self.singles(url, &missing).await?.into_iter();
                got.into_iter()
                    .map(|g| g.or_else(|| rest.next()).ok_or_else(|| Self::bad(url, "lost a range")))
                    .collect()
            }
        }
    }
}

impl RangeSource for HttpSource {
    async fn get(&self, path: &str) -> Result<Bytes, NetError> {
        let url = self.url(path);
        self.retrying(|| async {
            let (status, _, body) = self.send(&url, None).await?;
            if status.is_success() {
                Ok(body)
            } else {
                Err(NetError::Status {
                    status: status.as_u16(),
                    url: url.clone(),
                })
            }
        })
        .await
    }

    async fn fetch(&self, path: &str, ranges: &[ByteRange]) -> Result<Vec<Bytes>, NetError> {
        let url = self.url(path);
        if let Some(r) = ranges.iter().find(|r| r.start >= r.end) {
            return Err(NetError::OutOfRange {
                path: path.into(),
                start: r.start,
                end: r.end,
                size: 0,
            });
        }
        let multi = ranges.len() > 1
            && match self.opts.mode {
                RangeMode::Single => false,
                RangeMode::Multi => true,
                RangeMode::Auto => !self.multi_refused(),
            };
        if !multi {
            return self.singles(&url, ranges).await;
        }
        let chunks = join_all(ranges.chunks(MAX_RANGES_PER_REQUEST).map(|c| self.multi_chunk(&url, c))).await;
        let mut out = Vec::with_capacity(ranges.len());
        for c in chunks {
            out.extend(c?);
        }
        Ok(out)
    }

    fn stats(&self) -> &NetStats {
        &self.stats
    }
}
