r"""The display surface at the scan's resolution, deformed with the simulation surface (the scans issue's item 6).

An artifact from a ``--surface`` file or a label image keeps that surface (:mod:`pmask.precompute.display`) with
each display vertex's embedding in the simulation surface: the three simulation vertices of its triangle, the
barycentric weights b of its closest point there and the lift ℓ (the display vertex minus that point).  Its
deformation for the simulation surface's displacement u (eq. 16, :meth:`pmask.runtime.Contacts.deformation`):

.. math::  x_d' = x_d + \sum_k b_{d,k}\, u_{v_{d,k}} - w_d\, \ell_d, \qquad
           w_d = \max_c \operatorname{smoothstep}(1 - \lVert x_d - p_c \rVert / r)

with p_c the contacts' proxy points and r the mask radius: at a contact the display surface lies on the deformed
simulation surface, which meets the tool, and a mask radius away it keeps its own detail.  numpy here; the
native core computes the same (:func:`pmask.runtime.servo.display_deform`, ``pm_display_deform`` in C).
"""
from __future__ import annotations

import numpy as np

from pmask.errors import InputError


class DisplaySurface:
    """The display surface: ``points`` (m, 3), ``triangles`` (k, 3) and the embedding ``vertices`` (m, 3),
    ``bary`` (m, 3), ``lift`` (m, 3) (module docstring); :meth:`deform` moves it."""

    def __init__(self, points, triangles, vertices, bary, lift):
        self.points = np.ascontiguousarray(points, float)
        self.triangles = np.ascontiguousarray(triangles, np.int64)
        self.vertices = np.ascontiguousarray(vertices, np.int64)
        self.bary = np.ascontiguousarray(bary, float)
        self.lift = np.ascontiguousarray(lift, float)
        m = len(self.points)
        if not (self.vertices.shape == self.bary.shape == self.lift.shape == (m, 3)):
            raise InputError("display surface: the embedding's arrays do not match its points")

    @classmethod
    def from_artifact(cls, path, verify: bool = True) -> "DisplaySurface | None":
        """The artifact's display surface, or None when it has none (a model, a --volume mesh, --no-display);
        ``verify`` as :meth:`pmask.runtime.Model.load`'s."""
        from pmask.runtime.artifact import DISPLAY, read_artifact

        d = read_artifact(path, datasets=DISPLAY, verify=verify)
        if d.get("display/points") is None:
            return None
        return cls(*(d[k] for k in DISPLAY))

    def deform(self, u, contacts=(), radius: float = 0.0) -> np.ndarray:
        """The displaced display points (m, 3) for the simulation surface's displacement ``u`` (n_s, 3); with
        ``contacts`` (proxy points) and the mask ``radius`` the surface is laid onto the simulation surface
        around each contact (module docstring)."""
        out = self.points + self._carried(u)
        w = contact_weights(self.points, contacts, radius)
        if w is not None:
            out -= w[:, None] * self.lift
        return out

    def on(self, rest) -> "DisplaySurface":
        """This display surface laid onto the simulation surface drawn at ``rest`` (n_s, 3) rather than at the
        points it was embedded in: the lift becomes x_d − Σ_k b_{d,k} rest_{v_{d,k}} (ℓ_d less the embedding
        point's move), so that at a contact it lies on the rest surface plus u (the contact surface rounds the
        simulation mesh's creases: :attr:`pmask.runtime.contact.ContactSurface.mesh_points`)."""
        return DisplaySurface(self.points, self.triangles, self.vertices, self.bary, self.points - self._carried(rest))

    def _carried(self, values) -> np.ndarray:
        """Σ_k b_{d,k} values_{v_{d,k}} (m, 3): a per-vertex quantity of the simulation surface at the display
        vertices' embedding points."""
        return np.einsum("dk,dkc->dc", self.bary, np.asarray(values, float)[self.vertices])


def contact_weights(points: np.ndarray, contacts, radius: float) -> np.ndarray | None:
    """w_d = max over contacts of smoothstep(1 − ‖x_d − p_c‖ / r), or None without contacts."""
    contacts = [np.asarray(c, float) for c in contacts if c is not None]
    if not contacts or not radius > 0:
        return None
    w = np.zeros(len(points))
    for c in contacts:
        s = np.clip(1.0 - np.linalg.norm(points - c, axis=1) / radius, 0.0, 1.0)
        np.maximum(w, s * s * (3.0 - 2.0 * s), out=w)
    return w
