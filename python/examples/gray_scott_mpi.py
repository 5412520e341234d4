"""Gray–Scott reaction–diffusion in NumPy with mpi4py, each rank pushing its brick of v to a
generator-node through the Python client (the package insitu).

The model is the C example's (examples/mpi-gray-scott) without its noise: Du = 0.2, Dv = 0.1,
F = 0.01, k = 0.05, dt = 2, a 7-point Laplacian divided by 6, periodic boundaries, u = 1 and
v = 0 except a centred cube of side 12 (u = 0.25, v = 0.33). Every cell is computed with the
same operations whatever the decomposition, so any number of ranks gives the same field.

Decomposition: MPI.Compute_dims over a periodic 3-D Cartesian communicator (its first dim is
x); each rank owns a block and exchanges one halo layer with its six face neighbours before
every step. Every EVERY steps each rank pushes its owned points plus the first halo plane on
the upper side of each axis where it is not the last block, so neighbouring bricks share their
boundary plane.

    mpirun -np 4 python gray_scott_mpi.py GENERATOR_ADDR N STEPS EVERY
"""

import sys

import numpy as np
from mpi4py import MPI

import insitu

DU, DV, FEED, KILL, DT = 0.2, 0.1, 0.01, 0.05, 2.0
SEED_HALF = 6


def exchange(f, cart):
    """Fills f's halo layers (f is indexed [z, y, x]) from the face neighbours."""
    for dim in range(3):
        axis = 2 - dim  # the communicator's dim 0 is x, the array's last axis
        down, up = cart.Shift(dim, 1)
        n = f.shape[axis]
        send = np.ascontiguousarray(np.take(f, [n - 2], axis=axis))
        recv = np.empty_like(send)
        cart.Sendrecv(send, dest=up, recvbuf=recv, source=down)
        put(f, axis, 0, recv)
        send = np.ascontiguousarray(np.take(f, [1], axis=axis))
        cart.Sendrecv(send, dest=down, recvbuf=recv, source=up)
        put(f, axis, n - 1, recv)


def put(f, axis, at, plane):
    index = [slice(None)] * 3
    index[axis] = slice(at, at + 1)
    f[tuple(index)] = plane


def step(u, v):
    """One explicit step over the owned cells."""
    c = (slice(1, -1),) * 3

    def lap(f):
        return (
            (((((f[:-2, 1:-1, 1:-1] + f[2:, 1:-1, 1:-1]) + f[1:-1, :-2, 1:-1]) + f[1:-1, 2:, 1:-1])
              + f[1:-1, 1:-1, :-2]) + f[1:-1, 1:-1, 2:])
            - 6.0 * f[c]
        ) / 6.0

    tu, tv = u[c].copy(), v[c].copy()
    uvv = tu * tv * tv
    du = DU * lap(u) - uvv + FEED * (1.0 - tu)
    dv = DV * lap(v) + uvv - (FEED + KILL) * tv
    u[c] = tu + du * DT
    v[c] = tv + dv * DT


def main():
    if len(sys.argv) != 5:
        sys.exit("usage: gray_scott_mpi.py GENERATOR_ADDR N STEPS EVERY")
    addr, n, steps, every = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    world = MPI.COMM_WORLD
    dims = MPI.Compute_dims(world.size, 3)
    cart = world.Create_cart(dims, periods=[True] * 3)
    coords = cart.Get_coords(cart.rank)
    lo = [c * n // d for c, d in zip(coords, dims)]  # x, y, z
    owned = [(c + 1) * n // d - l for c, d, l in zip(coords, dims, lo)]
    brick = [o + (1 if c + 1 < d else 0) for o, c, d in zip(owned, coords, dims)]
    # Global indices of the block with its halo, per array axis (z, y, x), wrapped.
    idx = [np.arange(lo[a] - 1, lo[a] + owned[a] + 1) % n for a in (2, 1, 0)]
    gz, gy, gx = np.meshgrid(*idx, indexing="ij")
    inside = np.ones(gz.shape, bool)
    for g in (gx, gy, gz):
        inside &= (g >= n // 2 - SEED_HALF) & (g < n // 2 + SEED_HALF)
    u = np.where(inside, 0.25, 1.0)
    v = np.where(inside, 0.33, 0.0)
    failed = 0
    try:
        client = insitu.Client(addr)
    except insitu.Error as e:
        print(f"rank {cart.rank}: {e}", file=sys.stderr)
        client, failed = None, 1
    failed = cart.allreduce(failed, op=MPI.MAX)
    for s in range(1, steps + 1):
        if failed:
            break
        exchange(u, cart)
        exchange(v, cart)
        step(u, v)
        if s % every == 0:
            exchange(v, cart)
            field = np.ascontiguousarray(
                v[1 : 1 + brick[2], 1 : 1 + brick[1], 1 : 1 + brick[0]], dtype=np.float32
            )
            try:
                client.push(s, field, offset=tuple(lo), global_dims=(n, n, n), rank=cart.rank,
                            world_size=cart.size, sim_time=s * DT)
            except (insitu.Error, ValueError, TypeError) as e:
                print(f"rank {cart.rank}: push: {e}", file=sys.stderr)
                failed = 1
        # One rank failing stops all: a simulation would not go on half-observed.
        failed = cart.allreduce(failed, op=MPI.MAX)
    if client is not None:
        try:
            client.close(timeout=600)
        except insitu.Error as e:
            print(f"rank {cart.rank}: close: {e}", file=sys.stderr)
            failed = 1
    failed = cart.allreduce(failed, op=MPI.MAX)
    if cart.rank == 0 and not failed:
        print(f"gray-scott {n}^3, {cart.size} ranks ({dims[0]}x{dims[1]}x{dims[2]}), "
              f"{steps} steps: pushed every {every}")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
