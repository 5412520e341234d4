#!/usr/bin/env bash
# Downloads the public volumes the real-data tests and benchmarks use, converts each to the
# headerless raw layout the project reads (x fastest, little-endian; docs/data.md) and checks
# the result against a pinned SHA-256. Files go to data/ in the repository (git ignores it).
#
#   scripts/fetch-data.sh            # every volume
#   scripts/fetch-data.sh ocean      # only the named ones: teapot stent hydrogen neghip ocean
#
# Needs curl, python3 with venv, and for the ocean series either Debian's ferret-datasets
# (installed when run as root) or dpkg-deb to unpack its package without installing it.
# The converters run in data/.venv (numpy, pillow, netCDF4, vtk from PyPI).
set -euo pipefail
cd "$(dirname "$0")/.."
out=data
mkdir -p "$out"

declare -A sha=(
  [teapot]=e7b67180fe2d813bda6e9900ab21ea1a9b89069fab074e77996022b9512fab1e
  [stent]=8431cfdc59600c1a6e2b68adeac61a8535d01cfdba236150b92101f984454da1
  [hydrogen]=789756a94c4e8b43d04f7f89455f568d2fdb8dcb2d2170b75e078edc1b56d0b2
  [neghip]=a8032bb45132a1a87a0ef5989c37f7946fa42846c6016af5dddbbdb6fd3ec4cc
  [ocean]=8c7f68f61a68ff742c2479bf91d2ae93017c732ebc20099cd4de5f3b7177bcd6
)
declare -A file=(
  [teapot]=teapot_256x256x178_uint8.raw
  [stent]=stent_128x128x256_int16.raw
  [hydrogen]=hydrogen_64x64x64_float32.raw
  [neghip]=neghip_66x66x66_uint8.raw
  [ocean]=ocean_temp_ts_180x90x19x12_float32.raw
)
# Sources (docs/data.md says what each is and its licence).
gh=https://raw.githubusercontent.com
declare -A url=(
  [teapot]=$gh/lebarba/WebGLVolumeRendering/master/Web/teapot.raw.png
  [stent]=$gh/imageio/imageio-binaries/master/images/stent.npz
  [hydrogen]=$gh/pyvista/vtk-data/master/Data/hydrogen/hydrogen.vti
  [neghip]=$gh/pyvista/vtk-data/master/Data/neghip.slc
)
ferret_deb=http://deb.debian.org/debian/pool/main/f/ferret-vis/ferret-datasets_7.6.0-5_all.deb
ferret_nc=/usr/share/ferret-vis/data/ocean_atlas_subset.nc

names=("$@")
[ ${#names[@]} -gt 0 ] || names=(teapot stent hydrogen neghip ocean)

venv() {
  if [ ! -x "$out/.venv/bin/python" ]; then
    python3 -m venv "$out/.venv"
  fi
  "$out/.venv/bin/pip" install --quiet --disable-pip-version-check "$@"
}

check() { # name
  local got
  got=$(sha256sum "$out/${file[$1]}" | cut -d' ' -f1)
  if [ "$got" != "${sha[$1]}" ]; then
    echo "$1: ${file[$1]} has SHA-256 $got, expected ${sha[$1]}; removed" >&2
    rm -f "$out/${file[$1]}"
    return 1
  fi
  echo "$1: $out/${file[$1]} ok"
}

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
failed=0
for name in "${names[@]}"; do
  if [ -z "${file[$name]:-}" ]; then
    echo "unknown volume '$name' (teapot, stent, hydrogen, neghip, ocean)" >&2
    exit 2
  fi
  if [ -f "$out/${file[$name]}" ] && check "$name"; then
    continue
  fi
  case $name in
    teapot)
      curl -fsSL -o "$tmp/teapot.png" "${url[teapot]}" && venv numpy pillow &&
      "$out/.venv/bin/python" - "$tmp/teapot.png" "$out/${file[teapot]}" <<'PY' || failed=1
import sys, numpy as np
from PIL import Image
# A 16×16 sheet of 256² slices, row by row; slices 0–177 hold the volume.
sheet = np.asarray(Image.open(sys.argv[1]).convert("L"))
tiles = [sheet[(i // 16) * 256:(i // 16 + 1) * 256, (i % 16) * 256:(i % 16 + 1) * 256] for i in range(178)]
np.stack(tiles).astype("<u1").tofile(sys.argv[2])
PY
      ;;
    stent)
      curl -fsSL -o "$tmp/stent.npz" "${url[stent]}" && venv numpy &&
      "$out/.venv/bin/python" - "$tmp/stent.npz" "$out/${file[stent]}" <<'PY' || failed=1
import sys, numpy as np
a = np.load(sys.argv[1])
a = a[a.files[0]]  # stored (z, y, x): C order is x fastest
a.astype("<i2").tofile(sys.argv[2])
PY
      ;;
    hydrogen | neghip)
      curl -fsSL -o "$tmp/$name.src" "${url[$name]}" && venv numpy vtk &&
      "$out/.venv/bin/python" - "$tmp/$name.src" "$out/${file[$name]}" "$name" <<'PY' || failed=1
import sys, numpy as np, vtk
from vtk.util.numpy_support import vtk_to_numpy
r = vtk.vtkXMLImageDataReader() if sys.argv[3] == "hydrogen" else vtk.vtkSLCReader()
r.SetFileName(sys.argv[1]); r.Update()
img = r.GetOutput()
a = vtk_to_numpy(img.GetPointData().GetScalars())  # VTK's point order is x fastest
a.astype("<f4" if sys.argv[3] == "hydrogen" else "<u1").tofile(sys.argv[2])
PY
      ;;
    ocean)
      nc=$ferret_nc
      if [ ! -f "$nc" ] && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        apt-get install -y -qq --no-install-recommends ferret-datasets >/dev/null || true
      fi
      if [ ! -f "$nc" ]; then
        # Unpacked without installing: apt's own download where apt is configured, else the
        # pinned package from Debian's pool.
        (cd "$tmp" && apt-get download -qq ferret-datasets 2>/dev/null && mv ferret-datasets_*.deb ferret.deb) ||
          curl -fsSL -o "$tmp/ferret.deb" "$ferret_deb"
        dpkg-deb -x "$tmp/ferret.deb" "$tmp/ferret" && nc="$tmp/ferret$ferret_nc"
      fi
      venv numpy netCDF4 &&
      "$out/.venv/bin/python" - "$nc" "$out/${file[ocean]}" <<'PY' || failed=1
import sys, numpy as np, netCDF4
v = netCDF4.Dataset(sys.argv[1]).variables["TEMP"]  # (TIME, Z, Y, X), fill values masked
a = np.ma.filled(v[:].astype("f4"), np.nan)
a.astype("<f4").tofile(sys.argv[2])
PY
      ;;
  esac
  if [ -f "$out/${file[$name]}" ]; then
    check "$name" || failed=1
  else
    echo "$name: could not be made (see above)" >&2
    failed=1
  fi
done
exit $failed
