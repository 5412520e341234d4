#!/usr/bin/env bash
# VTK's CPU ray caster against `insitu render`, same volume, TF, camera and step, interleaved
# runs. Makes a venv with PyPI's vtk in bench/.venv on first use (needs network once),
# builds the release CLI, and prints both times, their ratio and the PSNR between the images.
#
#   bench/vtk_compare.sh                       # the teapot at 30°, 768², 5 runs
#   bench/vtk_compare.sh --runs 9              # the same, 9 runs
#   bench/vtk_compare.sh --volume V.raw --tf T.json --angle 10 --size 512 --runs 7
#   bench/vtk_compare.sh --volume V.raw --tf T.json --vdi 256 --vdi 768   # VDI renders too
#   bench/vtk_compare.sh --suite --runs 7      # the twelve views of the table of docs/performance.md (the five
#                                              # shared volumes at 30° and 10°, the ocean's first
#                                              # time step; and the low-opacity deep scan that
#                                              # bench/make_deep_scan.py makes from the stent), then the table
set -euo pipefail
cd "$(dirname "$0")/.."
venv=bench/.venv
if [ ! -x "$venv/bin/python" ]; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet vtk numpy pillow
fi
cargo build --release --quiet -p insitu-cli
# The volumes as the tests find them (docs/data.md): $INSITU_DATA_DIR, data/, ../shared/data,
# the first that holds the file named first (data/ may hold only the test fixtures).
first_dir() {
  local file=$1; shift
  for d in "$@"; do [ -n "$d" ] && [ -e "$d/$file" ] && { echo "$d"; return; }; done
  echo "$2"
}
data=$(first_dir teapot_256x256x178_uint8.raw "${INSITU_DATA_DIR:-}" data ../shared/data)
tfs=$(first_dir teapot.json "${INSITU_TF_DIR:-}" data/tf ../shared/tf)
args=("$@")
if [ "${1:-}" = "--suite" ]; then
  # Each view in turn (its own VTK window and insitu processes), each adding its row.
  table=$(mktemp)
  deep=$("$venv/bin/python" bench/make_deep_scan.py "$data" bench/.data)
  for angle in 30 10; do
    for v in "$data/teapot_256x256x178_uint8.raw $tfs/teapot.json" \
             "$data/hydrogen_64x64x64_float32.raw $tfs/hydrogen.json" \
             "$data/neghip_66x66x66_uint8.raw" "$data/stent_128x128x256_int16.raw" \
             "$data/ocean_temp_ts_180x90x19x12_float32.raw" "$deep bench/deep_scan.json"; do
      set -- $v
      tf=()
      [ -n "${2:-}" ] && tf=(--tf "$2")
      "$venv/bin/python" bench/vtk_compare.py --insitu target/release/insitu \
        --volume "$1" "${tf[@]}" --angle "$angle" --row "$table" "${args[@]:1}"
    done
  done
  echo
  echo "| volume | view | VTK median | insitu median | ratio of medians (of minima) | PSNR |"
  echo "|---|---|---|---|---|---|"
  cat "$table"
  rm -f "$table"
  exit 0
fi
# Without --volume, the teapot with its TF at 30° (the other options still apply).
case " $* " in
  *" --volume "*) ;;
  *) args=(--volume "$data/teapot_256x256x178_uint8.raw" --tf "$tfs/teapot.json" --angle 30 "${args[@]}") ;;
esac
# Offscreen: VTK looks for an X display first and falls back without one (a warning only).
exec "$venv/bin/python" bench/vtk_compare.py --insitu target/release/insitu "${args[@]}"
