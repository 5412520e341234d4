#!/usr/bin/env bash
# Starts a viz-node with its web viewer, a tuner-node and a generator-node on 127.0.0.1, wired
# together, from this checkout's release binaries (built first), or from prebuilt ones in
# INSITU_BIN_DIR (nothing is built then: e.g. INSITU_BIN_DIR=/opt/insitu/bin on a machine
# without Rust), prints the viewer's URL and the generator-node's address on stdout, and keeps
# them running until Ctrl-C (or SIGTERM), then stops them gracefully (the generator drains and
# prints what it dropped). The viewer listens on HTTP_LISTEN (default 127.0.0.1:0, an
# ephemeral port) and draws the tuner's budget. The tuner optimises TUNER_UTILITY (default
# size:1MB) and keeps its state in RECORDING_DIR/tuner-state; NO_TUNE=1 starts no tuner (P_M
# stays as configured).
#
#   deploy/local.sh [RECORDING_DIR] [-- extra generator-node flags]
#
# Then push data, e.g.:
#   target/release/insitu replay --series data/ocean_temp_ts_180x90x19x12_float32.raw \
#       --generator <generator address printed below>
# Configs: deploy/generator-node.toml, deploy/viz-node.toml and deploy/tuner-node.toml document
# every key; set GENERATOR_CONFIG / VIZ_CONFIG / TUNER_CONFIG to use your own.
set -euo pipefail
cd "$(dirname "$0")/.."
rec=${1:-recording}
shift $(( $# > 0 ? 1 : 0 ))
[[ ${1:-} == "--" ]] && shift
if [[ -n ${INSITU_BIN_DIR:-} ]]; then
  bin=$INSITU_BIN_DIR
  for b in viz-node tuner-node generator-node; do
    [[ -x $bin/$b ]] || { echo "INSITU_BIN_DIR=$bin has no executable $b" >&2; exit 1; }
  done
else
  cargo build --release --quiet --bins -p insitu-generator-node -p insitu-viz-node -p insitu-tuner-node -p insitu-cli
  bin=target/release
fi
logs=$(mktemp -d)

wait_addr() { # file → prints the address once the daemon has printed it
  for _ in $(seq 200); do
    if grep -q '^listening on ' "$1" 2>/dev/null; then sed -n 's/^listening on //p' "$1" | head -1; return; fi
    sleep 0.05
  done
  echo "daemon did not start; see $logs" >&2; exit 1
}

wait_url() { # file → prints the viewer's URL once the viz-node has printed it
  for _ in $(seq 200); do
    if grep -q '^web viewer on ' "$1" 2>/dev/null; then sed -n 's/^web viewer on //p' "$1" | head -1; return; fi
    sleep 0.05
  done
  echo "the viz-node printed no viewer URL; see $logs" >&2; exit 1
}

free_port() { # a port free now on 127.0.0.1 (the tuner's, which the viz-node dials for the budget)
  python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])' 2>/dev/null
}

tuner_listen=127.0.0.1:0
viz_tuner=()
if [[ ${NO_TUNE:-0} != 1 ]] && port=$(free_port); then
  tuner_listen=127.0.0.1:$port
  viz_tuner=(--tuner "$tuner_listen")
fi
"$bin/viz-node" ${VIZ_CONFIG:+--config "$VIZ_CONFIG"} --listen 127.0.0.1:0 --recording-dir "$rec" \
  --http "${HTTP_LISTEN:-127.0.0.1:0}" "${viz_tuner[@]}" >"$logs/viz.out" 2>"$logs/viz.log" &
viz_pid=$!
viz=$(wait_addr "$logs/viz.out")
url=$(wait_url "$logs/viz.out")
tuner_flag=()
tuner_pid=
if [[ ${NO_TUNE:-0} != 1 ]]; then
  "$bin/tuner-node" ${TUNER_CONFIG:+--config "$TUNER_CONFIG"} --listen "$tuner_listen" --viz "$viz" \
    --state-dir "$rec/tuner-state" --utility "${TUNER_UTILITY:-size:1MB}" \
    >"$logs/tuner.out" 2>"$logs/tuner.log" &
  tuner_pid=$!
  tuner=$(wait_addr "$logs/tuner.out")
  tuner_flag=(--tuner "$tuner")
fi
"$bin/generator-node" ${GENERATOR_CONFIG:+--config "$GENERATOR_CONFIG"} --listen 127.0.0.1:0 --viz "$viz" "${tuner_flag[@]}" "$@" \
  >"$logs/gen.out" 2>"$logs/gen.log" &
gen_pid=$!
gen=$(wait_addr "$logs/gen.out")

stop() {
  kill -TERM "$gen_pid" 2>/dev/null || true; wait "$gen_pid" 2>/dev/null || true
  if [[ -n $tuner_pid ]]; then kill -TERM "$tuner_pid" 2>/dev/null || true; wait "$tuner_pid" 2>/dev/null || true; fi
  kill -TERM "$viz_pid" 2>/dev/null || true; wait "$viz_pid" 2>/dev/null || true
  grep '^summary' "$logs/gen.out" || true
  echo "recording: $rec   logs: $logs"
}
trap stop EXIT
trap 'exit 130' INT TERM
echo "viewer         $url"
echo "viz-node       $viz   (recording: $rec)"
if [[ -n $tuner_pid ]]; then
  echo "tuner-node     $tuner   (${TUNER_UTILITY:-size:1MB}; log: $logs/tuner.log)"
  echo "               the first steps use the generator-node's P_M until the tuner's first decision (after its first tuning, seconds); until then the node lowers r itself when a step misses the budget by 1.25x or more"
fi
echo "generator-node $gen"
echo "push with: $bin/insitu replay --series <4-D raw file> --generator $gen    (Ctrl-C stops the daemons)"
wait "$gen_pid"
