"""Label images as input: ``--segmentation FILE --label N`` (NIfTI ``.nii``/``.nii.gz`` through nibabel, NRRD
through pynrrd, DICOM Segmentation objects through highdicom; the label of a DICOM SEG is its segment number).

The voxels equal to the label become a closed surface by scikit-image's marching cubes on the padded
mask, placed in space by the image's own voxel-to-world matrix (spacing, direction and origin; a matrix
with a negative determinant mirrors the voxels, and the triangles are turned back outwards), in NIfTI's
right-anterior-superior world: an NRRD's ``space`` (left-posterior-superior as ITK and 3D Slicer write it,
or RAS, LAS) and DICOM's patient space (LPS) are converted to it, and a NIfTI is placed by its sform or
qform as their codes say (:func:`nifti_affine`).  The staircase of the voxels is smoothed by Taubin's λ|μ filter (trimesh), which does not shrink a surface as
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


def nifti_affine(header, shape, path) -> np.ndarray:
    """A NIfTI image's voxel-to-world matrix by its codes (the NIfTI-1 standard's methods): the sform
    when ``sform_code`` > 0 (method 3: what 3D Slicer and ITK write, with the same qform), else the qform
    when ``qform_code`` > 0 (method 2: rotation, voxel sizes, origin and the qfac mirror), else the voxel
    sizes alone (method 1, ANALYZE's: the image is not placed in any world, said in a warning).  When
    both codes are set and the two matrices place the image's corners more than half a voxel apart, the
    sform is used and a warning says by how much they differ."""
    sform, scode = header.get_sform(coded=True)
    qform, qcode = header.get_qform(coded=True)
    if scode:
        if qcode:
            corners = np.array([[i, j, k, 1.0] for i in (0, shape[0] - 1) for j in (0, shape[1] - 1)
                                for k in (0, shape[2] - 1)]) if len(shape) >= 3 else np.eye(4)
            apart = float(np.abs(corners @ (sform - qform).T)[:, :3].max())
            voxel = float(np.min(np.linalg.norm(sform[:3, :3], axis=0)))
            if apart > 0.5 * voxel:
                log.warning("%s: its sform (code %d) and qform (code %d) place the image up to %.3g units apart; "
                            "the sform is used (NIfTI-1 method 3, as 3D Slicer and ITK write it)", path, int(scode),
                            int(qcode), apart)
        return np.asarray(sform, float)
    if qcode:
        return np.asarray(qform, float)
    log.warning("%s: neither its sform nor its qform code is set, so the image has no place in the world; it is "
                "placed by its voxel sizes alone (NIfTI-1 method 1), corner voxel at the origin", path)
    zooms = np.asarray(header.get_zooms()[:3], float)
    return np.diag([*zooms, 1.0])


def read_label_image(path: Path):
    """(labels, affine 4x4 voxel index -> world, unit or None) of a NIfTI, NRRD or DICOM SEG file."""
    name = path.name.lower()
    try:
        if name.endswith((".nii", ".nii.gz")):
            import nibabel

            img = nibabel.load(str(path))
            data = np.asanyarray(img.dataobj)
            unit = img.header.get_xyzt_units()[0]
            return data, nifti_affine(img.header, data.shape, path), _UNIT_NAMES.get(str(unit).lower())
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
        if name.endswith(".dcm") or _is_dicom(path):
            return dicom_seg_labels(path)
    except ImportError as exc:
        raise MeshError(f"{path}: reading label images needs the segmentation extra ({exc.name} is not "
                        "installed): pip install 'pmask[segmentation]'") from None
    except MeshError:
        raise  # already one line that names the file
    except Exception as exc:  # the readers raise many types for damaged files
        raise MeshError(f"{path}: cannot read this file as a label image ({exc})") from exc
    raise MeshError(f"{path}: a label image must be NIfTI (.nii, .nii.gz), NRRD (.nrrd, .nhdr) or a DICOM "
                    "Segmentation (.dcm)")


def _is_dicom(path: Path) -> bool:
    """A DICOM Part 10 file (the 'DICM' mark after the 128-byte preamble), whatever its name."""
    try:
        with open(path, "rb") as f:
            return f.read(132)[128:] == b"DICM"
    except OSError:
        return False


def dicom_seg_labels(path: Path):
    """(labels, affine, 'mm') of a DICOM Segmentation (as 3D Slicer exports it), read by highdicom: the
    segments' frames combined into one volume whose labels are the segment numbers, placed by the frames'
    positions, orientation and pixel spacing (highdicom sorts the frames and checks they are evenly
    spaced), in DICOM's patient space (left-posterior-superior, mm) taken to RAS like an NRRD's."""
    import highdicom
    import pydicom
    from pydicom.uid import SegmentationStorage

    ds = pydicom.dcmread(str(path))
    if ds.get("SOPClassUID") != SegmentationStorage:
        raise MeshError(f"{path}: a DICOM file, but not a Segmentation (its SOP class is "
                        f"{ds.get('SOPClassUID', 'missing')}); export the segmentation as DICOM SEG, NIfTI or NRRD")
    seg = highdicom.seg.Segmentation.from_dataset(ds)
    try:
        vol = seg.get_volume(combine_segments=True, relabel=False, dtype=np.uint16)
    except (ValueError, RuntimeError) as exc:
        raise MeshError(f"{path}: its segments cannot be read as one labelled volume ({exc}); export the segments "
                        "without overlap, or as NIfTI or NRRD") from None
    affine = np.diag([-1.0, -1.0, 1.0, 1.0]) @ np.asarray(vol.affine, float)  # LPS -> RAS
    return np.asarray(vol.array), affine, "mm"


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
