#!/usr/bin/env bash
# Sets up everything deeptissue needs on a Debian machine with Python 3.11:
# the system libraries the gmsh wheel links, a virtual environment in .venv,
# and the package (editable) with its pinned dependencies. Safe to run again.
set -euo pipefail
cd "$(dirname "$0")"

# The gmsh wheel imports headless but links these shared libraries.
sys_pkgs=(libglu1-mesa libgl1 libxrender1 libxcursor1 libxfixes3 libxext6 libxft2
          libfontconfig1 libxinerama1 libx11-6 libgomp1)
# MKL (PARDISO) exists for x86-64 only; elsewhere the FE solves use SuiteSparse CHOLMOD (extra "cholmod"),
# which builds against Debian's SuiteSparse and is fast with OpenBLAS
extras="test"
if [ "$(uname -m)" != "x86_64" ]; then
    sys_pkgs+=(libsuitesparse-dev libopenblas0-pthread build-essential)
    extras="test,cholmod"
fi
missing=()
for p in "${sys_pkgs[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "setup: installing system libraries: ${missing[*]}"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}"
fi

PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[$extras]"
echo "setup: ready (.venv)"
