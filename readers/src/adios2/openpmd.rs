//! openPMD meshes in ADIOS2 files, as openPMD-api's ADIOS2 backend writes them (the standard's
//! "Mesh Based Records"): each 3-D cartesian mesh record component is a field — a scalar record
//! by its name (`rho`), a vector record's component as `record/component` (`E/x`) — and each
//! iteration a time step, whichever iteration encoding the writer chose: one file per
//! iteration (`run_%T.bp5`, each file one step), all iterations in one file as groups
//! (`/data/<iteration>/meshes/…`), or one variable over ADIOS2 steps (`/data/meshes/…`).
//!
//! The mesh attributes are honoured as the standard defines them: `axisLabels` names the
//! axis of each of the writer's array dimensions in the order of its index operator, which
//! `dataOrder` says is C (first index slowest) or F (first index fastest); `gridSpacing` and
//! `gridGlobalOffset` are in `axisLabels`' order; a record component's `position` (in cells)
//! shifts where its samples lie. The samples are reordered so that the axis labelled `x` is
//! the volume's fastest, `y` the next and `z` the slowest — a mesh written `[x][y][z]` in C
//! order is transposed, not drawn mirrored. Spacing and origin stay in the simulation's units
//! (`gridUnitSI` and `unitSI` are reported in the notes, not applied: a grid in nanometres is
//! not drawn at 1e-9). Other geometries (`thetaMode`, `cylindrical`, `spherical`), meshes that
//! are not 3-D and labels that are not x, y and z are refused by name.

use super::Stream;
use crate::ReadError;
use glam::Vec3;

/// The root attribute every openPMD file carries: its standard's version.
const MARK: &str = "/openPMD";

/// One mesh record component of the series: a field.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Mesh {
    /// Its name: the record (`rho`) or `record/component` (`E/x`).
    pub name: String,
    /// Its iterations, ascending: the iteration number, the ADIOS2 variable holding it, and
    /// the ADIOS2 step it lies in where the iterations are steps of one variable (else the
    /// variable's own first step).
    pub iterations: Vec<Iteration>,
}

/// Where one iteration of a mesh lies.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Iteration {
    /// The iteration number (for iterations encoded as ADIOS2 steps: the step).
    pub number: u64,
    /// The ADIOS2 variable.
    pub var: String,
    /// The ADIOS2 step, where iterations are steps of one variable.
    pub step: Option<usize>,
}

/// How a mesh's samples lie: what [`layout`] reads from its attributes.
#[derive(Clone, Debug, PartialEq)]
pub struct Layout {
    /// Samples per axis (x, y, z).
    pub dims: [usize; 3],
    /// For x, y and z, the dimension of the ADIOS2 array (0 the slowest) that runs along it.
    pub axes: [usize; 3],
    /// Distance between samples per axis (x, y, z), simulation units.
    pub spacing: Vec3,
    /// Position of the first sample (x, y, z): `gridGlobalOffset + position · gridSpacing`.
    pub origin: Vec3,
    /// What the user should know (units not applied, attributes missing).
    pub notes: Vec<String>,
}

impl Layout {
    /// Whether the array's dimensions are already z, y, x (slowest first): no reordering.
    pub fn is_zyx(&self) -> bool {
        self.axes == [2, 1, 0]
    }
}

/// Whether `s` holds an openPMD series (its root attribute `/openPMD`).
pub fn is_openpmd(s: &Stream) -> bool {
    s.has_attribute(MARK)
}

/// The first text of attribute `name`.
fn text(s: &Stream, name: &str) -> Option<String> {
    s.texts(name).and_then(|t| t.into_iter().next())
}

/// The mesh record components among `s`'s variables, by name, each with its iterations
/// ascending; `steps` gives the ADIOS2 steps of a variable (for iterations encoded as steps).
pub fn meshes(s: &Stream, steps: impl Fn(&str) -> usize) -> Vec<Mesh> {
    // "/data/%T/" for iterations as files or groups, "/data" for iterations as steps.
    let base = text(s, "/basePath").unwrap_or_else(|| "/data/%T/".into());
    let base = base
        .split("%T")
        .next()
        .unwrap_or("/data")
        .trim_end_matches('/')
        .to_owned()
        + "/";
    let meshes_path = text(s, "/meshesPath").unwrap_or_else(|| "meshes/".into());
    let meshes_path = meshes_path.trim_matches('/').to_owned() + "/";
    let mut out: Vec<Mesh> = Vec::new();
    for var in s.variables() {
        let Some(rest) = var.strip_prefix(&base) else {
            continue;
        };
        // `<iteration>/meshes/<name>` (files, groups) or `meshes/<name>` (steps).
        let (number, name) = match rest.split_once('/') {
            Some((n, tail)) if n.bytes().all(|b| b.is_ascii_digit()) && !n.is_empty() => {
                match (n.parse::<u64>(), tail.strip_prefix(&meshes_path)) {
                    (Ok(n), Some(name)) => (Some(n), name),
                    _ => continue,
                }
            }
            _ => match rest.strip_prefix(&meshes_path) {
                Some(name) => (None, name),
                None => continue,
            },
        };
        if name.is_empty() {
            continue;
        }
        let iterations = match number {
            Some(n) => vec![Iteration {
                number: n,
                var: var.clone(),
                step: None,
            }],
            None => (0..steps(&var))
                .map(|t| Iteration {
                    number: t as u64,
                    var: var.clone(),
                    step: Some(t),
                })
                .collect(),
        };
        match out.iter_mut().find(|m| m.name == name) {
            Some(m) => m.iterations.extend(iterations),
            None => out.push(Mesh {
                name: name.to_owned(),
                iterations,
            }),
        }
    }
    for m in &mut out {
        m.iterations.sort_by_key(|i| i.number);
    }
    out.sort_by(|a, b| a.name.cmp(&b.name));
    out
}

/// The record of mesh variable `var`: the variable itself for a scalar record (its
/// attributes beside it), else its parent (a vector record's component).
fn record(s: &Stream, var: &str) -> String {
    let scalar = ["axisLabels", "gridSpacing", "geometry"]
        .iter()
        .any(|a| s.has_attribute(&format!("{var}/{a}")));
    match var.rsplit_once('/') {
        Some((parent, _)) if !scalar => parent.to_owned(),
        _ => var.to_owned(),
    }
}

/// How the samples of mesh `name` (its ADIOS2 variable `var`) lie, from the mesh's attributes.
///
/// # Errors
/// [`ReadError`] naming the stream and the mesh: not a 3-D global array of numbers, a
/// geometry other than cartesian, a `dataOrder` other than C or F, `axisLabels` that are not
/// x, y and z, a spacing that is not three positive numbers, or (in a build whose ADIOS2
/// cannot read text attributes safely) text attributes it cannot read.
pub fn layout(s: &Stream, name: &str, var: &str) -> Result<Layout, ReadError> {
    let bad = |what: String| ReadError::invalid(s.name(), format!("openPMD mesh {name}: {what}"));
    let v = s.variable(var)?;
    let rec = record(s, var);
    if !cfg!(adios2_string_data) {
        return Err(bad(
            "its axisLabels and dataOrder are text attributes, which this build's ADIOS2 cannot \
             read safely (it lacks adios2_attribute_string_data_array; build against a newer \
             ADIOS2, e.g. the PyPI wheel)"
                .into(),
        ));
    }
    if let Some(g) = text(s, &format!("{rec}/geometry")) {
        if g != "cartesian" {
            return Err(bad(format!(
                "geometry {g:?}: only cartesian meshes are volumes"
            )));
        }
    }
    let order = text(s, &format!("{rec}/dataOrder")).unwrap_or_else(|| "C".into());
    if order != "C" && order != "F" {
        return Err(bad(format!("dataOrder {order:?}: C or F")));
    }
    let mut notes = Vec::new();
    // The label of each index of the writer's index operator.
    let labels: Vec<String> = match s.texts(&format!("{rec}/axisLabels")) {
        Some(l) => l.iter().map(|l| l.to_ascii_lowercase()).collect(),
        None => {
            notes.push(format!(
                "openPMD mesh {name}: no axisLabels; its dimensions taken as z, y, x (slowest first)"
            ));
            let zyx = ["z", "y", "x"].map(String::from);
            if order == "C" {
                zyx.to_vec()
            } else {
                zyx.into_iter().rev().collect()
            }
        }
    };
    let index_of = |axis: &str| labels.iter().position(|l| l == axis);
    let index = match ["x", "y", "z"].map(index_of) {
        [Some(x), Some(y), Some(z)] if labels.len() == 3 => [x, y, z],
        _ => {
            // Seen with openPMD-api 0.17 writing SST and ADIOS2 2.12 reading: under SST's
            // default BP5 marshalling a string-array attribute arrives as one empty string.
            let hint = if labels.iter().all(String::is_empty) {
                " (an SST writer's string arrays arrive empty under SST's default marshalling: \
                 give the writer the SST parameter MarshalMethod=BP)"
            } else {
                ""
            };
            return Err(bad(format!(
                "axisLabels {labels:?}: a volume's labels are x, y and z in some order{hint}"
            )));
        }
    };
    // Index i of the writer's operator is array dimension i in C order, 2 − i in F order
    // (ADIOS2 presents a Fortran writer's dimensions reversed).
    let axes = index.map(|i| if order == "C" { i } else { 2 - i });
    let shape = [v.dims[2], v.dims[1], v.dims[0]];
    let dims = axes.map(|d| shape[d]);
    let three = |attr: &str| -> Option<Vec<f64>> {
        s.numbers(attr)
            .filter(|n| n.len() == 3 && n.iter().all(|x| x.is_finite()))
    };
    let by_axis = |n: &[f64]| Vec3::from(index.map(|i| n[i] as f32));
    let spacing = match three(&format!("{rec}/gridSpacing")) {
        Some(n) if n.iter().all(|&x| x > 0.0) => by_axis(&n),
        Some(n) => return Err(bad(format!("gridSpacing {n:?}: spacings are positive"))),
        None => {
            notes.push(format!(
                "openPMD mesh {name}: no gridSpacing of three numbers; unit spacing"
            ));
            Vec3::ONE
        }
    };
    let offset = three(&format!("{rec}/gridGlobalOffset")).map_or(Vec3::ZERO, |n| by_axis(&n));
    let position_attr = [format!("{var}/position"), format!("{rec}/position")]
        .into_iter()
        .find(|a| s.has_attribute(a));
    let position = match position_attr.as_deref().map(|a| (a, three(a))) {
        Some((_, Some(n))) => by_axis(&n),
        Some((a, None)) => {
            notes.push(format!(
                "openPMD mesh {name}: {a} is not three numbers of a type this reader takes \
                 (e.g. long double); samples taken at the cells' corners"
            ));
            Vec3::ZERO
        }
        None => Vec3::ZERO,
    };
    for (attr, what) in [
        (format!("{rec}/gridUnitSI"), "spacing and origin"),
        (format!("{var}/unitSI"), "values"),
    ] {
        if let Some(u) = s.numbers(&attr).and_then(|n| n.first().copied()) {
            if u != 1.0 {
                notes.push(format!(
                    "openPMD mesh {name}: {what} in the simulation's units ({attr} {u} not applied)"
                ));
            }
        }
    }
    Ok(Layout {
        dims,
        axes,
        spacing,
        origin: offset + position * spacing,
        notes,
    })
}

/// `bytes`, the samples of an array of `shape` (slowest first) of `size`-byte samples,
/// reordered so that array dimension `axes[0]` runs fastest, then `axes[1]`, then `axes[2]`.
///
/// # Panics
/// Never for `bytes` of `shape`'s samples and `axes` a permutation of 0, 1, 2 (what
/// [`layout`] gives); shorter `bytes` leave the rest zero.
pub fn reorder(bytes: &[u8], size: usize, shape: [usize; 3], axes: [usize; 3]) -> Vec<u8> {
    let stride = [shape[1] * shape[2], shape[2], 1];
    let dims = axes.map(|d| shape[d]);
    let step = axes.map(|d| stride[d] * size);
    let mut out = vec![0u8; bytes.len()];
    let mut o = 0;
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            let row = z * step[2] + y * step[1];
            for x in 0..dims[0] {
                let src = row + x * step[0];
                if let (Some(from), Some(to)) =
                    (bytes.get(src..src + size), out.get_mut(o..o + size))
                {
                    to.copy_from_slice(from);
                }
                o += size;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reordering_puts_the_chosen_dimension_fastest() {
        // An array [a][b][c] of shape (2, 3, 4), one byte each: value = 100a + 10b + c.
        let shape = [2, 3, 4];
        let bytes: Vec<u8> = (0..2)
            .flat_map(|a| (0..3).flat_map(move |b| (0..4).map(move |c| 100 * a + 10 * b + c)))
            .map(|v| v as u8)
            .collect();
        // Already c fastest, a slowest: unchanged.
        assert_eq!(reorder(&bytes, 1, shape, [2, 1, 0]), bytes);
        // a fastest, then b, then c: element (x = a, y = b, z = c).
        let t = reorder(&bytes, 1, shape, [0, 1, 2]);
        for c in 0..4 {
            for b in 0..3 {
                for a in 0..2 {
                    assert_eq!(t[a + 2 * (b + 3 * c)], (100 * a + 10 * b + c) as u8);
                }
            }
        }
        // Multi-byte samples move whole.
        let wide: Vec<u8> = bytes.iter().flat_map(|&v| [v, 0xAB]).collect();
        let tw = reorder(&wide, 2, shape, [0, 1, 2]);
        assert_eq!(tw.iter().step_by(2).copied().collect::<Vec<_>>(), t);
        assert!(tw.iter().skip(1).step_by(2).all(|&b| b == 0xAB));
    }
}
