"""Push simulation fields to an insitu generator-node from Python.

A NumPy field indexed ``[z, y, x]`` (C order, x fastest; ``field.shape == (nz, ny, nx)``) is
sent without a copy, with the GIL released while it is sent. Offsets and dims are (x, y, z),
as in the protocol and the C API. See ``insitu/__init__.pyi`` for every signature, and
docs/ranks-and-clients.md for an mpi4py simulation.

    import numpy as np, insitu
    with insitu.Client("127.0.0.1:50051") as c:
        c.push(step, field.astype(np.float32), sim_time=t)
"""

from ._insitu import Client, Error, RefusedError, TimeoutError, UnreachableError

__all__ = ["Client", "Error", "RefusedError", "TimeoutError", "UnreachableError"]
