"""The ``insitu`` command the Python package installs (also ``python -m insitu``).

What a recording holds, with the package alone:

    insitu export --recording DIR [--format csv|json]      # the stored steps, as the index says
    insitu view --recording DIR --time-step N [--angle A] [--elevation E] [--size N] [--out PNG]

Every other command (demo, replay, render, evaluate, study, steer, ...) is the Rust ``insitu``
command's, run with the same arguments when it is found: in ``INSITU_BIN_DIR``, else on
``PATH`` (this command excluded). ``cargo build --release -p insitu-cli`` builds it
(docs/own-simulation.md).
"""

import argparse
import csv
import json
import os
import shutil
import struct
import sys
import zlib

import numpy as np

from . import Recording

OWN = ("export", "view")


def write_png(path, rgb):
    """Writes ``rgb`` (h, w, 3) in [0, 1] as an 8-bit PNG, atomically (a temporary file renamed)."""
    h, w, _ = rgb.shape
    pixels = (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    rows = b"".join(b"\x00" + pixels[j].tobytes() for j in range(h))

    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(rows, 6)) + chunk(b"IEND", b"")
    tmp = f"{path}.tmp-{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(png)
    os.replace(tmp, path)


def rust_command():
    """The Rust ``insitu`` command: in INSITU_BIN_DIR, else on PATH other than this one."""
    bin_dir = os.environ.get("INSITU_BIN_DIR")
    if bin_dir:
        exe = os.path.join(bin_dir, "insitu")
        return exe if os.access(exe, os.X_OK) else None
    for d in os.environ.get("PATH", "").split(os.pathsep):
        exe = shutil.which("insitu", path=d) if d else None
        if exe and not is_script(exe):
            return exe
    return None


def is_script(path):
    """Whether ``path`` is a script (this package's own command is one), not a program."""
    try:
        with open(path, "rb") as f:
            return f.read(2) == b"#!"
    except OSError:
        return True


def export(args):
    steps = Recording(args.recording).steps
    if args.format == "json":
        print(json.dumps(steps, indent=1))
        return 0
    keys = sorted({k for s in steps for k in s}, key=lambda k: (k != "step", k))
    out = csv.DictWriter(sys.stdout, fieldnames=keys, lineterminator="\n")
    out.writeheader()
    for s in steps:
        out.writerow({k: json.dumps(v) if isinstance(v, list) else v for k, v in s.items()})
    return 0


def view(args):
    rec = Recording(args.recording)
    image = rec.image(args.time_step, size=args.size, angle=args.angle, elevation=args.elevation)
    write_png(args.out, image)
    print(f"step {args.time_step} of {args.recording}: {args.size}² at {args.angle}°, "
          f"elevation {args.elevation}° → {args.out}")
    return 0


def parser():
    p = argparse.ArgumentParser(
        prog="insitu",
        description="A recording's steps and pictures with the Python package alone; any other "
        "command runs the Rust insitu command (INSITU_BIN_DIR, else PATH).",
    )
    sub = p.add_subparsers(dest="command", required=True)
    e = sub.add_parser("export", help="the recording's stored steps as CSV or JSON")
    e.add_argument("--recording", required=True, help="a viz-node's recording directory")
    e.add_argument("--format", choices=("csv", "json"), default="csv")
    v = sub.add_parser("view", help="a stored step's picture, as a PNG")
    v.add_argument("--recording", required=True, help="a viz-node's recording directory")
    v.add_argument("--time-step", type=int, required=True, help="the stored step")
    v.add_argument("--angle", type=float, default=0.0, help="degrees about +y (default 0)")
    v.add_argument("--elevation", type=float, default=0.0, help="degrees up (default 0)")
    v.add_argument("--size", type=int, default=768, help="pixels per side (default 768)")
    v.add_argument("--out", default="view.png", help="the PNG written (default view.png)")
    return p


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    first = next((a for a in argv if not a.startswith("-")), None)
    if first is not None and first not in OWN:
        exe = rust_command()
        if exe is None:
            print(f"insitu {first}: the Rust insitu command runs it, and it was found neither in "
                  "INSITU_BIN_DIR nor on PATH (cargo build --release -p insitu-cli; this "
                  f"package's own commands: {', '.join(OWN)})", file=sys.stderr)
            return 2
        os.execv(exe, [exe, *argv])
    args = parser().parse_args(argv)
    try:
        return {"export": export, "view": view}[args.command](args)
    except (ValueError, KeyError, OSError) as e:
        print(f"insitu {args.command}: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
