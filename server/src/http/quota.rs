//! Who may create scenes, and how fast anyone may create and edit.
//!
//! Contract: creation is either open (anyone; the quota owner is the client's address) or needs
//! one of the server's creation tokens (`Authorization: Bearer`; the owner is the token). Rates are
//! token buckets: each key (an owner, a scene, a client address) holds up to `burst` requests and
//! regains `per_s` a second; a request takes one from every key it names or, if any is empty,
//! none, and is told how long to wait (`Retry-After`). IPv6 addresses count by /64 (one host can
//! hold a whole /64). The bucket map is bounded: past [`MAX_KEYS`] keys, full buckets (which are
//! the same as absent ones) are dropped, and if none is full the oldest are.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use super::auth;

/// The client's address, put in each request's extensions by the connection loop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Peer(pub IpAddr);

/// Who may create scenes.
#[derive(Clone, PartialEq, Eq)]
pub enum Creation {
    /// Anyone (the quotas then count per client address).
    Open,
    /// Only with one of these tokens (SHA-256 hashes); none: nobody but the server itself.
    Tokens(Vec<[u8; 32]>),
}

impl std::fmt::Debug for Creation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Open => f.write_str("Open"),
            Self::Tokens(t) => write!(f, "Tokens({} tokens)", t.len()),
        }
    }
}

impl Creation {
    /// Creation with these tokens.
    pub fn tokens<S: AsRef<str>>(tokens: &[S]) -> Self {
        Self::Tokens(tokens.iter().map(|t| auth::hash_token(t.as_ref())).collect())
    }

    /// The quota owner of a creation presenting `token` from `peer`: `Ok(owner)`, or `Err(true)`
    /// for no token, `Err(false)` for a wrong one.
    pub fn owner(&self, token: Option<&str>, peer: Option<IpAddr>) -> Result<String, bool> {
        match self {
            Self::Open => Ok(peer.map_or_else(|| "open".to_string(), |ip| format!("ip:{}", ip_key(ip)))),
            Self::Tokens(hashes) => {
                let t = token.ok_or(true)?;
                let h = auth::hash_token(t);
                // Every token compared, in constant time each: the time says nothing of which.
                let found = hashes.iter().fold(false, |acc, k| acc | auth::ct_eq(&h, k));
                if found {
                    Ok(format!("token:{}", &crate::store::assets::hex(&h)[..16]))
                } else {
                    Err(false)
                }
            }
        }
    }
}

/// An address as a rate key: IPv4 whole, IPv6 by its /64.
pub fn ip_key(ip: IpAddr) -> String {
    match ip {
        IpAddr::V4(v4) => v4.to_string(),
        IpAddr::V6(v6) => {
            if let Some(v4) = v6.to_ipv4_mapped() {
                v4.to_string()
            } else {
                let s = v6.segments();
                format!("{:x}:{:x}:{:x}:{:x}::/64", s[0], s[1], s[2], s[3])
            }
        }
    }
}

/// A rate: `per_s` requests a second, at most `burst` at once.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rate {
    /// Sustained requests per second.
    pub per_s: f64,
    /// Requests that may come at once.
    pub burst: f64,
}

impl Rate {
    /// `per_min` a minute, a minute's worth at once.
    pub fn per_minute(per_min: f64) -> Self {
        Self {
            per_s: per_min / 60.0,
            burst: per_min.max(1.0),
        }
    }

    /// `per_s` a second, ten seconds' worth at once.
    pub fn per_second(per_s: f64) -> Self {
        Self {
            per_s,
            burst: (per_s * 10.0).max(1.0),
        }
    }
}

/// Most keys one limiter tracks.
pub const MAX_KEYS: usize = 100_000;

#[derive(Debug, Clone, Copy)]
struct Bucket {
    tokens: f64,
    at: Instant,
}

/// Token buckets by key.
#[derive(Debug)]
pub struct RateLimiter {
    rate: Rate,
    buckets: Mutex<HashMap<String, Bucket>>,
}

impl RateLimiter {
    /// A limiter at `rate`.
    pub fn new(rate: Rate) -> Self {
        Self {
            rate,
            buckets: Mutex::new(HashMap::new()),
        }
    }

    fn level(&self, b: Option<&Bucket>, now: Instant) -> f64 {
        b.map_or(self.rate.burst, |b| {
            (b.tokens + now.saturating_duration_since(b.at).as_secs_f64() * self.rate.per_s).min(self.rate.burst)
        })
    }

    /// Takes one request from each of `keys`, or, if any has none left, none and says how long
    /// until all have one (at least a second: `Retry-After` counts whole seconds).
    pub fn take(&self, keys: &[&str]) -> Result<(), Duration> {
        self.take_at(keys, Instant::now())
    }

    fn take_at(&self, keys: &[&str], now: Instant) -> Result<(), Duration> {
        let mut map = self.buckets.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let levels: Vec<f64> = keys.iter().map(|k| self.level(map.get(*k), now)).collect();
        let short = levels.iter().fold(0.0f64, |m, &l| m.max(1.0 - l));
        if short > 0.0 {
            let wait = if self.rate.per_s > 0.0 {
                short / self.rate.per_s
            } else {
                86_400.0
            };
            return Err(Duration::from_secs_f64(wait.clamp(1.0, 86_400.0).ceil()));
        }
        if map.len() + keys.len() > MAX_KEYS {
            self.shrink(&mut map, now);
        }
        for (k, l) in keys.iter().zip(levels) {
            map.insert(
                (*k).to_string(),
                Bucket {
                    tokens: l - 1.0,
                    at: now,
                },
            );
        }
        Ok(())
    }

    fn shrink(&self, map: &mut HashMap<String, Bucket>, now: Instant) {
        map.retain(|_, b| self.level(Some(b), now) < self.rate.burst);
        if map.len() > MAX_KEYS / 2 {
            // All still refilling (a flood of keys): forget the oldest half.
            let mut ats: Vec<Instant> = map.values().map(|b| b.at).collect();
            ats.sort_unstable();
            let cut = ats[ats.len() / 2];
            map.retain(|_, b| b.at > cut);
        }
    }

    /// Keys tracked (tests, metrics).
    pub fn len(&self) -> usize {
        self.buckets
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .len()
    }

    /// True when no key is tracked.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buckets_refill_and_take_from_every_key_or_none() {
        let r = RateLimiter::new(Rate { per_s: 2.0, burst: 3.0 });
        let t0 = Instant::now();
        for _ in 0..3 {
            r.take_at(&["a", "ip"], t0).expect("burst");
        }
        let wait = r.take_at(&["a", "ip"], t0).expect_err("empty");
        assert_eq!(wait, Duration::from_secs(1));
        // "b" has tokens but the address has none: nothing is taken from "b".
        assert!(r.take_at(&["b", "ip"], t0).is_err());
        assert!(r.take_at(&["b"], t0).is_ok());
        assert!(r.take_at(&["b"], t0).is_ok());
        assert!(r.take_at(&["b"], t0).is_ok());
        assert!(r.take_at(&["b"], t0).is_err(), "b had its full burst of 3");
        // Half a second later, one more each.
        let t1 = t0 + Duration::from_millis(500);
        assert!(r.take_at(&["a", "ip"], t1).is_ok());
        assert!(r.take_at(&["a", "ip"], t1).is_err());
        let slow = RateLimiter::new(Rate::per_minute(6.0));
        for _ in 0..6 {
            slow.take_at(&["x"], t0).expect("burst of a minute's worth");
        }
        assert_eq!(slow.take_at(&["x"], t0), Err(Duration::from_secs(10)));
    }

    #[test]
    fn the_key_map_stays_bounded() {
        let r = RateLimiter::new(Rate {
            per_s: 0.001,
            burst: 1.0,
        });
        let t0 = Instant::now();
        for k in 0..MAX_KEYS + 10 {
            r.take_at(&[&k.to_string()], t0 + Duration::from_micros(k as u64))
                .expect("a new key has its burst");
        }
        assert!(r.len() <= MAX_KEYS, "{}", r.len());
    }

    #[test]
    fn creation_owners() {
        let open = Creation::Open;
        let v4: IpAddr = "10.1.2.3".parse().expect("ip");
        let v6: IpAddr = "2001:db8:1:2:3:4:5:6".parse().expect("ip");
        assert_eq!(open.owner(None, Some(v4)), Ok("ip:10.1.2.3".into()));
        assert_eq!(open.owner(None, Some(v6)), Ok("ip:2001:db8:1:2::/64".into()));
        assert_eq!(open.owner(None, None), Ok("open".into()));
        let closed = Creation::tokens(&["s3cret", "other"]);
        assert_eq!(closed.owner(None, Some(v4)), Err(true));
        assert_eq!(closed.owner(Some("nope"), Some(v4)), Err(false));
        let a = closed.owner(Some("s3cret"), Some(v4)).expect("a");
        let b = closed.owner(Some("other"), Some(v4)).expect("b");
        assert!(a.starts_with("token:") && a != b);
        assert_eq!(Creation::tokens::<&str>(&[]).owner(Some("x"), None), Err(false));
        assert!(!format!("{closed:?}").contains("s3cret"));
    }
}
