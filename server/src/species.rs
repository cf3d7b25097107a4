//! Species specs: TOML files (in `assets/species/`) that hold an L-system, its turtle settings and
//! its materials, and [`grow`], which turns one into a [`TreeModel`]. The format is documented in
//! `docs/species.md`.
//!
//! Unknown keys are rejected everywhere (a misspelt key must not silently fall back to a
//! default), and [`SpeciesSpec::from_toml_str`] compiles the grammar, so a spec that loads can
//! only fail to grow on a cap of [`Limits`] or a value error during derivation.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use canopy_shared::model::{LeafMaterial, Materials, ModelSource, TreeModel};
use canopy_shared::rng::mix64;
use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::lsystem::{Grammar, HARD_MAX_ITERATIONS, LSystemError, Limits, TurtleParams, interpret};

/// A species spec, as read from TOML.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct SpeciesSpec {
    /// Species name; becomes [`TreeModel::name`]. Not empty.
    pub name: String,
    /// Free text for people.
    #[serde(default)]
    pub description: String,
    /// RNG seed of the derivation and the leaf jitter.
    pub seed: u64,
    /// Derivation steps of the full-detail tree (at most 255).
    pub iterations: u32,
    /// The axiom, in grammar syntax (see [`crate::lsystem`]).
    pub axiom: String,
    /// Productions, one per string, in grammar syntax.
    pub productions: Vec<String>,
    /// Named constants usable in every expression.
    #[serde(default)]
    pub constants: BTreeMap<String, f64>,
    /// User functions, each `name(a, b) = expression` (see [`Grammar::with_definitions`]).
    #[serde(default)]
    pub functions: Vec<String>,
    /// Module macros, each `Z(a, b) = module list` (see [`Grammar::with_definitions`]).
    #[serde(default)]
    pub macros: Vec<String>,
    /// Turtle settings.
    #[serde(default)]
    pub turtle: TurtleSpec,
    /// Defaults and jitter for leaves.
    #[serde(default)]
    pub leaf: LeafSpec,
    /// Bark and leaf materials.
    #[serde(default)]
    pub materials: MaterialsSpec,
    /// How the variants of the unique forest differ from the spec (`[variation]`, optional):
    /// see [`SpeciesSpec::variant`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub variation: Option<VariationSpec>,
}

/// The `[variation]` table: the ranges a variant of the species draws its parameters from
/// (uniformly, inclusive), beside its own seed.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct VariationSpec {
    /// Derivation steps `[min, max]` (the tree's age: height and branching); at most 255.
    #[serde(default)]
    pub iterations: Option<[u32; 2]>,
    /// The constant that holds the iteration count (the species lay growth out for it, e.g.
    /// `N`); a variant sets it to its drawn iterations. Must be one of `constants`.
    #[serde(default)]
    pub iterations_constant: Option<String>,
    /// Constants drawn per variant, `name = [min, max]` (shoot lengths, vigour, leaf sizes…);
    /// each must be one of the spec's `constants`.
    #[serde(default)]
    pub constants: BTreeMap<String, [f64; 2]>,
    /// Factor `[min, max]` on the leaf size of a bare `L` (`leaf.width`, `leaf.length`).
    #[serde(default)]
    pub leaf_scale: Option<[f32; 2]>,
}

/// The `[turtle]` table.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct TurtleSpec {
    /// Angle of rotation modules without a parameter, degrees.
    pub angle: f32,
    /// Length of `F`/`f` without a parameter, metres (≥ 0).
    pub step: f32,
    /// Starting radius, metres (≥ 0).
    pub initial_radius: f32,
    /// Factor of a bare `!` (≥ 0).
    pub radius_factor: f32,
    /// Tropism vector (e.g. gravity `[0, -1, 0]`).
    pub tropism: [f32; 3],
    /// Default tropism strength `e` (ABOP); 0 disables.
    pub tropism_strength: f32,
}

impl Default for TurtleSpec {
    fn default() -> Self {
        let t = TurtleParams::default();
        Self {
            angle: t.angle_deg,
            step: t.step,
            initial_radius: t.initial_radius,
            radius_factor: t.radius_factor,
            tropism: t.tropism.to_array(),
            tropism_strength: t.tropism_strength,
        }
    }
}

/// The `[leaf]` table.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct LeafSpec {
    /// Width of a bare `L`, metres (≥ 0).
    pub width: f32,
    /// Length of a bare `L`, metres (≥ 0).
    pub length: f32,
    /// Largest random turn about each leaf axis, degrees, in `[0, 180]`.
    pub jitter_deg: f32,
    /// Largest relative random size change, in `[0, 1)`.
    pub size_jitter: f32,
}

impl Default for LeafSpec {
    fn default() -> Self {
        let t = TurtleParams::default();
        Self {
            width: t.leaf_width,
            length: t.leaf_length,
            jitter_deg: t.leaf_jitter_deg,
            size_jitter: t.leaf_size_jitter,
        }
    }
}

/// The `[materials]` table.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct MaterialsSpec {
    /// Linear RGBA bark colour, components in `[0, 1]`.
    pub bark_color: [f32; 4],
    /// Bark texture file name (relative to `assets/textures/`).
    pub bark_texture: Option<String>,
    /// Leaf materials (`[[materials.leaf]]`), 1 to 255; `L`'s third parameter indexes them.
    pub leaf: Vec<LeafMaterialSpec>,
}

impl Default for MaterialsSpec {
    fn default() -> Self {
        let m = Materials::default();
        Self {
            bark_color: m.bark_color,
            bark_texture: m.bark_texture,
            leaf: m
                .leaf
                .into_iter()
                .map(|l| LeafMaterialSpec {
                    color: l.color,
                    texture: l.texture,
                })
                .collect(),
        }
    }
}

/// One `[[materials.leaf]]` entry.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct LeafMaterialSpec {
    /// Linear RGBA colour, components in `[0, 1]`.
    pub color: [f32; 4],
    /// Texture file name (relative to `assets/textures/`).
    #[serde(default)]
    pub texture: Option<String>,
}

/// Why a spec could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum SpeciesError {
    /// The file could not be read.
    #[error("cannot read {}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// Not valid TOML, a missing or unknown key, or a value of the wrong type. The message names
    /// the line and column.
    #[error("invalid species TOML: {0}")]
    Toml(#[from] toml::de::Error),
    /// A value out of its documented range.
    #[error("invalid species spec: `{field}` {message}")]
    Invalid {
        /// The key, e.g. `leaf.size_jitter`.
        field: String,
        /// What is wrong with it.
        message: String,
    },
    /// The grammar does not compile.
    #[error("species grammar: {0}")]
    Grammar(#[from] LSystemError),
    /// An error in a named file.
    #[error("{}: {source}", path.display())]
    File {
        /// The file.
        path: PathBuf,
        /// The error.
        #[source]
        source: Box<SpeciesError>,
    },
}

fn invalid(field: &str, message: &str) -> SpeciesError {
    SpeciesError::Invalid {
        field: field.to_string(),
        message: message.to_string(),
    }
}

/// Largest texture name length (the `.ctree` materials section stores it with a `u8`-bounded length).
const MAX_TEXTURE_NAME: usize = 255;

impl SpeciesSpec {
    /// Parses and validates a spec: TOML syntax, no unknown keys, every value in range, and a
    /// grammar that compiles under `Limits::default()`.
    pub fn from_toml_str(text: &str) -> Result<Self, SpeciesError> {
        let spec: SpeciesSpec = toml::from_str(text)?;
        spec.validate()?;
        Ok(spec)
    }

    /// Reads and parses the spec at `path`; errors name the file.
    pub fn load(path: &Path) -> Result<Self, SpeciesError> {
        let text = std::fs::read_to_string(path).map_err(|source| SpeciesError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_toml_str(&text).map_err(|e| SpeciesError::File {
            path: path.to_path_buf(),
            source: Box::new(e),
        })
    }

    /// Loads every `*.toml` file in `dir`, sorted by file name.
    pub fn load_dir(dir: &Path) -> Result<Vec<Self>, SpeciesError> {
        let io = |source| SpeciesError::Io {
            path: dir.to_path_buf(),
            source,
        };
        let mut paths = Vec::new();
        for entry in std::fs::read_dir(dir).map_err(io)? {
            let path = entry.map_err(io)?.path();
            if path.extension().is_some_and(|e| e == "toml") {
                paths.push(path);
            }
        }
        paths.sort();
        paths.iter().map(|p| Self::load(p)).collect()
    }

    /// Checks every documented range and compiles the grammar.
    pub fn validate(&self) -> Result<(), SpeciesError> {
        if self.name.trim().is_empty() {
            return Err(invalid("name", "must not be empty"));
        }
        if self.iterations > HARD_MAX_ITERATIONS {
            return Err(invalid("iterations", "must be at most 255"));
        }
        let t = &self.turtle;
        let finite = |field: &str, v: f32| {
            if v.is_finite() {
                Ok(())
            } else {
                Err(invalid(field, "must be finite"))
            }
        };
        let non_negative = |field: &str, v: f32| {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err(invalid(field, "must be a finite number ≥ 0"))
            }
        };
        finite("turtle.angle", t.angle)?;
        non_negative("turtle.step", t.step)?;
        non_negative("turtle.initial_radius", t.initial_radius)?;
        non_negative("turtle.radius_factor", t.radius_factor)?;
        for v in t.tropism {
            finite("turtle.tropism", v)?;
        }
        finite("turtle.tropism_strength", t.tropism_strength)?;
        let l = &self.leaf;
        non_negative("leaf.width", l.width)?;
        non_negative("leaf.length", l.length)?;
        if !(0.0..=180.0).contains(&l.jitter_deg) {
            return Err(invalid("leaf.jitter_deg", "must be in [0, 180]"));
        }
        if !(0.0..1.0).contains(&l.size_jitter) {
            return Err(invalid("leaf.size_jitter", "must be in [0, 1)"));
        }
        let m = &self.materials;
        let color = |field: &str, c: [f32; 4]| {
            if c.iter().all(|v| (0.0..=1.0).contains(v)) {
                Ok(())
            } else {
                Err(invalid(field, "components must be in [0, 1]"))
            }
        };
        let texture = |field: &str, t: &Option<String>| match t {
            Some(name) if name.is_empty() || name.len() > MAX_TEXTURE_NAME => {
                Err(invalid(field, "must be 1 to 255 bytes"))
            }
            _ => Ok(()),
        };
        color("materials.bark_color", m.bark_color)?;
        texture("materials.bark_texture", &m.bark_texture)?;
        if m.leaf.is_empty() || m.leaf.len() > 255 {
            return Err(invalid("materials.leaf", "must have 1 to 255 entries"));
        }
        for lm in &m.leaf {
            color("materials.leaf.color", lm.color)?;
            texture("materials.leaf.texture", &lm.texture)?;
        }
        if let Some(v) = &self.variation {
            self.validate_variation(v)?;
        }
        self.grammar(&Limits::default())?;
        Ok(())
    }

    fn validate_variation(&self, v: &VariationSpec) -> Result<(), SpeciesError> {
        if let Some([lo, hi]) = v.iterations
            && (lo > hi || hi > HARD_MAX_ITERATIONS)
        {
            return Err(invalid(
                "variation.iterations",
                "must be [min, max] with min ≤ max ≤ 255",
            ));
        }
        if let Some(c) = &v.iterations_constant {
            if !self.constants.contains_key(c) {
                return Err(invalid(
                    "variation.iterations_constant",
                    &format!("names `{c}`, which is not one of the spec's constants"),
                ));
            }
            if v.iterations.is_none() {
                return Err(invalid("variation.iterations_constant", "needs variation.iterations"));
            }
        }
        for (name, [lo, hi]) in &v.constants {
            let field = format!("variation.constants.{name}");
            if !self.constants.contains_key(name) {
                return Err(invalid(&field, "is not one of the spec's constants"));
            }
            if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                return Err(invalid(&field, "must be [min, max], finite, with min ≤ max"));
            }
        }
        if let Some([lo, hi]) = v.leaf_scale
            && !(lo.is_finite() && hi.is_finite() && 0.0 < lo && lo <= hi)
        {
            return Err(invalid("variation.leaf_scale", "must be [min, max] with 0 < min ≤ max"));
        }
        Ok(())
    }

    /// Variant `index` of the species: its own seed (`mix64` of the spec's seed and `index`) and
    /// each parameter of `[variation]` drawn uniformly from its range, named
    /// `<name>-<index:03>`, without a `[variation]` of its own. The same spec and index always
    /// give the same variant. A spec without `[variation]` varies by seed only. The variant is
    /// validated again (a drawn value may make the grammar fail only when it grows).
    pub fn variant(&self, index: u64) -> Result<SpeciesSpec, SpeciesError> {
        let mut rng = canopy_shared::rng::SplitMix64::new(mix64(self.seed ^ mix64(index ^ 0x0076_6172_6961_6E74)));
        let mut out = self.clone();
        out.name = format!("{}-{index:03}", self.name);
        out.seed = rng.next_u64();
        out.variation = None;
        if let Some(v) = &self.variation {
            if let Some([lo, hi]) = v.iterations {
                out.iterations = lo + rng.below(u64::from(hi - lo) + 1) as u32;
                if let Some(c) = &v.iterations_constant {
                    out.constants.insert(c.clone(), f64::from(out.iterations));
                }
            }
            for (name, [lo, hi]) in &v.constants {
                out.constants.insert(name.clone(), rng.uniform(*lo, *hi));
            }
            if let Some([lo, hi]) = v.leaf_scale {
                let f = rng.uniform(f64::from(lo), f64::from(hi)) as f32;
                out.leaf.width *= f;
                out.leaf.length *= f;
            }
        }
        out.validate()?;
        Ok(out)
    }

    /// Compiles the grammar (axiom, productions, constants, functions, macros) under `limits`.
    pub fn grammar(&self, limits: &Limits) -> Result<Grammar, LSystemError> {
        Grammar::with_definitions(
            &self.axiom,
            &self.productions,
            &self.constants,
            &self.functions,
            &self.macros,
            limits,
        )
    }

    /// The turtle settings of this spec.
    pub fn turtle_params(&self) -> TurtleParams {
        TurtleParams {
            angle_deg: self.turtle.angle,
            step: self.turtle.step,
            initial_radius: self.turtle.initial_radius,
            radius_factor: self.turtle.radius_factor,
            tropism: Vec3::from_array(self.turtle.tropism),
            tropism_strength: self.turtle.tropism_strength,
            leaf_width: self.leaf.width,
            leaf_length: self.leaf.length,
            leaf_jitter_deg: self.leaf.jitter_deg,
            leaf_size_jitter: self.leaf.size_jitter,
            leaf_materials: self.materials.leaf.len(),
            // Decorrelated from the derivation stream, which uses the seed itself.
            seed: mix64(self.seed ^ 0x6C65_6166),
        }
    }

    /// The materials of this spec.
    pub fn materials(&self) -> Materials {
        Materials {
            bark_color: self.materials.bark_color,
            bark_texture: self.materials.bark_texture.clone(),
            leaf: self
                .materials
                .leaf
                .iter()
                .map(|l| LeafMaterial {
                    color: l.color,
                    texture: l.texture.clone(),
                })
                .collect(),
        }
    }
}

/// Grows the full-detail tree: `spec.iterations` derivation steps, then the turtle.
pub fn grow(spec: &SpeciesSpec, limits: &Limits) -> Result<TreeModel, LSystemError> {
    grow_iterations(spec, spec.iterations, limits)
}

/// Grows the tree with `iterations` steps instead of `spec.iterations` (iteration LOD). For the
/// project's species (apex growth) the result equals `grow(spec).at_iteration(iterations)` except
/// that a branch's polyline stops where the shorter derivation stopped.
pub fn grow_iterations(spec: &SpeciesSpec, iterations: u32, limits: &Limits) -> Result<TreeModel, LSystemError> {
    grow_with_progress(spec, iterations, limits, &mut |_, _| {})
}

/// [`grow_iterations`] with `progress(iteration, module_count)` called after the axiom and after
/// every derivation step.
pub fn grow_with_progress(
    spec: &SpeciesSpec,
    iterations: u32,
    limits: &Limits,
    progress: &mut dyn FnMut(u32, usize),
) -> Result<TreeModel, LSystemError> {
    let grammar = spec.grammar(limits)?;
    let string = grammar.derive_with_progress(spec.seed, iterations, limits, progress)?;
    let tree = interpret(&string, &spec.turtle_params(), limits)?;
    Ok(TreeModel {
        name: spec.name.clone(),
        branches: tree.branches,
        leaves: tree.leaves,
        bark_mesh: canopy_shared::model::TriangleMesh::default(),
        materials: spec.materials(),
        // derive_with_progress enforced iterations <= 255.
        iterations: iterations as u8,
        source: ModelSource::LSystem,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const MINIMAL: &str = r#"
name = "test"
seed = 1
iterations = 3
axiom = "A(1)"
productions = ["A(x) -> F(x, 0.01) [+(30) G(x)] A(x*0.9)"]
functions = ["half(a) = a * 0.5"]
macros = ["G(x) = F(half(x)) L"]
"#;

    #[test]
    fn minimal_spec_loads_and_grows() {
        let spec = SpeciesSpec::from_toml_str(MINIMAL).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(spec.materials.leaf.len(), 1);
        let t = grow(&spec, &Limits::default()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(t.name, "test");
        assert_eq!(t.iterations, 3);
        assert_eq!(t.leaves.len(), 3);
        assert_eq!(t.branches.len(), 4);
        assert!(t.check_invariants().is_ok());
        let t1 = grow_iterations(&spec, 1, &Limits::default()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(t1.iterations, 1);
        assert_eq!(t1.leaves.len(), 1);
    }

    #[test]
    fn unknown_keys_are_rejected() {
        let bad = format!("{MINIMAL}\ncolour = 1\n");
        let e = SpeciesSpec::from_toml_str(&bad)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(e.contains("colour"), "{e}");
        let bad = format!("{MINIMAL}\n[turtle]\nangel = 30\n");
        let e = SpeciesSpec::from_toml_str(&bad)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(e.contains("angel"), "{e}");
        let bad = format!("{MINIMAL}\n[[materials.leaf]]\ncolor = [0.1, 0.2, 0.3, 1.0]\nshine = 2\n");
        assert!(SpeciesSpec::from_toml_str(&bad).is_err());
    }

    #[test]
    fn ranges_are_checked() {
        let cases = [
            ("\n[leaf]\nsize_jitter = 1.5\n", "leaf.size_jitter"),
            ("\n[leaf]\nwidth = -1\n", "leaf.width"),
            ("\n[materials]\nbark_color = [2, 0, 0, 1]\n", "materials.bark_color"),
            ("\n[materials]\nleaf = []\n", "materials.leaf"),
            ("\n[turtle]\nstep = -1\n", "turtle.step"),
        ];
        for (extra, field) in cases {
            let text = format!("{MINIMAL}{extra}");
            match SpeciesSpec::from_toml_str(&text) {
                Err(SpeciesError::Invalid { field: f, .. }) => assert_eq!(f, field),
                other => panic!("{extra}: {other:?}"),
            }
        }
        let text = MINIMAL.replace("iterations = 3", "iterations = 300");
        assert!(matches!(
            SpeciesSpec::from_toml_str(&text),
            Err(SpeciesError::Invalid { .. })
        ));
        let text = MINIMAL.replace("A(x*0.9)", "A(x*)");
        assert!(matches!(
            SpeciesSpec::from_toml_str(&text),
            Err(SpeciesError::Grammar(_))
        ));
        let text = MINIMAL.replace("name = \"test\"", "name = \" \"");
        assert!(SpeciesSpec::from_toml_str(&text).is_err());
        assert!(matches!(
            SpeciesSpec::from_toml_str("name = "),
            Err(SpeciesError::Toml(_))
        ));
    }

    const VARIED: &str = r#"
[variation]
iterations = [2, 4]
iterations_constant = "N"
leaf_scale = [0.5, 2.0]

[variation.constants]
s = [0.5, 1.5]
"#;

    fn varied() -> SpeciesSpec {
        let text = format!(
            "{}\n[constants]\nN = 3\ns = 1.0\n{VARIED}",
            MINIMAL.replace("A(x) -> F(x, 0.01)", "A(x) -> F(x*s, 0.01)")
        );
        SpeciesSpec::from_toml_str(&text).unwrap_or_else(|e| panic!("{e}\n{text}"))
    }

    #[test]
    fn variants_are_deterministic_distinct_and_in_range() {
        let spec = varied();
        let a: Vec<SpeciesSpec> = (0..20)
            .map(|k| spec.variant(k).unwrap_or_else(|e| panic!("{e}")))
            .collect();
        let b: Vec<SpeciesSpec> = (0..20)
            .map(|k| spec.variant(k).unwrap_or_else(|e| panic!("{e}")))
            .collect();
        assert_eq!(a, b);
        for (k, v) in a.iter().enumerate() {
            assert_eq!(v.name, format!("test-{k:03}"));
            assert!(v.variation.is_none());
            assert!((2..=4).contains(&v.iterations));
            assert_eq!(v.constants["N"], f64::from(v.iterations));
            assert!((0.5..=1.5).contains(&v.constants["s"]));
            assert!((0.5 * spec.leaf.width..=2.0 * spec.leaf.width).contains(&v.leaf.width));
        }
        let seeds: std::collections::BTreeSet<u64> = a.iter().map(|v| v.seed).collect();
        assert_eq!(seeds.len(), a.len());
        // Every parameter actually varies across the variants.
        let iters: std::collections::BTreeSet<u32> = a.iter().map(|v| v.iterations).collect();
        assert_eq!(iters.len(), 3);
        // A variant grows like any spec.
        let t = grow(&a[0], &Limits::default()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(u32::from(t.iterations), a[0].iterations);
    }

    #[test]
    fn bad_variation_names_its_field() {
        let text = |extra: &str| format!("{MINIMAL}\n[constants]\nN = 3\ns = 1.0\n{extra}");
        let cases = [
            ("\n[variation]\niterations = [4, 2]\n", "variation.iterations"),
            ("\n[variation]\niterations = [2, 300]\n", "variation.iterations"),
            (
                "\n[variation]\niterations = [2, 3]\niterations_constant = \"M\"\n",
                "variation.iterations_constant",
            ),
            (
                "\n[variation]\niterations_constant = \"N\"\n",
                "variation.iterations_constant",
            ),
            ("\n[variation.constants]\nq = [0, 1]\n", "variation.constants.q"),
            ("\n[variation.constants]\ns = [2, 1]\n", "variation.constants.s"),
            ("\n[variation]\nleaf_scale = [0, 1]\n", "variation.leaf_scale"),
        ];
        for (extra, field) in cases {
            match SpeciesSpec::from_toml_str(&text(extra)) {
                Err(SpeciesError::Invalid { field: f, .. }) => assert_eq!(f, field, "{extra}"),
                other => panic!("{extra}: {other:?}"),
            }
        }
        let e = SpeciesSpec::from_toml_str(&text("\n[variation]\nscale = [1, 2]\n"));
        assert!(matches!(e, Err(SpeciesError::Toml(_))), "{e:?}");
        assert!(SpeciesSpec::from_toml_str(&text("")).is_ok());
    }

    #[test]
    fn load_names_the_file() {
        let e = SpeciesSpec::load(Path::new("/nonexistent/x.toml"));
        assert!(matches!(e, Err(SpeciesError::Io { .. })));
    }
}
