#!/usr/bin/env bash
# A newcomer's first build, timed: the release daemons (generator-node, viz-node, tuner-node),
# the `insitu` command and the C library, from nothing (a fresh target directory; the crates'
# sources fetched first, so the network is not timed). Prints the wall time and the machine.
# Not a test: its figure is quoted, with its machine, in docs/performance.md ("Building").
#
#   scripts/build-time.sh                          # as deploy/local.sh builds them
#   scripts/build-time.sh --no-default-features    # without the GPU path (wgpu)
#   TIMINGS=1 scripts/build-time.sh                # also cargo's per-crate report, kept in target/
set -euo pipefail
cd "$(dirname "$0")/.."
dir=$(mktemp -d "${TMPDIR:-/tmp}/insitu-build-time.XXXXXX")
trap 'rm -rf "$dir"' EXIT
cargo fetch --quiet
timings=()
[[ -n ${TIMINGS:-} ]] && timings=(--timings)
start=$(date +%s.%N)
CARGO_TARGET_DIR=$dir cargo build --release --quiet --bins "${timings[@]}" \
  -p insitu-generator-node -p insitu-viz-node -p insitu-tuner-node -p insitu-cli -p insitu-client-c "$@"
end=$(date +%s.%N)
if [[ -n ${TIMINGS:-} ]]; then
  mkdir -p target
  cp "$dir"/cargo-timings/cargo-timing.html target/build-time.html
  echo "per-crate timings: target/build-time.html"
fi
cpu=$(grep -m1 'model name' /proc/cpuinfo 2>/dev/null | cut -d: -f2 | xargs || echo unknown)
echo "release build of the daemons, the insitu command and the C library${*:+ ($*)}: $(awk "BEGIN { printf \"%.0f\", $end - $start }") s"
echo "machine: $(nproc) cores ($cpu), $(free -g 2>/dev/null | awk '/^Mem:/{print $2 " GiB"}'), $(rustc --version)"
