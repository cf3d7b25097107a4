//! The still radius: how far (model frame) the eye may move before a leaf node's proposal could
//! differ from the rate in force by switch control's step threshold. Switch control applies a
//! change only when `|proposal − rate in force|` reaches the step threshold
//! ([`SwitchState::update`]), so while the eye stays inside, the outcome of evaluating the node
//! is "no change" and [`super::TreeLodState`] skips it (its hold time still runs: the hold
//! threshold only matters once the step threshold is passed). The eye's path length is
//! compared, which is at least its displacement.
//!
//! # Proof
//!
//! Let the eye move by at most `δ` from where proposal `q` was made with the rate in force
//! `current` (f3 reads it); `gap = |q − current|`, `d` the sphere distance, `s = |centre − eye|`.
//!
//! 1. The sphere distance moves by at most `δ`: it stays in `[d − δ, d + δ]`.
//! 2. f1 (the layer) and f3 (the rate in force) do not move.
//! 3. On `near < d < far`, `|Δf2| ≤ k1·BL/ln h·δ/d_min` and `|Δf4| ≤ k3/ln 10·δ/d_min`
//!    (`d_min = d − δ`; the derivatives are `k1·BL/(ln h·d)` and `k3/(ln 10·d)`); beyond `far`
//!    both are constant. An interval that holds `near` or `far` (where f2 and f4 jump) gives
//!    radius 0.
//! 4. The line of sight turns by at most `φ = asin(x)`, `x = δ/s < 1`, so f5 = clip(cos θ) stays
//!    between clip(cos(θ ± φ)) (taken as 1 and 0 past 0 and π): exactly 0 while a node faces
//!    away by more than φ, second order in φ near θ = 0. Without the angle (θ unknown),
//!    `|Δf5| ≤ φ = asin(x) ≤ x/(1 − x)`.
//! 5. The rate is `clamp(Σ α_k f_k, 0, 1)` and the clamp does not widen differences, so the
//!    proposal moves by at most `|α2|·|Δf2| + |α4|·|Δf4| + |α5|·|Δf5|`.
//! 6. The step threshold is monotone in `d`, so its smallest value on `[d − δ, d + δ]` is at an
//!    end (at `d − δ` when `k1 > 0`).
//!
//! Hence if `gap + |α2|·|Δf2| + |α4|·|Δf4| + |α5|·|Δf5| + slack` is below that smallest
//! threshold, no eye position within `δ` brings a proposal to the threshold. `StillBound::fits`
//! checks exactly this inequality (the slack, 1e-5, covers the rounding of the proposal
//! itself); [`still_radius`] tries a guess at the largest `δ` that fits and a few fractions of
//! it, and returns the first that fits, or 0.

use super::leaf_table::Proposal;
use crate::lod::rate::RateConsts;
use crate::lod::switch::SwitchState;
use crate::lod::{LodParams, clamp01};

/// How far (model frame) the eye may move before a leaf node's proposal could differ from the
/// rate in force (`current`) by switch control's step threshold; 0 when it may already. `q` must
/// be the proposal made with `current` in force (f3 reads it). While the eye stays
/// inside, switch control provably applies no change, so the node need not be evaluated.
///
/// Bounds, for an eye displacement `δ` (the sphere distance `d` moves by at most `δ`): on
/// `near < d < far`, `|Δf2| ≤ k1·BL/ln h·δ/d_min` and `|Δf4| ≤ k3/ln 10·δ/d_min`; beyond `far`
/// both are constant; the line of sight turns by at most `φ = asin(x)`, `x = δ/|centre − eye| < 1`,
/// so f5 = clip(cos θ) stays between clip(cos(θ ± φ)) (taken as 1 and 0 past 0 and π): exactly 0
/// while a node faces away by more than φ, second order in φ near θ = 0 (without the angle,
/// `asin(x) ≤ x/(1 − x)`);
/// f1 and f3 (the rate in force) do not move. The step threshold is monotone in `d`, so its
/// smallest value on `[d − δ, d + δ]` is at an end. Intervals that hold `near` or `far` (where f2
/// and f4 jump) give 0.
pub(super) fn still_radius(
    p: &LodParams,
    k: &RateConsts,
    branch_level: u8,
    has_growth: bool,
    q: Proposal,
    current: f32,
) -> f32 {
    let Some(bound) = StillBound::new(p, k, branch_level, has_growth, q, current) else {
        return 0.0;
    };
    let first = bound.first_guess();
    for f in [1.0, 0.9, 0.7, 0.5, 0.3, 0.1] {
        let delta = first * f;
        if delta.is_finite() && delta > 0.0 && bound.fits(delta) {
            return delta;
        }
    }
    0.0
}

/// The bound of [`still_radius`] for one leaf node's proposal.
struct StillBound<'a> {
    p: &'a LodParams,
    /// `|proposal − rate in force|`.
    gap: f32,
    /// Sphere distance.
    d0: f32,
    /// `|centre − eye|`.
    sight: f32,
    /// Step threshold at `d0`.
    step0: f32,
    /// Bound on `|Δ(α2·f2 + α4·f4)|` per metre of eye movement, times the distance.
    a: f32,
    /// `|α5|`, 0 without a growth direction.
    b: f32,
    /// `cos θ` and `sin θ` (θ: line of sight to growth direction; NaN when unknown, then f5
    /// is bounded by the angle alone). `sin θ` is rounded up (see [`Self::new`]).
    cos: f32,
    sin: f32,
}

impl<'a> StillBound<'a> {
    /// Float slack: the proposal itself is computed with rounding.
    const SLACK: f32 = 1e-5;

    /// `None` when switch control may already apply a change (no room under the threshold).
    fn new(
        p: &'a LodParams,
        k: &RateConsts,
        branch_level: u8,
        has_growth: bool,
        q: Proposal,
        current: f32,
    ) -> Option<Self> {
        let gap = (q.rate - current).abs();
        let d0 = q.distance;
        let step0 = SwitchState::step_threshold(p, d0);
        // Written to be false for NaN.
        let room = step0 - gap > Self::SLACK && q.sight > 0.0;
        if !room {
            return None;
        }
        let bl = f32::from(branch_level).min(k.bl_max);
        let a = p.weights[1].abs() * (k.k1 * bl / k.ln_h).abs()
            + p.weights[3].abs() * k.k3.abs() * std::f32::consts::LOG10_E;
        let b = if has_growth { p.weights[4].abs() } else { 0.0 };
        let cos = q.cos_growth.clamp(-1.0, 1.0);
        // `sin θ` from a rounded cosine is least accurate near θ = 0 and π (a cosine 1e-7 off
        // moves it by up to 5e-4): the 1e-6 under the root keeps it at least 1e-3.
        let sin = ((1.0 - cos * cos).max(0.0) + 1e-6).sqrt().min(1.0);
        Some(Self {
            p,
            gap,
            d0,
            sight: q.sight,
            step0,
            a,
            b,
            cos,
            sin,
        })
    }

    /// Whether no eye movement of at most `delta` can bring a proposal to the step threshold.
    fn fits(&self, delta: f32) -> bool {
        let p = self.p;
        let (lo, hi) = (self.d0 - delta, self.d0 + delta);
        let above_near = lo > p.near && lo > 0.0;
        if !above_near {
            return false;
        }
        let dist_term = if hi < p.far {
            self.a * delta / lo
        } else if lo >= p.far {
            0.0
        } else {
            return false;
        };
        let x = delta / self.sight;
        let closer = x < 1.0;
        if !closer {
            return false;
        }
        // Non-decreasing in the distance for k1 > 0: the smallest is at `lo`.
        let step_min = if p.switch_k1 > 0.0 {
            SwitchState::step_threshold(p, lo)
        } else {
            SwitchState::step_threshold(p, lo).min(SwitchState::step_threshold(p, hi))
        };
        self.gap + dist_term + self.b * self.f5_move(x) + Self::SLACK < step_min
    }

    /// Bound on `|Δf5|` when the line of sight turns by at most `asin(x)` (`0 ≤ x < 1`).
    fn f5_move(&self, x: f32) -> f32 {
        let (u, s) = (self.cos, self.sin);
        if u.is_nan() {
            return x / (1.0 - x);
        }
        let c = (1.0 - x * x).max(0.0).sqrt();
        let now = clamp01(u);
        // cos(θ − φ), or 1 once φ reaches θ (cos θ ≥ cos φ); cos(θ + φ), or −1 past π.
        let hi = if u >= c { 1.0 } else { u * c + s * x };
        let lo = if -u >= c { -1.0 } else { u * c - s * x };
        (clamp01(hi) - now).max(now - clamp01(lo)).max(0.0)
    }

    /// A guess at the largest radius that [`Self::fits`] (which is what makes an answer safe).
    /// f5 moves about `sin θ·x` per `x` while the node faces the eye (θ < π/2, `cos θ > 0`); a
    /// node facing away keeps f5 = 0 for `x ≤ −cos θ`, so the guess without f5 stands when it
    /// lies inside that margin; beyond it f5 grows about as `x + cos θ`, which is the full
    /// slope with `b·(−cos θ)` more room.
    fn first_guess(&self) -> f32 {
        let (u, b) = (self.cos, self.b);
        if u.is_nan() || b == 0.0 {
            return self.guess(b, 0.0);
        }
        if u > 0.0 {
            return self.guess(b * self.sin, 0.0);
        }
        let without = self.guess(0.0, 0.0);
        let margin = -u * self.sight;
        if without <= margin {
            without
        } else {
            margin.max(self.guess(b, -u * b))
        }
    }

    /// With `y = δ/d0`, the bound is at most `gap + c·y/(1 − y)` (`c = a + b·d0/sight`, `b` the
    /// slope of f5's term per `x`) and the threshold falls about linearly as the eye nears,
    /// `step0 − e·y` below its cap (`e = d0·step'`); they meet at the smaller root of
    /// `e·y² − (c + e + room)·y + room = 0`, with `extra` added to the room.
    fn guess(&self, b: f32, extra: f32) -> f32 {
        let p = self.p;
        let span = p.far - p.near;
        let ratio = (self.d0 - p.near) / span;
        let step_slope = if self.step0 < p.switch_max_step && ratio > 0.0 && p.switch_k1 > 0.0 {
            // The default k1 = 1 needs no powf.
            let pow = if p.switch_k1 == 1.0 {
                1.0
            } else {
                ratio.powf(p.switch_k1 - 1.0)
            };
            p.switch_k1 * pow / span
        } else {
            0.0
        };
        let room = self.step0 - self.gap - Self::SLACK + extra;
        let c = self.a + b * self.d0 / self.sight;
        let e = if step_slope.is_finite() {
            self.d0 * step_slope
        } else {
            0.0
        };
        let s = c + e + room;
        // The smaller root in the form that does not cancel (and reads room/(c + room) at e = 0).
        let y = 2.0 * room / (s + (s * s - 4.0 * e * room).max(0.0).sqrt());
        if y.is_finite() && y > 0.0 {
            y * self.d0
        } else {
            self.d0.max(1.0)
        }
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;

    /// The radius found is safe (it fits) and not far below the largest that fits (found here by
    /// bisection), over proposals at every distance, gap and switch exponent: a loose radius
    /// costs evaluations every frame.
    #[test]
    fn still_radius_is_close_to_the_largest_that_fits() {
        let mut rng = canopy_shared::rng::SplitMix64::new(11);
        let (mut sum, mut n) = (0.0f64, 0u32);
        for case in 0..4000 {
            let p = LodParams {
                switch_k1: [1.0, 0.5, 2.0][case % 3],
                ..LodParams::default()
            };
            let k = RateConsts::new(&p);
            let distance = rng.uniform(0.0, 700.0) as f32;
            let current = rng.uniform(0.0, 1.0) as f32;
            let step = SwitchState::step_threshold(&p, distance);
            let q = Proposal {
                rate: current + step * rng.uniform(-1.0, 1.0) as f32,
                f: [0.0; 5],
                distance,
                sight: distance + rng.uniform(0.0, 5.0) as f32,
                cos_growth: if case % 4 == 0 {
                    f32::NAN
                } else {
                    rng.uniform(-1.0, 1.0) as f32
                },
            };
            let bl = (case % 7) as u8;
            let r = still_radius(&p, &k, bl, case % 5 != 0, q, current);
            let Some(bound) = StillBound::new(&p, &k, bl, case % 5 != 0, q, current) else {
                assert_eq!(r, 0.0);
                continue;
            };
            // The largest radius that fits (fits is monotone: a larger radius only loosens
            // every term of the bound).
            let (mut good, mut bad) = (0.0f32, distance.max(1.0) * 2.0);
            for _ in 0..40 {
                let mid = 0.5 * (good + bad);
                if bound.fits(mid) { good = mid } else { bad = mid }
            }
            if r > 0.0 {
                assert!(bound.fits(r), "case {case}: {r} does not fit");
            }
            if good > 1e-3 {
                assert!(r <= good * 1.0001, "case {case}: {r} > largest {good}");
                sum += f64::from(r / good);
                n += 1;
            }
        }
        let mean = sum / f64::from(n);
        assert!(n > 1000, "{n} cases with room");
        // 0.78 here (0.74 for nodes facing away, whose largest radius the angle bound made
        // larger); the linear guess of the bound without the angle gave 0.66.
        assert!(mean > 0.75, "mean radius is {mean:.3} of the largest that fits");
    }

    /// f5's bound holds for real eye moves: a random node (centre, growth direction) and eye,
    /// moved by at most `δ` in a random direction, never changes f5 by more than
    /// `f5_move(δ/sight)`; and a node facing away by more than the turn keeps f5 at exactly 0.
    #[test]
    fn f5_moves_within_its_bound() {
        let mut rng = canopy_shared::rng::SplitMix64::new(5);
        let p = LodParams::default();
        let k = RateConsts::new(&p);
        let unit = |rng: &mut canopy_shared::rng::SplitMix64| loop {
            let v = Vec3::new(
                rng.uniform(-1.0, 1.0) as f32,
                rng.uniform(-1.0, 1.0) as f32,
                rng.uniform(-1.0, 1.0) as f32,
            );
            if let Some(u) = v.try_normalize() {
                break u;
            }
        };
        let mut zero_kept = 0;
        for case in 0..20_000 {
            let center = unit(&mut rng) * rng.uniform(0.0, 5.0) as f32;
            let growth = unit(&mut rng);
            let sight = rng.uniform(0.5, 200.0) as f32;
            let eye = center - unit(&mut rng) * sight;
            let los = center - eye;
            let cos_growth = (los / los.length()).dot(growth);
            let q = Proposal {
                rate: 0.5,
                f: [0.0; 5],
                distance: 100.0,
                sight: los.length(),
                cos_growth,
            };
            let bound = StillBound::new(&p, &k, 1, true, q, 0.5).expect("room at rate 0.5, gap 0");
            let x = rng.uniform(0.0, 0.999) as f32;
            let delta = x * q.sight;
            // Mostly moves of the full length (the worst case), some shorter.
            let len = if case % 3 == 0 {
                delta * rng.uniform(0.0, 1.0) as f32
            } else {
                delta
            };
            let moved = eye + unit(&mut rng) * len;
            let los2 = center - moved;
            let f5_before = clamp01(cos_growth);
            let f5_after = clamp01((los2 / los2.length()).dot(growth));
            let change = (f5_after - f5_before).abs();
            let allowed = bound.f5_move(x);
            assert!(
                change <= allowed + 1e-5,
                "case {case}: f5 moved {change} > {allowed} (cos {cos_growth}, x {x})"
            );
            if cos_growth < 0.0 && x < -cos_growth * 0.999 {
                assert_eq!(allowed, 0.0, "case {case}: facing away by more than the turn");
                zero_kept += 1;
            }
        }
        assert!(zero_kept > 1000, "{zero_kept} nodes facing away");
    }
}
