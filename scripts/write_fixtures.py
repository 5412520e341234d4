"""Writes the readers' test files with the reference libraries: VTK (vtkXMLImageDataWriter,
vtkStructuredPointsWriter), pynrrd, netCDF4 (classic and netCDF-4), h5py (with XDMF
descriptions), ADIOS2 (BP5, several blocks per step) and openPMD-api (openPMD over BP5), from synthetic fields with several arrays, a
non-zero origin, anisotropic spacing, packed integers, fill values, big-endian and compressed
variants. Beside each the expected samples as raw files (x fastest, little-endian) and a
manifest.json that says, for every file, the field, the grid (dims, origin, spacing, steps), the
bounds VTK's own reader reports where VTK reads the format, and the raw file the samples must
equal bit for bit. Run by scripts/write-fixtures.sh (which makes the venv).

    python write_fixtures.py OUTDIR
"""

import json
import os
import sys
import warnings

import numpy as np

DIMS = (12, 10, 8)  # x, y, z
ORIGIN = (1.5, -2.0, 10.0)
SPACING = (0.5, 1.0, 2.5)
STEPS = 3


def fields(t=0):
    """The arrays of step t, each indexed [z, y, x] (C order, x fastest)."""
    z, y, x = np.meshgrid(*(np.arange(n, dtype=np.float64) for n in DIMS[::-1]), indexing="ij")
    r = np.sqrt((x - 5.5) ** 2 + (y - 4.5) ** 2 + (z - 3.5) ** 2)
    rho = np.maximum(0.0, 4.0 + t - r).astype(np.float32)
    rho[0, 0, :3] = np.float32(np.nan) if t else rho[0, 0, :3]
    temp = (np.sin(x * 0.3 + t) * np.cos(y * 0.2) * 1e3 + z * 1e-3).astype(np.float64)
    mask = ((x + y + z + t) % 3 == 0).astype(np.uint8) * 200
    level = ((x - y) * 300 + z * 7 - 1000 + t).astype(np.int16)
    return {"rho": rho, "temp": temp, "mask": mask, "level": level}


NAMES = {np.float32: "float32", np.float64: "float64", np.uint8: "uint8", np.int16: "int16"}


def expect(out, name, arrays, dims=DIMS):
    """Writes `arrays` (one per step, each of `dims` x, y, z) as a raw file named with its dims,
    steps and type (as the raw reader takes it, all as float32 when mixed); returns its name."""
    a = np.stack(arrays) if len(arrays) > 1 else arrays[0]
    kind = NAMES[a.dtype.newbyteorder("=").type]
    steps = f"x{len(arrays)}" if len(arrays) > 1 else ""
    fname = f"expect_{name}_{dims[0]}x{dims[1]}x{dims[2]}{steps}_{kind}.raw"
    a.astype(a.dtype.newbyteorder("<")).tofile(os.path.join(out, fname))
    return fname


def as_read(reader, name):
    """The array `name` as VTK's own reader returns it, indexed [z, y, x]: the source itself
    for binary files, and for ASCII ones what the text holds (VTK writes about 6 digits)."""
    from vtk.util import numpy_support

    a = numpy_support.vtk_to_numpy(reader.GetOutput().GetPointData().GetArray(name))
    return a.reshape(DIMS[::-1])


def vtk_files(out, entries):
    import vtk
    from vtk.util import numpy_support

    f = fields()
    image = vtk.vtkImageData()
    image.SetDimensions(*DIMS)
    image.SetOrigin(*ORIGIN)
    image.SetSpacing(*SPACING)
    for name in ["rho", "temp", "mask", "level"]:
        arr = numpy_support.numpy_to_vtk(f[name].ravel(), deep=True)
        arr.SetName(name)
        image.GetPointData().AddArray(arr)
    image.GetPointData().SetActiveScalars("rho")
    variants = {
        "appended_raw_zlib": dict(mode="appended", encode=False, zlib=True, header=64),
        "appended_base64": dict(mode="appended", encode=True, zlib=False, header=32),
        "binary_zlib": dict(mode="binary", zlib=True, header=32),
        "binary": dict(mode="binary", zlib=False, header=64),
        "ascii": dict(mode="ascii", zlib=False, header=32),
        "bigendian": dict(mode="appended", encode=False, zlib=False, header=32, big=True),
    }
    for tag, v in variants.items():
        path = os.path.join(out, f"vti_{tag}.vti")
        w = vtk.vtkXMLImageDataWriter()
        w.SetFileName(path)
        w.SetInputData(image)
        {"appended": w.SetDataModeToAppended, "binary": w.SetDataModeToBinary,
         "ascii": w.SetDataModeToAscii}[v["mode"]]()
        if v["mode"] == "appended":
            w.SetEncodeAppendedData(1 if v.get("encode") else 0)
        if v["zlib"]:
            w.SetCompressorTypeToZLib()
        else:
            w.SetCompressorTypeToNone()
        w.SetHeaderTypeToUInt64() if v["header"] == 64 else w.SetHeaderTypeToUInt32()
        if v.get("big"):
            w.SetByteOrderToBigEndian()
        assert w.Write() == 1, path
        r = vtk.vtkXMLImageDataReader()
        r.SetFileName(path)
        r.Update()
        bounds = list(r.GetOutput().GetBounds())
        for name in ["rho", "temp", "mask", "level"]:
            entries.append(dict(file=os.path.basename(path), field=name, steps=1, bounds=bounds,
                                expect=expect(out, f"{tag}_{name}", [as_read(r, name)])))
    for tag, binary in [("ascii", False), ("binary", True)]:
        path = os.path.join(out, f"legacy_{tag}.vtk")
        w = vtk.vtkStructuredPointsWriter()
        w.SetFileName(path)
        w.SetInputData(image)
        w.SetFileTypeToBinary() if binary else w.SetFileTypeToASCII()
        assert w.Write() == 1, path
        r = vtk.vtkStructuredPointsReader()
        r.SetFileName(path)
        r.Update()
        bounds = list(r.GetOutput().GetBounds())
        # VTK writes the active scalars as SCALARS (the others as FIELD data).
        entries.append(dict(file=os.path.basename(path), field="rho", steps=1, bounds=bounds,
                            expect=expect(out, f"legacy_{tag}_rho", [as_read(r, "rho")])))


def nrrd_files(out, entries):
    import nrrd

    f = fields()
    header = {
        "space dimension": 3,
        "space directions": np.diag(SPACING),
        "space origin": np.array(ORIGIN),
    }
    cases = [
        ("nrrd_raw.nrrd", "rho", dict(encoding="raw", endian="little"), False),
        ("nrrd_gzip.nrrd", "level", dict(encoding="gzip", endian="little"), False),
        ("nrrd_detached_be.nhdr", "temp", dict(encoding="raw", endian="big"), True),
        ("nrrd_u8.nrrd", "mask", dict(encoding="gzip"), False),
    ]
    for name, field, extra, detached in cases:
        h = dict(header, **extra)
        data = f[field]
        if extra.get("endian") == "big":
            # pynrrd writes the array's own byte order.
            data = data.astype(data.dtype.newbyteorder(">"))
        # pynrrd takes Fortran order: the array indexed [x, y, z].
        nrrd.write(os.path.join(out, name), data.transpose(2, 1, 0), h, index_order="F",
                   detached_header=detached)
        entries.append(dict(file=name, field=None, steps=1, bounds=None,
                            expect=expect(out, field, [f[field]])))


def netcdf_files(out, entries):
    import netCDF4

    steps = [fields(t) for t in range(STEPS)]
    scale, offset = np.float32(0.05), np.float32(3.0)
    # netCDF-4 variants (HDF5 underneath) are read through netCDF-C: `needs` names the feature.
    for fmt, tag, needs in [("NETCDF3_CLASSIC", "classic", None),
                            ("NETCDF3_64BIT_OFFSET", "64bit", None),
                            ("NETCDF3_64BIT_DATA", "cdf5", None),
                            ("NETCDF4", "nc4", "netcdf4"),
                            ("NETCDF4_CLASSIC", "nc4classic", "netcdf4")]:
        name = f"nc_{tag}.nc"
        ds = netCDF4.Dataset(os.path.join(out, name), "w", format=fmt)
        # netCDF-4: deflated and shuffled in chunks, rho big-endian.
        nc4 = dict(zlib=True, complevel=4, shuffle=True, chunksizes=(1, 4, 5, 6)) if needs else {}
        ds.createDimension("time", None)
        for axis, n in zip("zyx", DIMS[::-1]):
            ds.createDimension(axis, n)
        for a, (axis, n) in enumerate(zip("xyz", DIMS)):
            c = ds.createVariable(axis, "f8", (axis,))
            c.units = "m"
            c[:] = ORIGIN[a] + SPACING[a] * np.arange(n)
        ds.createVariable("time", "f8", ("time",))[:] = np.arange(STEPS) * 10.0
        ds.createVariable("surface", "f4", ("y", "x"))[:] = np.zeros(DIMS[1::-1])
        rho = ds.createVariable("rho", "f4", ("time", "z", "y", "x"), fill_value=np.float32(-9e33),
                                **nc4, **(dict(endian="big") if needs else {}))
        level = ds.createVariable("level", "i2", ("time", "z", "y", "x"),
                                  fill_value=np.int16(-32767), **nc4)
        level.scale_factor, level.add_offset = scale, offset
        level.set_auto_maskandscale(False)
        for t, f in enumerate(steps):
            r = f["rho"].copy()
            r[np.isnan(r)] = np.float32(-9e33)
            rho[t] = r
            packed = f["level"].copy()
            packed[1, 2, 3] = -32767  # a fill value
            level[t] = packed
        ds.close()
        exp_rho = [f["rho"] for f in steps]
        exp_level = []
        for f in steps:
            p = f["level"].copy()
            v = (p.astype(np.float64) * np.float64(scale) + np.float64(offset)).astype(np.float32)
            v[1, 2, 3] = np.float32(np.nan)
            exp_level.append(v)
        entries.append(dict(file=name, field="rho", steps=STEPS, bounds=None, needs=needs,
                            expect=expect(out, f"{tag}_rho", exp_rho)))
        entries.append(dict(file=name, field="level", steps=STEPS, bounds=None, needs=needs,
                            expect=expect(out, f"{tag}_level", exp_level)))


def hdf5_files(out, entries):
    """HDF5 written by h5py, bare (read on a unit grid) and described by XDMF (placed on the
    grid; a temporal collection of per-step datasets, node and cell data)."""
    import h5py

    steps = [fields(t) for t in range(STEPS)]
    unit = dict(dims=list(DIMS), origin=[0.0, 0.0, 0.0], spacing=[1.0, 1.0, 1.0])
    with h5py.File(os.path.join(out, "h5_series.h5"), "w") as f:
        g = f.create_group("fields")
        g.create_dataset("rho", data=np.stack([s["rho"] for s in steps]), compression="gzip",
                         shuffle=True, chunks=(1, 4, 5, 6))
        g.create_dataset("temp", data=np.stack([s["temp"] for s in steps]).astype(">f8"))
        f.create_dataset("level", data=steps[0]["level"])
        f.create_dataset("mask", data=steps[0]["mask"], compression="gzip", shuffle=True)
        f.create_dataset("surface", data=np.zeros(DIMS[1::-1], dtype=np.float32))
    for field, series in [("/fields/rho", True), ("/fields/temp", True), ("/level", False),
                          ("/mask", False)]:
        key = field.rsplit("/", 1)[1]
        arrays = [s[key] for s in steps] if series else [steps[0][key]]
        entries.append(dict(file="h5_series.h5", field=field, steps=len(arrays), bounds=None,
                            needs="hdf5", grid=unit,
                            expect=expect(out, f"h5_{key}", arrays)))
    # Per-step datasets; cell data one fewer per axis.
    cells = [s["rho"][1:, 1:, 1:] * 0.5 + np.float32(t) for t, s in enumerate(steps)]
    with h5py.File(os.path.join(out, "h5_steps.h5"), "w") as f:
        for t, s in enumerate(steps):
            f.create_dataset(f"t{t}/rho", data=s["rho"])
            f.create_dataset(f"t{t}/cellrho", data=cells[t])
            f.create_dataset(f"t{t}/mask", data=s["mask"])
    nx, ny, nz = DIMS
    geometry = f"""<Topology TopologyType="3DCoRectMesh" Dimensions="{nz} {ny} {nx}"/>
      <Geometry GeometryType="ORIGIN_DXDYDZ">
        <DataItem Format="XML" Dimensions="3">{ORIGIN[2]} {ORIGIN[1]} {ORIGIN[0]}</DataItem>
        <DataItem Format="XML" Dimensions="3">{SPACING[2]} {SPACING[1]} {SPACING[0]}</DataItem>
      </Geometry>"""

    def attribute(name, center, dims, dataset):
        return f"""<Attribute Name="{name}" AttributeType="Scalar" Center="{center}">
        <DataItem Format="HDF" NumberType="Float" Precision="4" Dimensions="{dims}">h5_steps.h5:{dataset}</DataItem>
      </Attribute>"""

    grids = "".join(f"""
    <Grid Name="step{t}" GridType="Uniform">
      <Time Value="{t * 10.0}"/>
      {geometry}
      {attribute("rho", "Node", f"{nz} {ny} {nx}", f"/t{t}/rho")}
      {attribute("cellrho", "Cell", f"{nz - 1} {ny - 1} {nx - 1}", f"/t{t}/cellrho")}
    </Grid>""" for t in range(STEPS))
    with open(os.path.join(out, "xdmf_series.xmf"), "w") as fh:
        fh.write(f"""<?xml version="1.0" ?>
<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>
<Xdmf Version="3.0">
  <Domain>
    <Grid Name="series" GridType="Collection" CollectionType="Temporal">{grids}
    </Grid>
  </Domain>
</Xdmf>
""")
    with open(os.path.join(out, "xdmf_one.xmf"), "w") as fh:
        fh.write(f"""<?xml version="1.0" ?>
<Xdmf Version="2.0">
  <Domain>
    <Grid Name="mesh" GridType="Uniform">
      {geometry}
      {attribute("mask", "Node", f"{nz} {ny} {nx}", "/t0/mask")}
    </Grid>
  </Domain>
</Xdmf>
""")
    entries.append(dict(file="xdmf_series.xmf", field="rho", steps=STEPS, bounds=None,
                        needs="hdf5", expect=expect(out, "xdmf_rho", [s["rho"] for s in steps])))
    half = [o + d / 2 for o, d in zip(ORIGIN, SPACING)]
    entries.append(dict(file="xdmf_series.xmf", field="cellrho", steps=STEPS, bounds=None,
                        needs="hdf5",
                        grid=dict(dims=[n - 1 for n in DIMS], origin=half, spacing=list(SPACING)),
                        expect=expect(out, "xdmf_cellrho", cells, dims=[n - 1 for n in DIMS])))
    entries.append(dict(file="xdmf_one.xmf", field=None, steps=1, bounds=None, needs="hdf5",
                        expect=expect(out, "xdmf_mask", [steps[0]["mask"]])))


def adios2_files(out, entries):
    """ADIOS2 BP5 written through ADIOS2's own Python API (the PyPI wheel): each step's global
    arrays put as two blocks split in z, as two writer ranks would put them (disjoint, no
    shared plane), grid attributes beside; and a file of what the reader refuses."""
    import adios2
    from adios2 import bindings

    steps = [fields(t) for t in range(STEPS)]
    nx, ny, nz = DIMS
    cut = nz // 2
    io = adios2.Adios().declare_io("fixtures")
    io.set_engine("BP5")
    shape = [nz, ny, nx]
    variables = {k: io.define_variable(k, steps[0][k][:cut], shape, [0, 0, 0], [cut, ny, nx])
                 for k in ("rho", "temp", "mask", "level")}
    io.define_attribute("spacing", np.array(SPACING, dtype=np.float64))
    io.define_attribute("origin", np.array(ORIGIN, dtype=np.float64))
    engine = io.open(os.path.join(out, "adios2_series.bp"), bindings.Mode.Write)
    for s in steps:
        engine.begin_step()
        for k, v in variables.items():
            for lo, hi in ((0, cut), (cut, nz)):
                v.set_selection([[lo, 0, 0], [hi - lo, ny, nx]])
                engine.put(v, np.ascontiguousarray(s[k][lo:hi]), bindings.Mode.Sync)
        engine.end_step()
    engine.close()
    for k in ("rho", "temp", "mask", "level"):
        entries.append(dict(file="adios2_series.bp", field=k, steps=STEPS, bounds=None,
                            needs="adios2",
                            expect=expect(out, f"adios2_{k}", [s[k] for s in steps])))
    # What a volume is not: a 2-D array, a value, strings, a 3-D complex array.
    io = adios2.Adios().declare_io("refused")
    io.set_engine("BP5")
    flat = np.zeros((ny, nx), dtype=np.float32)
    plane = io.define_variable("plane", flat, [ny, nx], [0, 0], [ny, nx])
    time = io.define_variable("time", np.zeros(1))
    waves = np.zeros((2, 2, 2), dtype=np.complex64)
    wave = io.define_variable("wave", waves, [2, 2, 2], [0, 0, 0], [2, 2, 2])
    engine = io.open(os.path.join(out, "adios2_refused.bp"), bindings.Mode.Write)
    engine.begin_step()
    engine.put(plane, flat, bindings.Mode.Sync)
    engine.put(time, np.array([1.5]), bindings.Mode.Sync)
    engine.put(wave, waves, bindings.Mode.Sync)
    engine.end_step()
    engine.close()


def openpmd_files(out, entries):
    """openPMD series written by openPMD-api (the PyPI wheel `openpmd-api`) through its ADIOS2
    backend (BP5), in each iteration encoding: iterations as groups of one file, as files, and
    as ADIOS2 steps of one variable. The meshes' axes are labelled in several orders, so that
    the reader must honour axisLabels, dataOrder, gridSpacing, gridGlobalOffset and position
    to give the samples and grid of the other readers; and a file of meshes it refuses."""
    import openpmd_api as io

    nx, ny, nz = DIMS
    spacing_zyx = list(SPACING[::-1])
    origin_zyx = list(ORIGIN[::-1])

    def scalar(mesh, a):
        rc = mesh[io.Mesh_Record_Component.SCALAR]
        rc.reset_dataset(io.Dataset(a.dtype, a.shape))
        rc.store_chunk(np.ascontiguousarray(a))

    def meshes(iteration, f):
        # rho: C order, labelled z, y, x — the arrays as the other readers' files hold them.
        rho = iteration.meshes["rho"]
        rho.axis_labels = ["z", "y", "x"]
        rho.grid_spacing = spacing_zyx
        rho.grid_global_offset = origin_zyx
        scalar(rho, f["rho"])
        # E: C order labelled x, y, z, so each component is stored [x][y][z] (transposed);
        # its samples sit half a cell along x into their cells (position), which the offset
        # takes back, so the grid is the other readers'.
        e = iteration.meshes["E"]
        e.axis_labels = ["x", "y", "z"]
        e.grid_spacing = list(SPACING)
        e.grid_global_offset = [ORIGIN[0] - 0.5 * SPACING[0], ORIGIN[1], ORIGIN[2]]
        for comp, key in (("x", "temp"), ("y", "level"), ("z", "mask")):
            c = e[comp]
            c.set_attribute("position", [0.5, 0.0, 0.0])  # as double, as C++ writers store it
            a = f[key].transpose(2, 1, 0)
            c.reset_dataset(io.Dataset(a.dtype, a.shape))
            c.store_chunk(np.ascontiguousarray(a))
        # level_f: Fortran order labelled x, y, z: the array ADIOS2 presents is [z][y][x].
        lf = iteration.meshes["level_f"]
        lf.data_order = "F"
        lf.axis_labels = ["x", "y", "z"]
        lf.grid_spacing = list(SPACING)
        lf.grid_global_offset = list(ORIGIN)
        scalar(lf, f["level"])

    steps = [fields(t) for t in range(STEPS)]
    # Iterations 0, 100, 200 as groups of one file.
    series = io.Series(os.path.join(out, "openpmd_groups.bp5"), io.Access.create)
    for t, f in enumerate(steps):
        it = series.iterations[100 * t]
        meshes(it, f)
        series.flush()
        it.close()
    series.close()
    # The same as one file per iteration, and as steps of one variable.
    series = io.Series(os.path.join(out, "openpmd_files_%T.bp5"), io.Access.create)
    for t, f in enumerate(steps):
        it = series.iterations[t]
        meshes(it, f)
        it.close()
    series.close()
    series = io.Series(os.path.join(out, "openpmd_steps.bp5"), io.Access.create,
                       '{"iteration_encoding": "variable_based"}')
    for t, f in enumerate(steps):
        it = series.write_iterations()[t]
        meshes(it, f)
        it.close()
    series.close()
    for key, mesh in (("rho", "rho"), ("temp", "E/x"), ("level", "E/y"), ("mask", "E/z"),
                      ("level", "level_f")):
        exp = expect(out, f"adios2_{key}", [s[key] for s in steps])
        for file in ("openpmd_groups.bp5", "openpmd_steps.bp5", "openpmd_files_%T.bp5"):
            entries.append(dict(file=file, field=mesh, steps=STEPS, bounds=None,
                                needs="adios2", expect=exp))
        entries.append(dict(file="openpmd_files_1.bp5", field=mesh, steps=1, bounds=None,
                            needs="adios2",
                            expect=expect(out, f"openpmd_{key}_1", [steps[1][key]])))
    # What is not a volume: a 2-D mesh, a thetaMode mesh, labels that are not x, y, z.
    series = io.Series(os.path.join(out, "openpmd_refused.bp5"), io.Access.create)
    it = series.iterations[0]
    cube = np.zeros((2, 3, 4), dtype=np.float32)
    scalar(it.meshes["plane"], np.zeros((3, 4), dtype=np.float32))
    er = it.meshes["Er"]
    er.geometry = io.Geometry.thetaMode
    er.axis_labels = ["r", "z"]
    scalar(er, cube)
    odd = it.meshes["odd"]
    odd.axis_labels = ["a", "b", "c"]
    scalar(odd, cube)
    series.flush()
    it.close()
    series.close()


def main():
    # netCDF4 warns that a native fill value meets a big-endian variable; it stores it right.
    warnings.filterwarnings("ignore", "endian-ness of dtype")
    out = sys.argv[1]
    os.makedirs(out, exist_ok=True)
    entries = []
    vtk_files(out, entries)
    nrrd_files(out, entries)
    netcdf_files(out, entries)
    hdf5_files(out, entries)
    adios2_files(out, entries)
    openpmd_files(out, entries)
    grid = dict(dims=list(DIMS), origin=list(ORIGIN), spacing=list(SPACING))
    with open(os.path.join(out, "manifest.json"), "w") as fh:
        json.dump(dict(grid=grid, files=entries), fh, indent=1)
    print(f"wrote {len(entries)} fixture entries to {out}")


if __name__ == "__main__":
    main()
