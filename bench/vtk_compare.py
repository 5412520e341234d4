"""Render one volume with VTK's CPU ray caster and with `insitu render`, interleaved; print
both times, their ratio and the PSNR between the images.

Run through bench/vtk_compare.sh, which makes the venv. The conventions match docs/conventions.md
("Conventions every part shares"), which chose VTK's where there was a choice:

- volume: image data with origin 0 and spacing 1, so voxel centres sit at integer coordinates
  and the box is [0, n - 1] per axis; trilinear samples (linear interpolation);
- TF: the same JSON (without --tf: a ramp over the data's finite range, the points of
  insitu's default ramp, `TransferFunction::default_for_range`, written to a file that both
  renderers read), points at domain[0] + x * (domain[1] - domain[0]); colour and opacity
  piecewise linear; opacity per unit length with VTK's scalar opacity unit distance = 1 voxel,
  so both correct a step of 0.5 voxel to alpha = 1 - (1 - a)^0.5; no shading;
- camera: perspective, 30 degrees vertical field of view, up +y, looking along -z at the box
  centre from R / sin(15 degrees), R the half diagonal, orbited about +y by --angle;
- timing: render only, warm on both sides: VTK's after a warm-up render in its window,
  insitu's the second render of `insitu render --repeat 2` (the first, cold one is printed
  apart: the thread pool's start and the ray-caster's occupancy bits);
- sampling: VTK's sample distance 0.5 (automatic adjustment off), image sample distance 1;
  ours --sample-distance 0.5 (the default); both stop a ray at opacity 0.99 (ours by default, VTK's
  fixed-point mapper at its built-in 0.99..1 cut-off);
- background black; images compared as 8-bit RGB, row 0 at the top;
- a time series (the ocean): its first step on both sides (insitu's `--time-step` defaults to 0);
- NaN (the ocean's land): missing and transparent for insitu (docs/conventions.md), so a sample with a
  NaN corner adds nothing; VTK's fixed-point mapper takes NaN as the bottom of the range (the
  same image as with NaN replaced by the minimum), which its opacity ramp makes transparent
  but which still blends into its neighbours' samples. The two images therefore differ along
  the coasts (about 33 dB), by convention, not by a camera or TF mismatch.
"""

import argparse
import json
import math
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import vtk
from PIL import Image
from vtk.util import numpy_support

# What the marcher aims for: VTK's time over insitu's on every volume and view of the suite
# (docs/performance.md, "Against VTK").
RATIO_AIM = 3.0

DTYPES = {"uint8": np.uint8, "uint16": np.uint16, "int16": np.int16, "float32": np.float32,
          "float64": np.float64}


def load(path, field=None):
    """The samples, dims, origin and spacing of a raw file (origin 0, spacing 1) or, as
    VTK's own reader places it, of a `.vti` file (its array `field`, else the active scalars)."""
    if path.endswith(".vti"):
        r = vtk.vtkXMLImageDataReader()
        r.SetFileName(path)
        r.Update()
        image = r.GetOutput()
        pd = image.GetPointData()
        arr = pd.GetArray(field) if field else pd.GetScalars()
        if arr is None:
            sys.exit(f"{path}: no array {field}")
        return (numpy_support.vtk_to_numpy(arr), image.GetDimensions(), image.GetOrigin(),
                image.GetSpacing())
    data, dims = load_raw(path)
    return data, dims, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)


def load_raw(path):
    m = re.search(r"_(\d+)x(\d+)x(\d+)(?:x\d+)?_([a-z0-9]+)\.raw$", os.path.basename(path))
    if not m:
        sys.exit(f"{path}: expected <name>_<X>x<Y>x<Z>_<type>.raw")
    nx, ny, nz, t = int(m[1]), int(m[2]), int(m[3]), m[4]
    if t not in DTYPES:
        sys.exit(f"{path}: unsupported type {t}")
    data = np.fromfile(path, dtype=DTYPES[t], count=nx * ny * nz)
    return data, (nx, ny, nz)


def default_ramp(data):
    """insitu's default TF (core/src/tf.rs, `default_for_range`) over the finite data range."""
    finite = data[np.isfinite(data)] if data.dtype.kind == "f" else data
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if not lo < hi:
        hi = lo + 1.0
    return {"domain": [lo, hi],
            "points": [[0.0, 0.0, 0.0, 0.0, 0.0], [0.1, 0.2, 0.3, 0.9, 0.0],
                       [0.3, 0.2, 0.6, 1.0, 0.02], [0.6, 0.9, 0.9, 0.3, 0.08],
                       [1.0, 1.0, 0.3, 0.1, 0.3]]}


def vtk_volume(data, dims, tf, step, origin=(0, 0, 0), spacing=(1, 1, 1)):
    image = vtk.vtkImageData()
    image.SetDimensions(*dims)
    image.SetOrigin(*origin)
    image.SetSpacing(*spacing)
    arr = numpy_support.numpy_to_vtk(data, deep=True)
    image.GetPointData().SetScalars(arr)

    lo, hi = tf["domain"]
    color = vtk.vtkColorTransferFunction()
    opacity = vtk.vtkPiecewiseFunction()
    for x, r, g, b, a in tf["points"]:
        v = lo + x * (hi - lo)
        color.AddRGBPoint(v, r, g, b)
        opacity.AddPoint(v, a)
    prop = vtk.vtkVolumeProperty()
    prop.SetColor(color)
    prop.SetScalarOpacity(opacity)
    prop.SetScalarOpacityUnitDistance(1.0)
    prop.SetInterpolationTypeToLinear()
    prop.ShadeOff()

    mapper = vtk.vtkFixedPointVolumeRayCastMapper()
    mapper.SetInputData(image)
    mapper.SetAutoAdjustSampleDistances(0)
    mapper.SetSampleDistance(step)
    mapper.SetImageSampleDistance(1.0)
    volume = vtk.vtkVolume()
    volume.SetMapper(mapper)
    volume.SetProperty(prop)
    return volume


def vtk_scene(volume, dims, size, angle, origin=(0, 0, 0), spacing=(1, 1, 1)):
    ren = vtk.vtkRenderer()
    ren.SetBackground(0, 0, 0)
    ren.AddVolume(volume)
    win = vtk.vtkRenderWindow()
    win.SetOffScreenRendering(1)
    win.SetSize(size, size)
    win.AddRenderer(ren)
    extent = [(n - 1) * s for n, s in zip(dims, spacing)]
    centre = [o + e / 2.0 for o, e in zip(origin, extent)]
    half_diagonal = 0.5 * math.sqrt(sum(e ** 2 for e in extent))
    dist = half_diagonal / math.sin(math.radians(15.0))
    cam = ren.GetActiveCamera()
    cam.SetFocalPoint(*centre)
    cam.SetPosition(centre[0], centre[1], centre[2] + dist)
    cam.SetViewUp(0, 1, 0)
    cam.SetViewAngle(30.0)
    cam.Azimuth(angle)
    ren.ResetCameraClippingRange()
    return ren, win


def vtk_image(win):
    grab = vtk.vtkWindowToImageFilter()
    grab.SetInput(win)
    grab.SetInputBufferTypeToRGB()
    grab.ReadFrontBufferOff()
    grab.Update()
    out = grab.GetOutput()
    w, h, _ = out.GetDimensions()
    rgb = numpy_support.vtk_to_numpy(out.GetPointData().GetScalars()).reshape(h, w, 3)
    return np.flipud(rgb)  # VTK's row 0 is the bottom


def insitu_render(exe, volume, tf, angle, size, step, out, field=None):
    """The cold render's time and the warm one's (`--repeat 2`: the second, as VTK's renders
    are timed after a warm-up render)."""
    cmd = [exe, "render", "--volume", volume, "--tf", tf, "--angle", str(angle), "--size",
           str(size), "--sample-distance", str(step), "--repeat", "2", "--backend", "cpu", "--out", out]
    if field:
        cmd += ["--field", field]
    p = subprocess.run(cmd, capture_output=True, text=True, check=True)
    m = re.search(r" in ([0-9.]+) s .*then ([0-9.]+) s", p.stdout + p.stderr)
    if not m:
        sys.exit(f"could not read the render times from: {p.stdout}{p.stderr}")
    return float(m[1]), float(m[2])


def insitu_generate(exe, volume, tf, r, gamma, out):
    cmd = [exe, "generate", "--volume", volume, "--tf", tf, "--r", str(r), "--gamma", str(gamma),
           "--backend", "cpu", "--out", out]
    subprocess.run(cmd, capture_output=True, text=True, check=True)


def insitu_view(exe, vdi, angle, size, out):
    """The warm render's time: `--repeat 2` reports the second (walk tables built)."""
    cmd = [exe, "view", "--vdi", vdi, "--angle", str(angle), "--size", str(size), "--repeat",
           "2", "--backend", "cpu", "--out", out]
    p = subprocess.run(cmd, capture_output=True, text=True, check=True)
    m = re.search(r"then ([0-9.]+) s", p.stdout + p.stderr)
    if not m:
        sys.exit(f"could not read the render time from: {p.stdout}{p.stderr}")
    return float(m[1])


def ratio(a, b):
    """a / b, or infinity where b rounds to no time at all (a tiny render timed as 0)."""
    return a / b if b > 0 else float("inf")


def psnr(a, b):
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return math.inf if mse == 0 else 10 * math.log10(255.0 ** 2 / mse)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--volume", required=True,
                    help="a raw file, or a .vti (VTK places it by its origin and spacing, insitu "
                         "by its reader: the images agree only where the two boxes do)")
    ap.add_argument("--field", help="the .vti's array (default: its active scalars)")
    ap.add_argument("--tf", help="TF JSON (default: a ramp over the data range)")
    ap.add_argument("--angle", type=float, default=30.0)
    ap.add_argument("--size", type=int, default=768)
    ap.add_argument("--sample-distance", dest="step", type=float, default=0.5)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--insitu", default="target/release/insitu")
    ap.add_argument("--vdi", type=int, action="append", default=[], metavar="R",
                    help="also render a VDI of resolution R (made at 0°, the default camera) "
                         "from the same view in each round (repeatable)")
    ap.add_argument("--gamma", type=float, default=0.013, help="the VDIs' interrupt threshold")
    ap.add_argument("--row", metavar="FILE",
                    help="also append this comparison to FILE as a Markdown table row: volume, "
                         "view, both medians, the ratio of medians (of minima), PSNR")
    a = ap.parse_args()

    data, dims, origin, spacing = load(a.volume, a.field)
    if a.tf is None:
        a.tf = os.path.join(tempfile.mkdtemp(), "ramp.json")
        with open(a.tf, "w") as f:
            json.dump(default_ramp(data), f)
    tf = json.load(open(a.tf))
    volume = vtk_volume(data, dims, tf, a.step, origin, spacing)
    ren, win = vtk_scene(volume, dims, a.size, a.angle, origin, spacing)
    win.Render()  # warm-up: builds the mapper's tables
    ours_png = os.path.join(tempfile.mkdtemp(), "insitu.png")
    insitu_render(a.insitu, a.volume, a.tf, a.angle, a.size, a.step, ours_png, a.field)

    tmp = tempfile.mkdtemp()
    vdis = []
    for r in a.vdi:
        path = os.path.join(tmp, f"r{r}.vdi")
        insitu_generate(a.insitu, a.volume, a.tf, r, a.gamma, path)
        vdis.append((r, path, os.path.join(tmp, f"r{r}.png"), []))

    t_vtk, t_ours, t_cold = [], [], []
    for _ in range(a.runs):  # interleaved, so all see the same machine state
        ren.GetActiveCamera().Modified()
        t0 = time.perf_counter()
        win.Render()
        t_vtk.append(time.perf_counter() - t0)
        cold, warm = insitu_render(a.insitu, a.volume, a.tf, a.angle, a.size, a.step, ours_png,
                                   a.field)
        t_cold.append(cold)
        t_ours.append(warm)
        for _, path, png, times in vdis:
            times.append(insitu_view(a.insitu, path, a.angle, a.size, png))
    theirs = vtk_image(win)
    ours = np.asarray(Image.open(ours_png).convert("RGB"))
    mv, mo = statistics.median(t_vtk), statistics.median(t_ours)
    print(f"{os.path.basename(a.volume)}, {a.size}², {a.angle:g}°, step {a.step:g}, "
          f"{a.runs} interleaved runs, medians (render only):")
    print(f"  VTK {vtk.vtkVersion.GetVTKVersion()} vtkFixedPointVolumeRayCastMapper: {mv:.3f} s"
          f"  (runs {', '.join(f'{t:.3f}' for t in t_vtk)})")
    print(f"  insitu render --backend cpu:          {mo:.3f} s"
          f"  (runs {', '.join(f'{t:.3f}' for t in t_ours)})")
    print(f"  (insitu's first render in its process, cold: {statistics.median(t_cold):.3f} s;"
          f" both sides are compared warm, VTK's after a warm-up render)")
    print(f"  ratio VTK / insitu: {ratio(mv, mo):.2f}× (aim ≥ {RATIO_AIM:g}×);  "
          f"PSNR between the images: {psnr(theirs, ours):.1f} dB")
    print(f"  (minima: VTK {min(t_vtk):.3f} s, insitu {min(t_ours):.3f} s, "
          f"ratio {ratio(min(t_vtk), min(t_ours)):.2f}×)")
    if a.row:
        with open(a.row, "a") as f:
            f.write(f"| {os.path.basename(a.volume)} | {a.angle:g}° | {mv:.3f} s | {mo:.3f} s | "
                    f"{ratio(mv, mo):.2f}× ({ratio(min(t_vtk), min(t_ours)):.2f}×) | "
                    f"{psnr(theirs, ours):.1f} dB |\n")
    for r, _, png, times in vdis:
        m = statistics.median(times)
        q = psnr(ours, np.asarray(Image.open(png).convert("RGB")))
        print(f"  insitu view, VDI r = {r} (γ {a.gamma:g}, made at 0°): {m:.3f} s"
              f"  (runs {', '.join(f'{t:.3f}' for t in times)}); VTK over it {mv / m:.2f}× "
              f"(minima {min(t_vtk) / min(times):.2f}×); {q:.1f} dB against insitu's DVR")


if __name__ == "__main__":
    main()
