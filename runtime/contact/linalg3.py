"""3x3 algebra on plain floats for the per-tick code (9 floats row-major), in the fixed order of operations
the native core (``core/pm_internal.h``) repeats."""
from __future__ import annotations

import math


def inverse3(K):
    """Inverse of a 3x3 matrix by cofactors; a singular one gives zeros."""
    a, b, c, d, e, f, g, h, i = K
    A, B, C = e * i - f * h, -(d * i - f * g), d * h - e * g
    det = a * A + b * B + c * C
    if det == 0.0 or not math.isfinite(det):
        return [0.0] * 9
    r = 1.0 / det
    return [A * r, -(b * i - c * h) * r, (b * f - c * e) * r,
            B * r, (a * i - c * g) * r, -(a * f - c * d) * r,
            C * r, -(a * h - b * g) * r, (a * e - b * d) * r]


def mul3(M, x, y, z):
    """M (x, y, z)."""
    return (M[0] * x + M[1] * y + M[2] * z, M[3] * x + M[4] * y + M[5] * z, M[6] * x + M[7] * y + M[8] * z)


def normal_compliance(Nx, Ny, Nz, Ki):
    """Nᵀ K⁻¹ N: the compliance along N with the tangential directions free (1/k_n)."""
    return (Nx * (Ki[0] * Nx + Ki[1] * Ny + Ki[2] * Nz) + Ny * (Ki[3] * Nx + Ki[4] * Ny + Ki[5] * Nz)
            + Nz * (Ki[6] * Nx + Ki[7] * Ny + Ki[8] * Nz))


def tangent_part(Nx, Ny, Nz, S):
    """P S P with P = I − N Nᵀ, for a symmetric S: S's action on the tangent plane."""
    vx, vy, vz = mul3(S, Nx, Ny, Nz)
    s = Nx * vx + Ny * vy + Nz * vz
    N = (Nx, Ny, Nz)
    v = (vx, vy, vz)
    return [S[3 * i + j] - N[i] * v[j] - v[i] * N[j] + s * N[i] * N[j] for i in range(3) for j in range(3)]


def speed_up(S, d):
    """(I − d S)⁻¹: how much faster than a probe d below the surface its projection moves along a surface
    of shape operator S (on the tangent plane)."""
    return inverse3([1.0 - d * S[0], -d * S[1], -d * S[2], -d * S[3], 1.0 - d * S[4], -d * S[5],
                     -d * S[6], -d * S[7], 1.0 - d * S[8]])


def largest_curvature(S):
    """κ_max of a shape operator on the tangent plane (symmetric, N its null vector): the larger root of
    κ² − tr S κ + m = 0, m the sum of the principal 2 x 2 minors (the third eigenvalue is zero)."""
    tr = S[0] + S[4] + S[8]
    m = S[0] * S[4] - S[1] * S[3] + S[0] * S[8] - S[2] * S[6] + S[4] * S[8] - S[5] * S[7]
    disc = tr * tr - 4.0 * m
    return 0.5 * (tr + math.sqrt(disc if disc > 0.0 else 0.0))


#: the proxy follows the probe's projection up to this fraction of the radius of curvature (the projection's
#: focal point is at 1): deeper, by dead reckoning at this depth's speed-up (I − δ S)⁻¹, at most 2
FOCAL_FRACTION = 0.5


#: from this fraction of the radius of curvature to FOCAL_FRACTION the proxy's move blends from following the
#: projection into dead reckoning.  A switch at FOCAL_FRACTION made it hop where κ_max δ hovered about it (sliding
#: over the kidney's hilum 7 mm deep): every third tick a following tick pulled the proxy back onto the projection
#: the dead-reckoning ticks had drifted from, and the force changed in a sawtooth (tests/test_haptics.py)
RECKON_FROM = 0.4


def tracking_depth(S, delta):
    """min(δ, FOCAL_FRACTION / κ_max): the depth whose speed-up (I − δ S)⁻¹ the proxy moves with."""
    return _depth(largest_curvature(S), delta)


def _depth(kmax, delta):
    """:func:`tracking_depth` from κ_max (which :func:`lag_weight` and :func:`reckoning` need too)."""
    return FOCAL_FRACTION / kmax if kmax * delta > FOCAL_FRACTION else delta


#: the proxy-offset term (:func:`lag_weight`) fades out from FOCAL_FRACTION, where the proxy moves by dead reckoning
#: alone (so dx = (I − δ_f S)⁻¹ P dp, the move the term assumes), to this fraction of the radius of curvature, short
#: of the focal point, where the penetration at the proxy stops being a smooth function of where the proxy is.
#: Faded out at 1 instead, sliding back across the hilum 5.9 mm deep (κ_max δ = 0.81) one tick's ‖Δ²F‖ was 1.21
#: ‖ΔF‖ (1.04 now; tests/test_haptics.py), and 12 mm deep at the pole (κ_max δ up to 1.75) the whole term was up to
#: 80 % of the force; faded from RECKON_FROM to 0.8, out and back over the hilum's lip 4 mm deep lost 0.6 %
LAG_TO = 0.8


def lag_weight(S, delta):
    """(:func:`tracking_depth`, w): w the share of the proxy-offset term the force keeps
    (:mod:`pmask.runtime.contact.output`), 1 up to κ_max δ = FOCAL_FRACTION, 0 from LAG_TO on, a smoothstep
    between; both from one κ_max (step 4 reads them every tick)."""
    kmax = largest_curvature(S)
    x, d = kmax * delta, _depth(kmax, delta)
    if x <= FOCAL_FRACTION:
        return d, 1.0
    if x >= LAG_TO:
        return d, 0.0
    u = (x - FOCAL_FRACTION) / (LAG_TO - FOCAL_FRACTION)
    return d, 1.0 - u * u * (3.0 - 2.0 * u)


def reckoning(S, delta):
    """(:func:`tracking_depth`, w): w the share of the proxy's move made by dead reckoning, 0 up to κ_max δ =
    RECKON_FROM, 1 from FOCAL_FRACTION, a smoothstep between (continuous in the state, so the proxy never hops
    between the two)."""
    kmax = largest_curvature(S)
    x, d = kmax * delta, _depth(kmax, delta)
    if x <= RECKON_FROM:
        return d, 0.0
    if x >= FOCAL_FRACTION:
        return d, 1.0
    u = (x - RECKON_FROM) / (FOCAL_FRACTION - RECKON_FROM)
    return d, u * u * (3.0 - 2.0 * u)
