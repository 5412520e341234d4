"""The offline functions on NumPy arrays (run by tests/tests/e2e/python.rs):

    python offline.py WORKDIR

Checks against invariants: a VDI rendered from its own camera is close to direct rendering
(≥ 25 dB), a saved VDI loads back to the same pictures (as floats) or within 45 dB of them
(at 8 bits, the default) and its file is σ as evaluate measures it, the volume's dtype does not change the picture, and bad input raises by name."""

import os
import sys

import numpy as np

import insitu
from check import raises


def psnr(a, b):
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)



def main():
    work = sys.argv[1]
    z, y, x = np.meshgrid(*(np.arange(32.0),) * 3, indexing="ij")
    ball = np.maximum(0.0, 12.0 - np.sqrt((x - 15.5) ** 2 + (y - 15.5) ** 2 + (z - 15.5) ** 2))
    vol = (ball * 20).astype(np.float32)
    dvr = insitu.render(vol, size=64, angle=20.0)
    assert dvr.shape == (64, 64, 3) and dvr.dtype == np.float32, (dvr.shape, dvr.dtype)
    lit = int((dvr.sum(axis=2) > 0.05).sum())
    assert lit > 300, lit
    assert np.array_equal(insitu.render(vol.astype(np.uint8), size=64, angle=20.0),
                          insitu.render(vol.astype(np.uint8).astype(np.float32), size=64, angle=20.0)), \
        "a uint8 volume renders as its values in float32"
    vdi = insitu.generate(vol, r=64, gamma=0.01)
    assert vdi.resolution == 64 and vdi.supersegments > 0, vdi
    q = psnr(vdi.render(size=64, angle=20.0), dvr)
    print(f"VDI vs direct rendering at 20°: {q:.1f} dB")
    assert q >= 25.0, q
    path = os.path.join(work, "ball.vdi")
    sigma = vdi.save(path)
    assert sigma == os.path.getsize(path), (sigma, os.path.getsize(path))
    again = insitu.Vdi.load(path)
    # Written at 8 bits (the default): the pictures move by far less than the VDI's own error.
    moved = psnr(again.render(size=48, angle=45.0), vdi.render(size=48, angle=45.0))
    assert moved > 45.0, moved
    exact = insitu.generate(vol, r=64, gamma=0.01, precision="f32")
    exact.save(path)
    assert np.array_equal(insitu.Vdi.load(path).render(size=48, angle=45.0),
                          exact.render(size=48, angle=45.0)), "f32 files are lossless"
    sigma = vdi.save(path)
    e = insitu.evaluate(vol, r=64, gamma=0.01, size=64, views=[0.0, 30.0])
    print("evaluate:", {k: e[k] for k in ("sigma_bytes", "supersegments", "tau_s", "q_db")})
    assert e["sigma_bytes"] == sigma, (e["sigma_bytes"], sigma)
    assert e["supersegments"] == vdi.supersegments
    assert e["q_db"] > 25.0 and [a for a, _ in e["views"]] == [0.0, 30.0], e
    raises(ValueError, "2 dimensions", lambda: insitu.render(np.zeros((4, 4), np.float32)))
    raises(TypeError, "complex128", lambda: insitu.render(np.zeros((4, 4, 4), complex)))
    raises(ValueError, "elevation 100", lambda: insitu.render(vol, elevation=100.0))
    raises(ValueError, "size 0", lambda: insitu.render(vol, size=0))
    raises(ValueError, "python", lambda: insitu.render(vol, tf='{"points": 3}'))
    raises(ValueError, "gamma", lambda: insitu.generate(vol, r=64, gamma=float("nan")))
    raises(ValueError, "codec", lambda: vdi.save(path, codec="lz4"))
    raises(ValueError, "precision", lambda: insitu.generate(vol, r=64, precision="3"))
    junk = os.path.join(work, "junk.vdi")
    with open(junk, "wb") as f:
        f.write(b"not a vdi")
    raises(ValueError, "junk.vdi", lambda: insitu.Vdi.load(junk))
    print("ok")


if __name__ == "__main__":
    main()
