//! The per-viewer frame rate limit of the live socket: a token bucket of
//! [`MAX_CLIENT_MSGS_PER_S`] frames a second holding one second's worth.

use super::live::MAX_CLIENT_MSGS_PER_S;

/// A token bucket of [`MAX_CLIENT_MSGS_PER_S`] frames a second holding at most one second's
/// worth. A bucket, not fixed one-second windows: frames that queued in the socket while the
/// server was busy arrive together, and a window would count a late backlog against the next
/// second (a steady 95 Hz viewer was closed under load that way); the bucket refills for the
/// time that passed, so only a sender above the rate runs it dry.
#[derive(Debug)]
pub(crate) struct RateLimit {
    tokens: f64,
    last: tokio::time::Instant,
}

impl RateLimit {
    pub(crate) fn new() -> Self {
        Self {
            tokens: f64::from(MAX_CLIENT_MSGS_PER_S),
            last: tokio::time::Instant::now(),
        }
    }

    /// Counts one frame; `false` when the viewer is over [`MAX_CLIENT_MSGS_PER_S`].
    pub(crate) fn admit(&mut self) -> bool {
        self.admit_at(tokio::time::Instant::now())
    }

    fn admit_at(&mut self, now: tokio::time::Instant) -> bool {
        let rate = f64::from(MAX_CLIENT_MSGS_PER_S);
        let elapsed = now.saturating_duration_since(self.last).as_secs_f64();
        self.tokens = (self.tokens + elapsed * rate).min(rate);
        self.last = now;
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            true
        } else {
            false
        }
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    #[test]
    fn a_steady_sender_under_the_rate_survives_a_late_backlog_and_a_flood_does_not() {
        let t0 = tokio::time::Instant::now();
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        // 95 Hz for 3 s, but everything sent in the second half of each second arrives at once
        // at the next full second (the server was busy): 47 frames together, then the rest.
        let mut steady = RateLimit {
            tokens: 100.0,
            last: t0,
        };
        for s in 0..3u64 {
            for i in 0..95u64 {
                let sent = s * 1000 + i * 1000 / 95;
                let arrives = if sent % 1000 >= 500 { (s + 1) * 1000 } else { sent };
                assert!(steady.admit_at(at(arrives)), "frame {i} of second {s}");
            }
        }
        // A sender at 150 Hz runs the bucket dry within 2 s (100 + 100·t = 150·t), and 101 at
        // once are refused at the 101st.
        let mut flood = RateLimit {
            tokens: 100.0,
            last: t0,
        };
        let first_refused = (0..450u64).position(|i| !flood.admit_at(at(i * 1000 / 150)));
        assert!(
            first_refused.is_some_and(|i| (290..=305).contains(&i)),
            "{first_refused:?}"
        );
        let mut burst = RateLimit {
            tokens: 100.0,
            last: t0,
        };
        assert_eq!((0..101).position(|_| !burst.admit_at(t0)), Some(100));
    }
}
