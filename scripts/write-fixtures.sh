#!/usr/bin/env bash
# Writes the readers' test files with the reference libraries (PyPI vtk, pynrrd, netCDF4, h5py, adios2, openpmd-api) into
# target/fixtures/ (or $INSITU_FIXTURE_DIR), from scripts/write_fixtures.py. Makes the venv
# target/fixtures-venv on first use (needs network once); its pandas and Pillow also read the
# Cinema databases `insitu export --cinema` writes (scripts/check_cinema.py) in the CLI tests.
# readers/tests/fixtures.rs reads the files.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${INSITU_FIXTURE_DIR:-target/fixtures}
venv=target/fixtures-venv
if [ ! -x "$venv/bin/python" ]; then
  python3 -m venv "$venv"
fi
if ! "$venv/bin/python" -c 'import numpy, vtk, nrrd, netCDF4, h5py, adios2, openpmd_api, pandas, PIL' 2>/dev/null; then
  "$venv/bin/pip" install --quiet numpy vtk pynrrd netCDF4 h5py adios2 openpmd-api pandas pillow
fi
"$venv/bin/python" scripts/write_fixtures.py "$out"
