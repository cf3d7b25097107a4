//! The text syntax of axioms and productions, compiled into a [`Grammar`].

use std::collections::BTreeMap;

use canopy_shared::rng::SplitMix64;

use super::expr::{Env, Expr, ParseError};
use super::rewrite::ModuleString;
use super::{LSystemError, Limits, MAX_PARAMS};

/// One module of a successor (or of the axiom): a symbol and its parameter expressions.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ModuleTemplate {
    pub(crate) symbol: u8,
    pub(crate) params: Vec<Expr>,
}

/// A compiled production.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Production {
    pub(crate) symbol: u8,
    pub(crate) arity: u8,
    pub(crate) condition: Option<Expr>,
    pub(crate) successor: Vec<ModuleTemplate>,
    /// `None`: the default weight 1.
    pub(crate) weight: Option<Expr>,
    /// `production N `text``, for error messages.
    pub(crate) context: String,
}

/// A compiled stochastic parametric L-system: axiom, productions, constants, functions and
/// macros.
///
/// # Syntax
///
/// ```text
/// production := predecessor [ ":" condition ] "->" successor [ ":" weight ]
/// predecessor := SYMBOL [ "(" [ NAME { "," NAME } ] ")" ]
/// successor  := { SYMBOL [ "(" [ expr { "," expr } ] ")" ] }
/// ```
///
/// - `SYMBOL` is one printable ASCII character other than `(`, `)`, `,` and `:`; whitespace
///   between modules is ignored. `→` may be written for `->`.
/// - A condition of `*` means "always" (as in ABOP). The weight defaults to 1; it may use the
///   predecessor's parameters, must not be negative, and a production whose weight is 0 is skipped.
/// - The successor may be empty (`A -> ` erases `A`).
/// - An axiom is a successor whose expressions use only constants (and `rand`).
///
/// Expressions: decimal numbers, the predecessor's parameters, constants, `pi`; `+ - * /`, `^`
/// (power, right-associative, tighter than unary minus), unary `-` `+` `!`, comparisons
/// `< <= > >= == !=` (1 or 0), `&&` `||` (non-zero is true), parentheses; functions `sqrt abs
/// sin cos tan asin acos atan atan2 exp ln log10 pow min max floor ceil round clamp sign rad deg`
/// (radians), and `rand(lo, hi)` / `nrand(mean, sd)` drawn from the derivation's RNG. Division by
/// zero and non-finite results are errors.
///
/// The whole-grammar text format of [`Grammar::parse`] has one item per line: `axiom: ...`,
/// `const NAME = EXPR`, `fn NAME(a, b) = EXPR`, `macro Z(a, b) = MODULES`, a production, a blank
/// line, or a comment starting with `#`.
///
/// Compiling checks the whole syntax and folds constant expressions, so a grammar that compiles
/// can only fail later on a cap, a division by zero, a non-finite or negative value.
#[derive(Debug, Clone, PartialEq)]
pub struct Grammar {
    pub(crate) axiom: Vec<ModuleTemplate>,
    pub(crate) productions: Vec<Production>,
    /// Production indices per symbol byte, in declaration order.
    pub(crate) by_symbol: Vec<Vec<u32>>,
}

impl Grammar {
    /// Compiles an axiom and a list of productions (each in the syntax above). `constants` may
    /// be used by name in every expression; formal parameters shadow them. Constant names must be
    /// identifiers and not the name of a built-in function or `pi`.
    ///
    /// Expression nesting is capped by `limits.max_expr_depth`.
    pub fn new<S: AsRef<str>>(
        axiom: &str,
        productions: &[S],
        constants: &BTreeMap<String, f64>,
        limits: &Limits,
    ) -> Result<Self, LSystemError> {
        let none: &[&str] = &[];
        Self::with_definitions(axiom, productions, constants, none, none, limits)
    }

    /// [`Self::new`] with user functions and module macros.
    ///
    /// A function is written `name(a, b) = expression`. Its body sees its own parameters, the
    /// constants, the built-ins and the functions listed before it (so no recursion). Calls are
    /// expanded when the grammar is compiled: an argument that calls `rand` is drawn afresh at
    /// each use of the parameter.
    ///
    /// A macro is written `Z(a, b) = module list`: every module `Z` with two parameters in the
    /// axiom, a successor or a later macro is replaced by the list, with the arguments substituted
    /// for `a` and `b` (same rule for `rand`). A macro's symbol and arity cannot also be a
    /// predecessor. Macros are how a successor repeats a structure (a leaf node, a whorl) without
    /// a helper module that would only expand one iteration later.
    ///
    /// A program longer than 65,536 instructions or a successor longer than 65,536 modules after
    /// expansion is a syntax error.
    pub fn with_definitions<S: AsRef<str>, T: AsRef<str>, U: AsRef<str>>(
        axiom: &str,
        productions: &[S],
        constants: &BTreeMap<String, f64>,
        functions: &[T],
        macros: &[U],
        limits: &Limits,
    ) -> Result<Self, LSystemError> {
        let mut env = Env::default();
        for (name, &value) in constants {
            check_constant(name, value, "constants")?;
            env.constants.insert(name.clone(), value);
        }
        let depth = limits.expr_depth_cap();
        for (i, f) in functions.iter().enumerate() {
            let context = format!("function {} `{}`", i + 1, f.as_ref().trim());
            define_function(&mut env, f.as_ref(), &context, depth)?;
        }
        let mut defs = Defs {
            env,
            macros: BTreeMap::new(),
            max_depth: depth,
        };
        for (i, m) in macros.iter().enumerate() {
            let context = format!("macro {} `{}`", i + 1, m.as_ref().trim());
            define_macro(&mut defs, m.as_ref(), &context)?;
        }
        let axiom = parse_modules(axiom, 0, &[], &defs, "axiom")?;
        let mut prods = Vec::with_capacity(productions.len());
        for (i, p) in productions.iter().enumerate() {
            let prod = parse_production(p.as_ref(), i, &defs)?;
            if defs.macros.contains_key(&(prod.symbol, prod.arity)) {
                return Err(syntax(
                    &prod.context,
                    0,
                    &format!(
                        "`{}` with {} parameter(s) is a macro, so it cannot be a predecessor",
                        char::from(prod.symbol),
                        prod.arity
                    ),
                ));
            }
            prods.push(prod);
        }
        let mut by_symbol = vec![Vec::new(); 256];
        for (i, p) in prods.iter().enumerate() {
            by_symbol[usize::from(p.symbol)].push(i as u32);
        }
        Ok(Self {
            axiom,
            productions: prods,
            by_symbol,
        })
    }

    /// Compiles a whole grammar written one item per line:
    ///
    /// ```text
    /// # seed 000's example
    /// const step = 2
    /// axiom: A(2)B(4)C(2)A(3)
    /// A(x) -> A(x+step) : 2
    /// ```
    ///
    /// `const NAME = EXPR` defines a constant (the expression may use earlier constants); exactly
    /// one `axiom:` line is required.
    pub fn parse(text: &str, limits: &Limits) -> Result<Self, LSystemError> {
        let mut constants = BTreeMap::new();
        let mut functions = Vec::new();
        let mut macros = Vec::new();
        let mut axiom: Option<&str> = None;
        let mut productions = Vec::new();
        for (n, raw) in text.lines().enumerate() {
            let line = raw.trim();
            let context = format!("grammar line {}", n + 1);
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            if let Some(rest) = line.strip_prefix("axiom:") {
                if axiom.is_some() {
                    return Err(syntax(&context, 0, "a second `axiom:` line"));
                }
                axiom = Some(rest);
            } else if let Some(rest) = line.strip_prefix("const ") {
                let Some((name, value)) = rest.split_once('=') else {
                    return Err(syntax(&context, 0, "expected `const NAME = EXPR`"));
                };
                let name = name.trim();
                let env = Env {
                    constants: constants.clone(),
                    ..Env::default()
                };
                let e =
                    Expr::parse(value, &[], &env, limits.expr_depth_cap()).map_err(|e| from_parse(e, &context, 0))?;
                let Some(v) = e.constant() else {
                    return Err(syntax(&context, 0, "a constant must not use `rand`"));
                };
                check_constant(name, v, &context)?;
                if constants.insert(name.to_string(), v).is_some() {
                    return Err(syntax(&context, 0, &format!("constant `{name}` defined twice")));
                }
            } else if let Some(rest) = line.strip_prefix("fn ") {
                functions.push(rest);
            } else if let Some(rest) = line.strip_prefix("macro ") {
                macros.push(rest);
            } else {
                productions.push(line);
            }
        }
        let Some(axiom) = axiom else {
            return Err(syntax("grammar", 0, "no `axiom:` line"));
        };
        Self::with_definitions(axiom, &productions, &constants, &functions, &macros, limits)
    }

    /// Number of productions.
    pub fn production_count(&self) -> usize {
        self.productions.len()
    }

    /// The axiom as a string (all modules born at iteration 0). Uses `rng` only if the axiom
    /// calls `rand`/`nrand`.
    pub(crate) fn axiom_string(&self, rng: &mut SplitMix64, limits: &Limits) -> Result<ModuleString, LSystemError> {
        let mut out = ModuleString::default();
        let mut stack = Vec::new();
        for m in &self.axiom {
            out.begin_module(m.symbol, 0, limits, 0)?;
            for e in &m.params {
                let v = e
                    .eval(&[], rng, &mut stack)
                    .map_err(|err| super::rewrite::eval_error(err, "axiom", e))?;
                out.push_param(v, "axiom", e)?;
            }
        }
        out.check_caps(limits, 0)?;
        Ok(out)
    }
}

fn syntax(context: &str, position: usize, message: &str) -> LSystemError {
    LSystemError::Syntax {
        context: context.to_string(),
        position,
        message: message.to_string(),
    }
}

/// Turns an expression parse error into an [`LSystemError`]; `offset` is where the expression
/// starts inside the text named by `context`.
fn from_parse(e: ParseError, context: &str, offset: usize) -> LSystemError {
    match e {
        ParseError::Syntax { position, message } => LSystemError::Syntax {
            context: context.to_string(),
            position: offset + position,
            message,
        },
        ParseError::TooDeep { cap } => LSystemError::ExprDepthCap {
            context: context.to_string(),
            cap,
        },
        ParseError::Eval(err) => match err {
            super::expr::EvalError::DivisionByZero => LSystemError::DivisionByZero {
                context: context.to_string(),
                expression: String::new(),
            },
            super::expr::EvalError::NonFinite(value) => LSystemError::NonFinite {
                context: context.to_string(),
                expression: String::new(),
                value,
            },
        },
    }
}

/// Like [`from_parse`] but fills in the expression text of evaluation errors.
fn from_parse_expr(e: ParseError, context: &str, offset: usize, text: &str) -> LSystemError {
    match from_parse(e, context, offset) {
        LSystemError::DivisionByZero { context, .. } => LSystemError::DivisionByZero {
            context,
            expression: text.trim().to_string(),
        },
        LSystemError::NonFinite { context, value, .. } => LSystemError::NonFinite {
            context,
            expression: text.trim().to_string(),
            value,
        },
        other => other,
    }
}

fn is_identifier(name: &str) -> bool {
    let mut chars = name.chars();
    chars.next().is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
        && chars.all(|c| c.is_ascii_alphanumeric() || c == '_')
}

fn check_constant(name: &str, value: f64, context: &str) -> Result<(), LSystemError> {
    if !is_identifier(name) {
        return Err(syntax(
            context,
            0,
            &format!("constant name `{name}` is not an identifier"),
        ));
    }
    if super::expr::is_reserved_name(name) {
        return Err(syntax(context, 0, &format!("constant name `{name}` is reserved")));
    }
    if !value.is_finite() {
        return Err(LSystemError::NonFinite {
            context: context.to_string(),
            expression: name.to_string(),
            value,
        });
    }
    Ok(())
}

/// Longest module list a successor, axiom or macro may expand to.
const MAX_SUCCESSOR_LEN: usize = 1 << 16;

/// Everything a module list may refer to.
struct Defs {
    env: Env,
    /// Module macros by (symbol, arity): bodies over the macro's own parameters.
    macros: BTreeMap<(u8, u8), Vec<ModuleTemplate>>,
    max_depth: usize,
}

/// Parses `Z(a, b) = modules` and adds it to `defs`.
fn define_macro(defs: &mut Defs, text: &str, context: &str) -> Result<(), LSystemError> {
    let Some((head, body)) = text.split_once('=') else {
        return Err(syntax(context, 0, "expected `Z(a, b) = modules`"));
    };
    let (symbol, formals, rest) = parse_head(head, context)?;
    if !rest.trim().is_empty() {
        return Err(syntax(context, 0, "expected `=` after the macro's parameters"));
    }
    // Formal lists are capped at MAX_PARAMS (16).
    let key = (symbol, formals.len() as u8);
    if defs.macros.contains_key(&key) {
        return Err(syntax(context, 0, "macro defined twice"));
    }
    let at = text.len() - body.len();
    let modules = parse_modules(body, at, &formals, defs, context)?;
    defs.macros.insert(key, modules);
    Ok(())
}

/// Parses `Z(a, b)` (a symbol and optional distinct formal names) at the start of `text`,
/// returning the rest.
fn parse_head<'t>(text: &'t str, context: &str) -> Result<(u8, Vec<String>, &'t str), LSystemError> {
    let lb = text.as_bytes();
    let mut i = 0;
    while i < lb.len() && lb[i].is_ascii_whitespace() {
        i += 1;
    }
    let Some(&symbol) = lb.get(i) else {
        return Err(syntax(context, 0, "missing predecessor"));
    };
    if !is_symbol(symbol) {
        return Err(syntax(context, i, "the predecessor must be one printable ASCII symbol"));
    }
    i += 1;
    while i < lb.len() && lb[i].is_ascii_whitespace() {
        i += 1;
    }
    let mut formals: Vec<String> = Vec::new();
    if lb.get(i) == Some(&b'(') {
        let Some(close) = matching_paren(lb, i) else {
            return Err(syntax(context, i, "`(` is never closed"));
        };
        let inner = &text[i + 1..close];
        if !inner.trim().is_empty() {
            for (o, name) in split_args(inner) {
                let name = name.trim();
                if !is_identifier(name) {
                    return Err(syntax(
                        context,
                        i + 1 + o,
                        &format!("formal parameter `{name}` is not an identifier"),
                    ));
                }
                if formals.iter().any(|f| f == name) {
                    return Err(syntax(context, i + 1 + o, &format!("`{name}` appears twice")));
                }
                formals.push(name.to_string());
            }
        }
        if formals.len() > MAX_PARAMS {
            return Err(syntax(
                context,
                i,
                &format!("a module may carry at most {MAX_PARAMS} parameters"),
            ));
        }
        i = close + 1;
    }
    Ok((symbol, formals, &text[i..]))
}

/// Parses `name(a, b) = body` and adds it to `env`.
fn define_function(env: &mut Env, text: &str, context: &str, max_depth: usize) -> Result<(), LSystemError> {
    let Some((head, body)) = text.split_once('=') else {
        return Err(syntax(context, 0, "expected `name(a, b) = expression`"));
    };
    let head = head.trim();
    let (name, params) = match head.split_once('(') {
        Some((name, rest)) => {
            let Some(inner) = rest.trim_end().strip_suffix(')') else {
                return Err(syntax(context, 0, "expected `)` after the parameters"));
            };
            (name.trim(), inner)
        }
        None => (head, ""),
    };
    if !is_identifier(name) {
        return Err(syntax(
            context,
            0,
            &format!("function name `{name}` is not an identifier"),
        ));
    }
    if env.is_taken(name) {
        return Err(syntax(context, 0, &format!("`{name}` is already defined or reserved")));
    }
    let mut formals: Vec<String> = Vec::new();
    if !params.trim().is_empty() {
        for p in params.split(',') {
            let p = p.trim();
            if !is_identifier(p) || formals.iter().any(|f| f == p) {
                return Err(syntax(context, 0, &format!("bad or repeated parameter `{p}`")));
            }
            formals.push(p.to_string());
        }
    }
    if formals.len() > MAX_PARAMS {
        return Err(syntax(
            context,
            0,
            &format!("a function takes at most {MAX_PARAMS} parameters"),
        ));
    }
    let at = text.len() - body.len();
    env.define_function(name, &formals, body, max_depth)
        .map_err(|e| from_parse_expr(e, context, at, body))
}

/// Whether `c` may be a module symbol.
fn is_symbol(c: u8) -> bool {
    c.is_ascii_graphic() && !matches!(c, b'(' | b')' | b',' | b':')
}

/// Byte offset of the first top-level (outside parentheses) occurrence of any of `needles`,
/// with the needle's length.
fn find_top_level(text: &str, needles: &[&str]) -> Option<(usize, usize)> {
    let mut depth = 0usize;
    for (i, c) in text.char_indices() {
        match c {
            '(' => depth += 1,
            ')' => depth = depth.saturating_sub(1),
            _ if depth == 0 => {
                if let Some(n) = needles.iter().find(|n| text[i..].starts_with(**n)) {
                    return Some((i, n.len()));
                }
            }
            _ => {}
        }
    }
    None
}

/// Index of the `)` matching the `(` at `open`, if any.
fn matching_paren(bytes: &[u8], open: usize) -> Option<usize> {
    let mut depth = 0usize;
    for (i, &c) in bytes.iter().enumerate().skip(open) {
        match c {
            b'(' => depth += 1,
            b')' => {
                depth -= 1;
                if depth == 0 {
                    return Some(i);
                }
            }
            _ => {}
        }
    }
    None
}

/// Splits `text` at top-level commas, giving `(offset, piece)` pairs.
fn split_args(text: &str) -> Vec<(usize, &str)> {
    let mut out = Vec::new();
    let mut depth = 0usize;
    let mut start = 0;
    for (i, c) in text.char_indices() {
        match c {
            '(' => depth += 1,
            ')' => depth = depth.saturating_sub(1),
            ',' if depth == 0 => {
                out.push((start, &text[start..i]));
                start = i + 1;
            }
            _ => {}
        }
    }
    out.push((start, &text[start..]));
    out
}

/// Parses a module list (successor, axiom or macro body) starting at byte `offset` of the text
/// named by `context`, expanding macros.
fn parse_modules(
    text: &str,
    offset: usize,
    formals: &[String],
    defs: &Defs,
    context: &str,
) -> Result<Vec<ModuleTemplate>, LSystemError> {
    let bytes = text.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        let c = bytes[i];
        if c.is_ascii_whitespace() {
            i += 1;
            continue;
        }
        if !is_symbol(c) {
            let what = text[i..].chars().next().unwrap_or(' ');
            return Err(syntax(
                context,
                offset + i,
                &format!("`{what}` cannot be a module symbol (symbols are printable ASCII)"),
            ));
        }
        let at = offset + i;
        i += 1;
        let mut j = i;
        while j < bytes.len() && bytes[j].is_ascii_whitespace() {
            j += 1;
        }
        let mut params = Vec::new();
        if j < bytes.len() && bytes[j] == b'(' {
            let Some(close) = matching_paren(bytes, j) else {
                return Err(syntax(context, offset + j, "`(` is never closed"));
            };
            let inner = &text[j + 1..close];
            if !inner.trim().is_empty() {
                for (o, piece) in split_args(inner) {
                    let at = offset + j + 1 + o;
                    let e = Expr::parse(piece, formals, &defs.env, defs.max_depth)
                        .map_err(|e| from_parse_expr(e, context, at, piece))?;
                    params.push(e);
                }
            }
            if params.len() > MAX_PARAMS {
                return Err(syntax(
                    context,
                    offset + j,
                    &format!("a module may carry at most {MAX_PARAMS} parameters"),
                ));
            }
            i = close + 1;
        }
        // Capped at MAX_PARAMS just above.
        match defs.macros.get(&(c, params.len() as u8)) {
            Some(body) => {
                for m in body {
                    let mut expanded = Vec::with_capacity(m.params.len());
                    for e in &m.params {
                        expanded.push(
                            e.substitute(&params)
                                .map_err(|err| from_parse_expr(err, context, at, &e.text))?,
                        );
                    }
                    out.push(ModuleTemplate {
                        symbol: m.symbol,
                        params: expanded,
                    });
                }
            }
            None => out.push(ModuleTemplate { symbol: c, params }),
        }
        if out.len() > MAX_SUCCESSOR_LEN {
            return Err(syntax(
                context,
                at,
                &format!("more than {MAX_SUCCESSOR_LEN} modules after macro expansion"),
            ));
        }
    }
    Ok(out)
}

fn parse_production(text: &str, index: usize, defs: &Defs) -> Result<Production, LSystemError> {
    let context = format!("production {} `{}`", index + 1, text.trim());
    let Some((arrow, arrow_len)) = find_top_level(text, &["->", "→"]) else {
        return Err(syntax(&context, 0, "missing `->`"));
    };
    let lhs = &text[..arrow];
    let rhs_at = arrow + arrow_len;
    let rhs = &text[rhs_at..];
    if find_top_level(rhs, &["->", "→"]).is_some() {
        return Err(syntax(&context, rhs_at, "a second `->`"));
    }

    // Predecessor: a symbol, then optional formals, then optional `: condition`.
    let (symbol, formals, rest) = parse_head(lhs, &context)?;
    let i = lhs.len() - rest.len();
    let condition = match rest.trim_start().strip_prefix(':') {
        None if rest.trim().is_empty() => None,
        None => {
            return Err(syntax(
                &context,
                i,
                "expected `:` (condition) or `->` after the predecessor",
            ));
        }
        Some(cond) if cond.trim() == "*" => None,
        Some(cond) => {
            let at = lhs.len() - cond.len();
            Some(
                Expr::parse(cond, &formals, &defs.env, defs.max_depth)
                    .map_err(|e| from_parse_expr(e, &context, at, cond))?,
            )
        }
    };

    // Successor, then optional `: weight`.
    let (succ, weight) = match find_top_level(rhs, &[":"]) {
        Some((c, _)) => {
            let w = &rhs[c + 1..];
            let at = rhs_at + c + 1;
            let e =
                Expr::parse(w, &formals, &defs.env, defs.max_depth).map_err(|e| from_parse_expr(e, &context, at, w))?;
            if let Some(v) = e.constant()
                && v < 0.0
            {
                return Err(LSystemError::NegativeWeight {
                    context,
                    expression: e.text.clone(),
                    value: v,
                });
            }
            (&rhs[..c], Some(e))
        }
        None => (rhs, None),
    };
    let successor = parse_modules(succ, rhs_at, &formals, defs, &context)?;
    Ok(Production {
        symbol,
        // Capped at MAX_PARAMS above.
        arity: formals.len() as u8,
        condition,
        successor,
        weight,
        context,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn compile(axiom: &str, prods: &[&str]) -> Result<Grammar, LSystemError> {
        Grammar::new(axiom, prods, &BTreeMap::new(), &Limits::default())
    }

    #[test]
    fn parses_the_paper_example() {
        let g = compile(
            "A(2)B(4)C(2)A(3)",
            &[
                "A(x) -> A(x+2) : 2",
                "A(x) -> C(x-1) : 3",
                "A(x) : x>2 -> B(x) : 5",
                "B(x) -> C(x+1) : 3",
            ],
        );
        let g = g.unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(g.production_count(), 4);
        assert_eq!(g.axiom.len(), 4);
        assert_eq!(g.by_symbol[usize::from(b'A')], vec![0, 1, 2]);
        assert!(g.productions[2].condition.is_some());
        assert_eq!(g.productions[3].successor[0].symbol, b'C');
    }

    #[test]
    fn syntax_variants() {
        let ok = [
            "A -> B",
            "A → B",
            "A() -> ",
            "A(x, y) : * -> F(x, min(x, y)) [ + A(x*0.5, y) ] : x + 1",
            "A ( x ) : x >= 1 && !(x == 3) -> A(x-1)",
            "[ -> [",
            "A(x) : x > -1 -> B",
        ];
        for p in ok {
            assert!(compile("A", &[p]).is_ok(), "{p}");
        }
        let bad = [
            "",
            "A",
            "A B -> C",
            "A(x -> B",
            "A(1) -> B",
            "A(x, x) -> B",
            "A -> B -> C",
            "A : -> B",
            "A -> B(",
            "A -> B(1,)",
            "A -> B : ",
            "A -> B : -1",
            "A -> é",
            "(-> B",
            "A(x) -> B(y)",
            "A -> B(1/0)",
        ];
        for p in bad {
            assert!(compile("A", &[p]).is_err(), "{p:?} should fail");
        }
        let many = format!(
            "A({}) -> B",
            (0..17).map(|i| format!("p{i}")).collect::<Vec<_>>().join(",")
        );
        assert!(compile("A", &[many.as_str()]).is_err());
    }

    #[test]
    fn errors_name_the_production() {
        let e = compile("A", &["A -> B", "B(x) -> C(x +)"]);
        let msg = e.err().map(|e| e.to_string()).unwrap_or_default();
        assert!(msg.contains("production 2"), "{msg}");
        assert!(msg.contains("B(x) -> C(x +)"), "{msg}");
    }

    #[test]
    fn text_format() {
        let g = Grammar::parse(
            "# comment\nconst s = 2\nconst t = s * 3\n\naxiom: A(t)\nA(x) : x > 0 -> A(x - s)\n",
            &Limits::default(),
        );
        assert!(g.is_ok(), "{g:?}");
        assert!(Grammar::parse("A -> B", &Limits::default()).is_err(), "no axiom");
        assert!(Grammar::parse("axiom: A\naxiom: B", &Limits::default()).is_err());
        assert!(Grammar::parse("const 1x = 2\naxiom: A", &Limits::default()).is_err());
        assert!(Grammar::parse("const sin = 2\naxiom: A", &Limits::default()).is_err());
        assert!(Grammar::parse("const r = rand(0,1)\naxiom: A", &Limits::default()).is_err());
        assert!(Grammar::parse("const r\naxiom: A", &Limits::default()).is_err());
    }

    #[test]
    fn functions() {
        let mut c = BTreeMap::new();
        c.insert("k".to_string(), 2.0);
        let none: &[&str] = &[];
        let g = Grammar::with_definitions(
            "A(1)",
            &["A(x) -> A(grow(x, 3))"],
            &c,
            &["scale(a) = a * k", "grow(a, b) = scale(a) + b"],
            none,
            &Limits::default(),
        );
        let s = g.and_then(|g| g.derive(0, 2, &Limits::default()));
        assert_eq!(s.map(|s| s.to_string()), Ok("A(13)".into()));
        for bad in [
            "f(x) x",
            "1f(x) = x",
            "sin(x) = x",
            "k(x) = x",
            "f(x, x) = x",
            "f(x = x",
            "f(x) = y",
            "f(x) = g(x)",
        ] {
            let r = Grammar::with_definitions("A", none, &c, &[bad], none, &Limits::default());
            assert!(r.is_err(), "{bad}");
        }
        let twice = Grammar::with_definitions("A", none, &c, &["f = 1", "f = 2"], none, &Limits::default());
        assert!(twice.is_err());
        let g = Grammar::parse("const k = 3\nfn f(a) = a + k\naxiom: A(f(1))", &Limits::default());
        let s = g.and_then(|g| g.derive(0, 0, &Limits::default()));
        assert_eq!(s.map(|s| s.to_string()), Ok("A(4)".into()));
    }

    #[test]
    fn macros() {
        let none: &[&str] = &[];
        let c = BTreeMap::new();
        let g = Grammar::with_definitions(
            "A(1)",
            &["A(x) -> N(x) N(x*2) A(x+1)"],
            &c,
            none,
            &["M(a) = [L(a)]", "N(a) = F(a) M(a+1) Q"],
            &Limits::default(),
        );
        let s = g.and_then(|g| g.derive(0, 1, &Limits::default()));
        assert_eq!(s.map(|s| s.to_string()), Ok("F(1)[L(2)]QF(2)[L(3)]QA(2)".into()));
        // Arity selects the macro: `N` without parameters is an ordinary module.
        let g = Grammar::with_definitions("N N(1)", none, &c, none, &["N(a) = F(a)"], &Limits::default());
        let s = g.and_then(|g| g.derive(0, 0, &Limits::default()));
        assert_eq!(s.map(|s| s.to_string()), Ok("NF(1)".into()));
        let bad: &[(&str, &[&str])] = &[
            ("A", &["M(a) F(a)"]),
            ("A", &["M(a) = F(b)"]),
            ("A", &["M(a) = F(a)", "M(b) = F(b)"]),
            ("A", &["(a) = F(a)"]),
            ("A", &["M(a) x = F(a)"]),
            ("M(1/0)", &["M(a) = F(a)"]),
        ];
        for (axiom, macros) in bad {
            let r = Grammar::with_definitions(axiom, none, &c, none, macros, &Limits::default());
            assert!(r.is_err(), "{macros:?}");
        }
        let r = Grammar::with_definitions("A", &["M(x) -> F"], &c, none, &["M(a) = F(a)"], &Limits::default());
        assert!(r.is_err(), "a macro cannot be a predecessor");
        // Exponential expansion is capped.
        let ms: Vec<String> = (0..5)
            .map(|i| {
                let inner = if i == 0 { "F".to_string() } else { (i - 1).to_string() };
                format!("{i} = {}", inner.repeat(16))
            })
            .collect();
        let r = Grammar::with_definitions("4", none, &c, none, &ms, &Limits::default());
        assert!(r.is_err(), "16^5 modules must fail");
        let g = Grammar::parse("macro M(a) = F(a) F(a)\naxiom: M(2)", &Limits::default());
        let s = g.and_then(|g| g.derive(0, 0, &Limits::default()));
        assert_eq!(s.map(|s| s.to_string()), Ok("F(2)F(2)".into()));
    }

    #[test]
    fn deep_nesting_is_an_error_not_a_crash() {
        let deep = format!("A -> F({}1{})", "(".repeat(5000), ")".repeat(5000));
        assert!(matches!(
            compile("A", &[deep.as_str()]),
            Err(LSystemError::ExprDepthCap { cap: 64, .. })
        ));
        let deep_cond = format!("A(x) : {}x{} -> B", "(".repeat(100), ")".repeat(100));
        assert!(matches!(
            compile("A", &[deep_cond.as_str()]),
            Err(LSystemError::ExprDepthCap { .. })
        ));
    }
}
