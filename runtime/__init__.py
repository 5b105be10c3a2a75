"""Runtime half: pressure masks, vertex and surface stiffness, deformation, haptic contact.

Imports numpy and h5py only, so it can live inside a haptic application::

    from runtime import Model
    model = Model.load("artifacts/kidney.h5")
    stiff = model.stiffness(mask="linear", radius=2.0 * model.mean_edge_length)
    K = stiff.at(triangle, barycentric)          # 3x3 surface stiffness K(x), eq. 15
    f = K @ u_bar                                # force on the body for displacement ū
    v = stiff.deformation(triangle, barycentric, f)   # surface displacement, eq. 16
"""
from runtime.artifact import ArtifactError, read_artifact
from runtime.haptics import HapticContact, Status
from runtime.masks import MASK_KINDS, Masks, pressure_masks
from runtime.model import Model
from runtime.stiffness import Stiffness, SurfaceStiffness, vertex_stiffness

__all__ = ["ArtifactError", "HapticContact", "MASK_KINDS", "Masks", "Model", "Status", "Stiffness",
           "SurfaceStiffness", "pressure_masks", "read_artifact", "vertex_stiffness"]
