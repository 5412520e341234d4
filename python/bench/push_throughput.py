"""The Python client's push throughput: PUSHES pushes of an N³ float32 field to a
generator-node, after one warm-up push; prints GB/s (a push returns once the node has queued
the step), then pushes a ZERO_COPY_MIB array once and prints how much the process's peak RSS
grew (a copy would add the array's size). Run by `cargo bench -p insitu-e2e --bench pipeline`
beside the Rust, C and Fortran clients.

    python push_throughput.py GENERATOR_ADDR N PUSHES [ZERO_COPY_MIB]
"""

import resource
import sys
import time

import numpy as np

import insitu


def main():
    addr, n, pushes = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    big_mib = int(sys.argv[4]) if len(sys.argv) > 4 else 0
    field = (np.arange(n**3, dtype=np.int64) % 977).astype(np.float32).reshape(n, n, n)
    with insitu.Client(addr) as c:
        c.push(0, field)
        t = time.perf_counter()
        for k in range(1, pushes + 1):
            c.push(k, field)
        secs = time.perf_counter() - t
        print(f"ingest (Python client): {pushes} pushes of {field.nbytes >> 20} MiB in "
              f"{secs:.2f} s = {pushes * field.nbytes / secs / 1e9:.2f} GB/s")
        if big_mib:
            big = np.ones((big_mib, 1024, 256), np.float32)  # big_mib MiB
            before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
            c.push(pushes + 1, big, global_dims=(256, 1024, big_mib))
            grew = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - before
            print(f"zero copy (Python client): a {big.nbytes >> 20} MiB push raised peak RSS by "
                  f"{grew / 2**20:.1f} MiB ({100 * grew / big.nbytes:.1f} % of the array)")


if __name__ == "__main__":
    main()
