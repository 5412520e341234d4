//! The candidate set of `P_M = (r, γ, precision)` (Sec. 5.5): a grid of resolutions,
//! thresholds and the VDI file's precisions.

use insitu_core::vdi::{Precision, VdiParams, MAX_RESOLUTION};
use serde::{Deserialize, Serialize};

/// A candidate `P_M`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Candidate {
    /// `r`, pixels per side.
    pub r: u32,
    /// `γ`.
    pub gamma: f32,
    /// The precision its file is written at (absent in records made before precision was a
    /// parameter: those were 32-bit floats).
    #[serde(default)]
    pub precision: Precision,
}

impl Candidate {
    /// What identifies it in maps: `r`, `γ`'s bits and the precision's bit count.
    pub fn key(&self) -> (u32, u32, u32) {
        (self.r, self.gamma.to_bits(), self.precision.bits())
    }

    /// As generation parameters.
    pub fn params(&self) -> VdiParams {
        VdiParams {
            resolution: self.r,
            gamma: self.gamma,
            precision: self.precision,
        }
    }
}

impl From<VdiParams> for Candidate {
    fn from(p: VdiParams) -> Self {
        Self {
            r: p.resolution,
            gamma: p.gamma,
            precision: p.precision,
        }
    }
}

/// The precisions a grid holds unless told otherwise: the nodes' default, 8 bits.
pub const DEFAULT_PRECISIONS: [Precision; 1] = [Precision::Bits(8)];

fn default_precisions() -> Vec<Precision> {
    DEFAULT_PRECISIONS.to_vec()
}

/// Errors of a grid description.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum GridError {
    /// A range does not parse or is empty/backwards.
    #[error("{what} {spec:?}: {problem} (expected START:END:STEP or a comma-separated list)")]
    Range {
        /// `r` or `gamma`.
        what: &'static str,
        /// As given.
        spec: String,
        /// What is wrong.
        problem: String,
    },
}

/// Resolutions × thresholds × precisions, each sorted ascending without duplicates (the
/// precisions by bit count, `f32` last).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ParamGrid {
    /// Resolutions, ascending.
    pub rs: Vec<u32>,
    /// Thresholds, ascending.
    pub gammas: Vec<f32>,
    /// Precisions (at least one).
    #[serde(default = "default_precisions")]
    pub precisions: Vec<Precision>,
}

impl Default for ParamGrid {
    /// The paper's grid: γ ∈ 0.001–0.26 step 0.004, r ∈ 160–768 step 32 (Sec. 5.5), at
    /// [`DEFAULT_PRECISIONS`].
    fn default() -> Self {
        Self {
            rs: (160..=768).step_by(32).collect(),
            gammas: (0..65)
                .map(|i| (0.001 + 0.004 * f64::from(i)) as f32)
                .collect(),
            precisions: default_precisions(),
        }
    }
}

/// Most values one `START:END:STEP` range may give.
const MAX_VALUES: usize = 100_000;

fn range_f64(what: &'static str, spec: &str) -> Result<Vec<f64>, GridError> {
    let err = |problem: &str| GridError::Range {
        what,
        spec: spec.to_owned(),
        problem: problem.to_owned(),
    };
    let num = |s: &str| s.trim().parse::<f64>().map_err(|_| err("not a number"));
    let values: Vec<f64> = if spec.contains(':') {
        let parts: Vec<&str> = spec.split(':').collect();
        let [a, b, step] = parts.as_slice() else {
            return Err(err("a range has three parts"));
        };
        let (a, b, step) = (num(a)?, num(b)?, num(step)?);
        if !(a.is_finite() && b.is_finite() && step.is_finite() && step > 0.0 && b >= a) {
            return Err(err("need START ≤ END and STEP > 0"));
        }
        // Counted in f64 and bounded before the conversion: a huge END / STEP (1e300, or
        // more values than a usize holds; infinite, never NaN, as the operands are finite and
        // STEP > 0) is refused, not saturated into an overflow.
        let n = ((b - a) / step + 1e-9).floor() + 1.0;
        if n > MAX_VALUES as f64 {
            return Err(err(&format!("more than {MAX_VALUES} values")));
        }
        (0..n as usize).map(|i| a + step * i as f64).collect()
    } else {
        spec.split(',').map(num).collect::<Result<_, _>>()?
    };
    if values.is_empty() {
        return Err(err("empty"));
    }
    Ok(values)
}

impl ParamGrid {
    /// Parses `r` and `γ` specs (`START:END:STEP` or `a,b,c`), sorts and checks them.
    ///
    /// # Errors
    /// [`GridError`] naming the spec: unparsable, empty, `r` outside 1..=16384, `γ` negative
    /// or not finite.
    pub fn parse(r: &str, gamma: &str) -> Result<Self, GridError> {
        let bad = |what, spec: &str, problem: String| GridError::Range {
            what,
            spec: spec.to_owned(),
            problem,
        };
        let mut rs = Vec::new();
        for v in range_f64("r", r)? {
            if v.fract() != 0.0 || !(1.0..=f64::from(MAX_RESOLUTION)).contains(&v) {
                return Err(bad(
                    "r",
                    r,
                    format!("{v} is not an integer in 1..={MAX_RESOLUTION}"),
                ));
            }
            rs.push(v as u32);
        }
        let mut gammas = Vec::new();
        for v in range_f64("gamma", gamma)? {
            if !(v.is_finite() && v >= 0.0) {
                return Err(bad("gamma", gamma, format!("{v} must be finite and ≥ 0")));
            }
            gammas.push(v as f32);
        }
        rs.sort_unstable();
        rs.dedup();
        gammas.sort_by(f32::total_cmp);
        gammas.dedup();
        Ok(Self {
            rs,
            gammas,
            precisions: default_precisions(),
        })
    }

    /// The grid with the precisions of `spec`: a comma-separated list of bit counts (4–16)
    /// and `f32`, e.g. `6,8,f32`.
    ///
    /// # Errors
    /// [`GridError`] naming the spec: empty, or an entry that is no precision.
    pub fn with_precisions(mut self, spec: &str) -> Result<Self, GridError> {
        let err = |problem: String| GridError::Range {
            what: "precision",
            spec: spec.to_owned(),
            problem,
        };
        let mut ps = spec
            .split(',')
            .map(|p| p.parse::<Precision>().map_err(|e| err(e.to_string())))
            .collect::<Result<Vec<_>, _>>()?;
        // By bit count, f32 (0 bits on the wire) last: the coarsest first.
        ps.sort_by_key(|p| match p {
            Precision::Float32 => u32::MAX,
            p => p.bits(),
        });
        ps.dedup();
        self.precisions = ps;
        Ok(self)
    }

    /// The grid at `precision` alone.
    pub fn at(&self, precision: Precision) -> Self {
        Self {
            precisions: vec![precision],
            ..self.clone()
        }
    }

    /// The precision a single-precision grid's candidates take (the first).
    pub fn precision(&self) -> Precision {
        self.precisions.first().copied().unwrap_or_default()
    }

    /// Every candidate, precision-major, then r-major.
    pub fn candidates(&self) -> Vec<Candidate> {
        self.precisions
            .iter()
            .flat_map(|&precision| {
                self.rs.iter().flat_map(move |&r| {
                    self.gammas.iter().map(move |&gamma| Candidate {
                        r,
                        gamma,
                        precision,
                    })
                })
            })
            .collect()
    }

    /// Number of candidates.
    pub fn len(&self) -> usize {
        self.rs.len() * self.gammas.len() * self.precisions.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_is_the_papers_grid() {
        let g = ParamGrid::default();
        assert_eq!((g.rs.len(), g.gammas.len()), (20, 65));
        assert_eq!((g.rs[0], g.rs[19]), (160, 768));
        assert!((g.gammas[64] - 0.257).abs() < 1e-6);
        assert_eq!(
            ParamGrid::parse("160:768:32", "0.001:0.26:0.004").unwrap(),
            g
        );
    }

    #[test]
    fn bad_specs_name_the_problem() {
        assert!(ParamGrid::parse("0:10:5", "0.1")
            .unwrap_err()
            .to_string()
            .contains("r"));
        assert!(ParamGrid::parse("100", "-0.1").is_err());
        assert!(ParamGrid::parse("100", "0.2:0.1:0.01").is_err());
        assert!(ParamGrid::parse("100", "").is_err());
        assert!(ParamGrid::parse("100.5", "0.1").is_err());
        assert!(ParamGrid::parse("100", "nan").is_err());
        assert!(ParamGrid::parse("1:2:0", "0.1").is_err());
        assert_eq!(
            ParamGrid::parse("64,32,64", "0.1,0.05").unwrap().rs,
            vec![32, 64]
        );
    }

    /// A range with more values than a `usize` holds (found by the `configs` fuzz target) and
    /// one just past the bound are refused with the bound named; one at the bound parses.
    #[test]
    fn ranges_beyond_the_bound_are_refused_not_overflowed() {
        for spec in ["0.001:1.1e56:0.008", "0.001:1e300:1e-300", "0:100000:1"] {
            let e = ParamGrid::parse("64", spec).unwrap_err().to_string();
            assert!(e.contains("more than 100000 values"), "{spec}: {e}");
        }
        assert_eq!(
            ParamGrid::parse("64", "0:99999:1").unwrap().gammas.len(),
            MAX_VALUES
        );
    }

    /// Precisions parse as bit counts and `f32`, coarsest first, without duplicates; anything
    /// else is refused with the spec named.
    #[test]
    fn precisions_parse_coarsest_first() {
        let g = ParamGrid::parse("64", "0.1").unwrap();
        assert_eq!(g.precisions, DEFAULT_PRECISIONS.to_vec());
        let g = g.with_precisions("f32, 10,8,10").unwrap();
        assert_eq!(
            g.precisions,
            vec![Precision::Bits(8), Precision::Bits(10), Precision::Float32]
        );
        assert_eq!(g.len(), 3);
        assert_eq!(g.candidates()[2].precision, Precision::Float32);
        for bad in ["3", "17", "", "8,half"] {
            let e = g.clone().with_precisions(bad).unwrap_err().to_string();
            assert!(e.contains("precision"), "{bad}: {e}");
        }
    }
}
