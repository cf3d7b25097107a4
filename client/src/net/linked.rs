//! A source behind a modelled link on a virtual clock: every request is served by the inner
//! source at once, then held until the [`LinkSim`] says its last byte has arrived. Headless
//! runs (`fly`, `eval`, `demo`) stream through it so that their figures depend on the link and
//! the frame time, never on how loaded the machine is.
//!
//! The clock moves only when the driver calls [`LinkedSource::advance_to`], and only while every
//! task that sends requests on the source (each holds a [`TaskToken`] from
//! [`RangeSource::task`]) is parked on a transfer: a task that has work to do (decoding what
//! arrived, sending its next request) does it at the instant its bytes arrived. Requests sent at
//! one instant start in a fixed order (by path and ranges), so a run is deterministic.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

use bytes::Bytes;
use tokio::sync::{Notify, oneshot};

use super::link::{LinkCounters, LinkModel, LinkSim, TransferId, request_wire_bytes, response_wire_bytes};
use super::{ByteRange, NetError, NetStats, RangeSource, TaskToken};

#[derive(Debug)]
struct State {
    sim: LinkSim,
    waiters: HashMap<TransferId, oneshot::Sender<()>>,
    /// Live task tokens.
    tasks: usize,
    /// Tasks parked on a transfer.
    parked: usize,
}

#[derive(Debug)]
struct Shared {
    state: Mutex<State>,
    changed: Notify,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        // The state stays consistent under a panic elsewhere: every update is one statement.
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// Decrements the task count when dropped.
#[derive(Debug)]
struct TaskGuard(Arc<Shared>);

impl Drop for TaskGuard {
    fn drop(&mut self) {
        self.0.lock().tasks -= 1;
        self.0.changed.notify_waiters();
    }
}

/// A [`RangeSource`] behind a modelled link on a virtual clock (see the module doc).
#[derive(Debug)]
pub struct LinkedSource<S> {
    inner: S,
    shared: Arc<Shared>,
}

/// A deterministic tie-break for requests sent at one instant (FNV-1a of path and ranges).
fn order_key(path: &str, ranges: &[ByteRange]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |b: &[u8]| {
        for &x in b {
            h ^= u64::from(x);
            h = h.wrapping_mul(0x0100_0000_01b3);
        }
    };
    eat(path.as_bytes());
    for r in ranges {
        eat(&r.start.to_le_bytes());
        eat(&r.end.to_le_bytes());
    }
    h
}

impl<S: RangeSource> LinkedSource<S> {
    /// `inner` behind `model`, at time 0.
    pub fn new(inner: S, model: LinkModel) -> Self {
        Self {
            inner,
            shared: Arc::new(Shared {
                state: Mutex::new(State {
                    sim: LinkSim::new(model),
                    waiters: HashMap::new(),
                    tasks: 0,
                    parked: 0,
                }),
                changed: Notify::new(),
            }),
        }
    }

    /// The inner source.
    pub fn inner(&self) -> &S {
        &self.inner
    }

    /// The link.
    pub fn model(&self) -> LinkModel {
        self.shared.lock().sim.model().clone()
    }

    /// The virtual clock, seconds.
    pub fn now(&self) -> f64 {
        self.shared.lock().sim.now()
    }

    /// The link's counters so far.
    pub fn counters(&self) -> LinkCounters {
        self.shared.lock().sim.counters()
    }

    /// Transfers sent and not arrived.
    pub fn in_flight(&self) -> usize {
        self.shared.lock().sim.in_flight()
    }

    /// Waits until every task holding a token is parked on a transfer (or gone).
    pub async fn settle(&self) {
        loop {
            let notified = self.shared.changed.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            {
                let st = self.shared.lock();
                if st.parked >= st.tasks {
                    return;
                }
            }
            notified.await;
        }
    }

    /// Runs the clock to `t` seconds: each transfer that completes on the way wakes its task,
    /// which runs (and may send more) at that instant before the clock moves on.
    pub async fn advance_to(&self, t: f64) {
        loop {
            self.settle().await;
            let mut st = self.shared.lock();
            let Some(next) = st.sim.next_event().filter(|&n| n <= t) else {
                st.sim.advance(t);
                return;
            };
            let done = st.sim.advance(next);
            for (id, _) in done {
                if let Some(tx) = st.waiters.remove(&id) {
                    st.parked -= 1;
                    let _ = tx.send(());
                }
            }
        }
    }

    /// Sends `up`/`down` wire bytes over the link now and waits until they have arrived.
    async fn carry(&self, up: f64, down: f64, order: u64) {
        let rx = {
            let mut st = self.shared.lock();
            let id = st.sim.submit(up, down, order);
            let (tx, rx) = oneshot::channel();
            st.waiters.insert(id, tx);
            st.parked += 1;
            rx
        };
        self.shared.changed.notify_waiters();
        // A dropped sender (the source dropped) ends the wait as well.
        let _ = rx.await;
    }
}

impl<S: RangeSource> RangeSource for LinkedSource<S> {
    async fn get(&self, path: &str) -> Result<Bytes, NetError> {
        let r = self.inner.get(path).await;
        let body = r.as_ref().map_or(0, |b| b.len() as u64);
        self.carry(
            request_wire_bytes(0),
            response_wire_bytes(body, 1),
            order_key(path, &[]),
        )
        .await;
        r
    }

    async fn fetch(&self, path: &str, ranges: &[ByteRange]) -> Result<Vec<Bytes>, NetError> {
        let r = self.inner.fetch(path, ranges).await;
        let body: u64 = r.as_ref().map_or(0, |b| b.iter().map(|x| x.len() as u64).sum());
        let n = if r.is_ok() { ranges.len() } else { 1 };
        self.carry(
            request_wire_bytes(ranges.len()),
            response_wire_bytes(body, n),
            order_key(path, ranges),
        )
        .await;
        r
    }

    fn stats(&self) -> &NetStats {
        self.inner.stats()
    }

    fn clock(&self) -> Option<f64> {
        Some(self.now())
    }

    fn task(&self) -> TaskToken {
        self.shared.lock().tasks += 1;
        TaskToken::new(TaskGuard(Arc::clone(&self.shared)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::net::file::FileSource;

    fn source(name: &str, link: &str) -> Arc<LinkedSource<FileSource>> {
        let dir = std::env::temp_dir().join(format!("canopy-linked-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("test setup");
        std::fs::write(dir.join("a.bin"), vec![7u8; 200_000]).expect("test setup");
        Arc::new(LinkedSource::new(
            FileSource::new(dir),
            link.parse().expect("test setup"),
        ))
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn transfers_arrive_on_the_virtual_clock() {
        // 1.6 Mbit/s = 200 kB/s, 100 ms.
        let src = source("arrive", "1.6,100");
        let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
        for k in 0..2u64 {
            let s = Arc::clone(&src);
            let tx = tx.clone();
            let token = s.task();
            tokio::spawn(async move {
                let _token = token;
                let range = k * 100_000..k * 100_000 + 100_000;
                let r = s.fetch("/a.bin", std::slice::from_ref(&range)).await;
                let _ = tx.send((k, r.map(|b| b[0].len()).ok(), s.now()));
            });
        }
        // Nothing arrives before the bytes could have.
        src.advance_to(0.5).await;
        assert!(rx.try_recv().is_err());
        src.advance_to(10.0).await;
        let mut got = vec![rx.try_recv().expect("test setup"), rx.try_recv().expect("test setup")];
        got.sort_by_key(|g| g.0);
        // Two bodies of ~104 kB share 200 kB/s after handshake, request and first byte.
        for (_, len, _) in &got {
            assert_eq!(*len, Some(100_000));
        }
        let c = src.counters();
        assert_eq!(c.transfers, 2);
        assert!(c.wire_bytes > 200_000.0 && c.wire_bytes < 210_000.0, "{c:?}");
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_chain_of_requests_runs_at_the_instants_its_bytes_arrive() {
        let src = source("chain", "8,100");
        let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
        let s = Arc::clone(&src);
        let token = s.task();
        tokio::spawn(async move {
            let _token = token;
            let mut times = Vec::new();
            for _ in 0..3 {
                let _ = s.fetch("/a.bin", std::slice::from_ref(&(0..10))).await;
                times.push(s.now());
            }
            let _ = tx.send(times);
        });
        src.advance_to(5.0).await;
        let times = rx.try_recv().expect("test setup");
        // Handshake + one round trip, then one round trip each (bytes take ~0.4 ms).
        let want = [0.2, 0.3, 0.4];
        for (t, w) in times.iter().zip(want) {
            assert!((t - w).abs() < 0.002, "{times:?}");
        }
    }
}
