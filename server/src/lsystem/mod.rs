//! Stochastic parametric L-systems (seed 000) and their 3-D turtle interpretation.
//!
//! An L-system `L = {V, Σ, W, P, Ω}` is written as an axiom `W` and productions `P` of the form
//!
//! ```text
//! Pred(x, y, ...) : condition -> Successor : weight
//! ```
//!
//! - modules are one ASCII symbol with an optional list of `f32` parameters: `A(2)`, `F(0.5, 0.02)`,
//!   `[`;
//! - the condition (optional) and the weight (optional, default 1) are expressions over the
//!   predecessor's formal parameters and the named constants;
//! - `Ω`: among the productions whose predecessor symbol and arity match a module and whose
//!   condition holds, one is chosen with probability `weight / Σ weights`; a module with no such
//!   production is copied unchanged.
//!
//! The engine is split into:
//! - expressions (private `expr` module): parsing with a depth cap into a postfix program, and
//!   evaluation; user functions and module macros are expanded when compiling,
//! - [`Grammar`]: a compiled L-system ([`Grammar::new`], [`Grammar::with_definitions`],
//!   [`Grammar::parse`]); the syntax is documented in the `grammar` module and `docs/species.md`,
//! - [`Grammar::derive`]: rewriting into a compact [`ModuleString`] that records every module's
//!   birth iteration,
//! - [`interpret`]: the 3-D turtle that turns a string into branches and leaves (the alphabet is
//!   in the `turtle` module's docs and `docs/species.md`).
//!
//! Everything is deterministic: the same grammar, seed and limits give a bit-identical result.
//! Every resource a hostile grammar could exhaust has a cap in [`Limits`], and hitting a cap gives
//! a typed [`LSystemError`] that names it.

mod expr;
mod grammar;
mod rewrite;
mod turtle;

pub use grammar::Grammar;
pub use rewrite::{Module, ModuleString};
pub use turtle::{Interpretation, TurtleParams, interpret};

/// Largest number of parameters a module may carry.
pub const MAX_PARAMS: usize = 16;

/// Largest expression nesting depth the parser ever accepts, whatever [`Limits::max_expr_depth`]
/// says: the parser is recursive, and this bounds its stack use (a few hundred KiB at most).
pub const HARD_MAX_EXPR_DEPTH: usize = 256;

/// Largest iteration count: [`canopy_shared::Branch::iteration`] and [`canopy_shared::Leaf::iteration`] are `u8`.
pub const HARD_MAX_ITERATIONS: u32 = 255;

/// Caps on every resource an L-system can exhaust. Hitting one gives the matching
/// [`LSystemError`] variant; nothing is ever allowed to grow without bound.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Most modules a derived string may hold (checked while rewriting).
    pub max_modules: usize,
    /// Most bytes of module parameters (4 per `f32`) a derived string may hold.
    pub max_param_bytes: usize,
    /// Most derivation steps; values above [`HARD_MAX_ITERATIONS`] act as that.
    pub max_iterations: u32,
    /// Deepest expression nesting (parentheses, unary operators, powers); values above
    /// [`HARD_MAX_EXPR_DEPTH`] act as that.
    pub max_expr_depth: usize,
    /// Deepest turtle `[` stack.
    pub max_stack_depth: usize,
    /// Most branches the turtle may create.
    pub max_branches: usize,
    /// Most leaves the turtle may create.
    pub max_leaves: usize,
    /// Most points on one branch polyline (the `.ctree` skeleton stores the count as `u16`).
    pub max_branch_points: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_modules: 8_000_000,
            max_param_bytes: 128 << 20,
            max_iterations: 64,
            max_expr_depth: 64,
            max_stack_depth: 1024,
            max_branches: 2_000_000,
            max_leaves: 4_000_000,
            max_branch_points: usize::from(u16::MAX),
        }
    }
}

impl Limits {
    /// The iteration cap actually applied.
    pub(crate) fn iteration_cap(&self) -> u32 {
        self.max_iterations.min(HARD_MAX_ITERATIONS)
    }

    /// The expression depth cap actually applied.
    pub(crate) fn expr_depth_cap(&self) -> usize {
        self.max_expr_depth.min(HARD_MAX_EXPR_DEPTH)
    }
}

/// Everything that can go wrong while compiling, deriving or interpreting an L-system.
///
/// `context` strings name the place: `axiom`, or ``production 3 `A(x) -> B(x)` ``.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LSystemError {
    /// The grammar text does not parse.
    #[error("syntax error in {context} at byte {position}: {message}")]
    Syntax {
        /// Where: `axiom`, a production, or `grammar line N`.
        context: String,
        /// Byte offset into that text.
        position: usize,
        /// What was expected or found.
        message: String,
    },
    /// An expression nests deeper than [`Limits::max_expr_depth`].
    #[error("expression in {context} nests deeper than the expression depth cap of {cap}")]
    ExprDepthCap {
        /// Where the expression is.
        context: String,
        /// The cap that was applied.
        cap: usize,
    },
    /// More iterations were asked for than [`Limits::max_iterations`] allows.
    #[error("{requested} iterations requested, over the iteration cap of {cap}")]
    IterationCap {
        /// Iterations asked for.
        requested: u32,
        /// The cap that was applied.
        cap: u32,
    },
    /// The derived string grew past [`Limits::max_modules`].
    #[error("derivation exceeded the module cap of {cap} modules in iteration {iteration}")]
    ModuleCap {
        /// The cap.
        cap: usize,
        /// The iteration (1-based) that overflowed.
        iteration: u32,
    },
    /// The derived string's parameters grew past [`Limits::max_param_bytes`].
    #[error("derivation exceeded the parameter memory cap of {cap} bytes in iteration {iteration}")]
    ParamMemoryCap {
        /// The cap in bytes.
        cap: usize,
        /// The iteration (1-based) that overflowed.
        iteration: u32,
    },
    /// An expression divided by zero.
    #[error("division by zero in {context}, expression `{expression}`")]
    DivisionByZero {
        /// The production (or axiom) that holds the expression.
        context: String,
        /// The expression's source text.
        expression: String,
    },
    /// An expression gave NaN or an infinity, or a value too large for `f32`.
    #[error("non-finite value {value} in {context}, expression `{expression}`")]
    NonFinite {
        /// The production (or axiom) that holds the expression.
        context: String,
        /// The expression's source text.
        expression: String,
        /// The offending value.
        value: f64,
    },
    /// A production weight evaluated below zero.
    #[error("negative weight {value} in {context}, expression `{expression}`")]
    NegativeWeight {
        /// The production.
        context: String,
        /// The weight expression.
        expression: String,
        /// The weight.
        value: f64,
    },
    /// A `]` without a matching `[`, or a `[` never closed.
    #[error("unbalanced bracket at module {position}: {message}")]
    UnbalancedBracket {
        /// Index of the module in the derived string.
        position: usize,
        /// Which way it is unbalanced.
        message: String,
    },
    /// The turtle stack grew deeper than [`Limits::max_stack_depth`].
    #[error("turtle stack exceeded the stack depth cap of {cap} at module {position}")]
    StackDepthCap {
        /// The cap.
        cap: usize,
        /// Index of the `[` in the derived string.
        position: usize,
    },
    /// More branches than [`Limits::max_branches`].
    #[error("interpretation exceeded the branch cap of {cap}")]
    BranchCap {
        /// The cap.
        cap: usize,
    },
    /// More leaves than [`Limits::max_leaves`].
    #[error("interpretation exceeded the leaf cap of {cap}")]
    LeafCap {
        /// The cap.
        cap: usize,
    },
    /// One branch polyline got more points than [`Limits::max_branch_points`].
    #[error("a branch exceeded the branch point cap of {cap} points")]
    BranchPointCap {
        /// The cap.
        cap: usize,
    },
    /// Branches nest deeper than the `u8` branch level can count (255).
    #[error("branch level exceeded the level cap of 255 at module {position}")]
    BranchLevelCap {
        /// Index of the module in the derived string.
        position: usize,
    },
    /// A leaf names a material index that does not exist.
    #[error("leaf at module {position} names material {index}, but there are only {count}")]
    LeafMaterial {
        /// Index of the `L` module in the derived string.
        position: usize,
        /// The index asked for.
        index: f32,
        /// Number of leaf materials.
        count: usize,
    },
    /// The turtle produced a non-finite position or size (e.g. an overflowing length).
    #[error("turtle produced a non-finite value at module {position} (`{symbol}`)")]
    TurtleNonFinite {
        /// Index of the module in the derived string.
        position: usize,
        /// The module's symbol.
        symbol: char,
    },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_limits_are_sane() {
        let l = Limits::default();
        assert_eq!(l.max_modules, 8_000_000);
        assert_eq!(l.iteration_cap(), 64);
        assert!(l.expr_depth_cap() <= HARD_MAX_EXPR_DEPTH);
        let big = Limits {
            max_iterations: 10_000,
            max_expr_depth: 1 << 30,
            ..l
        };
        assert_eq!(big.iteration_cap(), HARD_MAX_ITERATIONS);
        assert_eq!(big.expr_depth_cap(), HARD_MAX_EXPR_DEPTH);
    }
}
