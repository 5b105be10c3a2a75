"""Label images as input: ``--segmentation FILE --label N`` (NIfTI ``.nii``/``.nii.gz`` through nibabel, NRRD
through pynrrd).

The voxels equal to the label become a closed surface by scikit-image's marching cubes on the padded
mask, placed in space by the image's own voxel-to-world matrix (spacing, direction and origin; a matrix
with a negative determinant mirrors the voxels, and the triangles are turned back outwards), in NIfTI's
right-anterior-superior world: an NRRD's ``space`` (left-posterior-superior as ITK and 3D Slicer write it,
or RAS, LAS) is converted to it.  The
staircase of the voxels is smoothed by Taubin's λ|μ filter (trimesh), which does not shrink a surface as
Laplacian smoothing does; the volume change of the smoothing is measured and reported (more than 1 % is
refused), and so is the volume against the voxel count.  The surface then takes the ``--surface`` route (checks, debris, gmsh remesh to
``--edge-length``).  Lengths are in the header's unit; a header that names none needs ``--units``.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from pmask.precompute.meshing import MeshError

log = logging.getLogger(__name__)

#: Taubin smoothing (trimesh.smoothing.filter_taubin): the default λ and μ, this many passes
SMOOTHING_PASSES = 10
#: the smoothed surface may change the enclosed volume by at most this share of the voxels' volume
MAX_VOLUME_CHANGE = 0.01
_UNIT_NAMES = {"mm": "mm", "millimeter": "mm", "millimeters": "mm", "m": "m", "meter": "m", "meters": "m",
               "um": "um", "micron": "um", "micrometer": "um", "cm": "cm", "centimeter": "cm"}


#: NRRD's anatomical 'space' values (full and abbreviated) to the axis signs that take them to RAS, NIfTI's
#: world (the kinds without an anatomical frame, scanner-xyz and 3D-right-handed, are taken as they are)
NRRD_TO_RAS = {"left-posterior-superior": (-1.0, -1.0, 1.0), "lps": (-1.0, -1.0, 1.0),
               "right-anterior-superior": (1.0, 1.0, 1.0), "ras": (1.0, 1.0, 1.0),
               "left-anterior-superior": (-1.0, 1.0, 1.0), "las": (-1.0, 1.0, 1.0)}


def read_label_image(path: Path):
    """(labels, affine 4x4 voxel index -> world, unit or None) of a NIfTI or NRRD file."""
    name = path.name.lower()
    try:
        if name.endswith((".nii", ".nii.gz")):
            import nibabel

            img = nibabel.load(str(path))
            data = np.asanyarray(img.dataobj)
            unit = img.header.get_xyzt_units()[0]
            return data, np.asarray(img.affine, float), _UNIT_NAMES.get(str(unit).lower())
        if name.endswith((".nrrd", ".nhdr")):
            import nrrd

            data, header = nrrd.read(str(path))
            directions = np.asarray(header.get("space directions", np.eye(3)), float)
            origin = np.asarray(header.get("space origin", np.zeros(3)), float)
            affine = np.eye(4)
            affine[:3, :3] = directions.T  # row k of 'space directions' is the step of index k
            affine[:3, 3] = origin
            # NRRD's world is the header's 'space' (ITK and 3D Slicer write left-posterior-superior); NIfTI's
            # affine is right-anterior-superior: the model is placed in RAS, whichever file it came from
            to_ras = NRRD_TO_RAS.get(str(header.get("space", "")).strip().lower())
            if to_ras is not None:
                affine = np.diag([*to_ras, 1.0]) @ affine
            units = header.get("space units")
            unit = _UNIT_NAMES.get(str(units[0]).lower()) if units else None
            return data, affine, unit
    except ImportError as exc:
        raise MeshError(f"{path}: reading label images needs the segmentation extra ({exc.name} is not "
                        "installed): pip install 'pmask[segmentation]'") from None
    except Exception as exc:  # the readers raise many types for damaged files
        raise MeshError(f"{path}: cannot read this file as a label image ({exc})") from exc
    raise MeshError(f"{path}: a label image must be NIfTI (.nii, .nii.gz) or NRRD (.nrrd, .nhdr)")


def mask_surface(mask: np.ndarray, affine: np.ndarray, *, field: np.ndarray | None = None, level: float = 0.5):
    """Marching cubes (scikit-image) on the padded boolean ``mask`` at level 1/2 (or on ``field`` at
    ``level``, values increasing inwards), placed by the 4x4 voxel-to-world ``affine`` and turned
    outwards, then Taubin-smoothed.  Returns the trimesh surface and the volume before smoothing.
    (The label images' route and the voxel repair share it.)"""
    import trimesh
    from skimage.measure import marching_cubes

    volume = np.pad(mask, 1).astype(np.float32) if field is None else np.pad(field, 1, constant_values=field.min())
    if not volume.max() > level:
        raise MeshError("no part of the solid is thicker than a voxel")
    verts, faces, _, _ = marching_cubes(volume.astype(np.float32), level=level)
    verts -= 1.0  # back to the image's voxel indices
    world = verts @ affine[:3, :3].T + affine[:3, 3]
    mesh = trimesh.Trimesh(world, faces, process=True)
    if mesh.volume < 0:  # a mirroring voxel-to-world matrix turned the triangles inwards
        mesh.invert()
    raw_volume = float(mesh.volume)
    trimesh.smoothing.filter_taubin(mesh, iterations=SMOOTHING_PASSES)
    return mesh, raw_volume


def label_surface(path: Path, label: int, units: str | None, with_labels=()) -> tuple[np.ndarray, np.ndarray, dict]:
    """The closed surface of ``label`` (points in the image's length unit, triangles) and a report.
    ``with_labels``: labels inside it that belong to the body (a multi-label segmentation's inclusions): the
    surface is that of their union, so that an inclusion is not a cavity."""
    data, affine, header_unit = read_label_image(path)
    if data.ndim != 3:
        raise MeshError(f"{path}: a 3-D label image is needed, this one has shape {data.shape}")
    if header_unit is None and units is None:
        raise MeshError(f"{path}: the header does not say the voxel spacing's unit; pass --units mm (or m, cm, um)")
    if header_unit is not None and units is not None and header_unit != units:
        raise MeshError(f"{path}: the header says the spacing is in {header_unit}, --units says {units}; "
                        "leave --units out to use the header's")
    for extra in with_labels:
        if not np.any(np.asarray(data) == extra):
            present = np.unique(np.asarray(data))
            raise MeshError(f"{path}: --materials names label {extra}, but no voxel has it; the labels present are "
                            + ", ".join(str(v) for v in present[:20]))
    mask = np.isin(np.asarray(data), [label, *with_labels])
    if not mask.any():
        present = np.unique(np.asarray(data))
        shown = ", ".join(str(v) for v in present[:20]) + (" ..." if len(present) > 20 else "")
        raise MeshError(f"{path}: no voxel has label {label}; the labels present are {shown}")
    mesh, raw_volume = mask_surface(mask, affine)
    voxel_volume = float(mask.sum() * abs(np.linalg.det(affine[:3, :3])))
    change = float(mesh.volume) / raw_volume - 1.0
    report = {"label": int(label), "voxels": int(mask.sum()), "voxel_volume": voxel_volume,
              "marching_cubes_volume": raw_volume, "smoothed_volume": float(mesh.volume),
              "smoothing_volume_change": change, "volume_vs_voxels": float(mesh.volume) / voxel_volume - 1.0,
              "unit": header_unit or units}
    if abs(change) > MAX_VOLUME_CHANGE:
        raise MeshError(f"{path}: smoothing the surface of label {label} changes its volume by {100 * change:+.1f} % "
                        f"(more than {100 * MAX_VOLUME_CHANGE:g} %); the region is probably only a few voxels thick: "
                        "use an image with finer spacing")
    log.info("%s label %d: %d voxels, surface of %d triangles, smoothing changed its volume by %+.2f %%", path,
             label, int(mask.sum()), len(mesh.faces), 100 * change)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces), report
