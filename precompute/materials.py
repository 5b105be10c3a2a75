"""Materials by region (#26): a volume's named regions (a ``--volume`` mesh's physical volume groups, a built-in
model's inclusion) each with its own Young's modulus and Poisson ratio, assembled element by element
(:mod:`pmask.precompute.assembly`).  Green's functions from a finite-element solve can hold any material
distribution at no cost to the runtime: the stiffer mass under softer tissue is in Ξ, and so in every K_i.

``--materials NAME:E:nu,NAME:E:nu`` names regions of the mesh; tetrahedra in no named region keep the body's
material (``-E``, ``--nu`` or the model's).  A region named but absent from the mesh, an empty one, or two that
overlap are refused in one line.
"""
from __future__ import annotations

import numpy as np

from pmask.errors import InputError


class MaterialError(InputError):
    """A ``--materials`` text or a region assignment that cannot be used."""


def parse_materials(text: str | None) -> dict:
    """``"NAME:E:nu,..."`` -> {NAME: (E, nu)}; each pair checked as ``-E``/``--nu`` are."""
    from pmask.precompute.elasticity import check_material

    out: dict = {}
    if not text:
        return out
    for part in str(text).split(","):
        bits = part.strip().split(":")
        if len(bits) != 3 or not bits[0]:
            raise MaterialError(f"--materials entry '{part.strip()}': give NAME:E:nu (e.g. inclusion:1e5:0.45)")
        try:
            E, nu = float(bits[1]), float(bits[2])
        except ValueError:
            raise MaterialError(f"--materials entry '{part.strip()}': E and nu must be numbers") from None
        check_material(E, nu)
        if bits[0] in out:
            raise MaterialError(f"--materials names region '{bits[0]}' twice")
        out[bits[0]] = (E, nu)
    return out


def per_element(regions: dict, n_tets: int, base: tuple, assigned: dict):
    """(E, nu) per tetrahedron and a report [{name, E, nu, tets}] for the regions in ``assigned`` (NAME ->
    (E, nu)), the rest at ``base``; ``regions`` maps region names to boolean masks over the tetrahedra."""
    E = np.full(n_tets, float(base[0]))
    nu = np.full(n_tets, float(base[1]))
    label = np.full(n_tets, -1, np.int64)
    report = []
    for k, (name, (e, n)) in enumerate(assigned.items()):
        if name not in regions:
            have = ", ".join(sorted(regions)) or "none"
            raise MaterialError(f"--materials: no volume region named '{name}' (regions in this mesh: {have})")
        mask = np.asarray(regions[name], bool)
        if not mask.any():
            raise MaterialError(f"--materials: region '{name}' has no tetrahedra")
        if np.any(label[mask] >= 0):
            raise MaterialError(f"--materials: regions '{report[int(label[mask][label[mask] >= 0][0])]['name']}' and "
                                f"'{name}' overlap; give each tetrahedron one material")
        E[mask], nu[mask], label[mask] = e, n, k
        report.append({"name": name, "E": float(e), "nu": float(n), "tets": int(mask.sum())})
    return E, nu, label, report
