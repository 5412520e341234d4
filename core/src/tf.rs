//! Transfer functions (docs/conventions.md, "Transfer function").
//!
//! A [`TransferFunction`] is piecewise-linear RGBA over the data domain, read from JSON:
//! `{"domain": [lo, hi], "points": [[x, r, g, b, a], ...]}` with `x` in [0, 1] across the
//! domain, colours in [0, 1] and `a` the opacity per unit length (one voxel). A sample taken
//! with step `Δ` gets `α = 1 − (1 − a)^Δ` (opacity correction). Classification during
//! ray-casting goes through a [`Lut`], a table of [`LUT_SIZE`] entries built once per step.

use crate::volume::Fnv1a;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Entries in a classification table.
pub const LUT_SIZE: usize = 4096;

/// Errors from reading or checking a transfer function; each names the input.
#[derive(Debug, thiserror::Error)]
pub enum TfError {
    /// The file could not be read.
    #[error("cannot read transfer function {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The cause.
        source: std::io::Error,
    },
    /// The JSON does not parse into the expected shape.
    #[error("transfer function {source_name} is not valid JSON of the form {{\"domain\": [lo, hi], \"points\": [[x, r, g, b, a], ...]}}: {source}")]
    Json {
        /// Where it came from.
        source_name: String,
        /// The parse error.
        source: serde_json::Error,
    },
    /// The JSON parsed but breaks a rule.
    #[error("transfer function {source_name}: {problem}")]
    Invalid {
        /// Where it came from.
        source_name: String,
        /// What is wrong.
        problem: String,
    },
}

/// Piecewise-linear RGBA transfer function over a scalar domain.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TransferFunction {
    /// Data values mapped to x = 0 and x = 1.
    pub domain: [f64; 2],
    /// Control points `[x, r, g, b, a]`, x strictly increasing in [0, 1].
    pub points: Vec<[f64; 5]>,
}

impl TransferFunction {
    /// Parses and validates JSON text; `source_name` names it in errors.
    ///
    /// # Errors
    /// [`TfError::Json`] for malformed JSON, [`TfError::Invalid`] for an empty point list, a
    /// domain that is not finite with `lo < hi`, x not strictly increasing in [0, 1], or a
    /// colour or opacity outside [0, 1].
    pub fn from_json(text: &str, source_name: &str) -> Result<Self, TfError> {
        let tf: Self = serde_json::from_str(text).map_err(|source| TfError::Json {
            source_name: source_name.to_owned(),
            source,
        })?;
        tf.validate(source_name)?;
        Ok(tf)
    }

    /// Reads and validates a JSON file.
    ///
    /// # Errors
    /// [`TfError::Io`] when unreadable, otherwise as [`TransferFunction::from_json`].
    pub fn load(path: &Path) -> Result<Self, TfError> {
        let text = std::fs::read_to_string(path).map_err(|source| TfError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_json(&text, &path.display().to_string())
    }

    /// Checks the rules listed in [`TransferFunction::from_json`].
    ///
    /// # Errors
    /// [`TfError::Invalid`] naming the first broken rule.
    pub fn validate(&self, source_name: &str) -> Result<(), TfError> {
        let invalid = |problem: String| TfError::Invalid {
            source_name: source_name.to_owned(),
            problem,
        };
        let [lo, hi] = self.domain;
        if !(lo.is_finite() && hi.is_finite() && lo < hi) {
            return Err(invalid(format!(
                "domain [{lo}, {hi}] must be finite with lo < hi"
            )));
        }
        if self.points.is_empty() {
            return Err(invalid("has no points".into()));
        }
        for (i, p) in self.points.iter().enumerate() {
            if let Some(v) = p.iter().find(|v| !(0.0..=1.0).contains(*v)) {
                return Err(invalid(format!(
                    "point {i} {p:?} has {v} outside [0, 1] (x, r, g, b and a are all in [0, 1])"
                )));
            }
            if i > 0 && p[0] <= self.points[i - 1][0] {
                return Err(invalid(format!(
                    "point {i} has x = {} not above the previous x = {} (x must increase)",
                    p[0],
                    self.points[i - 1][0]
                )));
            }
        }
        Ok(())
    }

    /// A grey-to-warm ramp over `[lo, hi]` whose opacity grows with the value: the default
    /// when a scene names no transfer function. A degenerate range is widened by one unit.
    pub fn default_for_range(lo: f32, hi: f32) -> Self {
        let (lo, hi) = (f64::from(lo), f64::from(hi));
        let (lo, hi) = if lo.is_finite() && hi.is_finite() && lo < hi {
            (lo, hi)
        } else if lo.is_finite() {
            (lo, lo + 1.0)
        } else {
            (0.0, 1.0)
        };
        Self {
            domain: [lo, hi],
            points: vec![
                [0.0, 0.0, 0.0, 0.0, 0.0],
                [0.1, 0.2, 0.3, 0.9, 0.0],
                [0.3, 0.2, 0.6, 1.0, 0.02],
                [0.6, 0.9, 0.9, 0.3, 0.08],
                [1.0, 1.0, 0.3, 0.1, 0.3],
            ],
        }
    }

    /// [`Self::default_for_range`] with its name, `default[lo, hi]`: what every node, the CLI
    /// and the recording call the default over that range (so agreeing nodes name it alike).
    pub fn default_named(lo: f32, hi: f32) -> NamedTf {
        NamedTf::new(
            Self::default_for_range(lo, hi),
            format!("default[{lo}, {hi}]"),
        )
    }

    /// [`Self::default_named`] over `volume`'s finite values ([`crate::Volume::finite_range`]; over
    /// [0, 1] when it has none, e.g. all NaN).
    pub fn default_for_volume(volume: &crate::volume::Volume) -> NamedTf {
        let (lo, hi) = volume.finite_range().unwrap_or((0.0, 1.0));
        Self::default_named(lo, hi)
    }

    /// A transfer function with one constant RGBA over `[lo, hi]`.
    pub fn constant(lo: f64, hi: f64, rgba: [f64; 4]) -> Self {
        let [r, g, b, a] = rgba;
        Self {
            domain: [lo, hi],
            points: vec![[0.0, r, g, b, a], [1.0, r, g, b, a]],
        }
    }

    /// RGBA at normalised position `x` (clamped to the first and last point).
    pub fn eval_normalized(&self, x: f64) -> [f64; 4] {
        let pts = &self.points;
        let rgba = |p: &[f64; 5]| [p[1], p[2], p[3], p[4]];
        let Some(first) = pts.first() else {
            return [0.0; 4];
        };
        if x <= first[0] {
            return rgba(first);
        }
        let i = pts.partition_point(|p| p[0] <= x);
        if i >= pts.len() {
            return rgba(&pts[pts.len() - 1]);
        }
        let (p0, p1) = (&pts[i - 1], &pts[i]);
        let w = (x - p0[0]) / (p1[0] - p0[0]);
        std::array::from_fn(|c| p0[c + 1] + w * (p1[c + 1] - p0[c + 1]))
    }

    /// A 64-bit identity of the function (FNV-1a over domain and points), stored in VDIs.
    pub fn identity_hash(&self) -> u64 {
        let mut h = Fnv1a::new();
        for v in self.domain.iter().chain(self.points.iter().flatten()) {
            h.write(&v.to_bits().to_le_bytes());
        }
        h.finish()
    }
}

/// A transfer function with the name it goes by: a file's stem, `default` for one made over
/// the data's range, a steered scene's label. The name travels with the function into every
/// VDI made with it (its provenance, [`TfIdentity`]).
#[derive(Clone, Debug, PartialEq)]
pub struct NamedTf {
    /// The function.
    pub tf: TransferFunction,
    /// Its name.
    pub name: String,
}

impl NamedTf {
    /// `tf` named `name`.
    pub fn new(tf: TransferFunction, name: impl Into<String>) -> Self {
        Self {
            tf,
            name: name.into(),
        }
    }

    /// What a VDI made with it records: its identity hash and name.
    pub fn identity(&self) -> TfIdentity<'_> {
        TfIdentity {
            hash: self.tf.identity_hash(),
            name: &self.name,
        }
    }
}

/// What a VDI records of the transfer function it was made with: the function's
/// [`TransferFunction::identity_hash`] and its name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TfIdentity<'a> {
    /// [`TransferFunction::identity_hash`] of the function.
    pub hash: u64,
    /// Its name ([`NamedTf::name`]).
    pub name: &'a str,
}

/// One classification entry: colour, per-unit-length extinction and the opacity of a full step.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LutEntry {
    /// Colour (not premultiplied), in [0, 1].
    pub rgb: [f32; 3],
    /// Opacity per unit length `a`.
    pub alpha_unit: f32,
    /// Extinction per unit length `κ = −ln(1 − a)`; `+∞` for `a = 1`.
    pub kappa: f32,
    /// Opacity of one full step `Δ`: `1 − (1 − a)^Δ`.
    pub alpha_step: f32,
}

/// Classification table for a transfer function and a ray-casting step.
#[derive(Clone, Debug)]
pub struct Lut {
    entries: Vec<LutEntry>,
    /// Prefix count of entries with `κ > 0`, for O(1) "any visible in range" queries.
    visible_prefix: Vec<u32>,
    lo: f32,
    scale: f32,
}

impl Lut {
    /// Samples `tf` at [`LUT_SIZE`] evenly spaced values and applies opacity correction for
    /// step `step` (world units per sample, in voxels of unit spacing).
    pub fn new(tf: &TransferFunction, step: f32) -> Self {
        let entries: Vec<LutEntry> = (0..LUT_SIZE)
            .map(|i| {
                let [r, g, b, a] = tf.eval_normalized(i as f64 / (LUT_SIZE - 1) as f64);
                let kappa = -(1.0 - a).ln();
                LutEntry {
                    rgb: [r as f32, g as f32, b as f32],
                    alpha_unit: a as f32,
                    kappa: kappa as f32,
                    alpha_step: (1.0 - (-kappa * f64::from(step)).exp()) as f32,
                }
            })
            .collect();
        let mut visible_prefix = Vec::with_capacity(LUT_SIZE + 1);
        visible_prefix.push(0u32);
        for e in &entries {
            let last = visible_prefix.last().copied().unwrap_or(0);
            visible_prefix.push(last + u32::from(e.kappa > 0.0));
        }
        let [lo, hi] = tf.domain;
        Self {
            entries,
            visible_prefix,
            lo: lo as f32,
            scale: ((LUT_SIZE - 1) as f64 / (hi - lo)) as f32,
        }
    }

    /// Table index of a value (nearest entry; values outside the domain clamp, ±∞ too).
    /// The caller handles NaN (transparent) before calling.
    #[inline(always)]
    pub fn index(&self, value: f32) -> usize {
        let x = ((value - self.lo) * self.scale).clamp(0.0, (LUT_SIZE - 1) as f32);
        (x + 0.5) as usize
    }

    /// The entry for a value; NaN maps to a transparent entry.
    #[inline(always)]
    pub fn classify(&self, value: f32) -> LutEntry {
        if value.is_nan() {
            return LutEntry::default();
        }
        self.entries[self.index(value)]
    }

    /// All [`LUT_SIZE`] entries.
    pub fn entries(&self) -> &[LutEntry] {
        &self.entries
    }

    /// `(lo, scale)`: value `v` maps to table position `(v − lo)·scale` before rounding.
    pub fn mapping(&self) -> (f32, f32) {
        (self.lo, self.scale)
    }

    /// Entry by table index.
    #[inline(always)]
    pub fn entry(&self, index: usize) -> &LutEntry {
        &self.entries[index]
    }

    /// Whether any value in `[lo, hi]` has non-zero opacity (monotone index map, so exact for
    /// every value a trilinear interpolation of samples in that range can take).
    pub fn any_visible(&self, lo: f32, hi: f32) -> bool {
        if lo.is_nan() || hi.is_nan() || lo > hi {
            return false;
        }
        let (a, b) = (self.index(lo), self.index(hi));
        self.visible_prefix[b + 1] > self.visible_prefix[a]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEAPOT: &str =
        r#"{"domain": [0, 255], "points": [[0.0, 0,0,0,0], [0.5, 1,0.5,0,0.2], [1.0, 1,1,1,1]]}"#;

    #[test]
    fn parses_and_interpolates() {
        let tf = TransferFunction::from_json(TEAPOT, "t").unwrap();
        let [r, g, b, a] = tf.eval_normalized(0.25);
        assert!((r - 0.5).abs() < 1e-12 && (g - 0.25).abs() < 1e-12 && b == 0.0);
        assert!((a - 0.1).abs() < 1e-12);
        assert_eq!(tf.eval_normalized(-1.0), [0.0; 4]);
        assert_eq!(tf.eval_normalized(2.0), [1.0; 4]);
    }

    #[test]
    fn rejects_malformed() {
        let cases = [
            (r#"{"domain": [0, 1], "points": []}"#, "no points"),
            (r#"{"domain": [1, 1], "points": [[0,0,0,0,0]]}"#, "domain"),
            (
                r#"{"domain": [0, 1], "points": [[0.5,0,0,0,0],[0.5,0,0,0,0]]}"#,
                "increase",
            ),
            (
                r#"{"domain": [0, 1], "points": [[0,0,0,0,1.5]]}"#,
                "outside",
            ),
            (r#"{"domain": [0, 1], "points": [[0,0,0,0]]}"#, "JSON"),
            (r#"not json"#, "JSON"),
        ];
        for (text, needle) in cases {
            let err = TransferFunction::from_json(text, "case.json")
                .unwrap_err()
                .to_string();
            assert!(
                err.contains(needle) && err.contains("case.json"),
                "{text}: {err}"
            );
        }
    }

    #[test]
    fn opacity_correction_follows_the_power_law() {
        let tf = TransferFunction::constant(0.0, 1.0, [1.0, 1.0, 1.0, 0.3]);
        for step in [0.25f32, 0.5, 1.0, 2.0] {
            let lut = Lut::new(&tf, step);
            let e = lut.classify(0.5);
            let expect = 1.0 - 0.7f64.powf(f64::from(step));
            assert!((f64::from(e.alpha_step) - expect).abs() < 1e-6);
        }
        let opaque = Lut::new(&TransferFunction::constant(0.0, 1.0, [1.0; 4]), 0.5);
        let e = opaque.classify(0.3);
        assert_eq!((e.alpha_step, e.kappa), (1.0, f32::INFINITY));
        assert_eq!(opaque.classify(f32::NAN).alpha_step, 0.0);
    }

    #[test]
    fn visibility_ranges_are_exact() {
        let tf = TransferFunction::from_json(TEAPOT, "t").unwrap();
        let lut = Lut::new(&tf, 1.0);
        assert!(!lut.any_visible(0.0, 0.0));
        assert!(lut.any_visible(0.0, 1.0));
        assert!(lut.any_visible(-1e30, f32::INFINITY));
        assert!(!lut.any_visible(f32::NAN, 1.0));
    }
}
