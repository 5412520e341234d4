#!/usr/bin/env bash
# Installs the C and Fortran client as HPC codes expect to find it:
#   PREFIX/include/insitu.h
#   PREFIX/lib/libinsitu.a, libinsitu.so.VERSION (SONAME libinsitu.so.MAJOR) with the links
#     libinsitu.so.MAJOR and libinsitu.so
#   PREFIX/lib/pkgconfig/insitu.pc          pkg-config --cflags --libs insitu
#   PREFIX/lib/cmake/insitu/insituConfig.cmake, insituConfigVersion.cmake
#                                           find_package(insitu) → insitu::insitu, insitu::static
#   PREFIX/share/insitu/fortran/insitu.f90  the Fortran module's source (.mod files are
#                                           compiler-specific: compile it with your compiler)
# Usage (after `cargo build --release -p insitu-client-c`): client-c/install.sh PREFIX
# INSITU_LIB_DIR names where the built libraries are (default: the workspace's target/release).
set -euo pipefail
prefix=${1:?usage: client-c/install.sh PREFIX}
here=$(cd "$(dirname "$0")" && pwd)
libs=${INSITU_LIB_DIR:-$here/../target/release}
version=$(sed -n 's/^version = "\(.*\)"$/\1/p' "$here/../Cargo.toml" | head -1)
major=${version%%.*}
for f in libinsitu.a libinsitu.so; do
  if [ ! -f "$libs/$f" ]; then
    echo "install.sh: $libs/$f is missing: run cargo build --release -p insitu-client-c first" >&2
    exit 1
  fi
done
mkdir -p "$prefix/include" "$prefix/lib/pkgconfig" "$prefix/lib/cmake/insitu" "$prefix/share/insitu/fortran"
prefix=$(cd "$prefix" && pwd)
install -m 644 "$here/include/insitu.h" "$prefix/include/insitu.h"
install -m 644 "$here/fortran/insitu.f90" "$prefix/share/insitu/fortran/insitu.f90"
install -m 644 "$libs/libinsitu.a" "$prefix/lib/libinsitu.a"
install -m 755 "$libs/libinsitu.so" "$prefix/lib/libinsitu.so.$version"
ln -sf "libinsitu.so.$version" "$prefix/lib/libinsitu.so.$major"
ln -sf "libinsitu.so.$major" "$prefix/lib/libinsitu.so"

cat > "$prefix/lib/pkgconfig/insitu.pc" <<PC
prefix=$prefix
libdir=\${prefix}/lib
includedir=\${prefix}/include

Name: insitu
Description: Simulation client of the insitu VDI service (C API; Fortran module source in \${prefix}/share/insitu/fortran)
Version: $version
Cflags: -I\${includedir}
Libs: -L\${libdir} -Wl,-rpath,\${libdir} -linsitu
Libs.private: -lpthread -ldl -lm
PC

cat > "$prefix/lib/cmake/insitu/insituConfig.cmake" <<'CMAKE'
# find_package(insitu): the imported targets insitu::insitu (shared) and insitu::static.
get_filename_component(_insitu_prefix "${CMAKE_CURRENT_LIST_DIR}/../../.." ABSOLUTE)
if(NOT TARGET insitu::insitu)
  add_library(insitu::insitu SHARED IMPORTED)
  set_target_properties(insitu::insitu PROPERTIES
    IMPORTED_LOCATION "${_insitu_prefix}/lib/libinsitu.so.@VERSION@"
    IMPORTED_SONAME "libinsitu.so.@MAJOR@"
    INTERFACE_INCLUDE_DIRECTORIES "${_insitu_prefix}/include")
  add_library(insitu::static STATIC IMPORTED)
  set_target_properties(insitu::static PROPERTIES
    IMPORTED_LOCATION "${_insitu_prefix}/lib/libinsitu.a"
    INTERFACE_INCLUDE_DIRECTORIES "${_insitu_prefix}/include"
    INTERFACE_LINK_LIBRARIES "pthread;dl;m")
endif()
set(insitu_FORTRAN_MODULE_SOURCE "${_insitu_prefix}/share/insitu/fortran/insitu.f90")
unset(_insitu_prefix)
CMAKE
sed -i "s/@VERSION@/$version/; s/@MAJOR@/$major/" "$prefix/lib/cmake/insitu/insituConfig.cmake"

cat > "$prefix/lib/cmake/insitu/insituConfigVersion.cmake" <<CMAKE
# Compatible when the major version matches and the one installed is at least the one asked.
set(PACKAGE_VERSION "$version")
if(PACKAGE_FIND_VERSION VERSION_GREATER PACKAGE_VERSION OR NOT PACKAGE_FIND_VERSION_MAJOR STREQUAL "$major")
  set(PACKAGE_VERSION_COMPATIBLE FALSE)
else()
  set(PACKAGE_VERSION_COMPATIBLE TRUE)
  if(PACKAGE_FIND_VERSION STREQUAL PACKAGE_VERSION)
    set(PACKAGE_VERSION_EXACT TRUE)
  endif()
endif()
CMAKE
echo "installed insitu $version into $prefix"
