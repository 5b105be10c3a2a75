"""pmask: precomputed elastostatic Green's functions and pressure masks for point-like haptic contact.

After James & Pai, *Pressure Masks for Point-like Contact with Elastic Models*.  The package has an
offline half that needs the ``[precompute]`` extra and a runtime half that needs numpy and h5py only:

- :mod:`pmask.runtime`    masks, vertex and surface stiffness, deformation, haptic contact (numpy + h5py)
- :mod:`pmask.precompute` meshing, assembly, sparse factorisation, Green's functions (offline)
- :mod:`pmask.pipeline`   the ``pmask`` command line, stage orchestration, reference tables
- :mod:`pmask.meshes`     the built-in models (kidney, half-space, the Figure 5 family)
"""
__version__ = "0.2.0"
