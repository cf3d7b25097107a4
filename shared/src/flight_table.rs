//! Seed 002's visual-redundancy table as a scene stores it (JSON, `docs/scenes.md`): for each
//! flight-height band and speed band, how many levels the low-flight policy may raise its
//! `LOD_DV` before a viewer would notice. The client's pre-pass (`canopy redundancy`) computes
//! it; the server stores it with the scene (`PUT /api/scenes/{id}/flight-table`) and serves it
//! back; the client's `--flight-policy` reads it.
//!
//! Conventions: heights are metres above the ground under the camera, speeds metres per second;
//! `offsets[h][v]` holds for `H ∈ [h·dh_m, (h+1)·dh_m)` and `v ∈ [v·dv_mps, (v+1)·dv_mps)`.
//! A lookup past the table's last band (higher or faster than the pre-pass went) takes the last
//! row or column: the pre-pass's highest and fastest band is its best statement about beyond,
//! and raising the level further than it measured would be a guess. Offset 0 means "as the
//! policy says"; offset k raises each level by k, capped at the policy's coarsest.

use serde::{Deserialize, Serialize};

/// `format` of a flight table.
pub const FLIGHT_TABLE_FORMAT: &str = "canopy-flight-table";
/// Flight table version written and read.
pub const FLIGHT_TABLE_VERSION: u32 = 1;
/// Most height bands (rows) and speed bands (columns) a table may have.
pub const MAX_BANDS: usize = 1024;
/// Largest JSON text accepted (a full 1024 × 1024 table is about 2 MiB).
pub const MAX_TABLE_BYTES: usize = 4 << 20;
/// Most distance band edges of the policy the table was computed for.
pub const MAX_SIGMA: usize = 64;

/// The seed 002 policy a table was computed for: offsets are only meaningful for it.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct FlightPolicyParams {
    /// Distance band edges σ, ascending, metres (levels `0..=sigma.len()`).
    pub sigma_m: Vec<f32>,
    /// Full horizontal field angle θ, degrees.
    pub field_deg: f32,
    /// Threat-zone time t, seconds.
    pub threat_time_s: f32,
}

/// How the offsets were found: the objective stand-in for seed 002's opinion score.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct FlightTableMethod {
    /// Metric name (`"ssim"`).
    pub metric: String,
    /// The score a raised frame must keep against the unraised one, both under the motion of one
    /// frame at the band's speed (MOS 4).
    pub threshold: f64,
    /// Image size the frames were rendered at, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Frames per second (one frame's motion is `v / fps` metres).
    pub fps: f32,
    /// Viewpoints per height band.
    pub viewpoints: u32,
    /// The representation ladder the policy's levels drew (`--ladder`'s syntax; empty when not
    /// recorded): level k is rung k, so the offsets hold for this ladder.
    #[serde(default)]
    pub ladder: String,
}

/// A scene's visual-redundancy table.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct FlightTable {
    /// Must be [`FLIGHT_TABLE_FORMAT`].
    pub format: String,
    /// Must be [`FLIGHT_TABLE_VERSION`].
    pub format_version: u32,
    /// ΔH, metres (> 0).
    pub dh_m: f32,
    /// Δv, metres per second (> 0).
    pub dv_mps: f32,
    /// Level offsets, rows by height band, columns by speed band; every row the same length.
    pub offsets: Vec<Vec<u8>>,
    /// The policy the offsets are for.
    pub policy: FlightPolicyParams,
    /// How they were found.
    pub method: FlightTableMethod,
}

/// Why a flight table is refused.
#[derive(Debug, thiserror::Error)]
pub enum FlightTableError {
    /// Not JSON of the expected shape.
    #[error("flight table is not valid JSON of the expected shape: {0}")]
    Json(#[from] serde_json::Error),
    /// Larger than [`MAX_TABLE_BYTES`].
    #[error("flight table is {0} bytes, more than {MAX_TABLE_BYTES}")]
    TooLarge(usize),
    /// Another format or version.
    #[error("flight table format {format:?} version {version} is not {FLIGHT_TABLE_FORMAT:?} {FLIGHT_TABLE_VERSION}")]
    Version {
        /// Format found.
        format: String,
        /// Version found.
        version: u32,
    },
    /// Inconsistent contents.
    #[error("flight table is inconsistent: {0}")]
    Invalid(String),
}

impl FlightTable {
    /// Parses and checks a table ([`FlightTable::check`]).
    pub fn parse(bytes: &[u8]) -> Result<Self, FlightTableError> {
        if bytes.len() > MAX_TABLE_BYTES {
            return Err(FlightTableError::TooLarge(bytes.len()));
        }
        let t: Self = serde_json::from_slice(bytes)?;
        t.check()?;
        Ok(t)
    }

    /// Compact JSON, as stored and served.
    pub fn to_json(&self) -> Result<String, serde_json::Error> {
        serde_json::to_string(self)
    }

    /// Checks format, steps, a rectangular non-empty table within [`MAX_BANDS`], offsets within
    /// the policy's levels, and the policy's parameters.
    pub fn check(&self) -> Result<(), FlightTableError> {
        if self.format != FLIGHT_TABLE_FORMAT || self.format_version != FLIGHT_TABLE_VERSION {
            return Err(FlightTableError::Version {
                format: self.format.clone(),
                version: self.format_version,
            });
        }
        let bad = |s: String| Err(FlightTableError::Invalid(s));
        let positive = |x: f32| x.is_finite() && x > 0.0;
        if !positive(self.dh_m) || !positive(self.dv_mps) {
            return bad(format!(
                "steps dh_m {} and dv_mps {} must be finite and positive",
                self.dh_m, self.dv_mps
            ));
        }
        let rows = self.offsets.len();
        let cols = self.offsets.first().map_or(0, Vec::len);
        if rows == 0 || cols == 0 {
            return bad("the table has no cell".into());
        }
        if rows > MAX_BANDS || cols > MAX_BANDS {
            return bad(format!("{rows} × {cols} bands, more than {MAX_BANDS} a side"));
        }
        if let Some(r) = self.offsets.iter().position(|r| r.len() != cols) {
            return bad(format!(
                "row {r} has {} speed bands, row 0 has {cols}",
                self.offsets[r].len()
            ));
        }
        let p = &self.policy;
        if p.sigma_m.is_empty() || p.sigma_m.len() > MAX_SIGMA {
            return bad(format!(
                "policy has {} distance bands (1..={MAX_SIGMA})",
                p.sigma_m.len()
            ));
        }
        if !p.sigma_m.iter().all(|&s| positive(s)) || p.sigma_m.windows(2).any(|w| w[0] >= w[1]) {
            return bad(format!("policy sigma_m {:?} is not positive and ascending", p.sigma_m));
        }
        let field_ok = p.field_deg.is_finite() && p.field_deg > 0.0 && p.field_deg <= 360.0;
        let threat_ok = p.threat_time_s.is_finite() && p.threat_time_s >= 0.0;
        if !(field_ok && threat_ok) {
            return bad(format!(
                "policy field_deg {} must be in (0, 360] and threat_time_s {} finite and ≥ 0",
                p.field_deg, p.threat_time_s
            ));
        }
        let levels = p.sigma_m.len();
        if let Some((h, v, o)) = self.cells().find(|&(_, _, o)| usize::from(o) > levels) {
            return bad(format!(
                "offset {o} at height band {h}, speed band {v} is past the policy's {levels} levels"
            ));
        }
        let m = &self.method;
        let fps_ok = m.fps.is_finite() && m.fps > 0.0;
        if !(m.threshold.is_finite() && fps_ok && m.width > 0 && m.height > 0) {
            return bad("method threshold, fps and image size must be finite and positive".into());
        }
        Ok(())
    }

    /// Every cell: (height band, speed band, offset).
    pub fn cells(&self) -> impl Iterator<Item = (usize, usize, u8)> + '_ {
        self.offsets
            .iter()
            .enumerate()
            .flat_map(|(h, row)| row.iter().enumerate().map(move |(v, &o)| (h, v, o)))
    }

    /// Highest flight height the table measured, metres (the top of its last band).
    pub fn h_max_m(&self) -> f32 {
        self.dh_m * self.offsets.len() as f32
    }

    /// Highest speed the table measured, m/s (the top of its last band).
    pub fn v_max_mps(&self) -> f32 {
        self.dv_mps * self.offsets.first().map_or(0, Vec::len) as f32
    }

    /// The offset for flight height `h` and speed `v`; past the table, its last band (module
    /// doc); below 0 or NaN, the first band.
    pub fn offset(&self, h: f32, v: f32) -> u8 {
        let band = |x: f32, step: f32, len: usize| -> Option<usize> {
            if len == 0 || !(step.is_finite() && step > 0.0) {
                return None;
            }
            let i = (x / step).floor();
            let i = if i.is_nan() || i < 0.0 {
                0
            } else {
                i.min(usize::MAX as f32) as usize
            };
            Some(i.min(len - 1))
        };
        let Some(row) = band(h, self.dh_m, self.offsets.len()).map(|r| &self.offsets[r]) else {
            return 0;
        };
        band(v, self.dv_mps, row.len()).map_or(0, |c| row[c])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> serde_json::Value {
        serde_json::json!({
            "format": "canopy-flight-table", "format_version": 1, "dh_m": 20.0, "dv_mps": 10.0,
            "offsets": [[0, 0, 1], [0, 1, 2]],
            "policy": {"sigma_m": [100.0, 250.0, 500.0, 1000.0], "field_deg": 120.0, "threat_time_s": 2.0},
            "method": {"metric": "ssim", "threshold": 0.95, "width": 480, "height": 270, "fps": 30.0, "viewpoints": 2}
        })
    }

    fn parse(v: &serde_json::Value) -> Result<FlightTable, FlightTableError> {
        FlightTable::parse(v.to_string().as_bytes())
    }

    #[test]
    fn parses_and_looks_up() {
        let t = parse(&sample()).expect("valid");
        assert_eq!(t.offset(0.0, 0.0), 0);
        assert_eq!(t.offset(19.9, 25.0), 1);
        assert_eq!(t.offset(20.0, 15.0), 1);
        assert_eq!(t.offset(-5.0, f32::NAN), 0);
        assert_eq!((t.h_max_m(), t.v_max_mps()), (40.0, 30.0));
        let back = FlightTable::parse(t.to_json().expect("json").as_bytes()).expect("round trip");
        assert_eq!(back, t);
    }

    /// Past its range a lookup takes the last band, never more than the table says.
    #[test]
    fn speeds_and_heights_past_the_range_take_the_last_band() {
        let t = parse(&sample()).expect("valid");
        assert_eq!(t.offset(20.0, 1e6), 2);
        assert_eq!(t.offset(1e9, 0.0), 0);
        assert_eq!(t.offset(f32::INFINITY, f32::INFINITY), 2);
        assert_eq!(t.offset(0.0, 30.0), 1, "v = v_max is past the last band's open end");
    }

    #[test]
    fn rejects_bad_tables() {
        type Edit = Box<dyn Fn(&mut serde_json::Value)>;
        let cases: Vec<(&str, Edit)> = vec![
            ("version", Box::new(|v| v["format_version"] = 2.into())),
            ("format", Box::new(|v| v["format"] = "x".into())),
            ("zero step", Box::new(|v| v["dh_m"] = 0.0.into())),
            ("negative step", Box::new(|v| v["dv_mps"] = (-1.0).into())),
            ("empty", Box::new(|v| v["offsets"] = serde_json::json!([]))),
            ("empty row", Box::new(|v| v["offsets"] = serde_json::json!([[]]))),
            ("ragged", Box::new(|v| v["offsets"] = serde_json::json!([[0, 0], [0]]))),
            ("offset past levels", Box::new(|v| v["offsets"][0][0] = 5.into())),
            ("offset not a byte", Box::new(|v| v["offsets"][0][0] = 300.into())),
            (
                "sigma not ascending",
                Box::new(|v| v["policy"]["sigma_m"] = serde_json::json!([100.0, 50.0])),
            ),
            ("no sigma", Box::new(|v| v["policy"]["sigma_m"] = serde_json::json!([]))),
            ("field", Box::new(|v| v["policy"]["field_deg"] = 0.0.into())),
            ("fps", Box::new(|v| v["method"]["fps"] = 0.0.into())),
            ("unknown field", Box::new(|v| v["extra"] = 1.into())),
            (
                "missing field",
                Box::new(|v| drop(v.as_object_mut().map(|o| o.remove("policy")))),
            ),
        ];
        for (name, edit) in cases {
            let mut v = sample();
            edit(&mut v);
            assert!(parse(&v).is_err(), "{name}: accepted");
        }
        assert!(matches!(FlightTable::parse(b"{"), Err(FlightTableError::Json(_))));
        let big = vec![b' '; MAX_TABLE_BYTES + 1];
        assert!(matches!(FlightTable::parse(&big), Err(FlightTableError::TooLarge(_))));
        let mut v = sample();
        v["offsets"] = serde_json::json!(vec![vec![0u8; 1]; MAX_BANDS + 1]);
        assert!(matches!(parse(&v), Err(FlightTableError::Invalid(_))));
    }
}
