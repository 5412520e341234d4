#!/usr/bin/env bash
# Runs every fuzz target for SECONDS (default 30) on a copy of its seed corpus and prints
# executions and coverage; fails on the first crash (the input is left in fuzz/artifacts/).
#
# The targets are built first, all in one cargo invocation (their shared crates compiled once,
# in parallel), then run one after another without building again. FUZZ_OPT_LEVEL sets the
# optimisation of that build (default 3, cargo-fuzz's release build); CI's short smoke run asks
# for 1: on 2 cores the build took about 270 s instead of 420 s, and 20 s of each target ran
# 72–95 % as many inputs (from 43 000 for the readers to 1.7 million for step headers).
set -euo pipefail
cd "$(dirname "$0")"
secs=${1:-30}
export RUSTC_BOOTSTRAP=1
export CARGO_PROFILE_RELEASE_OPT_LEVEL=${FUZZ_OPT_LEVEL:-3}
targets=(vdi_decode chunk_receive tf_json step_header configs readers)
cargo fuzz build
for t in "${targets[@]}"; do
  work=$(mktemp -d)
  log=$(mktemp)
  cp -r "corpus/$t/." "$work/"
  if ! cargo fuzz run "$t" "$work" -- -max_total_time="$secs" -print_final_stats=1 >"$log" 2>&1; then
    tail -60 "$log"
    echo "fuzz: $t CRASHED (input in fuzz/artifacts/$t/)" >&2
    exit 1
  fi
  execs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' || echo "?")
  cov=$(grep -oE 'cov: [0-9]+ ft: [0-9]+' "$log" | tail -1 || echo "?")
  echo "fuzz: $t ${secs} s, ${execs} executions, ${cov}, no crash"
  rm -rf "$work" "$log"
done
