#!/usr/bin/env python3
"""General lossy float compressors on a VDI's planes, at the bounds of our format 4.

Reads the planes that `cargo bench -p insitu-core --bench codec` writes with
INSITU_BENCH_PLANES=DIR (`<scene>.<plane>.f32`, `<scene>.counts.u32`, `<scene>.json`) and codes
each plane with SZ3 (PyPI `pysz`, absolute error bound) and ZFP (PyPI `zfpy`, fixed accuracy)
at the error our 8-bit format allows that quantity: depths within half a depth quantum,
colour and opacity within 0.5 / 255. The per-pixel counts go through bzip2 (lossless), as
they would beside any float compressor. Prints one Markdown row per scene: the bytes of each,
and how many times smaller than the bzip2 floats (`sigma_bzip2_f32` in the JSON, written by
the bench) they are.

Run (from the repository root):
    python3 -m venv /tmp/codec-venv && /tmp/codec-venv/bin/pip install pysz zfpy numpy
    INSITU_BENCH_PLANES=/tmp/planes cargo bench -p insitu-core --bench codec
    /tmp/codec-venv/bin/python bench/codec_compare.py /tmp/planes
"""

import bz2
import json
import pathlib
import sys
import time

import numpy as np
import pysz
import zfpy

PLANES = ["z_start", "z_end", "red", "green", "blue", "alpha"]


def sz3(values: np.ndarray, bound: float) -> int:
    config = pysz.szConfig(values.shape)
    config.errorBoundMode = pysz.szErrorBoundMode.ABS
    config.absErrorBound = bound
    compressed, _ = pysz.sz.compress(values, config)
    back, _ = pysz.sz.decompress(compressed, np.float32, values.shape)
    assert np.max(np.abs(back - values)) <= bound * 1.0001, "SZ3 broke its bound"
    return compressed.nbytes


def zfp(values: np.ndarray, bound: float) -> int:
    compressed = zfpy.compress_numpy(values, tolerance=bound)
    back = zfpy.decompress_numpy(compressed)
    assert np.max(np.abs(back - values)) <= bound * 1.0001, "ZFP broke its bound"
    return len(compressed)


def main(folder: str) -> None:
    root = pathlib.Path(folder)
    print("| scene | n | bzip2 f32 (kB) | ours 8-bit (kB) | SZ3 (kB) | × smaller | ZFP (kB) | × smaller | SZ3 / ZFP s |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for meta_path in sorted(root.glob("*.json")):
        scene = meta_path.stem
        meta = json.loads(meta_path.read_text())
        counts = bz2.compress((root / f"{scene}.counts.u32").read_bytes(), 9)
        totals = {"sz3": len(counts), "zfp": len(counts)}
        seconds = {"sz3": 0.0, "zfp": 0.0}
        for plane in PLANES:
            values = np.fromfile(root / f"{scene}.{plane}.f32", dtype="<f4")
            if values.size == 0:
                continue
            bound = meta["depth_bound"] if plane.startswith("z_") else meta["color_bound_8"]
            for name, coder in (("sz3", sz3), ("zfp", zfp)):
                t = time.perf_counter()
                totals[name] += coder(values, bound)
                seconds[name] += time.perf_counter() - t
        base = meta["sigma_bzip2_f32"]
        print(
            f"| {scene} | {meta['n']} | {base / 1e3:.1f} | {meta['sigma_8bit'] / 1e3:.1f} | "
            f"{totals['sz3'] / 1e3:.1f} | {base / totals['sz3']:.2f} | "
            f"{totals['zfp'] / 1e3:.1f} | {base / totals['zfp']:.2f} | "
            f"{seconds['sz3']:.2f} / {seconds['zfp']:.2f} |"
        )


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "/tmp/planes")
