//! 3-D turtle interpretation of a derived string into branches and leaves; see [`interpret`].

use canopy_shared::model::{Branch, Leaf, SkeletonPoint};
use canopy_shared::rng::{SplitMix64, mix64};
use glam::{Quat, Vec3};

use super::rewrite::ModuleString;
use super::{LSystemError, Limits};

/// Turtle settings that do not come from the string itself.
#[derive(Debug, Clone, PartialEq)]
pub struct TurtleParams {
    /// Angle of rotation modules written without a parameter, degrees.
    pub angle_deg: f32,
    /// Length of `F` / `f` written without a parameter, metres.
    pub step: f32,
    /// Radius at the start, metres.
    pub initial_radius: f32,
    /// Factor applied to the radius by a bare `!`.
    pub radius_factor: f32,
    /// Tropism vector `T` (need not be unit; its length scales the effect).
    pub tropism: Vec3,
    /// Default tropism strength `e` (0 disables tropism).
    pub tropism_strength: f32,
    /// Leaf width of a bare `L`, metres.
    pub leaf_width: f32,
    /// Leaf length of a bare `L`, metres.
    pub leaf_length: f32,
    /// Largest random turn of a leaf about each of its axes, degrees.
    pub leaf_jitter_deg: f32,
    /// Largest relative random change of a leaf's size (0.1 = ±10 %), in `[0, 1)`.
    pub leaf_size_jitter: f32,
    /// Number of leaf materials; `L`'s third parameter must be below it.
    pub leaf_materials: usize,
    /// Seed of the leaf jitter hash.
    pub seed: u64,
}

impl Default for TurtleParams {
    fn default() -> Self {
        Self {
            angle_deg: 30.0,
            step: 1.0,
            initial_radius: 0.05,
            radius_factor: 0.7,
            tropism: Vec3::new(0.0, -1.0, 0.0),
            tropism_strength: 0.0,
            leaf_width: 0.05,
            leaf_length: 0.08,
            leaf_jitter_deg: 0.0,
            leaf_size_jitter: 0.0,
            leaf_materials: 1,
            seed: 0,
        }
    }
}

/// The turtle's result: branches and leaves in iteration order, ready for a
/// [`TreeModel`](canopy_shared::TreeModel).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Interpretation {
    /// Branches: parents before children, iterations non-decreasing.
    pub branches: Vec<Branch>,
    /// Leaves: iterations non-decreasing, `branch` indices into `branches`.
    pub leaves: Vec<Leaf>,
}

/// Turtle state; pushed and popped whole by `[` and `]`.
#[derive(Debug, Clone, Copy)]
struct State {
    pos: Vec3,
    h: Vec3,
    l: Vec3,
    u: Vec3,
    radius: f32,
    elasticity: f32,
    /// Parent of a branch this scope materializes.
    parent: Option<u32>,
    /// Branch the next `F` extends; `None`: the next `F` materializes a new one.
    drawing: Option<u32>,
    /// Branch a leaf here attaches to.
    leaf_branch: Option<u32>,
}

/// `(a, b)` rotated by `deg` in their plane: `a` turns toward `b`.
fn turn(a: Vec3, b: Vec3, deg: f32) -> (Vec3, Vec3) {
    let (s, c) = deg.to_radians().sin_cos();
    (a * c + b * s, b * c - a * s)
}

impl State {
    /// Restores orthonormality lost to rounding: `H` unit, `L ⟂ H`, `U = H × L`.
    fn orthonormalize(&mut self) {
        let h = self.h.try_normalize().unwrap_or(Vec3::Y);
        let l = (self.l - h * self.l.dot(h))
            .try_normalize()
            .unwrap_or_else(|| h.any_orthonormal_vector());
        self.h = h;
        self.l = l;
        self.u = h.cross(l);
    }
}

/// Hash of the turtle's exact state, the leaf's seed.
fn state_hash(seed: u64, st: &State, birth: u8) -> u64 {
    let mut x = mix64(seed ^ u64::from(birth));
    for v in [st.pos, st.h, st.u] {
        for c in v.to_array() {
            x = mix64(x ^ u64::from(c.to_bits()));
        }
    }
    x
}

/// 3-D turtle interpretation (ABOP ch. 1.5, 2.2) of a derived string into branches and leaves.
///
/// The turtle has a position and an orthonormal frame: heading `H`, left `L`, up `U`, with
/// `H × L = U`. It starts at the origin with `H = +Y` (up), `L = −X`, `U = +Z`. Lengths are metres,
/// angles degrees.
///
/// | module | action |
/// |---|---|
/// | `F(len, r)` | draw a segment of `len` (default [`TurtleParams::step`]) along `H`; `r`, if given, sets the radius first |
/// | `f(len)` | move without drawing (the branch polyline breaks: the next `F` starts a new branch with the same parent) |
/// | `[` `]` | push / pop the whole state |
/// | `+(a)` `-(a)` | yaw about `U`: `+` turns `H` toward `L` |
/// | `&(a)` `^(a)` | pitch about `L`: `&` turns `H` toward `−U` (down), `^` toward `U` |
/// | `\(a)` `/(a)` | roll about `H`: `\` turns `L` toward `U`, `/` the other way |
/// | `\|` | turn around (yaw 180°) |
/// | `!(r)` | set the radius; `!` alone multiplies it by [`TurtleParams::radius_factor`] |
/// | `$` | roll about `H` so that `L` is horizontal (ABOP's `$`) |
/// | `~(e)` | set the tropism strength for this scope; `~` alone restores the default |
/// | `L(w, l, m)` | leaf of width `w`, length `l`, material `m` (defaults from [`TurtleParams`]) |
///
/// Rotation modules without a parameter use [`TurtleParams::angle_deg`]. Every other symbol is
/// ignored.
///
/// **Tropism** (ABOP eq. 2.4): after each `F` the frame is rotated about `H × T` by
/// `α = e·|H × T|`, bending the heading toward `T` (gravity: `T = (0, −1, 0)`).
///
/// **Branches.** The string outside all brackets is the trunk scope. Each bracket scope that
/// draws becomes a [`Branch`]; its polyline starts where its first `F` starts and continues with
/// every `F` of the scope until its `]`. Its parent is the branch the enclosing scope was drawing
/// (or last drew) when `[` was read, its level the parent's plus one (1 without a parent). Its
/// `iteration` is the birth of its first `F`, raised to the parent's iteration if lower, so a
/// prefix of the iteration-sorted branches is always closed under parents (only odd grammars that
/// draw old segments inside young brackets are affected).
///
/// **Leaves.** A leaf's petiole sits at the turtle; its blade extends along `H` with normal `U`,
/// turned by up to ±[`TurtleParams::leaf_jitter_deg`] about each axis and scaled by up to
/// ±[`TurtleParams::leaf_size_jitter`]. The jitter is drawn from a hash of the seed and the
/// turtle's exact state, not from a running stream, so a leaf gets the same jitter whatever else
/// the string holds (a tree grown `k` iterations matches the first `k` iterations of a taller
/// one). `Leaf::branch` is the branch the scope is drawing, or, before its first `F`, the
/// enclosing one; its `iteration` is the `L` module's birth, raised to that branch's iteration.
///
/// After interpretation branches and leaves are stably sorted by iteration (indices remapped), so
/// `TreeModel::at_iteration(k)` is a prefix.
///
/// # Errors
///
/// Fails on a `]` without `[` or an unclosed `[`, on any cap of `limits` (stack depth, branches,
/// leaves, points per branch, branch level 255), on a leaf material index out of range, and on a
/// non-finite position or size.
pub fn interpret(
    string: &ModuleString,
    params: &TurtleParams,
    limits: &Limits,
) -> Result<Interpretation, LSystemError> {
    let mut st = State {
        pos: Vec3::ZERO,
        h: Vec3::Y,
        l: Vec3::NEG_X,
        u: Vec3::Z,
        radius: params.initial_radius,
        elasticity: params.tropism_strength,
        parent: None,
        drawing: None,
        leaf_branch: None,
    };
    let mut stack: Vec<State> = Vec::new();
    let mut branches: Vec<Branch> = Vec::new();
    let mut leaves: Vec<Leaf> = Vec::new();

    for (i, m) in string.iter().enumerate() {
        let p0 = m.params.first().copied();
        let angle = p0.unwrap_or(params.angle_deg);
        match m.symbol {
            'F' => {
                let len = p0.unwrap_or(params.step);
                if let Some(&r) = m.params.get(1) {
                    st.radius = r.max(0.0);
                }
                let start = st.pos;
                let end = start + st.h * len;
                if !end.is_finite() {
                    return Err(LSystemError::TurtleNonFinite {
                        position: i,
                        symbol: 'F',
                    });
                }
                let end_point = SkeletonPoint {
                    position: end,
                    radius: st.radius,
                };
                if let Some(b) = st.drawing.and_then(|b| branches.get_mut(b as usize)) {
                    if b.points.len() >= limits.max_branch_points {
                        return Err(LSystemError::BranchPointCap {
                            cap: limits.max_branch_points,
                        });
                    }
                    b.points.push(end_point);
                } else {
                    if branches.len() >= limits.max_branches {
                        return Err(LSystemError::BranchCap {
                            cap: limits.max_branches,
                        });
                    }
                    let parent = st.parent.and_then(|p| branches.get(p as usize));
                    let level = match parent {
                        None => 1,
                        Some(p) => p
                            .level
                            .checked_add(1)
                            .ok_or(LSystemError::BranchLevelCap { position: i })?,
                    };
                    let iteration = parent.map_or(m.birth, |p| p.iteration.max(m.birth));
                    let start_point = SkeletonPoint {
                        position: start,
                        radius: st.radius,
                    };
                    let index = branches.len() as u32;
                    branches.push(Branch {
                        points: vec![start_point, end_point],
                        parent: st.parent,
                        level,
                        iteration,
                    });
                    st.drawing = Some(index);
                    st.leaf_branch = Some(index);
                }
                st.pos = end;
                apply_tropism(&mut st, params.tropism);
            }
            'f' => {
                let len = p0.unwrap_or(params.step);
                st.pos += st.h * len;
                if !st.pos.is_finite() {
                    return Err(LSystemError::TurtleNonFinite {
                        position: i,
                        symbol: 'f',
                    });
                }
                st.drawing = None;
            }
            '[' => {
                if stack.len() >= limits.max_stack_depth {
                    return Err(LSystemError::StackDepthCap {
                        cap: limits.max_stack_depth,
                        position: i,
                    });
                }
                stack.push(st);
                st.parent = st.leaf_branch;
                st.drawing = None;
            }
            ']' => {
                let Some(prev) = stack.pop() else {
                    return Err(LSystemError::UnbalancedBracket {
                        position: i,
                        message: "`]` without a matching `[`".into(),
                    });
                };
                st = prev;
            }
            '+' => (st.h, st.l) = turn(st.h, st.l, angle),
            '-' => (st.h, st.l) = turn(st.h, st.l, -angle),
            '&' => (st.h, st.u) = turn(st.h, st.u, -angle),
            '^' => (st.h, st.u) = turn(st.h, st.u, angle),
            '\\' => (st.l, st.u) = turn(st.l, st.u, angle),
            '/' => (st.l, st.u) = turn(st.l, st.u, -angle),
            '|' => {
                st.h = -st.h;
                st.l = -st.l;
            }
            '$' => {
                // L = V × H / |V × H| with V = up; undefined (and skipped) when H is vertical.
                if let Some(l) = Vec3::Y.cross(st.h).try_normalize() {
                    st.l = l;
                    st.u = st.h.cross(l);
                }
            }
            '!' => {
                st.radius = match p0 {
                    Some(r) => r.max(0.0),
                    None => st.radius * params.radius_factor,
                };
            }
            '~' => st.elasticity = p0.unwrap_or(params.tropism_strength),
            'L' => {
                if leaves.len() >= limits.max_leaves {
                    return Err(LSystemError::LeafCap { cap: limits.max_leaves });
                }
                let leaf = make_leaf(&st, m.params, m.birth, params, &branches, i)?;
                leaves.push(leaf);
            }
            _ => {}
        }
        if matches!(m.symbol, '+' | '-' | '&' | '^' | '\\' | '/') {
            st.orthonormalize();
            if !st.h.is_finite() {
                return Err(LSystemError::TurtleNonFinite {
                    position: i,
                    symbol: m.symbol,
                });
            }
        }
    }
    if !stack.is_empty() {
        return Err(LSystemError::UnbalancedBracket {
            position: string.len(),
            message: format!("{} `[` never closed", stack.len()),
        });
    }
    Ok(sort_by_iteration(branches, leaves))
}

/// Bends the frame toward `t` by `e·|H × T|` (ABOP's tropism).
fn apply_tropism(st: &mut State, t: Vec3) {
    if st.elasticity == 0.0 {
        return;
    }
    let axis = st.h.cross(t);
    let n = axis.length();
    if n < 1e-6 {
        return;
    }
    let q = Quat::from_axis_angle(axis / n, st.elasticity * n);
    st.h = q * st.h;
    st.l = q * st.l;
    st.orthonormalize();
}

fn make_leaf(
    st: &State,
    p: &[f32],
    birth: u8,
    params: &TurtleParams,
    branches: &[Branch],
    position: usize,
) -> Result<Leaf, LSystemError> {
    let width = p.first().copied().unwrap_or(params.leaf_width).abs();
    let length = p.get(1).copied().unwrap_or(params.leaf_length).abs();
    let material = p.get(2).copied().unwrap_or(0.0);
    let count = params.leaf_materials.min(256);
    if !(material >= 0.0 && (material.floor() as usize) < count) {
        return Err(LSystemError::LeafMaterial {
            position,
            index: material,
            count: params.leaf_materials,
        });
    }
    let mut rng = SplitMix64::new(state_hash(params.seed, st, birth));
    let mut jit = |amount: f32| (rng.uniform(-1.0, 1.0) as f32) * amount;
    let j = params.leaf_jitter_deg;
    let (yaw, pitch, roll) = (jit(j), jit(j), jit(j));
    let scale = 1.0 + jit(params.leaf_size_jitter.clamp(0.0, 0.99));
    // Turn the leaf frame (axis = H, side = L, normal = U) like the turtle would.
    let (axis, _) = turn(st.h, st.l, yaw);
    let (axis, normal) = turn(axis, st.u, pitch);
    let side = axis.cross(normal);
    let (_, normal) = turn(side, normal, roll);
    let axis = axis.try_normalize().unwrap_or(Vec3::Y);
    let normal = (normal - axis * normal.dot(axis))
        .try_normalize()
        .unwrap_or_else(|| axis.any_orthonormal_vector());
    let (width, length) = (width * scale, length * scale);
    let center = st.pos + axis * (0.5 * length);
    if !(center.is_finite() && width.is_finite() && length.is_finite()) {
        return Err(LSystemError::TurtleNonFinite { position, symbol: 'L' });
    }
    let iteration = st
        .leaf_branch
        .and_then(|b| branches.get(b as usize))
        .map_or(birth, |b| b.iteration.max(birth));
    Ok(Leaf {
        center,
        normal,
        axis,
        width,
        length,
        branch: st.leaf_branch,
        iteration,
        material: material.floor() as u8,
    })
}

/// Stable sort of branches and leaves by iteration, remapping indices. Parents keep preceding
/// children because a child's iteration is never below its parent's and it was created later.
fn sort_by_iteration(branches: Vec<Branch>, mut leaves: Vec<Leaf>) -> Interpretation {
    let mut order: Vec<u32> = (0..branches.len() as u32).collect();
    order.sort_by_key(|&i| branches[i as usize].iteration);
    let mut new_index = vec![0u32; branches.len()];
    for (new, &old) in order.iter().enumerate() {
        new_index[old as usize] = new as u32;
    }
    let mut slots: Vec<Option<Branch>> = branches.into_iter().map(Some).collect();
    let mut sorted = Vec::with_capacity(slots.len());
    for &old in &order {
        if let Some(mut b) = slots[old as usize].take() {
            b.parent = b.parent.map(|p| new_index[p as usize]);
            sorted.push(b);
        }
    }
    for l in &mut leaves {
        l.branch = l.branch.map(|b| new_index[b as usize]);
    }
    leaves.sort_by_key(|l| l.iteration);
    Interpretation {
        branches: sorted,
        leaves,
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use super::super::Grammar;
    use super::*;

    fn run(axiom: &str, prods: &[&str], n: u32) -> Result<Interpretation, LSystemError> {
        let limits = Limits::default();
        let g = Grammar::new(axiom, prods, &BTreeMap::new(), &limits)?;
        let s = g.derive(1, n, &limits)?;
        interpret(&s, &TurtleParams::default(), &limits)
    }

    fn close(a: Vec3, b: Vec3) -> bool {
        a.distance(b) < 1e-5
    }

    #[test]
    fn trunk_and_rotations() {
        let r = run("F(2) +(90) F(1)", &[], 0).unwrap_or_default();
        assert_eq!(r.branches.len(), 1);
        let b = &r.branches[0];
        assert_eq!(b.level, 1);
        assert_eq!(b.parent, None);
        assert_eq!(b.points.len(), 3);
        assert!(close(b.points[1].position, Vec3::new(0.0, 2.0, 0.0)));
        // `+` turns H toward L = −X.
        assert!(close(b.points[2].position, Vec3::new(-1.0, 2.0, 0.0)));
        let r = run("&(90) F", &[], 0).unwrap_or_default();
        assert!(
            close(r.branches[0].points[1].position, Vec3::new(0.0, 0.0, -1.0)),
            "& pitches toward −U"
        );
        let r = run("&(90) \\(90) F", &[], 0).unwrap_or_default();
        assert!(
            close(r.branches[0].points[1].position, Vec3::new(0.0, 0.0, -1.0)),
            "roll keeps H"
        );
        let r = run("| F", &[], 0).unwrap_or_default();
        assert!(close(r.branches[0].points[1].position, Vec3::new(0.0, -1.0, 0.0)));
    }

    #[test]
    fn branches_levels_parents_and_leaves() {
        let r = run("F [+F L [-F] F] L [ L ] F", &[], 0).unwrap_or_default();
        assert_eq!(r.branches.len(), 3);
        assert_eq!(r.branches[0].level, 1);
        assert_eq!(r.branches[1].parent, Some(0));
        assert_eq!(r.branches[1].level, 2);
        assert_eq!(
            r.branches[1].points.len(),
            3,
            "the branch continues after its sub-branch"
        );
        assert_eq!(r.branches[2].parent, Some(1));
        assert_eq!(r.branches[2].level, 3);
        assert_eq!(r.branches[0].points.len(), 3, "the trunk continues after the bracket");
        assert_eq!(r.leaves.len(), 3);
        assert_eq!(r.leaves[0].branch, Some(1));
        assert_eq!(r.leaves[1].branch, Some(0));
        assert_eq!(
            r.leaves[2].branch,
            Some(0),
            "no F yet in the bracket: the enclosing branch"
        );
    }

    #[test]
    fn leaf_geometry() {
        let r = run("F(1) L(0.1, 0.2)", &[], 0).unwrap_or_default();
        let l = r.leaves[0];
        assert!(close(l.center, Vec3::new(0.0, 1.1, 0.0)));
        assert!(close(l.axis, Vec3::Y));
        assert!(close(l.normal, Vec3::Z));
        assert!((l.width - 0.1).abs() < 1e-6 && (l.length - 0.2).abs() < 1e-6);
        assert!(l.axis.dot(l.normal).abs() < 1e-5);
    }

    #[test]
    fn leaf_jitter_is_bounded_and_deterministic() {
        let limits = Limits::default();
        let g = Grammar::new("F L /(10) L /(10) L", &[] as &[&str], &BTreeMap::new(), &limits);
        let s = g.and_then(|g| g.derive(0, 0, &limits)).unwrap_or_default();
        let p = TurtleParams {
            leaf_jitter_deg: 20.0,
            leaf_size_jitter: 0.2,
            seed: 9,
            ..TurtleParams::default()
        };
        let a = interpret(&s, &p, &limits).unwrap_or_default();
        let b = interpret(&s, &p, &limits).unwrap_or_default();
        assert_eq!(a, b);
        for l in &a.leaves {
            assert!(l.axis.dot(Vec3::Y) > 0.8, "within about 35°");
            assert!((0.8 * 0.05 - 1e-6..=1.2 * 0.05 + 1e-6).contains(&l.width));
            assert!((l.axis.length() - 1.0).abs() < 1e-5 && (l.normal.length() - 1.0).abs() < 1e-5);
            assert!(l.axis.dot(l.normal).abs() < 1e-5);
        }
        assert_ne!(a.leaves[0].axis, a.leaves[1].axis);
    }

    #[test]
    fn tropism_bends_toward_t() {
        let limits = Limits::default();
        let g = Grammar::new("&(60) F F F F", &[] as &[&str], &BTreeMap::new(), &limits);
        let s = g.and_then(|g| g.derive(0, 0, &limits)).unwrap_or_default();
        let p = TurtleParams {
            tropism_strength: 0.3,
            ..TurtleParams::default()
        };
        let r = interpret(&s, &p, &limits).unwrap_or_default();
        let pts = &r.branches[0].points;
        let d1 = (pts[1].position - pts[0].position).normalize();
        let d4 = (pts[4].position - pts[3].position).normalize();
        assert!(d4.y < d1.y, "segments droop under gravity");
        // Scope-local strength: `~(0)` inside a bracket switches it off there only.
        let g = Grammar::new("[~(0) &(60) F F] &(60) F F", &[] as &[&str], &BTreeMap::new(), &limits);
        let s = g.and_then(|g| g.derive(0, 0, &limits)).unwrap_or_default();
        let r = interpret(&s, &p, &limits).unwrap_or_default();
        let straight = &r.branches[0].points;
        let dir_a = straight[1].position - straight[0].position;
        let dir_b = straight[2].position - straight[1].position;
        assert!(dir_a.normalize().distance(dir_b.normalize()) < 1e-5);
    }

    #[test]
    fn dollar_levels_the_left_vector() {
        let r = run("&(40) /(33) $ +(90) F", &[], 0).unwrap_or_default();
        // After `$`, L is horizontal, so yawing 90° toward it moves horizontally.
        let d = r.branches[0].points[1].position;
        assert!(d.y.abs() < 1e-5, "{d}");
    }

    #[test]
    fn radius_and_move() {
        let r = run("!(0.5) F F(1, 0.25) ! F f F", &[], 0).unwrap_or_default();
        let b = &r.branches[0];
        assert_eq!(b.points[0].radius, 0.5);
        assert_eq!(b.points[2].radius, 0.25);
        assert!((b.points[3].radius - 0.175).abs() < 1e-6);
        assert_eq!(r.branches.len(), 2, "`f` breaks the polyline");
        assert_eq!(r.branches[1].parent, None);
        assert_eq!(r.branches[1].level, 1);
    }

    #[test]
    fn errors() {
        assert!(matches!(
            run("F]", &[], 0),
            Err(LSystemError::UnbalancedBracket { position: 1, .. })
        ));
        assert!(matches!(run("[F", &[], 0), Err(LSystemError::UnbalancedBracket { .. })));
        assert!(matches!(
            run("F(1e38)F(1e38)F(1e38)F(1e38)", &[], 0),
            Err(LSystemError::TurtleNonFinite { .. })
        ));
        assert!(matches!(
            run("L(1,1,1)", &[], 0),
            Err(LSystemError::LeafMaterial { .. })
        ));
        assert!(matches!(
            run("L(1,1,-1)", &[], 0),
            Err(LSystemError::LeafMaterial { .. })
        ));
        assert!(matches!(
            run(&"[".repeat(1100), &[], 0),
            Err(LSystemError::StackDepthCap { cap: 1024, .. })
        ));
        let deep = "[F".repeat(300) + &"]".repeat(300);
        assert!(matches!(run(&deep, &[], 0), Err(LSystemError::BranchLevelCap { .. })));
    }

    #[test]
    fn caps() {
        let limits = Limits {
            max_branches: 10,
            max_leaves: 10,
            max_branch_points: 10,
            ..Limits::default()
        };
        let g = |a: &str| {
            Grammar::new(a, &[] as &[&str], &BTreeMap::new(), &limits)
                .and_then(|g| g.derive(0, 0, &limits))
                .unwrap_or_default()
        };
        let p = TurtleParams::default();
        assert!(matches!(
            interpret(&g(&"[F]".repeat(11)), &p, &limits),
            Err(LSystemError::BranchCap { cap: 10 })
        ));
        assert!(matches!(
            interpret(&g(&"L".repeat(11)), &p, &limits),
            Err(LSystemError::LeafCap { cap: 10 })
        ));
        assert!(matches!(
            interpret(&g(&"F".repeat(11)), &p, &limits),
            Err(LSystemError::BranchPointCap { cap: 10 })
        ));
    }

    #[test]
    fn iteration_order_and_clamping() {
        // Births: the trunk's F is written by step 1; the bracket's F is from the axiom (0), so
        // its branch is raised to its parent's iteration; the leaf likewise.
        let r = run("A [+F L]", &["A -> F"], 1).unwrap_or_default();
        assert_eq!(r.branches.len(), 2);
        assert_eq!(r.branches[0].iteration, 1);
        assert_eq!(r.branches[1].iteration, 1);
        assert_eq!(r.branches[1].parent, Some(0));
        assert_eq!(r.leaves[0].iteration, 1);
        // Sorting: an early branch drawn after a young one moves ahead.
        let r = run("F [A] [+F]", &["A -> +F"], 1).unwrap_or_default();
        assert_eq!(
            r.branches.iter().map(|b| b.iteration).collect::<Vec<_>>(),
            vec![0, 0, 1]
        );
        assert_eq!(r.branches[1].parent, Some(0));
        assert_eq!(r.branches[2].parent, Some(0));
        assert_ne!(r.branches[1].points[1].position.x, 0.0);
    }
}
