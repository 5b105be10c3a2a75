"""Region selectors: which surface vertices are fixed (Λu) or touchable.

A selector is a short string, evaluated on vertex positions (in the units of
the input geometry):

=========================  ===============================================
``group:NAME``             vertices of the gmsh physical group NAME
``z<-0.9``                 half-space; axis x|y|z, operator < <= > >=
``box:x0,y0,z0,x1,y1,z1``  axis-aligned box (inclusive)
``sphere:cx,cy,cz,r``      ball (inclusive)
``all``                    every vertex
``A|B``                    union of selectors
=========================  ===============================================
"""
from __future__ import annotations

import re

import numpy as np

from pmask.errors import InputError

_HALF = re.compile(r"^\s*([xyz])\s*(<=|>=|<|>)\s*([-+0-9.eE]+)\s*$")


class SelectorError(InputError):
    """A selector that cannot be parsed or names an unknown group."""


def select(selector: str, points: np.ndarray, groups: dict | None = None,
           geometric: np.ndarray | None = None) -> np.ndarray:
    """Boolean mask of the ``points`` that ``selector`` matches.

    ``geometric`` (bool over points): where the parts that are not ``group:`` may match, e.g. a hollow
    body's outer surface, so that ``z<-8`` holds the organ where it rests and not also its cavity's floor
    (a cavity's wall is selected by its group, ``group:cavity``)."""
    groups = {} if groups is None else groups  # an empty mapping (or parse()'s any-group placeholder) is kept
    if not isinstance(selector, str) or not selector.strip():
        raise SelectorError("empty selector; use e.g. 'z<-0.9', 'box:...', 'sphere:...' or 'group:NAME'")
    mask = np.zeros(len(points), bool)
    for part in selector.split("|"):
        one = _one(part.strip(), points, groups)
        if geometric is not None and not part.strip().startswith("group:"):
            one &= geometric
        mask |= one
    return mask


def parse(selector: str) -> None:
    """Check a selector's syntax before any work (a ``group:`` name is checked against the mesh later)."""
    select(selector, np.zeros((1, 3)), _AnyGroup())


class _AnyGroup(dict):
    def __contains__(self, key):
        return True

    def __getitem__(self, key):
        return np.zeros(1, bool)


def _floats(text: str, n: int, what: str) -> list[float]:
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != n or not all(np.isfinite(vals)):
        raise SelectorError(f"selector '{what}' needs {n} comma-separated finite numbers")
    return vals


def _one(sel: str, points: np.ndarray, groups: dict) -> np.ndarray:
    if sel == "all":
        return np.ones(len(points), bool)
    if sel.startswith("group:"):
        name = sel[6:]
        if name not in groups:
            have = ", ".join(sorted(groups)) or "none"
            raise SelectorError(f"no physical group named '{name}' (groups in this mesh: {have})")
        return np.asarray(groups[name], bool)
    if sel.startswith("box:"):
        v = _floats(sel[4:], 6, sel)
        lo, hi = np.minimum(v[:3], v[3:]), np.maximum(v[:3], v[3:])
        return np.all((points >= lo) & (points <= hi), axis=1)
    if sel.startswith("sphere:"):
        v = _floats(sel[7:], 4, sel)
        if v[3] <= 0:
            raise SelectorError(f"selector '{sel}': the radius must be > 0")
        return np.linalg.norm(points - v[:3], axis=1) <= v[3]
    m = _HALF.match(sel)
    if m:
        axis, op, val = "xyz".index(m.group(1)), m.group(2), float(m.group(3))
        c = points[:, axis]
        return {"<": c < val, "<=": c <= val, ">": c > val, ">=": c >= val}[op]
    raise SelectorError(f"cannot read selector '{sel}': use 'z<-0.9', 'box:x0,y0,z0,x1,y1,z1', "
                        "'sphere:cx,cy,cz,r', 'group:NAME', 'all' or unions with '|'")
