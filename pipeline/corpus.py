"""A corpus of damaged and awkward surfaces as segmentation exports carry them, made here (no downloads):
the real-inputs issue's test (tests/test_corpus.py) and `make bench`'s comparison of the repair routes
(bench/repair_compare.py) run over it.  Lengths in mm."""
from __future__ import annotations

import numpy as np

from pmask.precompute.meshing import join_surfaces


#: the overlapping case's second sphere: radius and centre distance from the 20 mm sphere's centre (mm)
OVERLAP = (12.0, 22.0)


def union_volume(R: float = 20.0, r: float = OVERLAP[0], d: float = OVERLAP[1]) -> float:
    """Volume of the union of two overlapping balls (radii R, r, centres d apart): both minus the lens."""
    lens = np.pi * (R + r - d) ** 2 * (d * d + 2 * d * r - 3 * r * r + 2 * d * R + 6 * r * R - 3 * R * R) / (12 * d)
    return 4 / 3 * np.pi * (R**3 + r**3) - lens


def sphere(r=20.0, sub=3, at=(0.0, 0.0, 0.0)):
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    return np.asarray(s.vertices) + at, np.asarray(s.faces)


def voxel_faces(inside: np.ndarray, spacing: float = 1.0):
    """The boundary faces of a voxel set as an outward triangle surface (two triangles per face, corners shared):
    a label image exported as its voxels' faces, every edge between faces a 90° crease."""
    pad = np.pad(np.asarray(inside, bool), 1)
    quads = []
    for axis in range(3):
        a, b = [k for k in range(3) if k != axis]
        for side in (0, 1):
            neighbour = np.roll(pad, -1 if side else 1, axis=axis)
            for i in np.argwhere(pad & ~neighbour) - 1:
                base = i.astype(float)
                base[axis] += side
                c = []
                for da, db in ((0, 0), (1, 0), (1, 1), (0, 1)):
                    q = base.copy()
                    q[a] += da
                    q[b] += db
                    c.append(q)
                normal = np.cross(c[1] - c[0], c[3] - c[0])
                if normal[axis] * (1 if side else -1) < 0:
                    c = c[::-1]
                quads.append(c)
    q = np.asarray(quads).reshape(-1, 3)
    pts, inverse = np.unique(q, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1, 4)
    return spacing * pts, np.vstack([inverse[:, [0, 1, 2]], inverse[:, [0, 2, 3]]])


def corpus() -> dict:
    """Case name -> (vertices, triangles)."""
    import trimesh

    v, f = sphere()
    cases = {}
    cases["several shells"] = join_surfaces(sphere(), sphere(at=(50.0, 0, 0)), sphere(at=(0, 50.0, 0)))
    a, b = sphere(), sphere(r=10.0, sub=2)
    b = (b[0] + a[0][a[1][0][0]] - b[0][b[1][0][0]] + [0, 0, 0.0], b[1])
    P, T = join_surfaces(a, b)
    n = len(a[0])
    edge, point = T.copy(), T.copy()
    edge[edge == b[1][0][0] + n], edge[edge == b[1][0][1] + n] = a[1][0][0], a[1][0][1]  # one shared edge
    point[point == b[1][0][0] + n] = a[1][0][0]  # one shared vertex
    cases["touching shells"] = (P, edge)
    cases["touching at a point"] = (P, point)
    cases["holes"] = (v, np.delete(f, [0, 7, 40, 41], axis=0))
    flipped = f.copy()
    patch = np.flatnonzero(v[f].mean(axis=1)[:, 2] > 15.0)
    flipped[patch] = flipped[patch][:, ::-1]
    cases["flipped patch"] = (v, flipped)
    poked = v.copy()
    poked[0] = -1.6 * poked[0]
    cases["self-intersection"] = (poked, f)
    plate = trimesh.creation.box(extents=(40.0, 40.0, 0.4))
    cases["thin feature"] = (np.asarray(plate.vertices), np.asarray(plate.faces))
    # two organs' surfaces exported together and running into each other: the body is their union
    cases["overlapping shells"] = join_surfaces(sphere(), sphere(r=OVERLAP[0], at=(OVERLAP[1], 0, 0)))
    cases["debris"] = join_surfaces(sphere(), sphere(r=0.4, sub=1, at=(30.0, 0, 0)),
                                    sphere(r=0.4, sub=1, at=(0, 30.0, 0)))
    # a label image's voxel faces exported unsmoothed (a ball of radius 14 voxels of 1.25 mm, centred): gmsh kept
    # every 90° crease as a feature curve, 37x the vertices --edge-length asked for
    g = np.indices((36, 36, 36)).reshape(3, -1).T - 17.5
    vp, vf = voxel_faces((np.linalg.norm(g, axis=1) <= 14.0).reshape(36, 36, 36), 1.25)
    cases["voxel staircase"] = (vp - 1.25 * 18.0, vf)
    # two chambers exported together, each closed, sharing a wall (the wall's rim is in four triangles): the
    # body is their union, 40 x 20 x 20 mm
    left, right = (trimesh.creation.box(extents=(20.0, 20.0, 20.0)) for _ in range(2))
    left.apply_translation((-10.0, 0.0, 0.0))
    right.apply_translation((10.0, 0.0, 0.0))
    cases["shared wall"] = join_surfaces((np.asarray(left.vertices), np.asarray(left.faces)),
                                         (np.asarray(right.vertices), np.asarray(right.faces)))
    # a hollow organ: a 3 mm wall between an outer shell and an inner one facing inwards (a cavity)
    inner = sphere(r=17.0)
    cases["hollow wall"] = join_surfaces(sphere(), (inner[0], inner[1][:, ::-1]))
    # an open scan with a thin part: a flap 5 mm thick (one edge length at the corpus's 5 mm) sunk into the
    # body, as finely triangulated as the body (MeshFix alone kept the flap: the shell with most triangles),
    # holes in both; the body is their union
    flap = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    P, T = join_surfaces(sphere(), (np.asarray(flap.vertices) * [2.5, 8.0, 12.0] + [0.0, 0.0, 26.0],
                                    np.asarray(flap.faces)))
    tip = np.flatnonzero((T.min(axis=1) >= len(v)) & (P[T].mean(axis=1)[:, 2] > 35.0))[:4]
    cases["open thin parts"] = (P, np.delete(T, np.concatenate([[0, 7, 40], tip]), axis=0))
    big = trimesh.creation.icosphere(subdivisions=7, radius=20.0)  # 327,680 triangles
    cases["over 300,000 triangles"] = (np.asarray(big.vertices), np.asarray(big.faces))
    return cases
