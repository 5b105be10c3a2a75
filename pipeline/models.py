"""Model registry: names a user can give to ``pmask precompute``."""
from __future__ import annotations

from functools import partial

from pmask.meshes import halfspace, kidney, liver, loop, palpation

from pmask.errors import InputError

#: name -> (builder, one-line description)
MODELS = {
    "kidney": (kidney.build, "kidney-shaped solid, 11 x 6 x 4 cm, fixed at the hilum (~1,500 free vertices)"),
    "palpation": (palpation.build, "block of soft tissue with a 10x stiffer ball 10 mm under its upper face (materials "
                                   "by region)"),
    "liver": (liver.build, "liver lobe, 15 x 10 x 5.5 cm, held on its flat posterior face, with a 5x stiffer 20 mm "
                           "mass under the anterior surface (materials by region)"),
    "halfspace": (halfspace.build, "hemisphere standing in for a half-space, graded mesh at the load point"),
    **{f"loop{k}": (partial(loop.build, level=k),
                    f"Figure 5 ellipsoid, Loop level {k} ({[34, 130, 514, 2050][k]} surface vertices)")
       for k in range(4)},
}


class UnknownModelError(InputError):
    """A model name that is not registered."""


def get_model(name: str):
    """The builder registered under ``name``."""
    try:
        return MODELS[name][0]
    except KeyError:
        raise UnknownModelError(f"unknown model '{name}'; models: {', '.join(MODELS)} "
                                "(or give your own geometry with --surface FILE or --volume FILE)") from None
