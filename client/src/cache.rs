//! A memory-bounded block cache, shared by every instance of a model.
//!
//! - **Keys** are `(ModelId, BlockKey)`: a model's bytes are cached once however many trees of
//!   that model are planted (instances differ only by transform), so there is no instance in
//!   the key.
//! - **Budget** counts payload bytes only (default [`DEFAULT_BUDGET_BYTES`] = 256 MiB). An
//!   insert that would exceed it evicts first; a single payload larger than the whole budget is
//!   rejected (not cached) rather than flushing everything.
//! - **Eviction** follows seed 001's "evict the least used": the entry with the **lowest use
//!   count** goes first (an insert counts as one use, each [`BlockCache::get`] hit as one more);
//!   ties go to the **least recently used** (oldest last use). Pure use counts never decay, so a
//!   block popular long ago outlives a block used a few times just now; [`BlockCache::halve_uses`]
//!   lets the caller age counts (e.g. once per second of flight).
//! - **Cost**: a lookup only updates its entry. The eviction order is a min-heap of
//!   `(uses, last use, key)` built when an insert first has to evict after lookups changed the
//!   counts (O(n)), kept while only inserts and evictions follow, and popped lazily (entries
//!   removed or touched since are skipped): the same victims as a sorted set kept up to date,
//!   without paying for it on every lookup of every frame (a B-tree took ~30 % of a frame at
//!   40,000 trees). A frame's uses of the blocks it draws go through
//!   [`BlockCache::touch_in_order`]: one pass over the table instead of one lookup per block,
//!   with the same outcome.
//! - **Counters**: hits, misses, evictions, insertions, rejections ([`CacheStats`]).
//!
//! Not thread-safe by itself; wrap it in a mutex to share it between loader tasks
//! ([`SharedBlockCache`]).

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap};
use std::hash::{BuildHasherDefault, Hasher};
use std::sync::{Arc, Mutex};

use canopy_shared::format::leaf::BandLayout;

/// Default budget: 256 MiB.
pub const DEFAULT_BUDGET_BYTES: u64 = 256 * 1024 * 1024;

/// A model (one `.ctree`), as numbered by the caller.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ModelId(pub u32);

/// A cacheable unit of a model's file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum BlockKey {
    /// Leaf block of leaf node `leaf_node` (ordinal) in band `band`.
    Leaf {
        /// Band.
        band: u8,
        /// Leaf-node ordinal.
        leaf_node: u32,
    },
    /// Skeleton bytes of iteration `iteration` alone.
    Skeleton {
        /// Iteration.
        iteration: u8,
    },
    /// One crown-hull level.
    Hull {
        /// Level.
        level: u16,
    },
    /// One billboard image.
    Atlas {
        /// Frame.
        frame: u32,
        /// Resolution index.
        resolution: u8,
    },
    /// All plane textures of one billboard-cloud level (one range, a CRC per plane).
    Cloud {
        /// Level.
        level: u8,
    },
    /// A whole section (node table, materials, …) by its kind code.
    Section {
        /// Section kind code.
        kind: u16,
    },
}

/// A fast hasher for cache keys (a few small integers): multiply-rotate per written word, as
/// rustc's FxHasher does. Keys are not attacker-chosen (the client makes them from file
/// offsets it computed), so SipHash's flood resistance buys nothing here and cost 15 % of a
/// frame in profiles.
#[derive(Debug, Default, Clone, Copy)]
pub struct KeyHasher(u64);

const KEY_HASH_SEED: u64 = 0x51_7c_c1_b7_27_22_0a_95;

impl Hasher for KeyHasher {
    fn write(&mut self, bytes: &[u8]) {
        for chunk in bytes.chunks(8) {
            let mut w = [0u8; 8];
            w[..chunk.len()].copy_from_slice(chunk);
            self.write_u64(u64::from_le_bytes(w));
        }
    }
    fn write_u8(&mut self, i: u8) {
        self.write_u64(u64::from(i));
    }
    fn write_u16(&mut self, i: u16) {
        self.write_u64(u64::from(i));
    }
    fn write_u32(&mut self, i: u32) {
        self.write_u64(u64::from(i));
    }
    fn write_u64(&mut self, i: u64) {
        self.0 = (self.0.rotate_left(5) ^ i).wrapping_mul(KEY_HASH_SEED);
    }
    fn write_usize(&mut self, i: usize) {
        self.write_u64(i as u64);
    }
    fn finish(&self) -> u64 {
        self.0
    }
}

/// Full cache key.
pub type CacheKey = (ModelId, BlockKey);

/// A cache shared between tasks.
pub type SharedBlockCache = Arc<Mutex<BlockCache>>;

/// Counters since creation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CacheStats {
    /// `get` calls that found the key.
    pub hits: u64,
    /// `get` calls that did not.
    pub misses: u64,
    /// Entries evicted to make room.
    pub evictions: u64,
    /// Entries inserted (replacements included).
    pub insertions: u64,
    /// Inserts refused because the payload exceeds the budget.
    pub rejections: u64,
}

#[derive(Debug)]
struct Entry {
    data: Arc<[u8]>,
    uses: u64,
    last: u64,
}

/// One model's blocks in use this frame, for [`BlockCache::touch_in_order`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FrameTouches {
    /// The model.
    pub model: ModelId,
    /// Per leaf node (ordinal), how many of its bands are in use (a prefix).
    pub leaf_bands: Vec<usize>,
    /// Its other blocks in use, in the order they are touched.
    pub others: Vec<BlockKey>,
}

/// The cache.
#[derive(Debug)]
pub struct BlockCache {
    budget: u64,
    used: u64,
    tick: u64,
    entries: HashMap<CacheKey, Entry, BuildHasherDefault<KeyHasher>>,
    /// `(uses, last use, key)`, least first; stale items (entry gone or touched since) are
    /// skipped. Valid only while `order_valid`.
    order: BinaryHeap<Reverse<(u64, u64, CacheKey)>>,
    /// Whether `order` holds every entry's current `(uses, last)`.
    order_valid: bool,
    stats: CacheStats,
    /// Bumped whenever the set of held blocks changes.
    generation: u64,
}

impl Default for BlockCache {
    fn default() -> Self {
        Self::new(DEFAULT_BUDGET_BYTES)
    }
}

impl BlockCache {
    /// An empty cache holding at most `budget` payload bytes.
    pub fn new(budget: u64) -> Self {
        Self {
            budget,
            used: 0,
            tick: 0,
            entries: HashMap::default(),
            order: BinaryHeap::new(),
            order_valid: false,
            stats: CacheStats::default(),
            generation: 0,
        }
    }

    /// Budget in bytes.
    pub fn budget(&self) -> u64 {
        self.budget
    }

    /// Payload bytes held.
    pub fn used_bytes(&self) -> u64 {
        self.used
    }

    /// Entries held.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether nothing is held.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Counters.
    pub fn stats(&self) -> CacheStats {
        self.stats
    }

    /// Changes whenever a block is inserted, replaced, evicted or removed (not on lookups), so
    /// callers can keep what they derived from the set of held blocks until it changes.
    pub fn generation(&self) -> u64 {
        self.generation
    }

    fn next_tick(&mut self) -> u64 {
        self.tick += 1;
        self.tick
    }

    /// Looks a block up, counting a hit (and a use) or a miss.
    pub fn get(&mut self, model: ModelId, key: BlockKey) -> Option<Arc<[u8]>> {
        let tick = self.next_tick();
        self.use_at((model, key), tick).map(|e| Arc::clone(&e.data))
    }

    /// Counts a lookup of `k` at `tick`: a hit (one more use, last used at `tick`) or a miss.
    fn use_at(&mut self, k: CacheKey, tick: u64) -> Option<&Entry> {
        let Some(e) = self.entries.get_mut(&k) else {
            self.stats.misses += 1;
            return None;
        };
        e.uses = e.uses.saturating_add(1);
        e.last = tick;
        self.order_valid = false;
        self.stats.hits += 1;
        Some(e)
    }

    /// Counts a use of each block a frame draws, exactly as calling [`Self::get`] on each would
    /// in this order: for each of `models` in turn (each model at most once), its leaf blocks
    /// band by band and, within a band, by leaf node (`Leaf { band: b, leaf_node: o }` for every
    /// `b < leaf_bands[o]`), then its `others` in their order. Same hits, misses, use counts and
    /// eviction order as those calls (use ticks keep their order; some ticks are left unused).
    ///
    /// Why: a frame touches tens of thousands of leaf blocks, and one hash lookup each is a
    /// cache miss each once the table outgrows the CPU caches (44 % of `canopy load`'s time).
    /// The leaf blocks are touched in one pass over the table instead.
    pub fn touch_in_order(&mut self, models: &[FrameTouches]) {
        // Ticks: model i's leaf block (b, o) gets leaf_base + b·n + o, its others others_base + j.
        let mut ticks = Vec::with_capacity(models.len());
        let mut leaf_visits = 0u64;
        for t in models {
            let n = t.leaf_bands.len() as u64;
            let bands = t.leaf_bands.iter().copied().max().unwrap_or(0) as u64;
            let leaf_base = self.tick + 1;
            let others_base = leaf_base + bands * n;
            ticks.push((leaf_base, others_base));
            leaf_visits += t.leaf_bands.iter().map(|&b| b as u64).sum::<u64>();
            self.tick = others_base + t.others.len() as u64 - 1;
        }
        // Which entry of `models` each model id is (ids are small: dense lookup).
        let top = models.iter().map(|t| t.model.0 as usize + 1).max().unwrap_or(0);
        let mut slot = vec![None; top];
        for (i, t) in models.iter().enumerate() {
            slot[t.model.0 as usize] = Some(i);
        }
        let mut found = 0u64;
        if leaf_visits > 0 {
            for ((model, key), e) in &mut self.entries {
                let BlockKey::Leaf { band, leaf_node } = *key else {
                    continue;
                };
                let Some(i) = slot.get(model.0 as usize).copied().flatten() else {
                    continue;
                };
                let t = &models[i];
                if t.leaf_bands
                    .get(leaf_node as usize)
                    .is_some_and(|&u| usize::from(band) < u)
                {
                    e.uses = e.uses.saturating_add(1);
                    e.last = ticks[i].0 + u64::from(band) * t.leaf_bands.len() as u64 + u64::from(leaf_node);
                    found += 1;
                }
            }
        }
        self.stats.hits += found;
        self.stats.misses += leaf_visits - found;
        if found > 0 {
            self.order_valid = false;
        }
        // The others after the leaves (a key among both keeps its later tick).
        for (t, &(_, others_base)) in models.iter().zip(&ticks) {
            for (j, &key) in t.others.iter().enumerate() {
                let _ = self.use_at((t.model, key), others_base + j as u64);
            }
        }
    }

    /// A held block without counting a hit or a use (for readers that follow the frame loop,
    /// such as the viewer's GPU upload, and must not change what the cache evicts).
    pub fn peek(&self, model: ModelId, key: BlockKey) -> Option<Arc<[u8]>> {
        self.entries.get(&(model, key)).map(|e| Arc::clone(&e.data))
    }

    /// Whether a block is held; counts nothing, changes no use.
    pub fn contains(&self, model: ModelId, key: BlockKey) -> bool {
        self.entries.contains_key(&(model, key))
    }

    /// Leaf bands of `leaf_node` held as a prefix (what [`crate::plan`] takes as "bands held"):
    /// the first band whose block is not cached. A band in which the node has no leaves has no
    /// block (the format stores nothing for an empty slice) and counts as held.
    pub fn held_leaf_bands(&self, model: ModelId, leaf_node: u32, layout: &BandLayout) -> usize {
        let bands = layout.band_count().min(256);
        (0..bands)
            .position(|b| {
                layout.block(b, leaf_node as usize).is_some()
                    && !self.contains(
                        model,
                        BlockKey::Leaf {
                            band: b as u8,
                            leaf_node,
                        },
                    )
            })
            .unwrap_or(bands)
    }

    /// Records `n` lookups that found nothing (blocks a frame needed and had to fetch): the
    /// planner tests presence without counting, so it reports its misses here.
    pub fn record_misses(&mut self, n: u64) {
        self.stats.misses += n;
    }

    /// Inserts (or replaces) a block, evicting least-used entries until it fits. Returns `false`
    /// (and caches nothing) when the payload alone exceeds the budget.
    pub fn insert(&mut self, model: ModelId, key: BlockKey, data: Arc<[u8]>) -> bool {
        let size = data.len() as u64;
        if size > self.budget {
            self.stats.rejections += 1;
            return false;
        }
        let k = (model, key);
        let uses = match self.remove_entry(k) {
            Some(old) => old.uses,
            None => 0,
        };
        self.evict_until(self.budget.saturating_sub(size));
        let tick = self.next_tick();
        let uses = uses.saturating_add(1);
        if self.order_valid {
            self.order.push(Reverse((uses, tick, k)));
            // Replaced and removed entries leave stale items: rebuild rather than let them pile up.
            if self.order.len() > 2 * self.entries.len() + 64 {
                self.invalidate_order();
            }
        }
        self.entries.insert(k, Entry { data, uses, last: tick });
        self.generation += 1;
        self.used += size;
        self.stats.insertions += 1;
        true
    }

    fn remove_entry(&mut self, k: CacheKey) -> Option<Entry> {
        let e = self.entries.remove(&k)?;
        self.generation += 1;
        // Its heap item, if any, is now stale and skipped when it comes up.
        self.used -= e.data.len() as u64;
        Some(e)
    }

    /// Drops the eviction heap (rebuilt by the next eviction) and its memory.
    fn invalidate_order(&mut self) {
        self.order_valid = false;
        self.order = BinaryHeap::new();
    }

    /// Evicts least-used entries (ties: least recently used) until at most `target` bytes are
    /// held.
    fn evict_until(&mut self, target: u64) {
        if self.used <= target {
            return;
        }
        if !self.order_valid {
            self.order = self
                .entries
                .iter()
                .map(|(k, e)| Reverse((e.uses, e.last, *k)))
                .collect();
            self.order_valid = true;
        }
        while self.used > target {
            let Some(Reverse((uses, last, victim))) = self.order.pop() else {
                break;
            };
            let current = self
                .entries
                .get(&victim)
                .is_some_and(|e| e.uses == uses && e.last == last);
            if current {
                self.remove_entry(victim);
                self.stats.evictions += 1;
            }
        }
    }

    /// Removes a block (not counted as an eviction).
    pub fn remove(&mut self, model: ModelId, key: BlockKey) -> Option<Arc<[u8]>> {
        self.remove_entry((model, key)).map(|e| e.data)
    }

    /// Removes every block of a model; returns the bytes freed.
    pub fn remove_model(&mut self, model: ModelId) -> u64 {
        let keys: Vec<CacheKey> = self.entries.keys().filter(|k| k.0 == model).copied().collect();
        let before = self.used;
        for k in keys {
            self.remove_entry(k);
        }
        before - self.used
    }

    /// Halves every use count (rounding down, at least 1 is kept), ageing old popularity.
    pub fn halve_uses(&mut self) {
        for e in self.entries.values_mut() {
            e.uses = (e.uses / 2).max(1);
        }
        self.invalidate_order();
    }

    /// Changes the budget, evicting as needed.
    pub fn set_budget(&mut self, budget: u64) {
        self.budget = budget;
        self.evict_until(budget);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const M: ModelId = ModelId(1);

    fn leaf(band: u8, leaf_node: u32) -> BlockKey {
        BlockKey::Leaf { band, leaf_node }
    }

    fn bytes(n: usize) -> Arc<[u8]> {
        vec![0u8; n].into()
    }

    #[test]
    fn default_budget_is_256_mib() {
        assert_eq!(BlockCache::default().budget(), 268_435_456);
    }

    #[test]
    fn budget_is_enforced() {
        let mut c = BlockCache::new(100);
        for i in 0..10 {
            assert!(c.insert(M, leaf(0, i), bytes(30)));
            assert!(c.used_bytes() <= 100);
        }
        assert_eq!(c.len(), 3);
        assert_eq!(c.used_bytes(), 90);
        assert_eq!(c.stats().evictions, 7);
        // Too big for the budget: rejected, nothing evicted.
        assert!(!c.insert(M, leaf(1, 0), bytes(101)));
        assert_eq!(c.len(), 3);
        assert_eq!(c.stats().rejections, 1);
        // Exactly the budget: fits after evicting everything.
        assert!(c.insert(M, leaf(1, 0), bytes(100)));
        assert_eq!(c.len(), 1);
        assert_eq!(c.used_bytes(), 100);
        // Shrinking the budget evicts.
        c.set_budget(50);
        assert!(c.is_empty());
        assert_eq!(c.used_bytes(), 0);
    }

    #[test]
    fn least_used_goes_first_then_least_recent() {
        let mut c = BlockCache::new(30);
        c.insert(M, leaf(0, 0), bytes(10));
        c.insert(M, leaf(0, 1), bytes(10));
        c.insert(M, leaf(0, 2), bytes(10));
        // Uses: node 0: 1 + 2, node 1: 1, node 2: 1 + 1.
        assert!(c.get(M, leaf(0, 0)).is_some());
        assert!(c.get(M, leaf(0, 0)).is_some());
        assert!(c.get(M, leaf(0, 2)).is_some());
        c.insert(M, leaf(0, 3), bytes(10));
        assert!(!c.contains(M, leaf(0, 1)));
        // Nodes 2 and 3: 2 uses vs 1 → node 3 (fresh, 1 use) is next.
        c.insert(M, leaf(0, 4), bytes(10));
        assert!(!c.contains(M, leaf(0, 3)));
        assert!(c.contains(M, leaf(0, 0)) && c.contains(M, leaf(0, 2)) && c.contains(M, leaf(0, 4)));
        // Tie on uses (node 2 and node 4 after one get): the least recent goes.
        assert!(c.get(M, leaf(0, 4)).is_some()); // node 4: 2 uses, more recent than node 2
        // Uses now 3 / 2 / 2: of the two 2-use entries node 2 was used less recently.
        c.insert(M, leaf(0, 5), bytes(10));
        assert!(!c.contains(M, leaf(0, 2)));
        assert!(c.contains(M, leaf(0, 4)));
        assert_eq!(c.stats().evictions, 3);
    }

    #[test]
    fn counters_and_sharing_by_model() {
        let mut c = BlockCache::new(1000);
        assert!(c.get(M, leaf(0, 0)).is_none());
        c.insert(M, leaf(0, 0), bytes(5));
        // Another instance of model 1 hits the same entry; model 2 does not.
        assert!(c.get(M, leaf(0, 0)).is_some());
        assert!(c.get(ModelId(2), leaf(0, 0)).is_none());
        let s = c.stats();
        assert_eq!((s.hits, s.misses, s.insertions, s.evictions), (1, 2, 1, 0));
        // Replacing keeps one entry and the right byte count.
        c.insert(M, leaf(0, 0), bytes(7));
        assert_eq!((c.len(), c.used_bytes()), (1, 7));
        c.insert(ModelId(2), BlockKey::Hull { level: 0 }, bytes(3));
        assert_eq!(c.remove_model(M), 7);
        assert_eq!(c.used_bytes(), 3);
        assert!(c.remove(ModelId(2), BlockKey::Hull { level: 0 }).is_some());
        assert!(c.is_empty());
    }

    #[test]
    fn held_bands_prefix_and_ageing() {
        let mut c = BlockCache::new(1000);
        for b in [0u8, 1, 3] {
            c.insert(M, leaf(b, 7), bytes(1));
        }
        // Leaf node 7 has 640 leaves: every band non-empty.
        let counts = vec![640u32; 9];
        let layout = BandLayout::new(&[1023, 2047, 4095, 8191, 16383, 32767, 49151, 65535], &counts);
        assert_eq!(c.held_leaf_bands(M, 7, &layout), 2);
        assert_eq!(c.held_leaf_bands(M, 8, &layout), 0);
        let two = BandLayout::new(&[32767, 65535], &counts);
        assert_eq!(c.held_leaf_bands(M, 7, &two), 2);
        // A 10-leaf node has one leaf in band 0 and none in band 1 (no block): holding band 0
        // and band 2 holds the prefix through band 2.
        let sparse = BandLayout::new(&[1023, 2047, 4095, 8191, 16383, 32767, 49151, 65535], &[10]);
        assert!(sparse.block(1, 0).is_none());
        let mut d = BlockCache::new(1000);
        for b in [0u8, 2] {
            d.insert(M, leaf(b, 0), bytes(1));
        }
        assert_eq!(d.held_leaf_bands(M, 0, &sparse), 3);
        for _ in 0..7 {
            c.get(M, leaf(0, 7));
        }
        c.halve_uses();
        // Band 0: 8 uses → 4; others 1 → 1 (kept at least 1). Victim order unchanged in kind.
        c.set_budget(2);
        assert!(c.contains(M, leaf(0, 7)));
        assert_eq!(c.len(), 2);
    }

    /// What the cache must do, written the slow and obvious way: on every insert, evict the
    /// entry with the least `(uses, last use)` until the payload fits.
    #[derive(Default)]
    struct Reference {
        budget: u64,
        tick: u64,
        entries: std::collections::BTreeMap<u32, (u64, u64, u64)>,
    }

    impl Reference {
        fn used(&self) -> u64 {
            self.entries.values().map(|e| e.2).sum()
        }

        fn evict_to(&mut self, target: u64) {
            while self.used() > target {
                let victim = self.entries.iter().min_by_key(|(_, e)| (e.0, e.1)).map(|(k, _)| *k);
                let Some(v) = victim else { break };
                self.entries.remove(&v);
            }
        }
    }

    /// Every key the touch test uses.
    fn touch_keys() -> Vec<CacheKey> {
        let mut keys = Vec::new();
        for m in 0..3u32 {
            for b in 0..4u8 {
                for o in 0..10u32 {
                    keys.push((ModelId(m), leaf(b, o)));
                }
            }
            keys.push((ModelId(m), BlockKey::Hull { level: 0 }));
            keys.push((ModelId(m), BlockKey::Hull { level: 1 }));
            keys.push((
                ModelId(m),
                BlockKey::Atlas {
                    frame: 0,
                    resolution: 0,
                },
            ));
        }
        keys
    }

    proptest::proptest! {
        /// `touch_in_order` leaves the cache as the `get` calls it stands for would: the same
        /// counters, and the same victims, in the same order, when the budget then shrinks.
        #[test]
        fn touching_in_order_equals_getting_each_block(
            held in proptest::collection::vec((0usize..129, 1u64..20), 0..80),
            gets in proptest::collection::vec(0usize..129, 0..30),
            frame in proptest::collection::vec(
                (proptest::collection::vec(0usize..5, 0..11), proptest::collection::vec(0usize..129, 0..4)),
                0..4,
            ),
            order_seed in 0u64..1000,
        ) {
            let keys = touch_keys();
            let (mut a, mut b) = (BlockCache::new(1 << 20), BlockCache::new(1 << 20));
            for &(k, n) in &held {
                let (m, key) = keys[k % keys.len()];
                a.insert(m, key, bytes(n as usize));
                b.insert(m, key, bytes(n as usize));
            }
            for &k in &gets {
                let (m, key) = keys[k % keys.len()];
                let _ = a.get(m, key);
                let _ = b.get(m, key);
            }
            // Distinct models, in an order drawn from the seed.
            let mut ids: Vec<u32> = (0..3).collect();
            ids.rotate_left((order_seed % 3) as usize);
            if order_seed % 2 == 1 {
                ids.reverse();
            }
            let touches: Vec<FrameTouches> = frame
                .iter()
                .zip(ids)
                .map(|((bands, others), m)| FrameTouches {
                    model: ModelId(m),
                    leaf_bands: bands.clone(),
                    others: others.iter().map(|&k| keys[k % keys.len()].1).collect(),
                })
                .collect();
            a.touch_in_order(&touches);
            for t in &touches {
                let most = t.leaf_bands.iter().copied().max().unwrap_or(0);
                for band in 0..most {
                    for (o, &u) in t.leaf_bands.iter().enumerate() {
                        if u > band {
                            let _ = b.get(t.model, leaf(band as u8, o as u32));
                        }
                    }
                }
                for &k in &t.others {
                    let _ = b.get(t.model, k);
                }
            }
            proptest::prop_assert_eq!(a.stats(), b.stats());
            // Later uses still come after the frame's.
            for (m, key) in keys.iter().take(5) {
                let _ = a.get(*m, *key);
                let _ = b.get(*m, *key);
            }
            let mut budget = a.used_bytes();
            while budget > 0 {
                budget = budget.saturating_sub(7);
                a.set_budget(budget);
                b.set_budget(budget);
                let held_a: Vec<&CacheKey> = keys.iter().filter(|(m, k)| a.contains(*m, *k)).collect();
                let held_b: Vec<&CacheKey> = keys.iter().filter(|(m, k)| b.contains(*m, *k)).collect();
                proptest::prop_assert_eq!(held_a, held_b);
            }
        }
    }

    proptest::proptest! {
        #[test]
        fn evicts_exactly_what_a_sorted_order_would(ops in proptest::collection::vec((0u8..5, 0u32..12, 1u64..40), 1..200)) {
            let mut c = BlockCache::new(100);
            let mut r = Reference { budget: 100, ..Reference::default() };
            for (op, key, n) in ops {
                match op {
                    0 | 1 => {
                        c.insert(M, leaf(0, key), bytes(n as usize));
                        r.tick += 1;
                        let uses = r.entries.remove(&key).map_or(0, |e| e.0);
                        r.evict_to(r.budget - n);
                        r.entries.insert(key, (uses + 1, r.tick, n));
                    }
                    2 => {
                        let hit = c.get(M, leaf(0, key)).is_some();
                        r.tick += 1;
                        let tick = r.tick;
                        proptest::prop_assert_eq!(hit, r.entries.contains_key(&key));
                        if let Some(e) = r.entries.get_mut(&key) {
                            e.0 += 1;
                            e.1 = tick;
                        }
                    }
                    3 => {
                        c.halve_uses();
                        for e in r.entries.values_mut() {
                            e.0 = (e.0 / 2).max(1);
                        }
                    }
                    _ => {
                        let b = 40 + n * 2;
                        c.set_budget(b);
                        r.budget = b;
                        r.evict_to(b);
                    }
                }
                let held: Vec<u32> = r.entries.keys().copied().collect();
                let cached: Vec<u32> = (0..12).filter(|&k| c.contains(M, leaf(0, k))).collect();
                proptest::prop_assert_eq!(cached, held);
                proptest::prop_assert_eq!(c.used_bytes(), r.used());
            }
        }
    }

    #[test]
    fn eviction_heap_stays_bounded_under_replacements() {
        let mut c = BlockCache::new(100);
        // An eviction builds the heap; then only replacements follow, without lookups.
        for i in 0..5 {
            c.insert(M, leaf(0, i), bytes(30));
        }
        assert!(c.order_valid);
        for round in 0..10_000u32 {
            c.insert(M, leaf(0, 4), bytes(30 + (round % 2) as usize));
        }
        assert!(
            c.order.len() <= 2 * c.len() + 64,
            "{} heap items for {} entries",
            c.order.len(),
            c.len()
        );
        // Evictions after the rebuild still pick the least used.
        c.insert(M, leaf(0, 9), bytes(60));
        assert!(c.contains(M, leaf(0, 4)) && c.contains(M, leaf(0, 9)));
    }
}
