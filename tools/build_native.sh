#!/usr/bin/env bash
# Build precompute/_selected_inverse.c (the P1 Green's-function stage: selected inversion over CHOLMOD) into
# the venv, against Debian's SuiteSparse and the system LAPACK (threaded OpenBLAS after
# tools/install_cholmod.sh).  Without the headers or a compiler it removes any old build and the
# precompute uses cvxopt's CHOLMOD and SciPy's LAPACK instead: same numbers, slower.
set -u
VENV="$1"
SRC="$(dirname "$0")/../precompute/_selected_inverse.c"
DEST="$VENV/lib/pmask/libpmask_selinv.so"
mkdir -p "$(dirname "$DEST")"
rm -f "$VENV/lib/pmask/libpmask_surface_factor.so"  # the dense-route library of ABI 2
if [ -f /usr/include/suitesparse/cholmod.h ] && command -v gcc >/dev/null 2>&1; then
  if gcc -O2 -Wall -shared -fPIC -pthread -I/usr/include/suitesparse "$SRC" -lcholmod -llapack -lblas \
       -o "$DEST.tmp" 2>"$DEST.log"; then
    mv "$DEST.tmp" "$DEST"
    rm -f "$DEST.log"
    exit 0
  fi
  echo "note: the native CHOLMOD library did not build (see $DEST.log); using cvxopt's CHOLMOD (slower)"
else
  echo "note: no SuiteSparse headers or no gcc: the precompute uses cvxopt's CHOLMOD (slower)"
fi
rm -f "$DEST" "$DEST.tmp"
exit 0
