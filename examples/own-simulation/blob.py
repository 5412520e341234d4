import sys
import numpy as np
import insitu

n, steps = 64, 10
z, y, x = np.mgrid[0:n, 0:n, 0:n].astype(np.float32)     # field[z, y, x]: x varies fastest
with insitu.Client(sys.argv[1]) as client:                 # the generator-node's address
    for step in range(steps):
        cx = 16.0 + 2.0 * step                             # a blob moving along x
        r2 = (x - cx) ** 2 + (y - 32.0) ** 2 + (z - 32.0) ** 2
        field = np.exp(-r2 / 128.0).astype(np.float32)
        client.push(step, field, sim_time=0.1 * step)      # returns once the node holds it
# leaving the block flushed: every step is stored
print(f"pushed {steps} steps of {n}^3")
