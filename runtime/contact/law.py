r"""Step 2, the contact law: the force a contact exerts for the displacement the tool imposes.

At the proxy, with N = N(x), K = K(x) (eq. 15, rendered: symmetric, the support blended, the region tapered
by λ), the displacement the tool imposes ū = p − r_tool N − x_a (x_a: the proxy, or with friction the
material point the tool holds) and the penetration δ = −N·ū:

- the normal force is λ k_n δ with k_n = 1/(Nᵀ K⁻¹ N), the normal stiffness when the surface may slide
  under the tool (the Schur complement of K's tangential block).  f = K ū pushed the hand sideways by
  0.5–0.8 x the normal force through K's normal–tangential coupling and did net work round closed loops;
- friction is a spring on the held point's tangential offset w with the tangential stiffness
  k_t = 2λ / (tr K⁻¹ − Nᵀ K⁻¹ N), kept while ‖k_t w‖ ≤ μ λ k_n δ and otherwise held on the cone's edge
  while the point slides; μ weakens from μ_s to μ_d over ``slip_length`` of slip, so breaking away is
  continuous.  Bounding the cone by the penetration's own normal force keeps K's coupling from locking it
  (a tangential offset raised the normal force, which widened the cone: a wedge);
- the tangential term ½ δ² ∇k_n (∇k_n averaged per vertex, interpolated) makes the force the gradient of
  the stored energy ½ λ k_n δ² + ½ k_t ‖w‖² (added in step 4, :mod:`pmask.runtime.contact.output`).

The native core's ``core/law.c`` is the same code operation for operation.
"""
from __future__ import annotations

import math

from pmask.runtime.contact.tracking import normal, point


def stiffness_at(srf, t, b0, b1, b2):
    """K(x) (eq. 15, 9 floats row-major), λ(x) and the interpolated ∇k_n at barycentric b of triangle t."""
    i0, i1, i2 = srf._idx[t]
    KK, G = srf._K, srf._G
    k0, k1, k2 = KK[i0], KK[i1], KK[i2]
    lam = srf._lam
    K = [b0 * k0[i] + b1 * k1[i] + b2 * k2[i] for i in range(9)]
    g0, g1, g2 = G[i0], G[i1], G[i2]
    g = (b0 * g0[0] + b1 * g1[0] + b2 * g2[0], b0 * g0[1] + b1 * g1[1] + b2 * g2[1],
         b0 * g0[2] + b1 * g1[2] + b2 * g2[2])
    return K, b0 * lam[i0] + b1 * lam[i1] + b2 * lam[i2], g


def inverse3(K):
    """Inverse of a 3x3 matrix (9 floats row-major) by cofactors; a singular one gives zeros."""
    a, b, c, d, e, f, g, h, i = K
    A, B, C = e * i - f * h, -(d * i - f * g), d * h - e * g
    det = a * A + b * B + c * C
    if det == 0.0 or not math.isfinite(det):
        return [0.0] * 9
    r = 1.0 / det
    return [A * r, -(b * i - c * h) * r, (b * f - c * e) * r,
            B * r, (a * i - c * g) * r, -(a * f - c * d) * r,
            C * r, -(a * h - b * g) * r, (a * e - b * d) * r]


def normal_compliance(Nx, Ny, Nz, Ki):
    """Nᵀ K⁻¹ N: the compliance along N with the tangential directions free (1/k_n)."""
    return (Nx * (Ki[0] * Nx + Ki[1] * Ny + Ki[2] * Nz) + Ny * (Ki[3] * Nx + Ki[4] * Ny + Ki[5] * Nz)
            + Nz * (Ki[6] * Nx + Ki[7] * Ny + Ki[8] * Nz))


def geometry(c, st, p):
    """N, K, K⁻¹, λ, ∇k_n at the proxy, and ū = p − r_tool N − x_a with x_a the proxy (frictionless) or the
    anchor the tool holds (the law's inputs)."""
    srf = c.surface
    t, (b0, b1, b2) = st.tri, st.b
    Nx, Ny, Nz = normal(srf, t, b0, b1, b2)
    K, lam, (gx, gy, gz) = stiffness_at(srf, t, b0, b1, b2)
    Ki = inverse3(K)
    gn = gx * Nx + gy * Ny + gz * Nz  # on the tangent plane
    cx, cy, cz = point(srf, t, b0, b1, b2)
    if st.anchor is not None:  # the anchor, kept on the tangent plane at the proxy (it would drift off a
        ax, ay, az = st.anchor  # curved surface as it slides along successive tangent planes)
        an = Nx * (ax - cx) + Ny * (ay - cy) + Nz * (az - cz)
        cx, cy, cz = ax - an * Nx, ay - an * Ny, az - an * Nz
        st.anchor = (cx, cy, cz)
    r = c.tool_radius
    return ((Nx, Ny, Nz, K, Ki, lam, (gx - gn * Nx, gy - gn * Ny, gz - gn * Nz)),
            (p[0] - r * Nx - cx, p[1] - r * Ny - cy, p[2] - r * Nz - cz))


def local_law(c, st, geo, ux, uy, uz):
    """The contact law for the displacement (ux, uy, uz) left to this contact.
    Returns (f on the body, ū' after the law, sliding, penetration δ)."""
    Nx, Ny, Nz, K, Ki, lam, _ = geo
    delta = -(Nx * ux + Ny * uy + Nz * uz)
    if delta <= 0.0 or lam <= 0.0:
        return (0.0, 0.0, 0.0), (ux, uy, uz), False, 0.0
    nkn = normal_compliance(Nx, Ny, Nz, Ki)
    fc = lam * delta / nkn  # the normal force: λ k_n δ, k_n = 1/(Nᵀ K⁻¹ N)
    fx, fy, fz = -fc * Nx, -fc * Ny, -fc * Nz
    if c._frictionless:
        return (fx, fy, fz), (-delta * Nx, -delta * Ny, -delta * Nz), True, delta
    # friction: a tangential spring on the anchor's offset w, stiffness k_t = 2λ / (tr K⁻¹ − Nᵀ K⁻¹ N)
    # (the tangential stiffness with the normal force free), bounded by μ f_c; the tool drags the point
    # it holds, so the force on the body is along w, as the normal part is along ū's normal part
    wx, wy, wz = ux + delta * Nx, uy + delta * Ny, uz + delta * Nz
    kt = 2.0 * lam / (Ki[0] + Ki[4] + Ki[8] - nkn)
    tx, ty, tz = kt * wx, kt * wy, kt * wz
    ft = math.sqrt(tx * tx + ty * ty + tz * tz)
    # friction weakens with slip from μ_s to μ_d: a continuous breakaway
    mu = (c.dynamic_friction + (c.friction - c.dynamic_friction) * math.exp(-st.slip / c.slip_length)
          if st.sliding else c.friction)
    if ft <= mu * fc:  # stick: inside the cone
        return (fx + tx, fy + ty, fz + tz), (ux, uy, uz), False, delta
    s = mu * fc / ft  # slide: on the cone's edge, the anchor moves so that the spring holds it there
    tx, ty, tz = s * tx, s * ty, s * tz
    return ((fx + tx, fy + ty, fz + tz), (-delta * Nx + tx / kt, -delta * Ny + ty / kt, -delta * Nz + tz / kt),
            True, delta)
