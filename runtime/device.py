"""The haptic device as the rendering's stability depends on it.

A sampled-data virtual wall of stiffness k is passive when the device's physical damping b exceeds
kT/2 plus the virtual damping B (Colgate & Schenkel): k < 2 (b − B) / T, with T the servo period.
``b`` is the damping at the handle the software cannot remove: the device's own viscous friction and,
while held, the hand's.  The default is the lightly held 3-DOF device the haptics issue measured with
(0.05 N·s/m device + 0.3 N·s/m light grip, 1 kHz): 700 N/m.  CHAI3D's device descriptions recommend
1,000–3,000 N/m for desk devices held firmly; pass your device's numbers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from pmask.errors import InputError


def stable_stiffness(damping: float, rate: float, virtual_damping: float = 0.0) -> float:
    """The largest passive wall stiffness [N/m]: 2 (b − B) / T = 2 (b − B) · rate."""
    return max(0.0, 2.0 * (damping - virtual_damping) * rate)


@dataclass(frozen=True)
class Device:
    """rate : servo rate [Hz]; damping : physical damping b at the handle [N·s/m]."""

    rate: float = 1000.0
    damping: float = 0.35

    def __post_init__(self):
        for name in ("rate", "damping"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InputError(f"Device {name} must be a finite number > 0, got {v!r}")

    @property
    def period(self) -> float:
        return 1.0 / self.rate

    def stable_stiffness(self, virtual_damping: float = 0.0) -> float:
        """k < 2 (b − B) / T for this device (see the module docstring)."""
        return stable_stiffness(self.damping, self.rate, virtual_damping)
