#!/usr/bin/env bash
# Optional fast path for the precompute: CHOLMOD from Debian's SuiteSparse, linked to a threaded
# OpenBLAS.  P1 uses it through our C (tools/build_native.sh, precompute/native.py); P2's blocked
# solves through scikit-sparse 0.4.16 (0.5 needs SuiteSparse 7, which Debian does not ship).
# Anything missing (no root, no apt, a failed build) leaves the cvxopt path in place: the results
# are the same to 1e-12, only slower.
set -u
PIP="$1"
have() { dpkg -s "$1" >/dev/null 2>&1; }
if ! { have libsuitesparse-dev && have libopenblas0-pthread; }; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
        libsuitesparse-dev libopenblas0-pthread; } >/dev/null 2>&1 \
      || echo "note: apt-get could not install SuiteSparse; the precompute uses cvxopt's CHOLMOD (slower)"
  else
    echo "note: for a ~3x faster factorisation run as root: apt-get install libsuitesparse-dev" \
         "libopenblas0-pthread, then make venv again; using cvxopt's CHOLMOD"
  fi
fi
if have libsuitesparse-dev; then
  "$PIP" install --quiet "scikit-sparse==0.4.16" \
    || echo "note: scikit-sparse did not build; the precompute uses cvxopt's CHOLMOD (slower)"
fi
exit 0
