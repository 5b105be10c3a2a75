"""pmask: precomputed elastostatic Green's functions and pressure masks for point-like haptic contact.

After James & Pai, *Pressure Masks for Point-like Contact with Elastic Models*.  The package has an
offline half that needs the ``[precompute]`` extra and a runtime half that needs numpy and h5py only:

- :mod:`pmask.runtime`    masks, vertex and surface stiffness, deformation, haptic contact (numpy + h5py)
- :mod:`pmask.precompute` meshing, assembly, sparse factorisation, Green's functions (offline)
- :mod:`pmask.pipeline`   the ``pmask`` command line, stage orchestration, reference tables
- :mod:`pmask.meshes`     the built-in models (kidney, half-space, the Figure 5 family)
"""
__version__ = "0.2.0"


def _from_a_checkout() -> None:
    """In a source checkout the subpackages live beside this folder (``runtime/``, not ``pmask/runtime/``;
    ``pyproject.toml`` maps them), so Python started in the checkout's root finds this folder first and, after a
    regular ``pip install .``, no ``pmask.runtime`` in it.  Then the installed package answers (with its
    compiled parts), or, with none installed, the checkout's own folders (pure Python: the C core's fallback).
    An editable install (``make venv``) maps the subpackages itself and needs none of this."""
    import sys
    from pathlib import Path

    here = Path(__file__).resolve().parent
    root = here.parent
    if not (root / "pyproject.toml").is_file() or not (root / "runtime" / "__init__.py").is_file():
        return  # an installed package
    if any(type(f).__name__.startswith("_EditableFinder") or "__editable__" in type(f).__module__
           for f in sys.meta_path):
        return  # the editable install's finder maps pmask.runtime -> runtime/
    for entry in sys.path:
        candidate = Path(entry or ".").resolve() / "pmask"
        if candidate != here and (candidate / "runtime" / "__init__.py").is_file():
            __path__[:] = [str(candidate)]  # the installed package, compiled parts and all
            return
    __path__.append(str(root))  # no installed package: the checkout's folders


_from_a_checkout()
