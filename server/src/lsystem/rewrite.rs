//! Derivation: parallel rewriting of a compact module string.
//!
//! A string is a `Vec` of 8-byte module records (symbol, arity, birth iteration, parameter offset)
//! plus one flat `Vec<f32>` of parameters, so a module costs 8 + 4·arity bytes and no heap
//! allocation of its own. Each step reads one string and writes the next.
//!
//! Randomness: one [`SplitMix64`] stream, seeded once, consumed strictly left to right: for each
//! module, the conditions and weights of its candidate productions in declaration order, then one
//! draw to choose (only when more than one candidate has a positive weight), then the chosen
//! successor's parameter expressions left to right. So the first `k` steps of an `n`-step
//! derivation are exactly a `k`-step derivation.

use std::fmt;

use canopy_shared::rng::SplitMix64;

use super::expr::{EvalError, Expr};
use super::grammar::Grammar;
use super::{LSystemError, Limits};

/// One module record: 8 bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Raw {
    symbol: u8,
    arity: u8,
    birth: u8,
    offset: u32,
}

/// A derived string of parametric modules.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ModuleString {
    modules: Vec<Raw>,
    params: Vec<f32>,
}

/// A view of one module of a [`ModuleString`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Module<'a> {
    /// The module's symbol.
    pub symbol: char,
    /// Its actual parameters (all finite).
    pub params: &'a [f32],
    /// The iteration that created it: 0 for the axiom, `i` for successors written by step `i`;
    /// a module copied unchanged keeps its birth.
    pub birth: u8,
}

impl ModuleString {
    /// Number of modules.
    pub fn len(&self) -> usize {
        self.modules.len()
    }

    /// Whether there are no modules.
    pub fn is_empty(&self) -> bool {
        self.modules.is_empty()
    }

    /// Total number of parameters over all modules.
    pub fn param_count(&self) -> usize {
        self.params.len()
    }

    /// The module at `index`, if any.
    pub fn get(&self, index: usize) -> Option<Module<'_>> {
        self.modules.get(index).map(|r| self.view(*r))
    }

    /// The modules in order.
    pub fn iter(&self) -> impl ExactSizeIterator<Item = Module<'_>> + '_ {
        self.modules.iter().map(|r| self.view(*r))
    }

    fn view(&self, r: Raw) -> Module<'_> {
        let start = r.offset as usize;
        let params = self.params.get(start..start + usize::from(r.arity)).unwrap_or(&[]);
        Module {
            symbol: char::from(r.symbol),
            params,
            birth: r.birth,
        }
    }

    /// Starts a new module with no parameters yet; [`Self::push_param`] adds them.
    pub(crate) fn begin_module(
        &mut self,
        symbol: u8,
        birth: u8,
        limits: &Limits,
        iteration: u32,
    ) -> Result<(), LSystemError> {
        if self.modules.len() >= limits.max_modules {
            return Err(LSystemError::ModuleCap {
                cap: limits.max_modules,
                iteration,
            });
        }
        self.modules.push(Raw {
            symbol,
            arity: 0,
            birth,
            // The parameter cap keeps this below u32::MAX (see `check_caps`).
            offset: self.params.len() as u32,
        });
        Ok(())
    }

    /// Appends a parameter to the module started last. `value` must come from evaluating `expr`
    /// in `context`; it is rejected if it does not fit a finite `f32`.
    pub(crate) fn push_param(&mut self, value: f64, context: &str, expr: &Expr) -> Result<(), LSystemError> {
        let v = value as f32;
        if !v.is_finite() {
            return Err(LSystemError::NonFinite {
                context: context.to_string(),
                expression: expr.text.clone(),
                value,
            });
        }
        self.params.push(v);
        if let Some(last) = self.modules.last_mut() {
            // Successor modules carry at most MAX_PARAMS (16) parameters.
            last.arity += 1;
        }
        Ok(())
    }

    /// Checks the parameter memory cap (modules are checked as they are added).
    pub(crate) fn check_caps(&self, limits: &Limits, iteration: u32) -> Result<(), LSystemError> {
        let cap = limits.max_param_bytes.min(u32::MAX as usize);
        if self.params.len() * 4 > cap {
            return Err(LSystemError::ParamMemoryCap {
                cap: limits.max_param_bytes,
                iteration,
            });
        }
        Ok(())
    }

    fn copy_from(&mut self, src: &ModuleString, r: Raw) {
        let start = r.offset as usize;
        let offset = self.params.len() as u32;
        if let Some(p) = src.params.get(start..start + usize::from(r.arity)) {
            self.params.extend_from_slice(p);
        }
        self.modules.push(Raw { offset, ..r });
    }

    fn clear(&mut self) {
        self.modules.clear();
        self.params.clear();
    }
}

impl fmt::Display for ModuleString {
    /// Writes the string in grammar syntax, e.g. `C(1)C(5)C(2)B(3)` (parameters with `f32`'s
    /// shortest round-trip formatting).
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for m in self.iter() {
            write!(f, "{}", m.symbol)?;
            if !m.params.is_empty() {
                f.write_str("(")?;
                for (i, p) in m.params.iter().enumerate() {
                    if i > 0 {
                        f.write_str(",")?;
                    }
                    write!(f, "{p}")?;
                }
                f.write_str(")")?;
            }
        }
        Ok(())
    }
}

/// Adds the context to an evaluation error.
pub(crate) fn eval_error(err: EvalError, context: &str, expr: &Expr) -> LSystemError {
    match err {
        EvalError::DivisionByZero => LSystemError::DivisionByZero {
            context: context.to_string(),
            expression: expr.text.clone(),
        },
        EvalError::NonFinite(value) => LSystemError::NonFinite {
            context: context.to_string(),
            expression: expr.text.clone(),
            value,
        },
    }
}

impl Grammar {
    /// Derives `iterations` steps from the axiom with the RNG seeded by `seed`.
    ///
    /// Deterministic: the same grammar, seed and iteration count give an identical string, and
    /// the first `k` steps of a longer derivation equal a `k`-step derivation.
    pub fn derive(&self, seed: u64, iterations: u32, limits: &Limits) -> Result<ModuleString, LSystemError> {
        self.derive_with_progress(seed, iterations, limits, &mut |_, _| {})
    }

    /// [`Self::derive`], calling `progress(iteration, module_count)` after the axiom
    /// (iteration 0) and after every step.
    pub fn derive_with_progress(
        &self,
        seed: u64,
        iterations: u32,
        limits: &Limits,
        progress: &mut dyn FnMut(u32, usize),
    ) -> Result<ModuleString, LSystemError> {
        let cap = limits.iteration_cap();
        if iterations > cap {
            return Err(LSystemError::IterationCap {
                requested: iterations,
                cap,
            });
        }
        let mut rng = SplitMix64::new(seed);
        let mut cur = self.axiom_string(&mut rng, limits)?;
        progress(0, cur.len());
        let mut next = ModuleString::default();
        let mut scratch = Scratch::default();
        for it in 1..=iterations {
            self.step(&cur, &mut next, it, &mut rng, limits, &mut scratch)?;
            std::mem::swap(&mut cur, &mut next);
            progress(it, cur.len());
        }
        Ok(cur)
    }

    /// One parallel rewriting step from `src` into `dst` (cleared first).
    fn step(
        &self,
        src: &ModuleString,
        dst: &mut ModuleString,
        iteration: u32,
        rng: &mut SplitMix64,
        limits: &Limits,
        s: &mut Scratch,
    ) -> Result<(), LSystemError> {
        dst.clear();
        // Iterations are capped at 255, so the birth fits a u8.
        let birth = iteration as u8;
        let mut since_check = 0usize;
        for &raw in &src.modules {
            let candidates = &self.by_symbol[usize::from(raw.symbol)];
            let params = src
                .params
                .get(raw.offset as usize..raw.offset as usize + usize::from(raw.arity))
                .unwrap_or(&[]);
            s.chosen.clear();
            let mut total = 0.0;
            for &pi in candidates {
                let p = &self.productions[pi as usize];
                if p.arity != raw.arity {
                    continue;
                }
                if let Some(c) = &p.condition {
                    let v = c
                        .eval(params, rng, &mut s.stack)
                        .map_err(|e| eval_error(e, &p.context, c))?;
                    if v == 0.0 {
                        continue;
                    }
                }
                let w = match &p.weight {
                    None => 1.0,
                    Some(e) => {
                        let w = e
                            .eval(params, rng, &mut s.stack)
                            .map_err(|err| eval_error(err, &p.context, e))?;
                        if w < 0.0 {
                            return Err(LSystemError::NegativeWeight {
                                context: p.context.clone(),
                                expression: e.text.clone(),
                                value: w,
                            });
                        }
                        w
                    }
                };
                if w > 0.0 {
                    total += w;
                    s.chosen.push((pi, w));
                }
            }
            let pick = match s.chosen.as_slice() {
                [] => None,
                [(pi, _)] => Some(*pi),
                many => {
                    // Roulette wheel: the first candidate whose cumulative weight exceeds u·Σw.
                    let r = rng.next_f64() * total;
                    let mut acc = 0.0;
                    let mut pick = many[many.len() - 1].0;
                    for &(pi, w) in many {
                        acc += w;
                        if r < acc {
                            pick = pi;
                            break;
                        }
                    }
                    Some(pick)
                }
            };
            match pick {
                None => {
                    if dst.modules.len() >= limits.max_modules {
                        return Err(LSystemError::ModuleCap {
                            cap: limits.max_modules,
                            iteration,
                        });
                    }
                    dst.copy_from(src, raw);
                    since_check += 1;
                }
                Some(pi) => {
                    let p = &self.productions[pi as usize];
                    for m in &p.successor {
                        dst.begin_module(m.symbol, birth, limits, iteration)?;
                        for e in &m.params {
                            let v = e
                                .eval(params, rng, &mut s.stack)
                                .map_err(|err| eval_error(err, &p.context, e))?;
                            dst.push_param(v, &p.context, e)?;
                        }
                        since_check += 1;
                    }
                }
            }
            // Checking the parameter cap every 4096 modules bounds the overshoot to
            // 4096 × (16 + successor) parameters while keeping the hot loop lean.
            if since_check >= 4096 {
                since_check = 0;
                dst.check_caps(limits, iteration)?;
            }
        }
        dst.check_caps(limits, iteration)
    }
}

/// Scratch buffers reused across modules and steps.
#[derive(Debug, Default)]
struct Scratch {
    stack: Vec<f64>,
    chosen: Vec<(u32, f64)>,
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use super::*;

    fn grammar(axiom: &str, prods: &[&str]) -> Grammar {
        Grammar::new(axiom, prods, &BTreeMap::new(), &Limits::default()).unwrap_or_else(|e| panic!("{e}"))
    }

    #[test]
    fn deterministic_rewriting_and_display() {
        let g = grammar("A(1)", &["A(x) -> F(x)[+A(x/2)]A(x+1)"]);
        let s = g.derive(0, 2, &Limits::default());
        let s = s.unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(s.to_string(), "F(1)[+F(0.5)[+A(0.25)]A(1.5)]F(2)[+A(1)]A(3)");
        let births: Vec<u8> = s.iter().map(|m| m.birth).collect();
        assert_eq!(births[0], 1, "F(1) was written by step 1");
        assert_eq!(births[3], 2, "F(0.5) was written by step 2");
        assert_eq!(s.get(0).map(|m| m.params.to_vec()), Some(vec![1.0]));
        assert!(s.get(s.len()).is_none());
    }

    #[test]
    fn copies_keep_birth() {
        let g = grammar("AB", &["A -> AC"]);
        let s = g.derive(0, 3, &Limits::default()).unwrap_or_default();
        assert_eq!(s.to_string(), "ACCCB");
        let births: Vec<u8> = s.iter().map(|m| m.birth).collect();
        assert_eq!(births, vec![3, 3, 2, 1, 0]);
    }

    #[test]
    fn empty_successor_erases() {
        let g = grammar("ABA", &["A -> "]);
        assert_eq!(
            g.derive(0, 1, &Limits::default()).map(|s| s.to_string()),
            Ok("B".into())
        );
    }

    #[test]
    fn zero_weight_is_never_chosen_and_negative_is_an_error() {
        let g = grammar("A(1)", &["A(x) -> B : 0", "A(x) -> C : x"]);
        for seed in 0..50 {
            assert_eq!(
                g.derive(seed, 1, &Limits::default()).map(|s| s.to_string()),
                Ok("C".into())
            );
        }
        let g = grammar("A(1)", &["A(x) -> B : x - 2"]);
        assert!(matches!(
            g.derive(0, 1, &Limits::default()),
            Err(LSystemError::NegativeWeight { .. })
        ));
        // All weights zero: copied unchanged.
        let g = grammar("A(1)", &["A(x) -> B : x - 1"]);
        assert_eq!(
            g.derive(0, 1, &Limits::default()).map(|s| s.to_string()),
            Ok("A(1)".into())
        );
    }

    #[test]
    fn arity_must_match() {
        let g = grammar("A(1)A", &["A(x) -> B(x)", "A -> C"]);
        assert_eq!(
            g.derive(0, 1, &Limits::default()).map(|s| s.to_string()),
            Ok("B(1)C".into())
        );
    }

    #[test]
    fn progress_is_reported() {
        let g = grammar("A", &["A -> AA"]);
        let mut seen = Vec::new();
        let r = g.derive_with_progress(0, 3, &Limits::default(), &mut |i, n| seen.push((i, n)));
        assert!(r.is_ok());
        assert_eq!(seen, vec![(0, 1), (1, 2), (2, 4), (3, 8)]);
    }
}
