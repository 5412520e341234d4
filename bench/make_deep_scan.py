"""Write the suite's low-opacity, deep-ray volume: the shared stent scan (128x128x256 int16)
mapped to u8 over its range [0, 2000] and resampled trilinearly (voxel centres at both ends
kept) to 301x370x316 voxels, the size of a scan nobody tuned for. With `deep_scan.json`, whose
opacity stays at 1-4 % per voxel over all of the tissue's values, rays stay semi-transparent
to the far side: little early termination and few empty cells, the regime where the marcher's
cost per sample shows.

    bench/.venv/bin/python bench/make_deep_scan.py SHARED_DATA_DIR OUT_DIR
"""

import os
import sys

import numpy as np

SOURCE = "stent_128x128x256_int16.raw"
SOURCE_DIMS = (128, 128, 256)  # x, y, z; x fastest in the file
DIMS = (301, 370, 316)
NAME = "deepscan_301x370x316_uint8.raw"


def resample(a, axis, n):
    """`a` linearly interpolated along `axis` to `n` samples, the end samples kept."""
    m = a.shape[axis]
    x = np.linspace(0.0, m - 1.0, n)
    lo = np.minimum(x.astype(np.int64), m - 2)
    f = (x - lo).astype(np.float32)
    shape = [1] * a.ndim
    shape[axis] = n
    f = f.reshape(shape)
    return np.take(a, lo, axis=axis) * (1 - f) + np.take(a, lo + 1, axis=axis) * f


def main():
    src_dir, out_dir = sys.argv[1], sys.argv[2]
    out = os.path.join(out_dir, NAME)
    if os.path.exists(out):
        print(out)
        return
    nx, ny, nz = SOURCE_DIMS
    a = np.fromfile(os.path.join(src_dir, SOURCE), dtype="<i2").reshape(nz, ny, nx)
    a = np.clip(a.astype(np.float32) * (255.0 / 2000.0), 0, 255)
    # Array axes are (z, y, x).
    for axis, n in ((2, DIMS[0]), (1, DIMS[1]), (0, DIMS[2])):
        a = resample(a, axis, n)
    os.makedirs(out_dir, exist_ok=True)
    tmp = out + ".tmp"
    np.rint(a).astype(np.uint8).tofile(tmp)
    os.replace(tmp, out)
    print(out)


if __name__ == "__main__":
    main()
