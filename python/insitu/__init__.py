"""Push simulation fields to an insitu generator-node from Python.

A NumPy field indexed ``[z, y, x]`` (C order, x fastest; ``field.shape == (nz, ny, nx)``) is
sent without a copy, with the GIL released while it is sent. Offsets and dims are (x, y, z),
as in the protocol and the C API. See ``insitu/__init__.pyi`` for every signature, and
docs/ranks-and-clients.md for an mpi4py simulation.

    import numpy as np, insitu
    with insitu.Client("127.0.0.1:50051") as c:
        c.push(step, field.astype(np.float32), sim_time=t)

Offline, on NumPy arrays (the CPU): render (direct volume rendering, the reference),
generate (a VDI, with Vdi.render, Vdi.save, Vdi.load) and evaluate (σ, τ and q of one P_M);
Recording(path) reads a viz-node's recording: its steps as dicts, any step's picture.
"""

from ._insitu import Client, Error, Recording, RefusedError, TimeoutError, UnreachableError, Vdi
from ._insitu import evaluate
from ._insitu import generate_vdi as generate
from ._insitu import render_volume as render

__all__ = [
    "Client",
    "Error",
    "Recording",
    "RefusedError",
    "TimeoutError",
    "UnreachableError",
    "Vdi",
    "evaluate",
    "generate",
    "render",
]
