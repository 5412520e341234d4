#!/usr/bin/env bash
# Builds the Python package (python/: PyO3 over the Rust client, the wheel `insitu`) with maturin
# into target/wheels, and installs it in the fixtures' venv (target/fixtures-venv, made by
# scripts/write-fixtures.sh) with mpi4py beside it, where the end-to-end tests run it
# (tests/tests/e2e/python.rs).
# A user installs it with `pip install ./python` (maturin builds it from the repository).
set -euo pipefail
cd "$(dirname "$0")/.."
venv=target/fixtures-venv
[ -x "$venv/bin/python" ] || bash scripts/write-fixtures.sh
[ -x "$venv/bin/maturin" ] || "$venv/bin/pip" install --quiet 'maturin>=1.5,<2'
# mpi4py for the MPI example (python/examples/gray_scott_mpi.py), over the machine's Open MPI.
if command -v mpirun >/dev/null 2>&1 && ! "$venv/bin/python" -c 'import mpi4py' 2>/dev/null; then
  "$venv/bin/pip" install --quiet mpi4py
fi
rm -f target/wheels/insitu-*.whl
"$venv/bin/maturin" build --quiet --manifest-path python/Cargo.toml --interpreter "$venv/bin/python" --out target/wheels
"$venv/bin/pip" install --quiet --force-reinstall --no-deps target/wheels/insitu-*.whl
"$venv/bin/python" -c 'import insitu; print("built and installed", insitu.__name__, "from", insitu.__file__)'
