"""An ADIOS2 writer as a simulation has one, through ADIOS2's own Python API (the PyPI
wheel): each step's field is put as the blocks of a global array that ranks would put,
split in z without a shared plane, then the step ends. The fields are read from raw files
(float32, x fastest) that the test wrote, so that the same samples can be pushed through our
client too.

    python adios2_writer.py NAME DIR NX NY NZ STEPS [--engine SST|BP5] [--blocks K]
                            [--own-block B] [--readers R] [--vanish-after S] [--openpmd]
                            [--synthetic] [--param KEY=VALUE ...]

NAME is the stream (SST: the contact file NAME.sst) or the BP file; DIR holds step_T.raw.
--vanish-after S ends the process without closing the stream a second after step S, as a
simulation that crashes while computing the next step would (an SST step lives in the
writer's memory until its readers have fetched it: a step a reader had not fetched dies with
the writer).
--own-block B puts block B of the K alone, as one of K writer processes that each open a
stream of their own (ADIOS2 on MPI_COMM_SELF) would.
--param passes an SST engine parameter (e.g. WANDataTransport=enet).
--synthetic writes (i mod 977) + t in place of step_T.raw, for the throughput bench.
--openpmd writes the field as openPMD-api does (the PyPI wheel `openpmd-api`), as the mesh
`density` of each iteration, labelled x, y, z in C order (so stored [x][y][z], transposed from
the raw files' order), in blocks split along x.
"""

import argparse
import os
import sys
import time

import adios2
import numpy as np
from adios2 import bindings


def main():
    p = argparse.ArgumentParser()
    p.add_argument("name")
    p.add_argument("dir")
    p.add_argument("dims", type=int, nargs=3)
    p.add_argument("steps", type=int)
    p.add_argument("--engine", default="SST")
    p.add_argument("--blocks", type=int, default=2)
    p.add_argument("--own-block", type=int, default=None)
    p.add_argument("--readers", type=int, default=1)
    p.add_argument("--vanish-after", type=int, default=None)
    p.add_argument("--openpmd", action="store_true")
    p.add_argument("--synthetic", action="store_true")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE")
    a = p.parse_args()
    if a.openpmd:
        return openpmd(a)
    nx, ny, nz = a.dims
    io = adios2.Adios().declare_io("simulation")
    io.set_engine(a.engine)
    if a.engine.upper() == "SST":
        io.set_parameters({"RendezvousReaderCount": str(a.readers), "QueueLimit": "4",
                           **dict(kv.split("=", 1) for kv in a.param)})
    cuts = [nz * k // a.blocks for k in range(a.blocks + 1)]
    shape = [nz, ny, nx]
    var = io.define_variable("density", np.zeros((1, ny, nx), dtype=np.float32), shape,
                             [0, 0, 0], [1, ny, nx])
    io.define_attribute("spacing", np.array([1.0, 1.0, 1.0]))
    io.define_attribute("origin", np.array([0.0, 0.0, 0.0]))
    engine = io.open(a.name, bindings.Mode.Write)
    base = (np.arange(nx * ny * nz, dtype=np.float32) % 977).reshape(nz, ny, nx)
    for t in range(a.steps):
        if a.synthetic:
            field = base + np.float32(t)
        else:
            field = np.fromfile(os.path.join(a.dir, f"step_{t}.raw"), dtype="<f4").reshape(nz, ny, nx)
        engine.begin_step()
        for b, (lo, hi) in enumerate(zip(cuts, cuts[1:])):
            if a.own_block is not None and b != a.own_block:
                continue
            var.set_selection([[lo, 0, 0], [hi - lo, ny, nx]])
            engine.put(var, np.ascontiguousarray(field[lo:hi]), bindings.Mode.Sync)
        engine.end_step()
        print(f"wrote step {t}", flush=True)
        if a.vanish_after is not None and t + 1 >= a.vanish_after:
            time.sleep(1.0)
            os._exit(0)
    engine.close()
    return 0


def openpmd(a):
    import json

    import openpmd_api as io

    nx, ny, nz = a.dims
    engine = {"type": a.engine.lower()}
    if a.engine.upper() == "SST":
        # Under SST's default BP5 marshalling openPMD's string-array attributes (axisLabels)
        # arrive empty; BP marshalling carries them.
        engine["parameters"] = {"RendezvousReaderCount": str(a.readers), "QueueLimit": "4",
                                "MarshalMethod": "BP"}
    series = io.Series(a.name + (".sst" if a.engine.upper() == "SST" else ""),
                       io.Access.create, json.dumps({"adios2": {"engine": engine}}))
    cuts = [nx * k // a.blocks for k in range(a.blocks + 1)]
    for t in range(a.steps):
        field = np.fromfile(os.path.join(a.dir, f"step_{t}.raw"), dtype="<f4").reshape(nz, ny, nx)
        xyz = field.transpose(2, 1, 0)
        it = series.write_iterations()[t]
        mesh = it.meshes["density"]
        mesh.axis_labels = ["x", "y", "z"]
        mesh.grid_spacing = [1.0, 1.0, 1.0]
        mesh.grid_global_offset = [0.0, 0.0, 0.0]
        rc = mesh[io.Mesh_Record_Component.SCALAR]
        rc.reset_dataset(io.Dataset(xyz.dtype, xyz.shape))
        for lo, hi in zip(cuts, cuts[1:]):
            rc.store_chunk(np.ascontiguousarray(xyz[lo:hi]), [lo, 0, 0], [hi - lo, ny, nz])
        it.close()
        print(f"wrote step {t}", flush=True)
    series.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
