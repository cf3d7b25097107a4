//! Integration tests of the L-system engine (seed 000) and the species specs.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use canopy_server::lsystem::{Grammar, LSystemError, Limits, TurtleParams, interpret};
use canopy_server::species::{SpeciesSpec, grow, grow_iterations, grow_with_progress};
use canopy_shared::TreeModel;
use proptest::prelude::*;

fn compile(axiom: &str, productions: &[&str]) -> Grammar {
    Grammar::new(axiom, productions, &BTreeMap::new(), &Limits::default()).unwrap_or_else(|e| panic!("{e}"))
}

/// Seed 000's worked example, eq. (3).
fn paper_grammar() -> Grammar {
    compile(
        "A(2)B(4)C(2)A(3)",
        &[
            "A(x) -> A(x+2) : 2",
            "A(x) -> C(x-1) : 3",
            "A(x) : x>2 -> B(x) : 5",
            "B(x) -> C(x+1) : 3",
        ],
    )
}

/// Over 20,000 seeds, the first derivation step picks P1/P2 for `A(2)` with probability
/// 0.4/0.6 and P1/P2/P3 for `A(3)` with 0.2/0.3/0.5.
///
/// Tolerance: a frequency over n = 20,000 independent draws has standard deviation
/// √(p(1−p)/n) ≤ √(0.25/20,000) ≈ 0.0035, so ±0.015 is over 4σ (a false failure would have
/// probability below 1e-4 per check; the seeds are fixed, so the test is deterministic anyway).
#[test]
fn paper_example_probabilities() {
    const N: u64 = 20_000;
    const TOL: f64 = 0.015;
    let g = paper_grammar();
    let limits = Limits::default();
    let mut first = [0u32; 2]; // A(2) -> A(4) (P1), C(1) (P2)
    let mut last = [0u32; 3]; // A(3) -> A(5) (P1), C(2) (P2), B(3) (P3)
    let mut outcomes: BTreeMap<String, u32> = BTreeMap::new();
    for seed in 0..N {
        let s = g.derive(seed, 1, &limits).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(s.len(), 4);
        let m0 = s.get(0).map(|m| (m.symbol, m.params.to_vec()));
        match m0 {
            Some(('A', p)) if p == [4.0] => first[0] += 1,
            Some(('C', p)) if p == [1.0] => first[1] += 1,
            other => panic!("A(2) became {other:?}"),
        }
        // B(4) has only P4; C(2) has no production and is copied.
        assert_eq!(s.get(1).map(|m| (m.symbol, m.params.to_vec())), Some(('C', vec![5.0])));
        assert_eq!(s.get(2).map(|m| (m.symbol, m.params.to_vec())), Some(('C', vec![2.0])));
        assert_eq!(s.get(2).map(|m| m.birth), Some(0), "a copied module keeps its birth");
        assert_eq!(s.get(1).map(|m| m.birth), Some(1));
        match s.get(3).map(|m| (m.symbol, m.params.to_vec())) {
            Some(('A', p)) if p == [5.0] => last[0] += 1,
            Some(('C', p)) if p == [2.0] => last[1] += 1,
            Some(('B', p)) if p == [3.0] => last[2] += 1,
            other => panic!("A(3) became {other:?}"),
        }
        *outcomes.entry(s.to_string()).or_default() += 1;
    }
    let freq = |c: u32| f64::from(c) / N as f64;
    for (got, want) in first.iter().zip([0.4, 0.6]) {
        assert!((freq(*got) - want).abs() < TOL, "A(2): {} vs {want}", freq(*got));
    }
    for (got, want) in last.iter().zip([0.2, 0.3, 0.5]) {
        assert!((freq(*got) - want).abs() < TOL, "A(3): {} vs {want}", freq(*got));
    }
    // Eq. (4): the most likely first derivation (probability 0.6 × 0.5 = 0.3).
    let (best, count) = outcomes
        .iter()
        .max_by_key(|(_, c)| **c)
        .map(|(s, c)| (s.clone(), *c))
        .unwrap_or_default();
    assert_eq!(best, "C(1)C(5)C(2)B(3)");
    assert!((freq(count) - 0.3).abs() < TOL);
    assert_eq!(outcomes.len(), 6, "2 × 3 combinations");
}

#[test]
fn derivation_is_deterministic() {
    let g = compile(
        "A(1)",
        &[
            "A(x) -> F(x) [+(rand(10, 50)) A(x*0.7)] A(x*0.9) : 3",
            "A(x) -> F(x) [-(nrand(30, 5)) A(x*0.6)] : 2",
            "A(x) : x < 0.3 -> L : 1",
        ],
    );
    let limits = Limits::default();
    let a = g.derive(42, 8, &limits).unwrap_or_else(|e| panic!("{e}"));
    let b = g.derive(42, 8, &limits).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(a, b);
    assert_eq!(a.to_string(), b.to_string());
    let c = g.derive(43, 8, &limits).unwrap_or_else(|e| panic!("{e}"));
    assert_ne!(a.to_string(), c.to_string(), "another seed gives another plant");
    // The first k steps of a longer derivation are a k-step derivation.
    let k = g.derive(42, 5, &limits).unwrap_or_else(|e| panic!("{e}"));
    let step6 = g.derive(42, 6, &limits).unwrap_or_else(|e| panic!("{e}"));
    assert!(step6.iter().filter(|m| m.birth <= 5).count() <= k.len());
    let old: Vec<_> = step6
        .iter()
        .filter(|m| m.birth < 5 && m.symbol != 'A')
        .map(|m| (m.symbol, m.params.to_vec(), m.birth))
        .collect();
    let old_k: Vec<_> = k
        .iter()
        .filter(|m| m.birth < 5 && m.symbol != 'A')
        .map(|m| (m.symbol, m.params.to_vec(), m.birth))
        .collect();
    assert_eq!(old, old_k);
}

// ---------------------------------------------------------------------------------------------
// Caps and errors: every failure mode is a typed error, raised where the cap is first crossed
// (the iteration or depth it names), not after the work it guards against. How fast that is
// belongs in benchmarks.

fn fails(f: impl FnOnce() -> Result<(), LSystemError>) -> LSystemError {
    f().err().unwrap_or_else(|| panic!("expected an error"))
}

#[test]
fn exploding_grammar_hits_the_module_cap() {
    let g = compile("A", &["A -> AA"]);
    let e = fails(|| g.derive(0, 64, &Limits::default()).map(|_| ()));
    match &e {
        LSystemError::ModuleCap { cap, iteration } => {
            assert_eq!(*cap, 8_000_000);
            assert_eq!(*iteration, 23, "2^23 > 8,000,000");
        }
        other => panic!("{other}"),
    }
    assert!(e.to_string().contains("module cap of 8000000"), "{e}");
    // A configurable cap.
    let small = Limits {
        max_modules: 1000,
        ..Limits::default()
    };
    assert!(matches!(
        g.derive(0, 64, &small),
        Err(LSystemError::ModuleCap {
            cap: 1000,
            iteration: 10
        })
    ));
}

#[test]
fn parameter_memory_cap() {
    let g = compile(
        "A(1)",
        &[
            "A(x) -> A(x,x,x,x,x,x,x,x) A(x,x,x,x,x,x,x,x)",
            "A(a,b,c,d,e,f,g,h) -> A(a) A(b)",
        ],
    );
    let limits = Limits {
        max_param_bytes: 1 << 16,
        ..Limits::default()
    };
    let e = fails(|| g.derive(0, 60, &limits).map(|_| ()));
    // Odd iterations hold 16·4^((i − 1)/2) parameters (4 bytes each): 64 KiB at 11, which is
    // the cap, 256 KiB at 13, where derivation stops.
    assert!(
        matches!(
            e,
            LSystemError::ParamMemoryCap {
                cap: 65_536,
                iteration: 13
            }
        ),
        "{e}"
    );
}

#[test]
fn iteration_cap() {
    let g = compile("A", &["A -> B", "B -> A"]);
    assert!(g.derive(0, 64, &Limits::default()).is_ok());
    let e = g.derive(0, 65, &Limits::default());
    assert!(matches!(e, Err(LSystemError::IterationCap { requested: 65, cap: 64 })));
    let e = g.derive(
        0,
        1000,
        &Limits {
            max_iterations: 10_000,
            ..Limits::default()
        },
    );
    assert!(
        matches!(e, Err(LSystemError::IterationCap { cap: 255, .. })),
        "u8 iterations"
    );
}

#[test]
fn deep_expression_nesting_is_an_error() {
    let text = format!("A -> F({}1{})", "(".repeat(100_000), ")".repeat(100_000));
    let e = fails(|| Grammar::new("A", &[text.as_str()], &BTreeMap::new(), &Limits::default()).map(|_| ()));
    assert!(matches!(e, LSystemError::ExprDepthCap { cap: 64, .. }), "{e}");
    let text = format!("A(x) : {}x > 1 -> F", "!".repeat(100_000));
    let e = Grammar::new("A(1)", &[text.as_str()], &BTreeMap::new(), &Limits::default());
    assert!(matches!(e, Err(LSystemError::ExprDepthCap { .. })));
}

#[test]
fn division_by_zero_names_production_and_expression() {
    let g = compile("A(1)", &["B -> C", "A(x) -> A(x/0)"]);
    let e = g.derive(0, 1, &Limits::default()).err();
    match &e {
        Some(LSystemError::DivisionByZero { context, expression }) => {
            assert!(context.contains("production 2"), "{context}");
            assert!(context.contains("A(x) -> A(x/0)"), "{context}");
            assert_eq!(expression, "x/0");
        }
        other => panic!("{other:?}"),
    }
    let msg = e.map(|e| e.to_string()).unwrap_or_default();
    assert!(msg.contains("x/0") && msg.contains("production 2"), "{msg}");
    // Also in a condition, a weight, and a constant expression (caught when compiling).
    assert!(matches!(
        compile("A(0)", &["A(x) : 1/x > 0 -> B"]).derive(0, 1, &Limits::default()),
        Err(LSystemError::DivisionByZero { .. })
    ));
    assert!(matches!(
        compile("A(0)", &["A(x) -> B : 1/x"]).derive(0, 1, &Limits::default()),
        Err(LSystemError::DivisionByZero { .. })
    ));
    assert!(matches!(
        Grammar::new("A", &["A -> B(1/0)"], &BTreeMap::new(), &Limits::default()),
        Err(LSystemError::DivisionByZero { .. })
    ));
}

#[test]
fn non_finite_parameters_are_errors() {
    let g = compile("A(10)", &["A(x) -> A(x*1e30)"]);
    let e = g.derive(0, 10, &Limits::default());
    match e {
        Err(LSystemError::NonFinite {
            context, expression, ..
        }) => {
            assert!(context.contains("A(x) -> A(x*1e30)"));
            assert_eq!(expression, "x*1e30");
        }
        other => panic!("{other:?}"),
    }
    let g = compile("A(-1)", &["A(x) -> A(sqrt(x))"]);
    assert!(matches!(
        g.derive(0, 1, &Limits::default()),
        Err(LSystemError::NonFinite { .. })
    ));
    let g = compile("A(1)", &["A(x) -> A(x) : x - 5"]);
    assert!(matches!(
        g.derive(0, 1, &Limits::default()),
        Err(LSystemError::NegativeWeight { .. })
    ));
}

fn turtle(axiom: &str, productions: &[&str], n: u32, limits: &Limits) -> Result<(), LSystemError> {
    let g = Grammar::new(axiom, productions, &BTreeMap::new(), limits)?;
    let s = g.derive(0, n, limits)?;
    interpret(&s, &TurtleParams::default(), limits).map(|_| ())
}

#[test]
fn turtle_errors_and_caps() {
    let l = Limits::default();
    assert!(matches!(
        turtle("F]", &[], 0, &l),
        Err(LSystemError::UnbalancedBracket { .. })
    ));
    assert!(matches!(
        turtle("F[F[F]", &[], 0, &l),
        Err(LSystemError::UnbalancedBracket { .. })
    ));
    assert!(matches!(
        turtle(
            "A",
            &["A -> F[+A"],
            40,
            &Limits {
                max_stack_depth: 16,
                ..l
            }
        ),
        Err(LSystemError::StackDepthCap { cap: 16, .. })
    ));
    assert!(matches!(
        turtle("A", &["A -> [F]A"], 30, &Limits { max_branches: 20, ..l }),
        Err(LSystemError::BranchCap { cap: 20 })
    ));
    assert!(matches!(
        turtle("A", &["A -> LA"], 30, &Limits { max_leaves: 20, ..l }),
        Err(LSystemError::LeafCap { cap: 20 })
    ));
    assert!(matches!(
        turtle(
            "A",
            &["A -> FA"],
            30,
            &Limits {
                max_branch_points: 20,
                ..l
            }
        ),
        Err(LSystemError::BranchPointCap { cap: 20 })
    ));
    assert!(matches!(
        turtle("A", &["A -> F(3e38) A"], 3, &l),
        Err(LSystemError::TurtleNonFinite { .. })
    ));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    /// Any grammar text gives `Ok` or `Err`: no panic, no hang (small caps keep each case fast).
    #[test]
    fn arbitrary_grammar_text_never_panics(
        axiom in "[AB()F\\[\\]+\\-&^/|!$L~0-9.,x ]{0,24}",
        prods in proptest::collection::vec("[ABF()\\[\\]+\\-*/^<>=!&|:,.0-9xy L~$ ]{0,40}(->|: x > 1 ->|→)[ABF()\\[\\]+\\-*/^<>=!&|:,.0-9xy L~$rand]{0,40}", 0..4),
        seed in any::<u64>(),
        n in 0u32..8,
    ) {
        let limits = Limits {
            max_modules: 20_000,
            max_param_bytes: 1 << 18,
            max_branches: 5_000,
            max_leaves: 5_000,
            ..Limits::default()
        };
        if let Ok(g) = Grammar::new(&axiom, &prods, &BTreeMap::new(), &limits)
            && let Ok(s) = g.derive(seed, n, &limits)
            && let Ok(t) = interpret(&s, &TurtleParams::default(), &limits)
        {
            let model = TreeModel {
                name: "fuzz".into(),
                branches: t.branches,
                leaves: t.leaves,
                bark_mesh: canopy_shared::TriangleMesh::default(),
                materials: canopy_shared::Materials::default(),
                iterations: n as u8,
                source: canopy_shared::ModelSource::LSystem,
            };
            prop_assert!(model.check_invariants().is_ok());
        }
        // The whole-text format too.
        let text = format!("axiom: {axiom}\n{}", prods.join("\n"));
        let _ = Grammar::parse(&text, &limits);
    }

    /// Random bytes as a species file: an error, never a panic.
    #[test]
    fn arbitrary_species_text_never_panics(text in "\\PC{0,200}") {
        let _ = SpeciesSpec::from_toml_str(&text);
    }
}

// ---------------------------------------------------------------------------------------------
// Species.

fn species_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../assets/species")
}

fn all_species() -> Vec<SpeciesSpec> {
    let specs = SpeciesSpec::load_dir(&species_dir()).unwrap_or_else(|e| panic!("{e}"));
    assert!(specs.len() >= 4, "at least four species");
    specs
}

/// Asserts that `small` (grown `k` iterations) is `full.at_iteration(k)`, except that a branch's
/// polyline in `full` may continue past where `small`'s stops (a branch keeps growing at its
/// apex; its later points were drawn by later iterations).
fn assert_iteration_prefix(small: &TreeModel, full: &TreeModel, k: u8) {
    let cut = full.at_iteration(k);
    assert_eq!(small.leaves.len(), cut.leaves.len(), "{}: leaves at {k}", full.name);
    assert!(small.leaves == cut.leaves, "{}: leaves differ at {k}", full.name);
    assert_eq!(
        small.branches.len(),
        cut.branches.len(),
        "{}: branches at {k}",
        full.name
    );
    for (i, (a, b)) in small.branches.iter().zip(&cut.branches).enumerate() {
        assert_eq!(
            (a.parent, a.level, a.iteration),
            (b.parent, b.level, b.iteration),
            "{} branch {i}",
            full.name
        );
        assert!(a.points.len() <= b.points.len());
        assert!(
            a.points[..] == b.points[..a.points.len()],
            "{} branch {i} points",
            full.name
        );
    }
}

#[test]
fn every_species_grows_at_reduced_iterations() {
    for spec in all_species() {
        let k = spec.iterations.saturating_sub(5);
        let mut steps = Vec::new();
        let t = grow_with_progress(&spec, k, &Limits::default(), &mut |i, n| steps.push((i, n)))
            .unwrap_or_else(|e| panic!("{}: {e}", spec.name));
        assert_eq!(steps.len() as u32, k + 1, "progress after the axiom and every step");
        t.check_invariants().unwrap_or_else(|e| panic!("{}: {e}", spec.name));
        assert_eq!(t.name, spec.name);
        assert_eq!(u32::from(t.iterations), k);
        assert!(!t.branches.is_empty(), "{}", spec.name);
        let (lo, hi) = t.bounds().unwrap_or_default();
        assert!(
            lo.y > -1.0 && hi.y > 1.0,
            "{}: stands on the ground: {lo} {hi}",
            spec.name
        );
        assert!(t.branches.iter().all(|b| b.points.len() >= 2));
    }
}

#[test]
fn species_iteration_lod_is_a_prefix() {
    for spec in all_species() {
        // Two fewer iterations than full detail keeps the test fast in the dev profile; the
        // prefix property does not depend on how far the taller tree was grown.
        let n = spec.iterations.saturating_sub(2);
        let full = grow_iterations(&spec, n, &Limits::default()).unwrap_or_else(|e| panic!("{e}"));
        full.check_invariants().unwrap_or_else(|e| panic!("{}: {e}", spec.name));
        for k in [n / 2, n * 3 / 4, n - 1] {
            let small = grow_iterations(&spec, k, &Limits::default()).unwrap_or_else(|e| panic!("{e}"));
            assert_iteration_prefix(&small, &full, k as u8);
            small
                .at_iteration(k as u8)
                .check_invariants()
                .unwrap_or_else(|e| panic!("{e}"));
        }
    }
}

#[test]
fn species_are_deterministic() {
    let specs = all_species();
    let spec = specs.iter().find(|s| s.name == "small_shrub").unwrap_or(&specs[0]);
    let a = grow(spec, &Limits::default()).unwrap_or_else(|e| panic!("{e}"));
    let b = grow(spec, &Limits::default()).unwrap_or_else(|e| panic!("{e}"));
    assert!(a == b);
    let mut other = spec.clone();
    other.seed += 1;
    let c = grow(&other, &Limits::default()).unwrap_or_else(|e| panic!("{e}"));
    assert!(a != c);
}

#[test]
fn small_species_at_full_detail() {
    for spec in all_species()
        .iter()
        .filter(|s| s.name == "small_shrub" || s.name == "spruce")
    {
        let t = grow(spec, &Limits::default()).unwrap_or_else(|e| panic!("{e}"));
        t.check_invariants().unwrap_or_else(|e| panic!("{e}"));
        let n = t.leaves.len();
        match spec.name.as_str() {
            "small_shrub" => assert!((2_000..=8_000).contains(&n), "{n}"),
            _ => assert!((30_000..=80_000).contains(&n), "{n}"),
        }
    }
}

/// Full-detail growth of every species with timings and statistics; run with
/// `cargo test --release -p canopy-server --test lsystem -- --ignored --nocapture`.
#[test]
#[ignore = "slow in the dev profile; run in release"]
fn grow_all_species_full() {
    for spec in all_species() {
        let t0 = Instant::now();
        let t = grow(&spec, &Limits::default()).unwrap_or_else(|e| panic!("{}: {e}", spec.name));
        let dt = t0.elapsed();
        t.check_invariants().unwrap_or_else(|e| panic!("{}: {e}", spec.name));
        let (lo, hi) = t.bounds().unwrap_or_default();
        let max_level = t.branches.iter().map(|b| b.level).max().unwrap_or(0);
        let points: usize = t.branches.iter().map(|b| b.points.len()).sum();
        let mean_leaf = t.leaves.iter().map(|l| l.length).sum::<f32>() / t.leaves.len().max(1) as f32;
        println!(
            "{:12} iterations {:2}  leaves {:7}  branches {:6}  points {:7}  height {:5.2} m  crown {:5.2} x {:5.2} m  max level {:2}  mean leaf {:.3} m  grow {:.3} s",
            spec.name,
            t.iterations,
            t.leaves.len(),
            t.branches.len(),
            points,
            hi.y,
            hi.x - lo.x,
            hi.z - lo.z,
            max_level,
            mean_leaf,
            dt.as_secs_f64()
        );
        let n = t.leaves.len();
        let ok = match spec.name.as_str() {
            "small_shrub" => (2_000..=8_000).contains(&n),
            "spruce" => (30_000..=80_000).contains(&n),
            "maple" => (50_000..=100_000).contains(&n),
            "linden" => (290_000..=320_000).contains(&n),
            _ => true,
        };
        assert!(ok, "{}: {n} leaves outside the documented range", spec.name);
        assert!((4.0..=25.0).contains(&hi.y), "{}: height {}", spec.name, hi.y);
    }
}
