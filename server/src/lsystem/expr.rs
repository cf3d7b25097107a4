//! Parameter and condition expressions: parsing (recursive descent with a depth cap) into a small
//! postfix program, and evaluation of that program.
//!
//! Syntax, lowest precedence first:
//!
//! | level | operators | associativity |
//! |---|---|---|
//! | 1 | `\|\|` | left |
//! | 2 | `&&` | left |
//! | 3 | `==` `!=` | left |
//! | 4 | `<` `<=` `>` `>=` | left |
//! | 5 | `+` `-` | left |
//! | 6 | `*` `/` | left |
//! | 7 | unary `-` `+` `!` | prefix |
//! | 8 | `^` (power) | right, binds tighter than unary minus: `-x^2 = -(x^2)` |
//!
//! Operands: decimal numbers (`2`, `0.5`, `.5`, `1e-3`), the predecessor's formal parameters,
//! named constants, `pi`, and function calls (see [`Func`]). Booleans are numbers: comparisons
//! give 1 or 0, and anything non-zero is true.
//!
//! Evaluation is in `f64`. Division by zero and any non-finite intermediate result are errors
//! (NaN would otherwise slip through comparisons silently).

use std::collections::BTreeMap;

use canopy_shared::rng::SplitMix64;

/// One instruction of the postfix program.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Op {
    Num(f64),
    Param(u8),
    Neg,
    Not,
    Add,
    Sub,
    Mul,
    Div,
    Pow,
    Lt,
    Le,
    Gt,
    Ge,
    Eq,
    Ne,
    And,
    Or,
    Call(Func),
}

/// Built-in functions. Angles are radians (`rad`/`deg` convert).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Func {
    Sqrt,
    Abs,
    Sin,
    Cos,
    Tan,
    Asin,
    Acos,
    Atan,
    Atan2,
    Exp,
    Ln,
    Log10,
    Pow,
    Min,
    Max,
    Floor,
    Ceil,
    Round,
    Clamp,
    Sign,
    Rad,
    Deg,
    /// `rand(lo, hi)`: uniform in `[lo, hi)`, drawn from the derivation's RNG.
    Rand,
    /// `nrand(mean, sd)`: normal, drawn from the derivation's RNG.
    Nrand,
}

const FUNCS: &[(&str, Func, usize)] = &[
    ("sqrt", Func::Sqrt, 1),
    ("abs", Func::Abs, 1),
    ("sin", Func::Sin, 1),
    ("cos", Func::Cos, 1),
    ("tan", Func::Tan, 1),
    ("asin", Func::Asin, 1),
    ("acos", Func::Acos, 1),
    ("atan", Func::Atan, 1),
    ("atan2", Func::Atan2, 2),
    ("exp", Func::Exp, 1),
    ("ln", Func::Ln, 1),
    ("log10", Func::Log10, 1),
    ("pow", Func::Pow, 2),
    ("min", Func::Min, 2),
    ("max", Func::Max, 2),
    ("floor", Func::Floor, 1),
    ("ceil", Func::Ceil, 1),
    ("round", Func::Round, 1),
    ("clamp", Func::Clamp, 3),
    ("sign", Func::Sign, 1),
    ("rad", Func::Rad, 1),
    ("deg", Func::Deg, 1),
    ("rand", Func::Rand, 2),
    ("nrand", Func::Nrand, 2),
];

/// Names of the built-in functions (for documentation and constant-name validation).
pub(crate) fn is_reserved_name(name: &str) -> bool {
    name == "pi" || FUNCS.iter().any(|(n, _, _)| *n == name)
}

/// Longest compiled program (after user functions are substituted), in instructions. Bounds the
/// blow-up of nested user functions such as `f2(x) = f1(f1(x))`.
pub(crate) const MAX_PROGRAM_LEN: usize = 1 << 16;

/// A user function: `name(a, b) = body`, substituted at every call like a macro.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct UserFn {
    arity: usize,
    /// The body, with `Param(j)` naming the function's own parameter `j`.
    ops: Vec<Op>,
}

/// Names an expression may use besides the predecessor's parameters.
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct Env {
    pub(crate) constants: BTreeMap<String, f64>,
    pub(crate) functions: BTreeMap<String, UserFn>,
}

impl Env {
    /// Whether `name` is already taken by a built-in, a constant or a user function.
    pub(crate) fn is_taken(&self, name: &str) -> bool {
        is_reserved_name(name) || self.constants.contains_key(name) || self.functions.contains_key(name)
    }

    /// Compiles a user function body over its own `params` (which shadow constants) and adds it.
    /// The body may call built-ins and functions defined earlier, so recursion is impossible.
    pub(crate) fn define_function(
        &mut self,
        name: &str,
        params: &[String],
        body: &str,
        max_depth: usize,
    ) -> Result<(), ParseError> {
        let e = Expr::parse(body, params, self, max_depth)?;
        let ops = match e.constant {
            Some(v) => vec![Op::Num(v)],
            None => e.ops,
        };
        self.functions.insert(
            name.to_string(),
            UserFn {
                arity: params.len(),
                ops,
            },
        );
        Ok(())
    }
}

/// Why an evaluation failed; the caller adds the context.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum EvalError {
    DivisionByZero,
    NonFinite(f64),
}

/// A compiled expression.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Expr {
    ops: Vec<Op>,
    /// Source text, trimmed, for error messages.
    pub(crate) text: String,
    /// The value, when the expression uses neither parameters nor the RNG.
    constant: Option<f64>,
}

/// Why parsing failed; the caller adds the context.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum ParseError {
    Syntax {
        position: usize,
        message: String,
    },
    TooDeep {
        cap: usize,
    },
    /// A constant sub-expression failed to evaluate (e.g. `1/0`).
    Eval(EvalError),
}

impl Expr {
    /// Compiles `text`. `params` are the formal parameter names (they shadow constants),
    /// `env` the constants and user functions, `max_depth` the nesting cap.
    pub(crate) fn parse(text: &str, params: &[String], env: &Env, max_depth: usize) -> Result<Self, ParseError> {
        let mut p = Parser {
            src: text.as_bytes(),
            pos: 0,
            depth: 0,
            max_depth,
            params,
            env,
            ops: Vec::new(),
        };
        p.skip_ws();
        if p.pos >= p.src.len() {
            return Err(ParseError::Syntax {
                position: p.pos,
                message: "empty expression".into(),
            });
        }
        p.expr()?;
        p.skip_ws();
        if p.pos < p.src.len() {
            return Err(p.error(format!("unexpected `{}`", p.peek_char())));
        }
        Self::finish(p.ops, text.trim().to_string())
    }

    /// This expression with every parameter `j` replaced by `args[j]` (module macros), folded
    /// again if the result is constant.
    pub(crate) fn substitute(&self, args: &[Expr]) -> Result<Self, ParseError> {
        let mut ops = Vec::with_capacity(self.ops.len());
        for op in &self.ops {
            match *op {
                Op::Param(j) => match args.get(usize::from(j)) {
                    Some(a) => match a.constant {
                        Some(v) => ops.push(Op::Num(v)),
                        None => ops.extend_from_slice(&a.ops),
                    },
                    None => ops.push(Op::Num(0.0)),
                },
                other => ops.push(other),
            }
        }
        if ops.len() > MAX_PROGRAM_LEN {
            return Err(ParseError::Syntax {
                position: 0,
                message: format!("expression longer than {MAX_PROGRAM_LEN} instructions after macro expansion"),
            });
        }
        Self::finish(ops, self.text.clone())
    }

    /// Wraps a program, folding it when it uses neither parameters nor the RNG.
    fn finish(ops: Vec<Op>, text: String) -> Result<Self, ParseError> {
        let mut e = Expr {
            ops,
            text,
            constant: None,
        };
        let pure = !e
            .ops
            .iter()
            .any(|op| matches!(op, Op::Param(_) | Op::Call(Func::Rand | Func::Nrand)));
        if pure {
            // Fold now: evaluation of the folded form cannot fail later, and bad constants
            // (`1/0`) are reported when the grammar is compiled.
            let mut stack = Vec::new();
            let v = e
                .eval_ops(&[], &mut SplitMix64::new(0), &mut stack)
                .map_err(ParseError::Eval)?;
            e.constant = Some(v);
        }
        Ok(e)
    }

    /// The folded value, if the expression is constant.
    pub(crate) fn constant(&self) -> Option<f64> {
        self.constant
    }

    /// Evaluates with the given actual parameters. `stack` is scratch space reused between calls.
    /// Parameters the program names but `params` lacks read as 0 (cannot happen for programs
    /// compiled against a predecessor with the same arity; this keeps evaluation panic-free).
    pub(crate) fn eval(&self, params: &[f32], rng: &mut SplitMix64, stack: &mut Vec<f64>) -> Result<f64, EvalError> {
        match self.constant {
            Some(v) => Ok(v),
            None => self.eval_ops(params, rng, stack),
        }
    }

    fn eval_ops(&self, params: &[f32], rng: &mut SplitMix64, stack: &mut Vec<f64>) -> Result<f64, EvalError> {
        stack.clear();
        for &op in &self.ops {
            let v = match op {
                Op::Num(v) => v,
                Op::Param(i) => f64::from(params.get(usize::from(i)).copied().unwrap_or(0.0)),
                Op::Neg => -pop(stack),
                Op::Not => bool_num(pop(stack) == 0.0),
                Op::Call(f) => call(f, stack, rng)?,
                _ => {
                    let b = pop(stack);
                    let a = pop(stack);
                    binary(op, a, b)?
                }
            };
            if !v.is_finite() {
                return Err(EvalError::NonFinite(v));
            }
            stack.push(v);
        }
        Ok(pop(stack))
    }
}

/// Pops an operand. The compiler guarantees one is there; NaN (an error downstream) otherwise.
fn pop(stack: &mut Vec<f64>) -> f64 {
    stack.pop().unwrap_or(f64::NAN)
}

fn bool_num(b: bool) -> f64 {
    if b { 1.0 } else { 0.0 }
}

fn binary(op: Op, a: f64, b: f64) -> Result<f64, EvalError> {
    Ok(match op {
        Op::Add => a + b,
        Op::Sub => a - b,
        Op::Mul => a * b,
        Op::Div => {
            if b == 0.0 {
                return Err(EvalError::DivisionByZero);
            }
            a / b
        }
        Op::Pow => a.powf(b),
        Op::Lt => bool_num(a < b),
        Op::Le => bool_num(a <= b),
        Op::Gt => bool_num(a > b),
        Op::Ge => bool_num(a >= b),
        Op::Eq => bool_num(a == b),
        Op::Ne => bool_num(a != b),
        Op::And => bool_num(a != 0.0 && b != 0.0),
        Op::Or => bool_num(a != 0.0 || b != 0.0),
        // Not binary: unreachable from eval_ops, but stay total.
        Op::Num(_) | Op::Param(_) | Op::Neg | Op::Not | Op::Call(_) => f64::NAN,
    })
}

fn call(f: Func, stack: &mut Vec<f64>, rng: &mut SplitMix64) -> Result<f64, EvalError> {
    Ok(match f {
        Func::Sqrt => pop(stack).sqrt(),
        Func::Abs => pop(stack).abs(),
        Func::Sin => pop(stack).sin(),
        Func::Cos => pop(stack).cos(),
        Func::Tan => pop(stack).tan(),
        Func::Asin => pop(stack).asin(),
        Func::Acos => pop(stack).acos(),
        Func::Atan => pop(stack).atan(),
        Func::Exp => pop(stack).exp(),
        Func::Ln => pop(stack).ln(),
        Func::Log10 => pop(stack).log10(),
        Func::Floor => pop(stack).floor(),
        Func::Ceil => pop(stack).ceil(),
        Func::Round => pop(stack).round(),
        Func::Sign => {
            let x = pop(stack);
            if x > 0.0 {
                1.0
            } else if x < 0.0 {
                -1.0
            } else {
                0.0
            }
        }
        Func::Rad => pop(stack).to_radians(),
        Func::Deg => pop(stack).to_degrees(),
        Func::Atan2 | Func::Pow | Func::Min | Func::Max | Func::Rand | Func::Nrand => {
            let b = pop(stack);
            let a = pop(stack);
            match f {
                Func::Atan2 => a.atan2(b),
                Func::Pow => a.powf(b),
                Func::Min => a.min(b),
                Func::Max => a.max(b),
                Func::Rand => rng.uniform(a, b),
                _ => rng.normal(a, b),
            }
        }
        Func::Clamp => {
            let hi = pop(stack);
            let lo = pop(stack);
            let x = pop(stack);
            if lo > hi {
                // `f64::clamp` would panic; an inverted range is the grammar's error.
                return Err(EvalError::NonFinite(f64::NAN));
            }
            x.clamp(lo, hi)
        }
    })
}

struct Parser<'a> {
    src: &'a [u8],
    pos: usize,
    depth: usize,
    max_depth: usize,
    params: &'a [String],
    env: &'a Env,
    ops: Vec<Op>,
}

type PResult = Result<(), ParseError>;

impl Parser<'_> {
    fn error(&self, message: String) -> ParseError {
        ParseError::Syntax {
            position: self.pos,
            message,
        }
    }

    fn peek(&self) -> Option<u8> {
        self.src.get(self.pos).copied()
    }

    /// The character at `pos` for messages (lossy for non-ASCII).
    fn peek_char(&self) -> char {
        let rest = &self.src[self.pos.min(self.src.len())..];
        String::from_utf8_lossy(&rest[..rest.len().min(4)])
            .chars()
            .next()
            .unwrap_or(' ')
    }

    fn skip_ws(&mut self) {
        while self.peek().is_some_and(|c| c.is_ascii_whitespace()) {
            self.pos += 1;
        }
    }

    /// Consumes `tok` (after whitespace) if it is next.
    fn eat(&mut self, tok: &str) -> bool {
        self.skip_ws();
        if self.src[self.pos..].starts_with(tok.as_bytes()) {
            self.pos += tok.len();
            true
        } else {
            false
        }
    }

    fn expr(&mut self) -> PResult {
        self.or()
    }

    fn or(&mut self) -> PResult {
        self.and()?;
        while self.eat("||") {
            self.and()?;
            self.ops.push(Op::Or);
        }
        Ok(())
    }

    fn and(&mut self) -> PResult {
        self.equality()?;
        while self.eat("&&") {
            self.equality()?;
            self.ops.push(Op::And);
        }
        Ok(())
    }

    fn equality(&mut self) -> PResult {
        self.relational()?;
        loop {
            let op = if self.eat("==") {
                Op::Eq
            } else if self.eat("!=") {
                Op::Ne
            } else {
                return Ok(());
            };
            self.relational()?;
            self.ops.push(op);
        }
    }

    fn relational(&mut self) -> PResult {
        self.additive()?;
        loop {
            let op = if self.eat("<=") {
                Op::Le
            } else if self.eat(">=") {
                Op::Ge
            } else if self.eat("<") {
                Op::Lt
            } else if self.eat(">") {
                Op::Gt
            } else {
                return Ok(());
            };
            self.additive()?;
            self.ops.push(op);
        }
    }

    fn additive(&mut self) -> PResult {
        self.multiplicative()?;
        loop {
            let op = if self.eat("+") {
                Op::Add
            } else if self.eat("-") {
                Op::Sub
            } else {
                return Ok(());
            };
            self.multiplicative()?;
            self.ops.push(op);
        }
    }

    fn multiplicative(&mut self) -> PResult {
        self.unary()?;
        loop {
            let op = if self.eat("*") {
                Op::Mul
            } else if self.eat("/") {
                Op::Div
            } else {
                return Ok(());
            };
            self.unary()?;
            self.ops.push(op);
        }
    }

    /// Every recursive cycle of the parser passes through here, so counting depth here bounds
    /// the recursion (about nine frames per level).
    fn unary(&mut self) -> PResult {
        self.depth += 1;
        if self.depth > self.max_depth {
            return Err(ParseError::TooDeep { cap: self.max_depth });
        }
        let r = self.unary_inner();
        self.depth -= 1;
        r
    }

    fn unary_inner(&mut self) -> PResult {
        self.skip_ws();
        // `!=` cannot start an operand, so a leading `!` is always logical not.
        if self.eat("-") {
            self.unary()?;
            self.ops.push(Op::Neg);
        } else if self.eat("+") {
            self.unary()?;
        } else if self.eat("!") {
            self.unary()?;
            self.ops.push(Op::Not);
        } else {
            self.primary()?;
            if self.eat("^") {
                self.unary()?;
                self.ops.push(Op::Pow);
            }
        }
        Ok(())
    }

    fn primary(&mut self) -> PResult {
        self.skip_ws();
        match self.peek() {
            None => Err(self.error("expression ends early".into())),
            Some(b'(') => {
                self.pos += 1;
                self.expr()?;
                if self.eat(")") {
                    Ok(())
                } else {
                    Err(self.error("expected `)`".into()))
                }
            }
            Some(c) if c.is_ascii_digit() || c == b'.' => self.number(),
            Some(c) if c.is_ascii_alphabetic() || c == b'_' => self.identifier(),
            Some(_) => Err(self.error(format!("unexpected `{}`", self.peek_char()))),
        }
    }

    fn number(&mut self) -> PResult {
        let start = self.pos;
        while self.peek().is_some_and(|c| c.is_ascii_digit() || c == b'.') {
            self.pos += 1;
        }
        if matches!(self.peek(), Some(b'e' | b'E')) {
            let save = self.pos;
            self.pos += 1;
            if matches!(self.peek(), Some(b'+' | b'-')) {
                self.pos += 1;
            }
            if self.peek().is_some_and(|c| c.is_ascii_digit()) {
                while self.peek().is_some_and(|c| c.is_ascii_digit()) {
                    self.pos += 1;
                }
            } else {
                // `2e` is not an exponent; let the caller complain about the `e`.
                self.pos = save;
            }
        }
        let text = std::str::from_utf8(&self.src[start..self.pos]).unwrap_or("");
        match text.parse::<f64>() {
            Ok(v) if v.is_finite() => {
                self.ops.push(Op::Num(v));
                Ok(())
            }
            _ => Err(ParseError::Syntax {
                position: start,
                message: format!("bad number `{text}`"),
            }),
        }
    }

    fn identifier(&mut self) -> PResult {
        let start = self.pos;
        while self.peek().is_some_and(|c| c.is_ascii_alphanumeric() || c == b'_') {
            self.pos += 1;
        }
        let name = std::str::from_utf8(&self.src[start..self.pos]).unwrap_or("");
        self.skip_ws();
        if self.peek() == Some(b'(') {
            self.pos += 1;
            let builtin = FUNCS.iter().find(|(n, _, _)| *n == name);
            let user = self.env.functions.get(name);
            let arity = match (builtin, user) {
                (Some(&(_, _, a)), _) => a,
                (None, Some(f)) => f.arity,
                (None, None) => {
                    return Err(ParseError::Syntax {
                        position: start,
                        message: format!("unknown function `{name}`"),
                    });
                }
            };
            // Each argument is compiled into its own program so that a user function can
            // substitute it for its parameter.
            let outer = std::mem::take(&mut self.ops);
            let mut args: Vec<Vec<Op>> = Vec::new();
            if !self.eat(")") {
                loop {
                    self.expr()?;
                    args.push(std::mem::take(&mut self.ops));
                    if self.eat(",") {
                        continue;
                    }
                    if self.eat(")") {
                        break;
                    }
                    return Err(self.error("expected `,` or `)` in function call".into()));
                }
            }
            self.ops = outer;
            if args.len() != arity {
                return Err(ParseError::Syntax {
                    position: start,
                    message: format!("`{name}` takes {arity} argument(s), got {}", args.len()),
                });
            }
            match (builtin, user) {
                (Some(&(_, func, _)), _) => {
                    self.ops.extend(args.into_iter().flatten());
                    self.ops.push(Op::Call(func));
                }
                (None, Some(f)) => {
                    for op in &f.ops {
                        match *op {
                            Op::Param(j) => {
                                if let Some(a) = args.get(usize::from(j)) {
                                    self.ops.extend_from_slice(a);
                                }
                            }
                            other => self.ops.push(other),
                        }
                    }
                }
                (None, None) => {}
            }
            if self.ops.len() > MAX_PROGRAM_LEN {
                return Err(ParseError::Syntax {
                    position: start,
                    message: format!("expression longer than {MAX_PROGRAM_LEN} instructions after expanding `{name}`"),
                });
            }
            return Ok(());
        }
        if let Some(i) = self.params.iter().position(|p| p == name) {
            // Formal lists are capped at MAX_PARAMS (16), so the index fits a u8.
            self.ops.push(Op::Param(i as u8));
        } else if let Some(&v) = self.env.constants.get(name) {
            self.ops.push(Op::Num(v));
        } else if name == "pi" {
            self.ops.push(Op::Num(std::f64::consts::PI));
        } else {
            return Err(ParseError::Syntax {
                position: start,
                message: format!("unknown name `{name}` (not a parameter or constant)"),
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn eval_str(text: &str, params: &[(&str, f32)]) -> Result<f64, String> {
        let names: Vec<String> = params.iter().map(|(n, _)| (*n).to_string()).collect();
        let values: Vec<f32> = params.iter().map(|(_, v)| *v).collect();
        let mut env = Env::default();
        env.constants.insert("k".to_string(), 10.0);
        let fp = ["a".to_string(), "b".to_string()];
        env.define_function("hyp", &fp, "sqrt(a*a + b*b)", 64)
            .map_err(|e| format!("{e:?}"))?;
        env.define_function("twice", &fp[..1], "2 * a + k", 64)
            .map_err(|e| format!("{e:?}"))?;
        env.define_function("quad", &fp[..1], "twice(twice(a))", 64)
            .map_err(|e| format!("{e:?}"))?;
        env.define_function("noise", &fp[..1], "a + rand(0, 1)", 64)
            .map_err(|e| format!("{e:?}"))?;
        let e = Expr::parse(text, &names, &env, 64).map_err(|e| format!("{e:?}"))?;
        e.eval(&values, &mut SplitMix64::new(1), &mut Vec::new())
            .map_err(|e| format!("{e:?}"))
    }

    #[test]
    fn arithmetic_and_precedence() {
        assert_eq!(eval_str("1 + 2 * 3", &[]), Ok(7.0));
        assert_eq!(eval_str("(1 + 2) * 3", &[]), Ok(9.0));
        assert_eq!(eval_str("2 ^ 3 ^ 2", &[]), Ok(512.0));
        assert_eq!(eval_str("-2 ^ 2", &[]), Ok(-4.0));
        assert_eq!(eval_str("2 ^ -1", &[]), Ok(0.5));
        assert_eq!(eval_str("10 - 4 - 3", &[]), Ok(3.0));
        assert_eq!(eval_str("8 / 4 / 2", &[]), Ok(1.0));
        assert_eq!(eval_str("x + k", &[("x", 2.0)]), Ok(12.0));
        assert_eq!(eval_str("k", &[("k", 1.0)]), Ok(1.0), "parameters shadow constants");
        assert_eq!(eval_str(".5e1 + 1E-1", &[]), Ok(5.1));
        assert_eq!(eval_str("--3", &[]), Ok(3.0));
    }

    #[test]
    fn logic_and_comparisons() {
        assert_eq!(eval_str("x > 2", &[("x", 3.0)]), Ok(1.0));
        assert_eq!(eval_str("x > 2", &[("x", 2.0)]), Ok(0.0));
        assert_eq!(eval_str("x >= 2 && x <= 2", &[("x", 2.0)]), Ok(1.0));
        assert_eq!(eval_str("x == 1 || x != 2", &[("x", 2.0)]), Ok(0.0));
        assert_eq!(eval_str("!(x < 1)", &[("x", 2.0)]), Ok(1.0));
        assert_eq!(eval_str("1 + 1 == 2", &[]), Ok(1.0));
    }

    #[test]
    fn functions() {
        assert_eq!(eval_str("sqrt(16) + abs(-1)", &[]), Ok(5.0));
        assert_eq!(eval_str("min(3, max(1, 2))", &[]), Ok(2.0));
        assert_eq!(eval_str("clamp(5, 0, 1)", &[]), Ok(1.0));
        assert!((eval_str("sin(pi / 2)", &[]).unwrap_or(0.0) - 1.0).abs() < 1e-12);
        assert!((eval_str("cos(rad(180))", &[]).unwrap_or(0.0) + 1.0).abs() < 1e-12);
        let r = eval_str("rand(2, 3)", &[]).unwrap_or(0.0);
        assert!((2.0..3.0).contains(&r));
        assert!(eval_str("nrand(0, 1)", &[]).is_ok());
    }

    #[test]
    fn user_functions() {
        assert_eq!(eval_str("hyp(3, 4)", &[]), Ok(5.0));
        assert_eq!(eval_str("hyp(x, 4) + 1", &[("x", 3.0)]), Ok(6.0));
        assert_eq!(eval_str("twice(1)", &[]), Ok(12.0), "bodies see constants");
        assert_eq!(eval_str("quad(1)", &[]), Ok(34.0), "and earlier functions");
        assert_eq!(
            eval_str("twice(a)", &[("a", 2.0)]),
            Ok(14.0),
            "no capture of caller names"
        );
        let r = eval_str("noise(1)", &[]).unwrap_or(0.0);
        assert!((1.0..2.0).contains(&r));
        assert!(eval_str("hyp(1)", &[]).is_err());
        // Exponential expansion is capped.
        let mut env = Env::default();
        let a = ["a".to_string()];
        let mut ok = env.define_function("f0", &a, "a*a*a*a", 64).is_ok();
        for i in 1..12 {
            let body = format!("f{}(f{}(a))", i - 1, i - 1);
            ok &= env.define_function(&format!("f{i}"), &a, &body, 64).is_ok();
        }
        assert!(!ok, "expansion past MAX_PROGRAM_LEN must fail");
    }

    #[test]
    fn errors() {
        assert!(eval_str("", &[]).is_err());
        assert!(eval_str("1 +", &[]).is_err());
        assert!(eval_str("(1", &[]).is_err());
        assert!(eval_str("1)", &[]).is_err());
        assert!(eval_str("y", &[]).is_err());
        assert!(eval_str("foo(1)", &[]).is_err());
        assert!(eval_str("min(1)", &[]).is_err());
        assert!(eval_str("1e999", &[]).is_err());
        assert!(eval_str("1..2", &[]).is_err());
        assert!(eval_str("2e", &[]).is_err());
        assert_eq!(eval_str("x / 0", &[("x", 1.0)]), Err("DivisionByZero".into()));
        assert!(eval_str("sqrt(x)", &[("x", -1.0)]).is_err_and(|e| e.contains("NonFinite")));
        assert!(
            eval_str("sqrt(-1) > 0", &[]).is_err(),
            "NaN must not hide in a comparison"
        );
        assert!(eval_str("clamp(x, 1, 0)", &[("x", 0.5)]).is_err());
        assert!(eval_str("é", &[]).is_err());
    }

    #[test]
    fn depth_cap() {
        let deep = format!("{}1{}", "(".repeat(100), ")".repeat(100));
        let env = Env::default();
        let e = Expr::parse(&deep, &[], &env, 64);
        assert_eq!(e, Err(ParseError::TooDeep { cap: 64 }));
        let shallow = format!("{}1{}", "(".repeat(20), ")".repeat(20));
        assert!(Expr::parse(&shallow, &[], &env, 64).is_ok());
        let unary = "-".repeat(10_000) + "1";
        assert!(matches!(
            Expr::parse(&unary, &[], &env, 64),
            Err(ParseError::TooDeep { .. })
        ));
        // Long but flat expressions are fine.
        let flat = vec!["1"; 10_000].join("+");
        assert!(Expr::parse(&flat, &[], &env, 64).is_ok());
    }
}
