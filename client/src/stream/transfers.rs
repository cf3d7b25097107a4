//! The transfers stage: the network work of the stream, off the frame. Tile loads, model
//! openings and unit requests run as tasks; the frame starts them and, next time, takes what has
//! arrived ([`Transfers::drain`]) without ever waiting for a byte. It also estimates the link
//! (throughput while work is pending, round trip) and from that sizes the window of requests
//! in flight: about one bandwidth-delay product, so the link stays busy while what is not sent
//! yet can still be re-prioritised by the next frame.
//!
//! Conventions: times are the stream's clock (the sum of the frames' `dt`, seconds); bytes are
//! response body bytes as the source counts them.

use std::collections::{BTreeSet, HashMap, VecDeque};
use std::sync::Arc;

use bytes::Bytes;
use tokio::sync::mpsc::{UnboundedReceiver, UnboundedSender, unbounded_channel};

use super::model::ModelIndex;
use canopy_shared::format::Directory;

use super::model::open::{GeometryPart, OPEN_REQUEST_LEN, OpenError, OpeningReads, open_geometry, open_stand_ins};
use super::schedule::Request;
use crate::cache::BlockKey;
use crate::net::{ByteRange, NetError, RangeSource};

/// Least bytes in flight the window allows (one request of a few leaf blocks on any link).
pub const MIN_WINDOW_BYTES: u64 = 64 * 1024;
/// Bytes in flight before the link has been measured.
pub const FIRST_WINDOW_BYTES: u64 = 256 * 1024;
/// Most unit requests in flight (a browser's HTTP/1.1 connections per host).
pub const MAX_UNIT_REQUESTS: usize = 6;
/// Seconds of measured throughput the window holds beyond the round trip: enough to keep the
/// link busy between frames, short enough that the next frame's priorities apply soon.
pub const WINDOW_EXTRA_S: f64 = 0.25;
/// Completed transfers kept for the estimate.
pub const ESTIMATE_SAMPLES: usize = 64;
/// Seconds the rate estimate looks back over.
pub const RATE_HORIZON_S: f64 = 2.0;
/// Completed transfers the estimate uses however old they are (a quiet link keeps its estimate).
const MIN_SAMPLES: usize = 4;
/// Transfers this small measure the round trip rather than the rate, bytes.
const SMALL_TRANSFER_BYTES: u64 = 16 * 1024;

/// Bytes of a model's geometry part: its node table, materials and skeleton-radii sections.
pub(crate) fn geometry_part_len(directory: &Directory) -> u64 {
    use canopy_shared::format::directory::SectionKind;
    [
        SectionKind::NodeTable,
        SectionKind::Materials,
        SectionKind::SkeletonRadii,
    ]
    .into_iter()
    .filter_map(|k| directory.section(k))
    .map(|e| e.length)
    .sum()
}

/// Something that arrived.
#[derive(Debug)]
pub(crate) enum Arrival {
    /// Instance tiles (indexes into the manifest's tiles) and their bodies.
    Tiles {
        tiles: Vec<usize>,
        result: Result<Vec<Bytes>, NetError>,
    },
    /// Terrain tiles (indexes into the manifest's terrain tiles) and their bodies.
    Terrain {
        tiles: Vec<usize>,
        result: Result<Vec<Bytes>, NetError>,
    },
    /// A model's opening (its stand-ins part).
    Opened {
        model: usize,
        result: Box<Result<(ModelIndex, OpeningReads), OpenError>>,
    },
    /// A model's geometry part.
    Geometry {
        model: usize,
        result: Box<Result<(GeometryPart, OpeningReads), OpenError>>,
    },
    /// A unit request's bodies.
    Units {
        request: Request,
        result: Result<Vec<Bytes>, NetError>,
    },
}

#[derive(Debug, Clone, Copy)]
struct Sent {
    at: f64,
    bytes: u64,
}

/// A completed transfer, for the estimate.
#[derive(Debug, Clone, Copy)]
struct Done {
    sent: f64,
    arrived: f64,
    bytes: u64,
}

/// The link as the client sees it.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct LinkEstimate {
    /// Bytes over the time some measured transfer was in flight, bytes/s (`None` before any;
    /// infinite where they took no time).
    pub rate: Option<f64>,
    /// Shortest latency of a small transfer lately, seconds.
    pub rtt: Option<f64>,
}

/// The stream's clock: the source's where it has one, else wall time since the stream began.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Clock(std::time::Instant);

impl Clock {
    pub fn new() -> Self {
        Self(std::time::Instant::now())
    }

    pub fn now<S: RangeSource>(&self, src: &S) -> f64 {
        src.clock().unwrap_or_else(|| self.0.elapsed().as_secs_f64())
    }
}

/// Work in flight, and the link estimate.
#[derive(Debug)]
pub(crate) struct Transfers {
    clock: Clock,
    tx: UnboundedSender<(u64, f64, Arrival)>,
    rx: UnboundedReceiver<(u64, f64, Arrival)>,
    next_id: u64,
    sent: HashMap<u64, Sent>,
    /// Tiles being loaded.
    pub tiles: BTreeSet<usize>,
    /// Terrain tiles being loaded.
    pub terrain: BTreeSet<usize>,
    /// Models being opened.
    pub opening: BTreeSet<usize>,
    /// Models whose geometry part is being opened.
    pub opening_geometry: BTreeSet<usize>,
    /// Units in flight, per model: key and range.
    units: HashMap<usize, Vec<(BlockKey, ByteRange)>>,
    unit_requests: usize,
    unit_bytes: u64,
    /// Recent completed transfers, oldest first.
    done: VecDeque<Done>,
    /// Arrivals received by [`Self::wait`], not drained yet.
    early: Vec<(u64, f64, Arrival)>,
}

impl Transfers {
    pub fn new(clock: Clock) -> Self {
        let (tx, rx) = unbounded_channel();
        Self {
            clock,
            tx,
            rx,
            next_id: 0,
            sent: HashMap::new(),
            tiles: BTreeSet::new(),
            terrain: BTreeSet::new(),
            opening: BTreeSet::new(),
            opening_geometry: BTreeSet::new(),
            units: HashMap::new(),
            unit_requests: 0,
            unit_bytes: 0,
            done: VecDeque::new(),
            early: Vec::new(),
        }
    }

    /// Waits until something arrives, unless nothing is in flight.
    pub async fn wait(&mut self) {
        if self.sent.len() > self.early.len()
            && let Some(a) = self.rx.recv().await
        {
            self.early.push(a);
        }
    }

    /// Runs `work` as a task holding the source's task token; its result comes back through
    /// [`Self::drain`], stamped with the time it arrived.
    fn spawn<S, F>(&mut self, src: &Arc<S>, bytes: u64, work: F)
    where
        S: RangeSource,
        F: Future<Output = Arrival> + Send + 'static,
    {
        let id = self.next_id;
        self.next_id += 1;
        let at = self.clock.now(src.as_ref());
        self.sent.insert(id, Sent { at, bytes });
        let tx = self.tx.clone();
        let token = src.task();
        let (s, clock) = (Arc::clone(src), self.clock);
        tokio::spawn(async move {
            let _token = token;
            let a = work.await;
            // The stream may have gone: nothing to deliver to then.
            let _ = tx.send((id, clock.now(s.as_ref()), a));
        });
    }

    /// Starts loading `tiles` (their ranges of the pack at `url`).
    pub fn load_tiles<S: RangeSource>(&mut self, src: &Arc<S>, url: &str, tiles: Vec<usize>, ranges: Vec<ByteRange>) {
        self.tiles.extend(&tiles);
        let bytes = ranges.iter().map(|r| r.end - r.start).sum();
        let (s, url) = (Arc::clone(src), url.to_string());
        self.spawn(src, bytes, async move {
            let result = s.fetch(&url, &ranges).await;
            Arrival::Tiles { tiles, result }
        });
    }

    /// Starts loading terrain tiles.
    pub fn load_terrain<S: RangeSource>(&mut self, src: &Arc<S>, url: &str, tiles: Vec<usize>, ranges: Vec<ByteRange>) {
        self.terrain.extend(&tiles);
        let bytes = ranges.iter().map(|r| r.end - r.start).sum();
        let (s, url) = (Arc::clone(src), url.to_string());
        self.spawn(src, bytes, async move {
            let result = s.fetch(&url, &ranges).await;
            Arrival::Terrain { tiles, result }
        });
    }

    /// Starts opening model `m` (its stand-ins part).
    pub fn open<S: RangeSource>(&mut self, src: &Arc<S>, m: usize, url: &str, size: u64) {
        self.opening.insert(m);
        let (s, url) = (Arc::clone(src), url.to_string());
        // Its size is known once it has arrived: the first request's, for the backlog.
        self.spawn(src, OPEN_REQUEST_LEN.min(size), async move {
            let result = Box::new(open_stand_ins(s.as_ref(), &url, size).await);
            Arrival::Opened { model: m, result }
        });
    }

    /// Starts opening model `m`'s geometry part.
    pub fn open_geometry<S: RangeSource>(
        &mut self,
        src: &Arc<S>,
        m: usize,
        url: &str,
        directory: Directory,
        head: Bytes,
    ) {
        self.opening_geometry.insert(m);
        let (s, url) = (Arc::clone(src), url.to_string());
        let bytes = geometry_part_len(&directory);
        self.spawn(src, bytes, async move {
            let result = Box::new(open_geometry(s.as_ref(), &url, &directory, &head).await);
            Arrival::Geometry { model: m, result }
        });
    }

    /// Sends one unit request.
    pub fn request<S: RangeSource>(&mut self, src: &Arc<S>, url: &str, request: Request) {
        let bytes: u64 = request.ranges.iter().map(|r| r.end - r.start).sum();
        let list = self.units.entry(request.model).or_default();
        list.extend(request.wants.iter().map(|w| (w.key, w.range.clone())));
        self.unit_requests += 1;
        self.unit_bytes += bytes;
        let (s, url) = (Arc::clone(src), url.to_string());
        self.spawn(src, bytes, async move {
            let result = s.fetch(&url, &request.ranges).await;
            Arrival::Units { request, result }
        });
    }

    /// Whether unit `key` of model `m` is in flight.
    pub fn has_unit(&self, m: usize, key: BlockKey) -> bool {
        self.units.get(&m).is_some_and(|l| l.iter().any(|(k, _)| *k == key))
    }

    /// Whether some unit of model `m` in flight overlaps `a..b`.
    pub fn overlaps(&self, m: usize, a: u64, b: u64) -> bool {
        self.units
            .get(&m)
            .is_some_and(|l| l.iter().any(|(_, r)| r.start < b && a < r.end))
    }

    /// Unit requests and their bytes in flight.
    pub fn units_in_flight(&self) -> (usize, u64) {
        (self.unit_requests, self.unit_bytes)
    }

    /// Transfers in flight (tiles, openings, unit requests).
    pub fn in_flight(&self) -> usize {
        self.sent.len()
    }

    /// Bytes in flight (an opening's first request counted until it arrives).
    pub fn bytes_in_flight(&self) -> u64 {
        self.sent.values().map(|s| s.bytes).sum()
    }

    /// What arrived since the last call; the in-flight sets and the estimate follow.
    pub fn drain(&mut self) -> Vec<Arrival> {
        let mut out = Vec::new();
        let mut got: Vec<(u64, f64, Arrival)> = std::mem::take(&mut self.early);
        while let Ok(x) = self.rx.try_recv() {
            got.push(x);
        }
        for (id, arrived, a) in got {
            let mut bytes = self.sent.get(&id).map_or(0, |s| s.bytes);
            match &a {
                Arrival::Tiles { tiles, .. } => {
                    for t in tiles {
                        self.tiles.remove(t);
                    }
                }
                Arrival::Terrain { tiles, .. } => {
                    for t in tiles {
                        self.terrain.remove(t);
                    }
                }
                Arrival::Opened { model, result } => {
                    self.opening.remove(model);
                    if let Ok((_, (ranges, _))) = result.as_ref() {
                        bytes = ranges.iter().map(|r| r.end - r.start).sum();
                    }
                }
                Arrival::Geometry { model, result } => {
                    self.opening_geometry.remove(model);
                    if let Ok((_, (ranges, _))) = result.as_ref() {
                        // Past the head, which came with the opening.
                        bytes = ranges.iter().skip(1).map(|r| r.end - r.start).sum();
                    }
                }
                Arrival::Units { request, .. } => {
                    if let Some(list) = self.units.get_mut(&request.model) {
                        list.retain(|(k, _)| !request.wants.iter().any(|w| w.key == *k));
                        if list.is_empty() {
                            self.units.remove(&request.model);
                        }
                    }
                    self.unit_requests -= 1;
                    self.unit_bytes -= request.ranges.iter().map(|r| r.end - r.start).sum::<u64>();
                }
            }
            if let Some(s) = self.sent.remove(&id) {
                self.done.push_back(Done {
                    sent: s.at,
                    arrived,
                    bytes,
                });
                if self.done.len() > ESTIMATE_SAMPLES {
                    self.done.pop_front();
                }
            }
            out.push(a);
        }
        out
    }

    /// The link as measured over the last [`ESTIMATE_SAMPLES`] transfers and those in flight:
    /// the bytes that arrived over the union of their times in flight, and the shortest latency
    /// of a small one.
    pub fn estimate(&self, now: f64) -> LinkEstimate {
        // The transfers that arrived within the horizon (at least the last few), and those still
        // in flight as busy time up to now with no bytes yet: a link that has slowed down shows
        // in the estimate within the horizon, before anything completes.
        let recent = self.done.iter().filter(|d| d.arrived >= now - RATE_HORIZON_S).count();
        let used: Vec<Done> = self
            .done
            .iter()
            .skip(self.done.len() - recent.max(MIN_SAMPLES.min(self.done.len())))
            .copied()
            .collect();
        let rtt = used
            .iter()
            .filter(|d| d.bytes <= SMALL_TRANSFER_BYTES)
            .map(|d| d.arrived - d.sent)
            .reduce(f64::min);
        // Bytes flow from a round trip after a request was sent: the time before is latency,
        // not link capacity (many small requests would otherwise read as a slow link).
        let lead = rtt.unwrap_or(0.0).max(0.0);
        let mut spans: Vec<(f64, f64)> = used
            .iter()
            .map(|d| ((d.sent + lead).min(d.arrived), d.arrived.max(d.sent)))
            .collect();
        spans.extend(
            self.sent
                .values()
                .filter(|s| now > s.at + lead)
                .map(|s| (s.at + lead, now)),
        );
        spans.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut busy = 0.0;
        let mut cur: Option<(f64, f64)> = None;
        for (a, b) in spans {
            match &mut cur {
                Some((_, e)) if a <= *e => *e = e.max(b),
                _ => {
                    if let Some((s, e)) = cur {
                        busy += e - s;
                    }
                    cur = Some((a, b));
                }
            }
        }
        if let Some((s, e)) = cur {
            busy += e - s;
        }
        let bytes: u64 = used.iter().map(|d| d.bytes).sum();
        LinkEstimate {
            // No busy time: an instant link, or (after round trips) nothing measured yet.
            rate: match (bytes, busy > 0.0) {
                (0, _) => None,
                (b, true) => Some(b as f64 / busy),
                (_, false) => (lead == 0.0).then_some(f64::INFINITY),
            },
            rtt,
        }
    }

    /// Bytes the window lets be in flight: a round trip and [`WINDOW_EXTRA_S`] at the measured
    /// rate; unbounded where transfers take no time (an instant link).
    pub fn window_bytes(&self, now: f64) -> u64 {
        let e = self.estimate(now);
        match e.rate {
            Some(r) if r.is_infinite() => u64::MAX,
            Some(r) => {
                let rtt = e.rtt.unwrap_or(0.0);
                ((r * (rtt + WINDOW_EXTRA_S)) as u64).max(MIN_WINDOW_BYTES)
            }
            None => FIRST_WINDOW_BYTES,
        }
    }
}
