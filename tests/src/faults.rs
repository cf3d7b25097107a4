//! A fault-injecting HTTP/1.1 proxy for end-to-end tests of the streaming client, and a canned
//! responder that answers every request with the same bytes.
//!
//! [`FaultProxy`] listens on `127.0.0.1:0` and forwards each request to an upstream server on a
//! fresh connection with `Connection: close`, reads the whole response, and answers the client on
//! its keep-alive connection with a `Content-Length` framed copy — unless its [`Fault`] says
//! otherwise: cut the body short and close, answer 503, hold the response back, flip a byte of a
//! range response's data, or refuse multi-range requests as a server without them does. Everything is std threads; every read has a timeout, every loop a
//! bound, and dropping the proxy stops it (open client connections are shut down).
//!
//! It parses just enough HTTP/1.1 for this: a request line, headers and a `Content-Length` body
//! from the client; a status line, headers and a body read to the end (de-chunked) from the
//! upstream.

use std::collections::HashSet;
use std::fmt::Write as _;
use std::io::{ErrorKind, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// How often blocked reads and sleeps look at the stop flag.
const POLL: Duration = Duration::from_millis(50);
/// A client connection with no new request for this long is closed.
const IDLE: Duration = Duration::from_mins(1);
/// Longest wait for an upstream response.
const UPSTREAM_TIMEOUT: Duration = Duration::from_secs(30);
/// Largest request head accepted from a client.
const MAX_HEAD: usize = 64 * 1024;
/// Largest body accepted (request or response).
const MAX_BODY: usize = 512 << 20;

/// A byte window of one resource: `target` (the request path) and `start..end`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Window {
    /// Request target (path).
    pub target: String,
    /// First byte.
    pub start: u64,
    /// One past the last byte.
    pub end: u64,
}

/// What the proxy does wrong.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Fault {
    /// Forward every request faithfully.
    None,
    /// For every `every`-th request: forward the response head (with the full `Content-Length`)
    /// and half the body, then close the connection. Never twice for the same request (method,
    /// target and `Range`): a client that retries gets through on its second attempt.
    Truncate {
        /// Period, in requests (1 = every request).
        every: u64,
    },
    /// For every `every`-th request: answer `503 Service Unavailable` without asking upstream.
    /// Never twice for the same request, as with `Truncate`.
    Unavailable {
        /// Period, in requests.
        every: u64,
    },
    /// Hold every response back for `ms` milliseconds.
    Delay {
        /// Milliseconds.
        ms: u64,
    },
    /// For every `every`-th `206` response, at most `limit` times: flip the first data byte of
    /// the first part (the body of a single-part answer counts as one part). With `within`
    /// non-empty, only the first part that starts inside one of the windows is eligible, and
    /// only responses with such a part count. The HTTP framing stays valid, and the flipped
    /// byte is always the first byte of a requested range, or with `window_starts` the first
    /// byte of a window that a part covers.
    FlipRangeByte {
        /// Period, in eligible 206 responses.
        every: u64,
        /// Most flips.
        limit: u64,
        /// Where flips may land; empty: anywhere.
        within: Vec<Window>,
        /// Also eligible: a part that starts before a window and covers its first byte, which
        /// is then the byte flipped (a window that starts a section of blocks starts a block).
        window_starts: bool,
    },
    /// Answer every request whose `Range` header lists more than one range the way a server
    /// without multi-range support does (what [`Refusal`] says); other requests pass through.
    NoMultiRange(Refusal),
}

/// How [`Fault::NoMultiRange`] refuses a multi-range request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// `200 OK` with the whole resource (the `Range` header is dropped on the way upstream).
    Whole,
    /// `206` with one part: the first range only (the others are dropped on the way upstream).
    FirstRange,
}

/// A request the proxy saw.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Seen {
    /// Sequence number from 1, in arrival order.
    pub seq: u64,
    /// Method.
    pub method: String,
    /// Request target (path and query).
    pub target: String,
    /// The `Range` header, if any.
    pub range: Option<String>,
    /// The fault applied to it, if any.
    pub fault: Option<&'static str>,
}

/// A byte the proxy flipped.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Flip {
    /// Sequence number of the request whose response was changed.
    pub seq: u64,
    /// Request target.
    pub target: String,
    /// Absolute offset of the flipped byte in the resource.
    pub offset: u64,
}

#[derive(Debug, Default)]
struct Shared {
    stop: AtomicBool,
    requests: AtomicU64,
    partials: AtomicU64,
    faults: AtomicU64,
    seen: Mutex<Vec<Seen>>,
    flips: Mutex<Vec<Flip>>,
    conns: Mutex<Vec<TcpStream>>,
    /// Requests (method, target, `Range`) that a transport fault hit.
    faulted: Mutex<HashSet<(String, String, Option<String>)>>,
}

impl Shared {
    fn stopped(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }
}

/// A listener on a loopback port whose connections are handled on threads; stopped on drop.
#[derive(Debug)]
struct Acceptor {
    addr: SocketAddr,
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
}

impl Acceptor {
    fn start<F>(handler: F) -> Self
    where
        F: Fn(TcpStream, &Shared) + Send + Sync + 'static,
    {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind a loopback port");
        listener.set_nonblocking(true).expect("nonblocking listener");
        let addr = listener.local_addr().expect("local address");
        let shared = Arc::new(Shared::default());
        let handler = Arc::new(handler);
        let sh = Arc::clone(&shared);
        let thread = std::thread::spawn(move || {
            let mut workers: Vec<JoinHandle<()>> = Vec::new();
            while !sh.stopped() {
                match listener.accept() {
                    Ok((s, _)) => {
                        let _ = s.set_nonblocking(false);
                        if let Ok(c) = s.try_clone() {
                            sh.conns.lock().unwrap_or_else(PoisonError::into_inner).push(c);
                        }
                        let (sh, h) = (Arc::clone(&sh), Arc::clone(&handler));
                        workers.push(std::thread::spawn(move || h(s, &sh)));
                        workers.retain(|w| !w.is_finished());
                    }
                    Err(e) if e.kind() == ErrorKind::WouldBlock => std::thread::sleep(Duration::from_millis(5)),
                    Err(_) => std::thread::sleep(POLL),
                }
            }
            for c in sh.conns.lock().unwrap_or_else(PoisonError::into_inner).drain(..) {
                let _ = c.shutdown(Shutdown::Both);
            }
            for w in workers {
                let _ = w.join();
            }
        });
        Self {
            addr,
            shared,
            thread: Some(thread),
        }
    }
}

impl Drop for Acceptor {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A fault-injecting proxy in front of one upstream HTTP server; stopped on drop.
#[derive(Debug)]
pub struct FaultProxy {
    acceptor: Acceptor,
    /// The proxy's address (`http://ADDR/...` reaches the upstream through it).
    pub addr: SocketAddr,
}

impl FaultProxy {
    /// Starts a proxy to `upstream` on a free loopback port.
    pub fn start(upstream: SocketAddr, fault: Fault) -> Self {
        let fault = Arc::new(fault);
        let acceptor = Acceptor::start(move |s, sh| proxy_connection(s, sh, upstream, &fault));
        Self {
            addr: acceptor.addr,
            acceptor,
        }
    }

    /// Requests received so far.
    pub fn requests(&self) -> u64 {
        self.acceptor.shared.requests.load(Ordering::Relaxed)
    }

    /// Faults injected so far.
    pub fn faults(&self) -> u64 {
        self.acceptor.shared.faults.load(Ordering::Relaxed)
    }

    /// Every request seen, in arrival order.
    pub fn seen(&self) -> Vec<Seen> {
        self.acceptor
            .shared
            .seen
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Every byte flipped.
    pub fn flips(&self) -> Vec<Flip> {
        self.acceptor
            .shared
            .flips
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Whether a request after `seq` asked for a range of `target` that holds byte `offset`.
    pub fn refetched(&self, seq: u64, target: &str, offset: u64) -> bool {
        self.seen().iter().any(|s| {
            s.seq > seq
                && s.target == target
                && s.range
                    .as_deref()
                    .is_some_and(|r| parse_range_spec(r).iter().any(|&(a, b)| a <= offset && offset <= b))
        })
    }
}

/// Answers every request with the same raw bytes (status line, headers and body), then closes
/// the connection; stopped on drop. For a server that sends garbage.
#[derive(Debug)]
pub struct CannedServer {
    acceptor: Acceptor,
    /// Its address.
    pub addr: SocketAddr,
}

impl CannedServer {
    /// Starts one on a free loopback port.
    pub fn start(response: Vec<u8>) -> Self {
        let acceptor = Acceptor::start(move |mut s, sh| {
            let mut buf = Vec::new();
            if let Some(req) = read_request(&mut s, &mut buf, sh) {
                sh.requests.fetch_add(1, Ordering::Relaxed);
                sh.seen.lock().unwrap_or_else(PoisonError::into_inner).push(Seen {
                    seq: sh.requests.load(Ordering::Relaxed),
                    method: req.method,
                    target: req.target,
                    range: req.range,
                    fault: None,
                });
                let _ = s.write_all(&response);
            }
            let _ = s.shutdown(Shutdown::Both);
        });
        Self {
            addr: acceptor.addr,
            acceptor,
        }
    }

    /// A `200 OK` JSON response with `body`.
    pub fn json_200(body: &[u8]) -> Vec<u8> {
        let mut r = format!(
            "HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
            body.len()
        )
        .into_bytes();
        r.extend_from_slice(body);
        r
    }

    /// Requests answered so far.
    pub fn requests(&self) -> u64 {
        self.acceptor.shared.requests.load(Ordering::Relaxed)
    }
}

/// Parses `bytes=a-b,c-d,…` into inclusive `(first, last)` pairs (open-ended and suffix ranges
/// are skipped; they are not what the client sends).
pub fn parse_range_spec(spec: &str) -> Vec<(u64, u64)> {
    let Some((unit, list)) = spec.split_once('=') else {
        return Vec::new();
    };
    if !unit.trim().eq_ignore_ascii_case("bytes") {
        return Vec::new();
    }
    list.split(',')
        .filter_map(|r| {
            let (a, b) = r.trim().split_once('-')?;
            Some((a.trim().parse().ok()?, b.trim().parse().ok()?))
        })
        .collect()
}

fn find(h: &[u8], n: &[u8]) -> Option<usize> {
    h.windows(n.len()).position(|w| w == n)
}

/// One parsed client request.
#[derive(Debug)]
struct Request {
    method: String,
    target: String,
    version: String,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
    range: Option<String>,
    close: bool,
}

/// Reads once into `buf`; `false` when the peer closed, the proxy stops, or `deadline` passed.
fn fill(s: &mut TcpStream, buf: &mut Vec<u8>, sh: &Shared, deadline: Instant) -> bool {
    let mut chunk = [0u8; 16 * 1024];
    loop {
        if sh.stopped() || Instant::now() > deadline {
            return false;
        }
        match s.read(&mut chunk) {
            Ok(0) => return false,
            Ok(n) => {
                buf.extend_from_slice(&chunk[..n]);
                return true;
            }
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted
                ) => {}
            Err(_) => return false,
        }
    }
}

/// Reads the next request from a client connection (`buf` keeps bytes read past it).
fn read_request(s: &mut TcpStream, buf: &mut Vec<u8>, sh: &Shared) -> Option<Request> {
    s.set_read_timeout(Some(POLL)).ok()?;
    let deadline = Instant::now() + IDLE;
    let head_end = loop {
        if let Some(e) = find(buf, b"\r\n\r\n") {
            break e;
        }
        if buf.len() > MAX_HEAD || !fill(s, buf, sh, deadline) {
            return None;
        }
    };
    let head = String::from_utf8_lossy(&buf[..head_end]).to_string();
    let mut lines = head.split("\r\n");
    let mut first = lines.next()?.split(' ');
    let (method, target, version) = (
        first.next()?.to_string(),
        first.next()?.to_string(),
        first.next()?.to_string(),
    );
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_string(), v.trim().to_string()))
        .collect();
    let get = |name: &str| {
        headers
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.clone())
    };
    let len: usize = get("content-length").and_then(|v| v.parse().ok()).unwrap_or(0);
    if len > MAX_BODY || get("transfer-encoding").is_some() {
        return None;
    }
    let body_start = head_end + 4;
    while buf.len() < body_start + len {
        if !fill(s, buf, sh, deadline) {
            return None;
        }
    }
    let body = buf[body_start..body_start + len].to_vec();
    buf.drain(..body_start + len);
    let close = get("connection").is_some_and(|v| v.to_ascii_lowercase().contains("close")) || version == "HTTP/1.0";
    Some(Request {
        range: get("range"),
        method,
        target,
        version,
        headers,
        body,
        close,
    })
}

/// An upstream response, body read to the end and de-chunked.
#[derive(Debug)]
struct Response {
    status_line: String,
    status: u16,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Response {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }

    /// Head for the client: the upstream's headers less hop-by-hop and framing ones, with a
    /// `Content-Length` of `len`.
    fn head(&self, len: usize, close: bool, head_request: bool) -> String {
        let mut h = format!("{}\r\n", self.status_line);
        for (k, v) in &self.headers {
            let k_l = k.to_ascii_lowercase();
            if matches!(k_l.as_str(), "connection" | "keep-alive" | "transfer-encoding")
                || (k_l == "content-length" && !head_request)
            {
                continue;
            }
            let _ = write!(h, "{k}: {v}\r\n");
        }
        if !head_request {
            let _ = write!(h, "Content-Length: {len}\r\n");
        }
        if close {
            h.push_str("Connection: close\r\n");
        }
        h.push_str("\r\n");
        h
    }
}

fn dechunk(mut b: &[u8]) -> Option<Vec<u8>> {
    let mut out = Vec::new();
    loop {
        let e = find(b, b"\r\n")?;
        let size = String::from_utf8_lossy(&b[..e]);
        let n = usize::from_str_radix(size.split(';').next()?.trim(), 16).ok()?;
        if n == 0 {
            return Some(out);
        }
        out.extend_from_slice(b.get(e + 2..e + 2 + n)?);
        b = b.get(e + 2 + n + 2..)?;
    }
}

/// Sends `req` upstream with `Connection: close` and reads the whole response.
fn forward(req: &Request, upstream: SocketAddr, sh: &Shared) -> Option<Response> {
    let mut up = TcpStream::connect_timeout(&upstream, Duration::from_secs(5)).ok()?;
    let mut head = format!("{} {} {}\r\n", req.method, req.target, req.version);
    for (k, v) in &req.headers {
        if !matches!(k.to_ascii_lowercase().as_str(), "connection" | "keep-alive") {
            let _ = write!(head, "{k}: {v}\r\n");
        }
    }
    head.push_str("Connection: close\r\n\r\n");
    up.write_all(head.as_bytes()).ok()?;
    up.write_all(&req.body).ok()?;
    up.set_read_timeout(Some(POLL)).ok()?;
    let deadline = Instant::now() + UPSTREAM_TIMEOUT;
    let mut raw = Vec::new();
    while fill(&mut up, &mut raw, sh, deadline) {
        if raw.len() > MAX_BODY {
            return None;
        }
    }
    if sh.stopped() {
        return None;
    }
    let end = find(&raw, b"\r\n\r\n")?;
    let head = String::from_utf8_lossy(&raw[..end]).to_string();
    let mut lines = head.split("\r\n");
    let status_line = lines.next()?.to_string();
    let status = status_line.split(' ').nth(1)?.parse().ok()?;
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_string(), v.trim().to_string()))
        .collect();
    let mut resp = Response {
        status_line,
        status,
        headers,
        body: raw[end + 4..].to_vec(),
    };
    if resp
        .header("transfer-encoding")
        .is_some_and(|v| v.to_ascii_lowercase().contains("chunked"))
    {
        resp.body = dechunk(&resp.body)?;
    } else if let Some(n) = resp.header("content-length").and_then(|v| v.parse::<usize>().ok())
        && req.method != "HEAD"
    {
        if resp.body.len() < n {
            return None;
        }
        resp.body.truncate(n);
    }
    Some(resp)
}

/// The parts of a 206 response: where each part's data starts in the body, and the resource
/// offset of that byte.
fn parts(resp: &Response) -> Vec<(usize, u64, usize)> {
    let content_range =
        |v: &str| -> Option<u64> { v.trim().strip_prefix("bytes ")?.split('-').next()?.trim().parse().ok() };
    let ct = resp.header("content-type").unwrap_or("").to_ascii_lowercase();
    let Some(boundary) = ct
        .strip_prefix("multipart/byteranges")
        .and_then(|r| r.split("boundary=").nth(1))
        .map(|b| b.split(';').next().unwrap_or(b).trim().trim_matches('"').to_string())
    else {
        return resp
            .header("content-range")
            .and_then(content_range)
            .filter(|_| !resp.body.is_empty())
            .map(|start| vec![(0, start, resp.body.len())])
            .unwrap_or_default();
    };
    // The boundary was lowercased with the content type; compare case-insensitively.
    let delim = format!("--{boundary}").into_bytes();
    let body = &resp.body;
    let mut out = Vec::new();
    let mut at = 0usize;
    while let Some(i) = body[at..]
        .windows(delim.len())
        .position(|w| w.eq_ignore_ascii_case(&delim))
    {
        let head_start = at + i + delim.len();
        if body[head_start..].starts_with(b"--") {
            break;
        }
        let Some(head_len) = find(&body[head_start..], b"\r\n\r\n") else {
            break;
        };
        let head = String::from_utf8_lossy(&body[head_start..head_start + head_len]);
        let data = head_start + head_len + 4;
        let start = head.split("\r\n").find_map(|l| {
            l.split_once(':')
                .filter(|(k, _)| k.trim().eq_ignore_ascii_case("content-range"))
                .and_then(|(_, v)| content_range(v))
        });
        let (Some(start), true) = (start, data < body.len()) else {
            break;
        };
        // Skip the part's data by its length (from Content-Range) to find the next delimiter.
        let len = head
            .split("\r\n")
            .find_map(|l| {
                let (k, v) = l.split_once(':')?;
                if !k.trim().eq_ignore_ascii_case("content-range") {
                    return None;
                }
                let (a, b) = v.trim().strip_prefix("bytes ")?.split('/').next()?.split_once('-')?;
                (b.trim().parse::<u64>().ok()? + 1).checked_sub(a.trim().parse::<u64>().ok()?)
            })
            .unwrap_or(0);
        let end = (data + len as usize).min(body.len());
        out.push((data, start, end - data));
        at = end;
    }
    out
}

/// The byte to flip in a 206 response: its position in the body and its resource offset.
fn flip_target(resp: &Response, target: &str, within: &[Window], window_starts: bool) -> Option<(usize, u64)> {
    let parts = parts(resp);
    if within.is_empty() {
        return parts.first().map(|&(at, off, _)| (at, off));
    }
    parts.into_iter().find_map(|(at, off, len)| {
        within.iter().filter(|w| w.target == target).find_map(|w| {
            if w.start <= off && off < w.end {
                Some((at, off))
            } else if window_starts && off < w.start && w.start < off + len as u64 {
                Some((at + (w.start - off) as usize, w.start))
            } else {
                None
            }
        })
    })
}

/// Sleeps `d` in small steps; `false` if the proxy stopped meanwhile.
fn nap(d: Duration, sh: &Shared) -> bool {
    let end = Instant::now() + d;
    while Instant::now() < end {
        if sh.stopped() {
            return false;
        }
        std::thread::sleep(POLL.min(end.saturating_duration_since(Instant::now())));
    }
    true
}

fn proxy_connection(mut client: TcpStream, sh: &Shared, upstream: SocketAddr, fault: &Fault) {
    let mut buf = Vec::new();
    // Bounded: at most this many requests per connection (far more than a test sends).
    for _ in 0..100_000 {
        let Some(req) = read_request(&mut client, &mut buf, sh) else {
            break;
        };
        let seq = sh.requests.fetch_add(1, Ordering::Relaxed) + 1;
        let every = |k: u64| k > 0 && seq.is_multiple_of(k);
        // A transport fault: every k-th request, but never the same request twice.
        let transport_fault = |k: u64| {
            every(k)
                && sh.faulted.lock().unwrap_or_else(PoisonError::into_inner).insert((
                    req.method.clone(),
                    req.target.clone(),
                    req.range.clone(),
                ))
        };
        let mut applied: Option<&'static str> = None;
        let record = |applied: Option<&'static str>| {
            if applied.is_some() {
                sh.faults.fetch_add(1, Ordering::Relaxed);
            }
            sh.seen.lock().unwrap_or_else(PoisonError::into_inner).push(Seen {
                seq,
                method: req.method.clone(),
                target: req.target.clone(),
                range: req.range.clone(),
                fault: applied,
            });
        };
        if let Fault::Unavailable { every: k } = *fault
            && transport_fault(k)
        {
            record(Some("503"));
            let body = b"injected fault: service unavailable\n";
            let head = format!(
                "HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\nContent-Length: {}\r\n{}\r\n",
                body.len(),
                if req.close { "Connection: close\r\n" } else { "" }
            );
            if client.write_all(head.as_bytes()).is_err() || client.write_all(body).is_err() || req.close {
                break;
            }
            continue;
        }
        let refused = match fault {
            Fault::NoMultiRange(how) if req.range.as_deref().is_some_and(|r| r.contains(',')) => Some(*how),
            _ => None,
        };
        let upstream_req;
        let to_send = if let Some(how) = refused {
            // What the client sees in `Seen` stays its own header; only the upstream request changes.
            let first = req
                .range
                .as_deref()
                .and_then(|r| r.split(',').next())
                .unwrap_or_default();
            let headers = req
                .headers
                .iter()
                .filter_map(|(k, v)| match (k.eq_ignore_ascii_case("range"), how) {
                    (false, _) => Some((k.clone(), v.clone())),
                    (true, Refusal::Whole) => None,
                    (true, Refusal::FirstRange) => Some((k.clone(), first.trim().to_string())),
                })
                .collect();
            upstream_req = Request {
                method: req.method.clone(),
                target: req.target.clone(),
                version: req.version.clone(),
                headers,
                body: req.body.clone(),
                range: None,
                close: req.close,
            };
            applied = Some(match how {
                Refusal::Whole => "multi-range as 200",
                Refusal::FirstRange => "multi-range as one part",
            });
            &upstream_req
        } else {
            &req
        };
        let Some(mut resp) = forward(to_send, upstream, sh) else {
            record(None);
            // The upstream failed (or the proxy stops): tell the client with a 502.
            let _ = client.write_all(b"HTTP/1.1 502 Bad Gateway\r\nContent-Length: 0\r\nConnection: close\r\n\r\n");
            break;
        };
        let head_request = req.method == "HEAD";
        match fault {
            Fault::Delay { ms } => {
                applied = Some("delay");
                if !nap(Duration::from_millis(*ms), sh) {
                    break;
                }
            }
            Fault::Truncate { every: k } if transport_fault(*k) => {
                record(Some("truncate"));
                if resp.body.len() >= 2 {
                    let head = resp.head(resp.body.len(), false, head_request);
                    let _ = client.write_all(head.as_bytes());
                    let _ = client.write_all(&resp.body[..resp.body.len() / 2]);
                    let _ = client.flush();
                }
                let _ = client.shutdown(Shutdown::Both);
                break;
            }
            Fault::FlipRangeByte {
                every: k,
                limit,
                within,
                window_starts,
            } if resp.status == 206 && req.range.is_some() => {
                if let Some((at, offset)) = flip_target(&resp, &req.target, within, *window_starts) {
                    let n = sh.partials.fetch_add(1, Ordering::Relaxed) + 1;
                    let mut flips = sh.flips.lock().unwrap_or_else(PoisonError::into_inner);
                    if *k > 0 && n.is_multiple_of(*k) && (flips.len() as u64) < *limit {
                        resp.body[at] ^= 0x5a;
                        flips.push(Flip {
                            seq,
                            target: req.target.clone(),
                            offset,
                        });
                        applied = Some("flip");
                    }
                }
            }
            _ => {}
        }
        record(applied);
        let head = resp.head(resp.body.len(), req.close, head_request);
        let ok = client.write_all(head.as_bytes()).is_ok() && (head_request || client.write_all(&resp.body).is_ok());
        if !ok || req.close {
            break;
        }
    }
    let _ = client.shutdown(Shutdown::Both);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn response(content_type: &str, content_range: Option<&str>, body: &[u8]) -> Response {
        let mut headers = vec![("Content-Type".to_string(), content_type.to_string())];
        if let Some(cr) = content_range {
            headers.push(("Content-Range".to_string(), cr.to_string()));
        }
        Response {
            status_line: "HTTP/1.1 206 Partial Content".into(),
            status: 206,
            headers,
            body: body.to_vec(),
        }
    }

    #[test]
    fn range_specs_and_chunks() {
        assert_eq!(parse_range_spec("bytes=0-9, 20-29"), vec![(0, 9), (20, 29)]);
        assert_eq!(parse_range_spec("bytes=5-,-3"), Vec::<(u64, u64)>::new());
        assert_eq!(parse_range_spec("items=0-1"), Vec::<(u64, u64)>::new());
        assert_eq!(
            dechunk(b"3\r\nabc\r\n2;x=y\r\nde\r\n0\r\n\r\n").as_deref(),
            Some(&b"abcde"[..])
        );
        assert_eq!(dechunk(b"5\r\nab"), None);
    }

    #[test]
    fn flip_targets_are_the_first_data_byte_of_a_part() {
        let single = response("application/octet-stream", Some("bytes 100-104/1000"), b"hello");
        assert_eq!(parts(&single), vec![(0, 100, 5)]);
        let body = b"\r\n--XyZ\r\nContent-Type: application/octet-stream\r\nContent-Range: bytes 0-2/50\r\n\r\nabc\
                     \r\n--XyZ\r\nContent-Range: bytes 40-41/50\r\n\r\nde\r\n--XyZ--\r\n";
        let multi = response("multipart/byteranges; boundary=XyZ", None, body);
        let p = parts(&multi);
        assert_eq!(p.len(), 2);
        assert_eq!((&body[p[0].0..p[0].0 + p[0].2], p[0].1), (&b"abc"[..], 0));
        assert_eq!((&body[p[1].0..p[1].0 + p[1].2], p[1].1), (&b"de"[..], 40));
        let w = |start, end| Window {
            target: "/f".into(),
            start,
            end,
        };
        assert_eq!(flip_target(&multi, "/f", &[], false), Some((p[0].0, p[0].1)));
        assert_eq!(flip_target(&multi, "/f", &[w(30, 50)], false), Some((p[1].0, p[1].1)));
        assert_eq!(flip_target(&multi, "/g", &[w(30, 50)], false), None);
        assert_eq!(flip_target(&multi, "/f", &[w(1, 40)], false), None);
        // A window starting inside a part: its first byte, with `window_starts`.
        assert_eq!(flip_target(&multi, "/f", &[w(1, 40)], true), Some((p[0].0 + 1, 1)));
        assert_eq!(
            flip_target(&multi, "/f", &[w(3, 40)], true),
            None,
            "past the part's end"
        );
    }
}
