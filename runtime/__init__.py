"""Runtime half: pressure masks, vertex and surface stiffness, deformation, haptic contact.

Imports numpy and h5py only, so it can live inside a haptic application::

    from pmask.runtime import Model
    model = Model.load("artifacts/kidney.h5")
    stiff = model.stiffness()                    # cone masks of the default radius
    K = stiff.at(triangle, barycentric)          # 3x3 surface stiffness K(x), eq. 15
    f = K @ u_bar                                # force on the body for displacement ū
    v = stiff.deformation(triangle, barycentric, f)   # surface displacement, eq. 16
"""
from pmask.runtime.artifact import ArtifactError, read_artifact
from pmask.runtime.device import Device, stable_stiffness
from pmask.runtime.haptics import Contacts, HapticContact, Status
from pmask.runtime.masks import MASK_KINDS, Masks, pressure_masks
from pmask.runtime.model import Model
from pmask.runtime.stiffness import Stiffness, SurfaceStiffness, vertex_stiffness

__all__ = ["ArtifactError", "Contacts", "Device", "HapticContact", "stable_stiffness", "MASK_KINDS", "Masks", "Model", "Status", "Stiffness",
           "SurfaceStiffness", "pressure_masks", "read_artifact", "vertex_stiffness"]
