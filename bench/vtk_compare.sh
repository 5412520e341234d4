#!/usr/bin/env bash
# VTK's CPU ray caster against `insitu render`, same volume, TF, camera and step, interleaved
# (issue 17). Makes a venv with PyPI's vtk in bench/.venv on first use (needs network once),
# builds the release CLI, and prints both times, their ratio and the PSNR between the images.
#
#   bench/vtk_compare.sh                       # the teapot at 30°, 768², 5 runs
#   bench/vtk_compare.sh --runs 9              # the same, 9 runs
#   bench/vtk_compare.sh --volume V.raw --tf T.json --angle 10 --size 512 --runs 7
#   bench/vtk_compare.sh --volume V.raw --tf T.json --vdi 256 --vdi 768   # VDI renders too
set -euo pipefail
cd "$(dirname "$0")/.."
venv=bench/.venv
if [ ! -x "$venv/bin/python" ]; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet vtk numpy pillow
fi
cargo build --release --quiet -p insitu-cli
data=${INSITU_DATA_DIR:-../shared/data}
tfs=${INSITU_TF_DIR:-../shared/tf}
args=("$@")
# Without --volume, the teapot with its TF at 30° (the other options still apply).
case " $* " in
  *" --volume "*) ;;
  *) args=(--volume "$data/teapot_256x256x178_uint8.raw" --tf "$tfs/teapot.json" --angle 30 "${args[@]}") ;;
esac
# Offscreen: VTK looks for an X display first and falls back without one (a warning only).
exec "$venv/bin/python" bench/vtk_compare.py --insitu target/release/insitu "${args[@]}"
