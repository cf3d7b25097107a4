//! Connections: the accept loop, a deadline at every stage, and a bound on open connections.
//!
//! hyper serves each HTTP/1.1 connection, but without a timer nothing ever times out, and
//! `axum::serve` has no bound: idle sockets once took every descriptor, and `/healthz` with them
//! (issue 23). So each socket is wrapped in a [`TimedIo`] that knows, from hooks around every
//! request, where its connection is:
//! - waiting for a request head: the header deadline (from accept on a new connection, from the
//!   first byte on a kept-alive one) or, before that first byte, the idle deadline;
//! - a request in flight: no read deadline here (an API body has its own, `read_body` in the
//!   parent module; other routes never read one);
//! - upgraded to a WebSocket: none (presence keeps its own).
//!
//! Any write that makes no progress for the write timeout fails, whatever the stage; while the
//! last bytes of a response wait for the client, that is the only deadline.
//!
//! At `max_connections` the accept loop closes the connection that has waited longest without a
//! request in flight or a response still being written (idle keep-alive, never used, or a head
//! still arriving: nothing is lost but a socket) and admits the new one; only when every
//! connection is busy does it answer 503 with `Retry-After` from the accept loop itself, without
//! a task, and close.

use std::collections::HashMap;
use std::convert::Infallible;
use std::future::Future;
use std::io;
use std::pin::{Pin, pin};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, LazyLock, Mutex, MutexGuard, OnceLock, PoisonError};
use std::task::{Context, Poll, Waker};
use std::time::Duration;

use axum::Router;
use axum::body::Body;
use axum::http::{Request, Response, StatusCode};
use bytes::Bytes;
use hyper::body::Incoming;
use hyper_util::rt::TokioIo;
use hyper_util::service::TowerToHyperService;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Notify, watch};
use tokio::time::{Instant, Sleep};

use super::AppState;
use super::metrics::{Shed, Stage};

/// Where a connection is, as far as deadlines go.
#[derive(Debug, Clone, Copy)]
enum Phase {
    /// No request in flight since `since` (accept, or the end of the last response). `head`: when
    /// the header deadline started; `None` while a kept-alive connection is idle.
    Waiting { since: Instant, head: Option<Instant> },
    /// A request in flight, from its head to the end of its response body.
    Busy,
    /// Upgraded to a WebSocket.
    Upgraded,
}

/// One connection as the registry and its socket see it.
#[derive(Debug)]
struct Conn {
    phase: Mutex<Phase>,
    /// The task last waiting to read: hyper does not read again when a response ends (it already
    /// waits on the socket), so the end of a request wakes it to arm the idle deadline.
    reader: Mutex<Option<Waker>>,
    /// A write is blocked: hyper holds bytes of a response that the client has not taken yet
    /// (the last ones may still be there after the body ended).
    flushing: AtomicBool,
    /// Picked by the bound to close (picked once).
    evicting: AtomicBool,
    evict: Notify,
}

impl Conn {
    fn phase(&self) -> MutexGuard<'_, Phase> {
        self.phase.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// No request in flight and nothing left to write: closing loses nothing but the socket.
    fn quiet(&self) -> bool {
        matches!(*self.phase(), Phase::Waiting { .. }) && !self.flushing.load(Relaxed)
    }

    /// Wakes the task so that its next read arms the deadline of the new phase.
    fn wake_reader(&self) {
        let waker = self.reader.lock().unwrap_or_else(PoisonError::into_inner).take();
        if let Some(w) = waker {
            w.wake();
        }
    }

    /// The last response's bytes are all with the kernel: the wait for the next request starts.
    fn flushed(&self) {
        {
            let mut phase = self.phase();
            let Phase::Waiting { since, head } = &mut *phase else {
                return;
            };
            let now = Instant::now();
            *since = now;
            if head.is_some() {
                *head = Some(now);
            }
        }
        self.wake_reader();
    }
}

/// The open connections.
#[derive(Debug, Default)]
struct Registry {
    conns: Mutex<HashMap<u64, Arc<Conn>>>,
    next_id: AtomicU64,
}

impl Registry {
    fn conns(&self) -> MutexGuard<'_, HashMap<u64, Arc<Conn>>> {
        self.conns.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn len(&self) -> usize {
        self.conns().len()
    }

    /// Registers a new connection; the header deadline starts now.
    fn admit(self: &Arc<Self>, state: &AppState) -> Slot {
        let now = Instant::now();
        let conn = Arc::new(Conn {
            phase: Mutex::new(Phase::Waiting {
                since: now,
                head: Some(now),
            }),
            reader: Mutex::new(None),
            flushing: AtomicBool::new(false),
            evicting: AtomicBool::new(false),
            evict: Notify::new(),
        });
        let id = self.next_id.fetch_add(1, Relaxed);
        self.conns().insert(id, conn.clone());
        state.inner.metrics.connections(1);
        Slot {
            id,
            conn,
            registry: self.clone(),
            state: state.clone(),
        }
    }

    /// Tells the connection that has waited longest without a request in flight to close.
    /// `false` when every connection is busy or upgraded. O(open connections), only at the bound.
    fn evict_oldest(&self) -> bool {
        let conns = self.conns();
        let mut oldest: Option<(Instant, &Arc<Conn>)> = None;
        for c in conns.values() {
            if c.evicting.load(Relaxed) || c.flushing.load(Relaxed) {
                continue;
            }
            if let Phase::Waiting { since, .. } = *c.phase()
                && oldest.is_none_or(|(t, _)| since < t)
            {
                oldest = Some((since, c));
            }
        }
        let Some((_, c)) = oldest else { return false };
        c.evicting.store(true, Relaxed);
        c.evict.notify_one();
        true
    }
}

/// A connection's place in the registry, given back when its socket is dropped (which, for a
/// WebSocket, is when the socket closes, long after hyper let go of it).
#[derive(Debug)]
struct Slot {
    id: u64,
    conn: Arc<Conn>,
    registry: Arc<Registry>,
    state: AppState,
}

impl Drop for Slot {
    fn drop(&mut self) {
        self.registry.conns().remove(&self.id);
        self.state.inner.metrics.connections(-1);
    }
}

/// The deadlines [`TimedIo`] keeps.
#[derive(Debug, Clone, Copy)]
struct Timeouts {
    header: Duration,
    idle: Duration,
    write: Duration,
}

/// Polls `timer` set to `deadline` (re-armed when the deadline moved); true once it has passed.
fn expired(timer: &mut Option<(Instant, Pin<Box<Sleep>>)>, deadline: Instant, cx: &mut Context<'_>) -> bool {
    if let Some((at, sleep)) = timer {
        if *at != deadline {
            sleep.as_mut().reset(deadline);
            *at = deadline;
        }
        sleep.as_mut().poll(cx).is_ready()
    } else {
        let mut sleep = Box::pin(tokio::time::sleep_until(deadline));
        let done = sleep.as_mut().poll(cx).is_ready();
        *timer = Some((deadline, sleep));
        done
    }
}

fn timed_out(what: &str) -> io::Error {
    io::Error::new(io::ErrorKind::TimedOut, format!("{what} timed out"))
}

/// A client socket with the read and write deadlines of its connection's phase.
#[derive(Debug)]
struct TimedIo {
    // The slot is given back before the socket closes: whoever sees the close sees it counted.
    slot: Slot,
    tcp: TcpStream,
    timeouts: Timeouts,
    read_timer: Option<(Instant, Pin<Box<Sleep>>)>,
    write_timer: Option<(Instant, Pin<Box<Sleep>>)>,
    /// When the current write first made no progress.
    write_stalled: Option<Instant>,
}

impl TimedIo {
    /// Fails a write that has made no progress for the write timeout.
    fn write_deadline<T>(&mut self, r: Poll<io::Result<T>>, cx: &mut Context<'_>) -> Poll<io::Result<T>> {
        let conn = &self.slot.conn;
        if r.is_ready() {
            if self.write_stalled.take().is_some() {
                conn.flushing.store(false, Relaxed);
                conn.flushed();
            }
            return r;
        }
        let since = *self.write_stalled.get_or_insert_with(|| {
            conn.flushing.store(true, Relaxed);
            Instant::now()
        });
        if expired(&mut self.write_timer, since + self.timeouts.write, cx) {
            self.slot.state.inner.metrics.timeout(Stage::Write);
            return Poll::Ready(Err(timed_out("response write")));
        }
        Poll::Pending
    }
}

impl AsyncRead for TimedIo {
    fn poll_read(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        match Pin::new(&mut this.tcp).poll_read(cx, buf) {
            Poll::Ready(Ok(())) => {
                // The first byte of a kept-alive connection's next head starts its header deadline.
                // (A head that came pipelined, in the last request's read, is under the idle one.)
                if buf.filled().len() > before
                    && let Phase::Waiting { head: head @ None, .. } = &mut *this.slot.conn.phase()
                {
                    *head = Some(Instant::now());
                }
                Poll::Ready(Ok(()))
            }
            Poll::Pending => {
                {
                    let mut reader = this.slot.conn.reader.lock().unwrap_or_else(PoisonError::into_inner);
                    if !reader.as_ref().is_some_and(|w| w.will_wake(cx.waker())) {
                        *reader = Some(cx.waker().clone());
                    }
                }
                // While a response is still being written the write deadline is the one that runs.
                if this.slot.conn.flushing.load(Relaxed) {
                    return Poll::Pending;
                }
                let (deadline, stage) = match *this.slot.conn.phase() {
                    Phase::Waiting { head: Some(h), .. } => (h + this.timeouts.header, Stage::Header),
                    Phase::Waiting { since, head: None } => (since + this.timeouts.idle, Stage::Idle),
                    Phase::Busy | Phase::Upgraded => return Poll::Pending,
                };
                if expired(&mut this.read_timer, deadline, cx) {
                    this.slot.state.inner.metrics.timeout(stage);
                    let what = if stage == Stage::Header {
                        "request head"
                    } else {
                        "idle keep-alive"
                    };
                    return Poll::Ready(Err(timed_out(what)));
                }
                Poll::Pending
            }
            err @ Poll::Ready(Err(_)) => err,
        }
    }
}

impl AsyncWrite for TimedIo {
    fn poll_write(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        let r = Pin::new(&mut this.tcp).poll_write(cx, buf);
        this.write_deadline(r, cx)
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        let r = Pin::new(&mut this.tcp).poll_write_vectored(cx, bufs);
        this.write_deadline(r, cx)
    }

    fn is_write_vectored(&self) -> bool {
        self.tcp.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let r = Pin::new(&mut this.tcp).poll_flush(cx);
        this.write_deadline(r, cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let r = Pin::new(&mut this.tcp).poll_shutdown(cx);
        this.write_deadline(r, cx)
    }
}

/// Marks a request in flight on its connection, from its head until its response body is done,
/// and counts it in `canopy_http_requests_in_flight`.
#[derive(Debug)]
struct Busy {
    conn: Arc<Conn>,
    state: AppState,
}

impl Busy {
    fn begin(conn: &Arc<Conn>, state: &AppState) -> Self {
        *conn.phase() = Phase::Busy;
        state.inner.metrics.in_flight(1);
        Self {
            conn: conn.clone(),
            state: state.clone(),
        }
    }

    fn upgraded(&self) {
        let mut phase = self.conn.phase();
        if matches!(*phase, Phase::Busy) {
            self.state.inner.metrics.in_flight(-1);
        }
        *phase = Phase::Upgraded;
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        {
            let mut phase = self.conn.phase();
            if !matches!(*phase, Phase::Busy) {
                return;
            }
            self.state.inner.metrics.in_flight(-1);
            *phase = Phase::Waiting {
                since: Instant::now(),
                head: None,
            };
        }
        self.conn.wake_reader();
    }
}

/// A response body that holds its request's [`Busy`] mark until hyper has taken all of it.
#[derive(Debug)]
struct Tracked {
    body: Body,
    _busy: Busy,
}

impl http_body::Body for Tracked {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.get_mut().body).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.body.size_hint()
    }
}

/// Resolves once `stop` says so (never if it was dropped without saying it).
async fn stopped(stop: &mut watch::Receiver<bool>) {
    let gone = stop.wait_for(|s| *s).await.is_err();
    if gone {
        std::future::pending::<()>().await;
    }
}

/// Serves one connection until it ends, is evicted, or the server stops.
async fn serve_conn(tcp: TcpStream, slot: Slot, app: Router, timeouts: Timeouts, alive: watch::Receiver<()>) {
    let conn = slot.conn.clone();
    let mut stop = slot.state.inner.shutdown.clone();
    // The client's address, for the rate limits of the scene API.
    let peer = tcp.peer_addr().ok().map(|a| super::quota::Peer(a.ip()));
    let hooks_state = slot.state.clone();
    let io = TimedIo {
        slot,
        tcp,
        timeouts,
        read_timer: None,
        write_timer: None,
        write_stalled: None,
    };
    let app = TowerToHyperService::new(app);
    let hooks = conn.clone();
    let service = hyper::service::service_fn(move |mut req: Request<Incoming>| {
        if let Some(p) = peer {
            req.extensions_mut().insert(p);
        }
        let busy = Busy::begin(&hooks, &hooks_state);
        let answer = hyper::service::Service::call(&app, req);
        async move {
            let resp: Response<Body> = match answer.await {
                Ok(r) => r,
                Err(never) => match never {},
            };
            if resp.status() == StatusCode::SWITCHING_PROTOCOLS {
                busy.upgraded();
            }
            Ok::<_, Infallible>(resp.map(|body| Tracked { body, _busy: busy }))
        }
    });
    let mut http = pin!(
        hyper::server::conn::http1::Builder::new()
            // hyper's own header timeout would also cut idle keep-alive at the same length.
            .header_read_timeout(Option::<Duration>::None)
            .serve_connection(TokioIo::new(io), service)
            .with_upgrades()
    );
    let mut closing = false;
    loop {
        tokio::select! {
            r = http.as_mut() => {
                if let Err(e) = r {
                    tracing::debug!(error = %e, "connection closed");
                }
                break;
            }
            () = conn.evict.notified(), if !closing => {}
            () = stopped(&mut stop), if !closing => {}
        }
        // Evicted or stopping: close now unless a request is in flight or its response is still
        // being written, which may finish first (hyper's graceful shutdown flushes before it
        // closes, but would not close a connection that never sent a request).
        if conn.quiet() {
            break;
        }
        http.as_mut().graceful_shutdown();
        closing = true;
    }
    drop(alive);
}

/// What a connection the bound cannot take gets: a JSON error, as the API's, and `Retry-After`.
static REFUSED: LazyLock<Vec<u8>> = LazyLock::new(|| {
    let body = r#"{"error":"server busy: too many open connections, retry later"}"#;
    format!(
        "HTTP/1.1 503 Service Unavailable\r\nRetry-After: 1\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\nAccess-Control-Allow-Origin: *\r\n\r\n{body}",
        body.len()
    )
    .into_bytes()
});

/// Answers 503 and lets the socket close, without a task or a parse: refusing must cost less
/// than serving.
fn refuse(tcp: &TcpStream) {
    // Whatever the request already sent is read first: closing with unread input sends a reset,
    // which can destroy the answer before the client reads it.
    let mut sink = [0u8; 2048];
    let _ = tcp.try_read(&mut sink);
    let _ = tcp.try_write(&REFUSED);
}

fn is_connection_error(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionRefused | io::ErrorKind::ConnectionAborted | io::ErrorKind::ConnectionReset
    )
}

/// Accepts connections on `listener` and serves `app` on each until `shutdown` resolves; then
/// stops accepting, closes connections without a request in flight, and returns once the others
/// have finished theirs (upgraded sockets are not waited for here).
pub(super) async fn serve(listener: TcpListener, app: Router, state: &AppState, shutdown: impl Future<Output = ()>) {
    let config = &state.inner.config;
    let timeouts = Timeouts {
        header: config.header_timeout,
        idle: config.idle_timeout,
        write: config.write_timeout,
    };
    let max = config.max_connections.max(1);
    let metrics = &state.inner.metrics;
    let registry = Arc::new(Registry::default());
    let (alive_tx, alive_rx) = watch::channel(());
    let mut shutdown = pin!(shutdown);
    loop {
        let accepted = tokio::select! {
            r = listener.accept() => r,
            () = &mut shutdown => break,
        };
        let tcp = match accepted {
            Ok((tcp, _)) => tcp,
            Err(e) if is_connection_error(&e) => continue,
            Err(e) => {
                // Out of descriptors (or memory): free one and back off rather than spin.
                tracing::warn!(error = %e, open = registry.len(), "accept failed");
                if registry.evict_oldest() {
                    metrics.shed(Shed::Evicted);
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let _ = tcp.set_nodelay(true);
        if registry.len() >= max {
            if registry.evict_oldest() {
                metrics.shed(Shed::Evicted);
            } else {
                metrics.shed(Shed::Refused);
                refuse(&tcp);
                continue;
            }
        }
        let slot = registry.admit(state);
        tokio::spawn(serve_conn(tcp, slot, app.clone(), timeouts, alive_rx.clone()));
    }
    drop(listener);
    drop(alive_rx);
    alive_tx.closed().await;
}

/// The process's soft limit on open descriptors (`RLIMIT_NOFILE`), read from `/proc/self/limits`
/// (no `libc` call, which would need `unsafe`); `None` off Linux or when unlimited.
pub fn descriptor_limit() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/self/limits").ok()?;
    let rest = text.lines().find_map(|l| l.strip_prefix("Max open files"))?;
    rest.split_whitespace().next()?.parse().ok()
}

/// The default bound on open connections: half the descriptor limit (the other half is for asset
/// files, the database and the listener), at least 64 and at most 16,384 (an idle connection
/// holds about 9 KiB, mostly hyper's read buffer); 1,024 when the limit is unknown.
pub fn default_max_connections() -> usize {
    static MAX: OnceLock<usize> = OnceLock::new();
    *MAX.get_or_init(|| descriptor_limit().map_or(1024, |n| (n / 2).clamp(64, 16_384) as usize))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_refusal_is_one_well_formed_response() {
        let text = String::from_utf8(REFUSED.clone()).expect("ascii");
        let (head, body) = text.split_once("\r\n\r\n").expect("head");
        assert!(head.starts_with("HTTP/1.1 503 "));
        let len: usize = head
            .lines()
            .find_map(|l| l.strip_prefix("Content-Length: "))
            .and_then(|v| v.parse().ok())
            .expect("length");
        assert_eq!(len, body.len());
        let v: serde_json::Value = serde_json::from_str(body).expect("JSON");
        assert!(v["error"].is_string());
    }

    #[test]
    fn the_default_bound_follows_the_descriptor_limit() {
        let n = default_max_connections();
        assert!((64..=16_384).contains(&n), "{n}");
        if let Some(limit) = descriptor_limit() {
            assert!(n as u64 <= limit.max(128) / 2, "{n} of {limit}");
        }
    }
}
