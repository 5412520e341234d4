//! XDMF descriptions (`.xmf`, `.xdmf`; XDMF 2 and 3) of uniform grids whose fields live in
//! HDF5 files: a `3DCoRectMesh` topology (`Dimensions="nz ny nx"`) placed by an
//! `ORIGIN_DXDYDZ` geometry (two XML data items, each z y x), with scalar attributes whose
//! data items name `file.h5:/path/to/dataset` (the file relative to the description). A
//! temporal collection of such grids is a series, one grid per step, all on the same grid.
//!
//! Node-centred attributes are samples at the grid's points. Cell-centred ones
//! (`Center="Cell"`, one fewer per axis) are samples at the cells' centres: the volume read
//! has the cells' dims and starts half a cell in from the origin (said in
//! [`crate::Dataset::notes`]); docs/data.md states the convention.
//!
//! The description is parsed here in pure Rust (fuzzed); reading the datasets needs the `hdf5`
//! feature.

use crate::{check_grid, numbers, Dataset, Options, ReadError};
use glam::Vec3;
use quick_xml::events::Event;
use std::path::{Path, PathBuf};

/// Descriptions larger than this are refused.
const MAX_BYTES: u64 = 16 << 20;
/// Elements nested deeper than this are refused.
const MAX_DEPTH: usize = 32;

/// An XML element: name, attributes, text, children.
#[derive(Debug, Default)]
struct Element {
    name: String,
    attrs: Vec<(String, String)>,
    text: String,
    children: Vec<Element>,
}

impl Element {
    fn attr(&self, key: &str) -> Option<&str> {
        self.attrs
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }

    fn child(&self, name: &str) -> Option<&Element> {
        self.children.iter().find(|c| c.name == name)
    }

    fn all<'a>(&'a self, name: &'a str) -> impl Iterator<Item = &'a Element> + 'a {
        self.children.iter().filter(move |c| c.name == name)
    }
}

fn parse(path: &Path, xml: &[u8]) -> Result<Element, ReadError> {
    let bad = |m: String| ReadError::invalid(path, m);
    let mut reader = quick_xml::Reader::from_reader(xml);
    let mut buf = Vec::new();
    let mut stack: Vec<Element> = vec![Element::default()];
    let open = |e: &quick_xml::events::BytesStart<'_>| -> Element {
        Element {
            name: String::from_utf8_lossy(e.local_name().as_ref()).into_owned(),
            attrs: e
                .attributes()
                .flatten()
                .map(|a| {
                    (
                        String::from_utf8_lossy(a.key.local_name().as_ref()).into_owned(),
                        a.unescape_value()
                            .map(|v| v.into_owned())
                            .unwrap_or_default(),
                    )
                })
                .collect(),
            ..Element::default()
        }
    };
    loop {
        match reader.read_event_into(&mut buf) {
            Ok(Event::Start(e)) => {
                if stack.len() > MAX_DEPTH {
                    return Err(bad(format!("elements nested deeper than {MAX_DEPTH}")));
                }
                stack.push(open(&e));
            }
            Ok(Event::Empty(e)) => {
                let el = open(&e);
                if let Some(top) = stack.last_mut() {
                    top.children.push(el);
                }
            }
            Ok(Event::Text(t)) => {
                if let (Some(top), Ok(s)) = (stack.last_mut(), t.unescape()) {
                    top.text.push_str(&s);
                }
            }
            Ok(Event::End(_)) => {
                let el = stack
                    .pop()
                    .filter(|_| !stack.is_empty())
                    .ok_or_else(|| bad("XML: an end tag without its start".into()))?;
                if let Some(top) = stack.last_mut() {
                    top.children.push(el);
                }
            }
            Ok(Event::Eof) => break,
            Ok(_) => {}
            Err(e) => return Err(bad(format!("XML: {e}"))),
        }
        buf.clear();
    }
    if stack.len() != 1 {
        return Err(bad("XML: the document ends inside an element".into()));
    }
    stack.pop().ok_or_else(|| bad("XML: no document".into()))
}

/// Where an attribute is centred.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Center {
    Node,
    Cell,
}

/// One uniform grid of the description: its points and its attributes' HDF5 datasets.
#[derive(Debug)]
struct Uniform {
    /// Points per axis (x, y, z).
    dims: [usize; 3],
    origin: Vec3,
    spacing: Vec3,
    /// Name, centring, HDF5 file and dataset path.
    attributes: Vec<(String, Center, PathBuf, String)>,
}

fn uniform(path: &Path, grid: &Element, inherited: Option<&Element>) -> Result<Uniform, ReadError> {
    let bad = |m: String| ReadError::invalid(path, m);
    let name = grid.attr("Name").unwrap_or("(unnamed)");
    let find = |what: &str| {
        grid.child(what)
            .or_else(|| inherited.and_then(|p| p.child(what)))
            .ok_or_else(|| bad(format!("grid {name} has no {what}")))
    };
    let topology = find("Topology")?;
    let kind = topology
        .attr("TopologyType")
        .or_else(|| topology.attr("Type"))
        .unwrap_or("");
    if !kind.eq_ignore_ascii_case("3DCoRectMesh") {
        return Err(bad(format!(
            "grid {name}: topology {kind:?}; only a uniform 3DCoRectMesh is read"
        )));
    }
    let d = numbers(
        path,
        "Topology Dimensions",
        topology.attr("Dimensions").unwrap_or(""),
        3,
    )?;
    let mut dims = [0usize; 3];
    for (a, v) in d.iter().rev().enumerate() {
        if v.fract() != 0.0 || *v < 1.0 || *v > 1e9 {
            return Err(bad(format!("grid {name}: dimension {v} is not a count")));
        }
        dims[a] = *v as usize;
    }
    let geometry = find("Geometry")?;
    let kind = geometry
        .attr("GeometryType")
        .or_else(|| geometry.attr("Type"))
        .unwrap_or("");
    if !kind.eq_ignore_ascii_case("ORIGIN_DXDYDZ") {
        return Err(bad(format!(
            "grid {name}: geometry {kind:?}; only ORIGIN_DXDYDZ is read"
        )));
    }
    let items: Vec<&Element> = geometry.all("DataItem").collect();
    let [o, s] = items.as_slice() else {
        return Err(bad(format!(
            "grid {name}: ORIGIN_DXDYDZ needs two data items, not {}",
            items.len()
        )));
    };
    for item in [o, s] {
        if !item
            .attr("Format")
            .unwrap_or("XML")
            .eq_ignore_ascii_case("XML")
        {
            return Err(bad(format!(
                "grid {name}: the origin and spacing must be XML data items"
            )));
        }
    }
    let zyx = |v: Vec<f64>| Vec3::new(v[2] as f32, v[1] as f32, v[0] as f32);
    let origin = zyx(numbers(path, "origin", &o.text, 3)?);
    let spacing = zyx(numbers(path, "spacing", &s.text, 3)?);
    check_grid(path, dims, spacing, origin)?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut attributes = Vec::new();
    for a in grid.all("Attribute") {
        let an = a.attr("Name").unwrap_or("").to_owned();
        let kind = a.attr("AttributeType").unwrap_or("Scalar");
        if !kind.eq_ignore_ascii_case("Scalar") {
            return Err(bad(format!(
                "attribute {an}: type {kind}; only scalar fields are read"
            )));
        }
        let center = match a.attr("Center").unwrap_or("Node") {
            c if c.eq_ignore_ascii_case("Node") => Center::Node,
            c if c.eq_ignore_ascii_case("Cell") => Center::Cell,
            other => {
                return Err(bad(format!(
                    "attribute {an}: centre {other}; Node or Cell is read"
                )))
            }
        };
        let item = a
            .child("DataItem")
            .ok_or_else(|| bad(format!("attribute {an} has no DataItem")))?;
        if !item
            .attr("Format")
            .unwrap_or("")
            .eq_ignore_ascii_case("HDF")
        {
            return Err(bad(format!(
                "attribute {an}: format {:?}; only HDF data items are read",
                item.attr("Format").unwrap_or("XML")
            )));
        }
        let text = item.text.trim();
        let (file, dataset) = text
            .split_once(':')
            .ok_or_else(|| bad(format!("attribute {an}: {text:?} is not file.h5:/dataset")))?;
        attributes.push((an, center, dir.join(file.trim()), dataset.trim().to_owned()));
    }
    Ok(Uniform {
        dims,
        origin,
        spacing,
        attributes,
    })
}

/// The grids of a description, one per step.
fn grids(path: &Path, root: &Element) -> Result<Vec<Uniform>, ReadError> {
    let bad = |m: &str| ReadError::invalid(path, m);
    let xdmf = root
        .child("Xdmf")
        .ok_or_else(|| bad("not an XDMF description (no Xdmf element)"))?;
    let domain = xdmf
        .child("Domain")
        .ok_or_else(|| bad("XDMF without a Domain"))?;
    let grid = domain
        .child("Grid")
        .ok_or_else(|| bad("XDMF Domain without a Grid"))?;
    match grid.attr("GridType").unwrap_or("Uniform") {
        t if t.eq_ignore_ascii_case("Uniform") => Ok(vec![uniform(path, grid, None)?]),
        t if t.eq_ignore_ascii_case("Collection") => {
            let kind = grid.attr("CollectionType").unwrap_or("Spatial");
            if !kind.eq_ignore_ascii_case("Temporal") {
                return Err(bad(
                    "a spatial collection of grids: only one grid or a temporal collection is read",
                ));
            }
            let steps = grid
                .all("Grid")
                .map(|g| uniform(path, g, Some(grid)))
                .collect::<Result<Vec<_>, _>>()?;
            if steps.is_empty() {
                return Err(bad("a temporal collection without a grid"));
            }
            Ok(steps)
        }
        other => Err(ReadError::invalid(
            path,
            format!("grid type {other}: Uniform or a temporal Collection is read"),
        )),
    }
}

/// Opens an XDMF description, choosing the attribute `options.field` (else the first grid's
/// first).
///
/// # Errors
/// [`ReadError`] naming the description: malformed XML, a topology other than
/// `3DCoRectMesh`, a geometry other than `ORIGIN_DXDYDZ`, steps on different grids or without
/// the field, a data item that is not HDF; naming an HDF5 file whose dataset is missing or
/// has another shape; and, without the `hdf5` feature, that the datasets cannot be read.
pub fn open(path: &Path, options: &Options) -> Result<Dataset, ReadError> {
    use std::io::Read;
    let mut xml = Vec::new();
    crate::open_file(path)?
        .take(MAX_BYTES + 1)
        .read_to_end(&mut xml)
        .map_err(ReadError::io(path))?;
    if xml.len() as u64 > MAX_BYTES {
        return Err(ReadError::invalid(
            path,
            format!("a description over {MAX_BYTES} bytes"),
        ));
    }
    let steps = grids(path, &parse(path, &xml)?)?;
    let first = &steps[0];
    let fields: Vec<String> = first.attributes.iter().map(|a| a.0.clone()).collect();
    let field = match &options.field {
        Some(f) => f.clone(),
        None => fields
            .first()
            .cloned()
            .ok_or_else(|| ReadError::invalid(path, "the grid has no attribute"))?,
    };
    let mut parts = Vec::with_capacity(steps.len());
    let mut center = Center::Node;
    for (t, g) in steps.iter().enumerate() {
        if (g.dims, g.origin, g.spacing) != (first.dims, first.origin, first.spacing) {
            return Err(ReadError::invalid(
                path,
                format!("step {t} is on another grid than step 0: a series keeps one grid"),
            ));
        }
        let (_, c, file, dataset) =
            g.attributes.iter().find(|a| a.0 == field).ok_or_else(|| {
                ReadError::invalid(
                    path,
                    format!(
                        "step {t} has no attribute {field:?}; attributes here: {}",
                        fields.join(", ")
                    ),
                )
            })?;
        center = *c;
        parts.push((file.clone(), dataset.clone()));
    }
    let (mut dims, mut origin, spacing) = (first.dims, first.origin, first.spacing);
    let mut notes = Vec::new();
    if center == Center::Cell {
        if dims.contains(&1) {
            return Err(ReadError::invalid(
                path,
                format!("cell data on a grid of {dims:?} points has no cell along an axis"),
            ));
        }
        dims = dims.map(|d| d - 1);
        origin += spacing * 0.5;
        notes.push(format!(
            "{field} is cell data: its {}x{}x{} samples sit at the cells' centres, half a cell in from the origin",
            dims[0], dims[1], dims[2]
        ));
    }
    finish(
        path,
        Described {
            field,
            fields,
            dims,
            origin,
            spacing,
            notes,
            parts,
        },
    )
}

/// What a description says of the field read: its grid and each step's HDF5 dataset.
#[cfg_attr(not(feature = "hdf5"), allow(dead_code))]
struct Described {
    field: String,
    fields: Vec<String>,
    dims: [usize; 3],
    origin: Vec3,
    spacing: Vec3,
    notes: Vec<String>,
    /// Per step: the HDF5 file and the dataset's path.
    parts: Vec<(PathBuf, String)>,
}

#[cfg(feature = "hdf5")]
fn finish(path: &Path, d: Described) -> Result<Dataset, ReadError> {
    let parts = d
        .parts
        .into_iter()
        .map(|(file, dataset)| crate::hdf5::Part {
            file,
            dataset,
            index: None,
        })
        .collect();
    let parts = crate::hdf5::Parts::checked(parts, d.dims)?;
    Ok(Dataset {
        path: path.to_owned(),
        dims: d.dims,
        steps: parts.len(),
        spacing: d.spacing,
        origin: d.origin,
        field: d.field,
        fields: d.fields,
        notes: d.notes,
        source: crate::Source::Hdf5(parts),
    })
}

#[cfg(not(feature = "hdf5"))]
fn finish(path: &Path, _: Described) -> Result<Dataset, ReadError> {
    Err(ReadError::invalid(
        path,
        "its fields are HDF5 datasets: this build reads HDF5 only with `--features hdf5` \
         (needs Debian's libhdf5-dev)",
    ))
}
