r"""Step 2, the contact law: the force a contact exerts for the displacement the tool imposes.

At the proxy x (the surface point under the probe), with N = N(x), the rendered stiffness K = K(x) (eq. 15:
symmetric, the support blended) and the normal stiffness k(x) = Σ_j φ_j(x) k_j (k_j = λ_j / (n_jᵀ K_j⁻¹ n_j),
the stiffness along the normal with the surface free to slide under the tool, tapered by λ), the
displacement the tool imposes is ū = p − r_tool N − x_a (x_a: the proxy, or with friction the material point
the tool holds, the anchor) and the penetration δ = −N·ū.  The law's stiffness is K̃ = c K with
c = k Nᵀ K⁻¹ N, the rendered K scaled so that its normal stiffness with the tangential directions free is
exactly k: one compliance D = K̃⁻¹ serves the frictionless, the stuck and the coupled contacts alike.

- **Frictionless** (and the limit of every sliding contact): f_free = −k δ N.  f = K ū pushed the hand
  sideways by 0.5–0.8 x the normal force through K's normal–tangential coupling and did net work round closed
  loops.
- **Stuck**: the tool holds the anchor, f_stuck = K̃ ū: the full stiffness, tangential coupling included,
  while its tangential part ‖P f_stuck‖ ≤ μ (−N·f_stuck).
- **Sliding**: f = (1 − τ) f_stuck + τ f_free with the smallest τ ∈ (0, 1] that puts f on the friction cone,
  τ = (‖t_0‖ − μ φ_0) / (‖t_0‖ − μ φ_0 + μ k δ) (φ_0, t_0: f_stuck's normal and tangential parts).  The anchor
  slips by τ s with s = ū − K̃⁻¹ f_free (tangential: the slip that frees the contact), so the force stays the
  stiffness of the surface's own displacement, f = K̃ (ū − τ s).  Every force lies between the frictionless
  and the stuck one; the normal force never depends on a tangential offset in a way that can wedge (a cone
  bounded by a normal force that the tangential offset raises locked grasps before), and the slip dissipates:
  f · s = tᵀDt − (NᵀDt)² / (NᵀDN) ≥ 0 (Cauchy–Schwarz in D's inner product).  μ weakens from μ_s to μ_d over
  ``slip_length`` of slip, so breaking away is continuous.
- The tangential term ½ δ² (I − δ S)⁻¹ ∇k (∇k averaged per vertex and interpolated, S the contact normals'
  shape operator, :mod:`pmask.runtime.contact.surface`) makes the frictionless force the gradient of the
  stored energy ½ k δ² as the probe moves: the proxy under a probe δ deep moves (I − δ S)⁻¹ as fast as the
  probe (added in step 4, :mod:`pmask.runtime.contact.output`).

**Deep presses.**  Two consequences of the linear model on the undeformed surface would be felt deep in the
body: the probe's projection runs off sideways near the surface's focal point (at the kidney's pole the force
turned 45-65° and fell), and the tangential term ½ δ² ∇k outgrows the normal force (turning the force more
than 10° off the normal on the flat top).  The first is step 1's (the proxy moves by dead reckoning past half
the radius of curvature, :func:`pmask.runtime.contact.tracking.follow`); for the second, past the depth
δ_t = min(δ_lin, c k / ‖∇k‖) (where k changes by c = 1/(8√2) of itself, :data:`FROZEN_CHANGE`; only inside the
full contact region, λ = 1) the contact remembers δ* and k* = k at the tick it gets there: δ* = δ_t when a press
crosses it, and δ* = δ, its own depth, when a contact already deeper enters the full region or slides to where δ_t is
smaller
(freezing at δ_t there turned the tangential term from ½ δ² ∇k to (δ_t δ − ½ δ_t²) ∇k in one tick; at δ it
changes nothing), and while δ ≥ δ* its stored energy is

    E = k(x) (δ* δ − ½ δ*²) + ½ λ(x) k* (δ − δ*)²,

which is ½ k δ² where it begins: the normal force k(x) δ* + λ k* (δ − δ*) keeps growing, and equals k δ*
where it ends again as δ falls below δ*, so entering and leaving are continuous and loops through it stay
conservative.  The increments' stiffness is tapered as k is (:func:`increment_stiffness`), so a frozen contact
that slides into a contact region's edge band fades out with the rest of the force; the energy's surface
gradient then has the term ½ k* (δ − δ*)² ∇λ too (∇λ the triangle's own, :func:`taper_gradient`).  (It used to
unfreeze at the band's first tick, a step of (k* − k)(δ − δ*) in one tick: 7.7x the slide's largest change per
tick on the test's region-edge slide, 1.4x now.)  The tangential term (δ* δ − ½ δ*²) ∇k grows only as fast as
the normal force, its share
tending to δ* ‖A ∇k‖ / k* ≤ c ‖A‖ with A = (I − δ_f S)⁻¹, ‖A‖ ≤ 2 (δ_f ≤ R/2): within atan(2c) = 10.0° of the
normal (measured in normal pushes to 15 mm, tests/test_deep.py: ≤ 9.6° at the pole, top, lateral face, hilum lip
and support rim).  With c = 1/8, the form before, the bound was 14°: measured 9.2° and 17.5° at the support rim
while step 1's projection drifted (two fixed-point steps, :func:`pmask.runtime.contact.tracking.project`), 12.3°
at the lateral face and 12.6° at the rim once it was exact.  A smaller c freezes sooner, so a contact that slides
into stiffer tissue feels less of it (a 4 mm deep slide from the top face into the hilum, whose support ramps the
stiffness tenfold, ends 22 % below the unfrozen law's force, 6 % with 1/8 and 36 % with 1/16; by hand).  The law
is the same with the secant stiffness k_s = φ / δ in place of k (:func:`secant`).  The status ``DEEP``
says when δ ≥ δ_lin (:func:`pmask.runtime.contact.surface.linear_depths`: 0.29 x the smallest radius of
curvature or 1.5 mask radii), where the linear model stops being meaningful.  There the law's ‖F‖ can still fall
on an oblique push (a frozen contact sliding into stiffer tissue, the proxy moving by dead reckoning beside the
support); step 4 holds its magnitude while the press goes on (:mod:`pmask.runtime.contact.output`'s deep hold).

The native core's ``core/law.c`` is the same code operation for operation.
"""
from __future__ import annotations

import math

from pmask.runtime.contact.linalg3 import inverse3, mul3, normal_compliance, tangent_part
from pmask.runtime.contact.surface import at
from pmask.runtime.contact.tracking import normal, point

#: where the law's inputs sit in :func:`geometry`'s first result, after N's three components: K̃ (9), K̃⁻¹ (9),
#: k, λ, the energy gradient ∇k on the tangent plane (3), the shape operator on the tangent plane (9), δ_lin
GEO_K, GEO_KI, GEO_k, GEO_LAM, GEO_G, GEO_S, GEO_DLIN = range(3, 10)


def scaled(K, Ki, k, Nx, Ny, Nz):
    """K̃ = c K and K̃⁻¹ = K⁻¹ / c with c = k Nᵀ K⁻¹ N: normal stiffness k with the tangential directions free."""
    c = k * normal_compliance(Nx, Ny, Nz, Ki)
    return [c * v for v in K], [v / c for v in Ki]


def geometry(c, st, p):
    """The law's inputs at the proxy (see :data:`GEO_K` ...: N, K̃, K̃⁻¹, k, λ, ∇k and S on the tangent plane,
    δ_lin) and ū = p − r_tool N − x_a with x_a the proxy (frictionless) or the anchor the tool holds."""
    srf = c.surface
    t, (b0, b1, b2) = st.tri, st.b
    r = c.tool_radius
    Nx, Ny, Nz = normal(srf, t, b0, b1, b2)
    K, lam, k, (gx, gy, gz), S, dlin = at(srf, t, b0, b1, b2)
    Ki = inverse3(K)
    Kt, Kti = scaled(K, Ki, k, Nx, Ny, Nz) if k > 0.0 else ([0.0] * 9, [0.0] * 9)
    gn = gx * Nx + gy * Ny + gz * Nz  # on the tangent plane
    cx, cy, cz = point(srf, t, b0, b1, b2)
    if st.anchor is not None:  # the anchor, kept on the tangent plane at the proxy (it would drift off a
        ax, ay, az = st.anchor  # curved surface as it slides along successive tangent planes)
        an = Nx * (ax - cx) + Ny * (ay - cy) + Nz * (az - cz)
        cx, cy, cz = ax - an * Nx, ay - an * Ny, az - an * Nz
        st.anchor = (cx, cy, cz)
    return ((Nx, Ny, Nz, Kt, Kti, k, lam, (gx - gn * Nx, gy - gn * Ny, gz - gn * Nz), tangent_part(Nx, Ny, Nz, S),
             dlin),
            (p[0] - r * Nx - cx, p[1] - r * Ny - cy, p[2] - r * Nz - cz))


def taper_gradient(srf, t, Nx, Ny, Nz):
    """∇λ on triangle t, on the tangent plane of N: the gradient of the linearly interpolated taper,
    (λ_1 − λ_0) a + (λ_2 − λ_0) b with a, b the duals of the triangle's edges (exact for the interpolant, so the
    frozen increments' energy ½ λ k* (δ − δ*)² has it as its surface gradient).  Only a frozen contact reads it
    (step 4), so it is not among the per-tick inputs of :func:`geometry`."""
    i0, i1, i2 = srf._idx[t]
    lam = srf._lam
    _, _, _, ax, ay, az, bx, by, bz, _, _, _ = srf._tri[t]
    d1, d2 = lam[i1] - lam[i0], lam[i2] - lam[i0]
    lx, ly, lz = d1 * ax + d2 * bx, d1 * ay + d2 * by, d1 * az + d2 * bz
    ln = lx * Nx + ly * Ny + lz * Nz
    return lx - ln * Nx, ly - ln * Ny, lz - ln * Nz


#: past δ_t = min(δ_lin, FROZEN_CHANGE k / ‖∇k‖) increments of depth keep the stiffness where they began: 1/(8√2),
#: so that the tangential term's share of the force stays within 2 FROZEN_CHANGE = tan 10.0° where the proxy's
#: speed-up reaches 2 (half the radius of curvature deep; module docstring)
FROZEN_CHANGE = 0.125 / math.sqrt(2.0)


def increment_depth(dlin, k, gx, gy, gz):
    """δ_t = min(δ_lin, FROZEN_CHANGE k / ‖∇k‖): the depth over which k changes by FROZEN_CHANGE of itself."""
    gm = math.sqrt(gx * gx + gy * gy + gz * gz)
    if FROZEN_CHANGE * k < dlin * gm:
        return FROZEN_CHANGE * k / gm
    return dlin


def increment_stiffness(st, lam):
    """λ k*: the stiffness of the frozen increments of depth, tapered as k is (λ = 1 where freezing begins), so a
    frozen contact that slides into a contact region's edge band fades out with it instead of stepping."""
    return lam * st.frozen_stiffness


def secant(st, k, lam, delta):
    """The frictionless normal force φ(δ) and its ratio q = φ / (k δ): k δ, or past δ*
    k δ* + λ k* (δ − δ*)."""
    d0 = st.frozen_depth
    if st.frozen and delta > d0:
        fc = k * d0 + increment_stiffness(st, lam) * (delta - d0)
        return fc, fc / (k * delta)
    return k * delta, 1.0


def local_law(c, st, geo, ux, uy, uz):
    """The contact law for the displacement (ux, uy, uz) left to this contact.
    Returns (f on the body, ū' the surface's own displacement K̃⁻¹ f, sliding, penetration δ)."""
    Nx, Ny, Nz, Kt, Kti, k, lam = geo[:7]
    delta = -(Nx * ux + Ny * uy + Nz * uz)
    if delta <= 0.0 or lam <= 0.0 or k <= 0.0:
        return (0.0, 0.0, 0.0), (ux, uy, uz), False, 0.0
    fc, q = secant(st, k, lam, delta)  # the frictionless normal force; q scales K̃ to the secant stiffness
    if c._frictionless:
        fx, fy, fz = -fc * Nx, -fc * Ny, -fc * Nz
        u2x, u2y, u2z = mul3(Kti, fx, fy, fz)
        return (fx, fy, fz), (u2x / q, u2y / q, u2z / q), True, delta
    sx, sy, sz = mul3(Kt, ux, uy, uz)  # stuck: the full stiffness on ū
    sx, sy, sz = q * sx, q * sy, q * sz
    phi = -(Nx * sx + Ny * sy + Nz * sz)
    tx, ty, tz = sx + phi * Nx, sy + phi * Ny, sz + phi * Nz
    ft = math.sqrt(tx * tx + ty * ty + tz * tz)
    # friction weakens with slip from μ_s to μ_d: a continuous breakaway
    mu = (c.dynamic_friction + (c.friction - c.dynamic_friction) * math.exp(-st.slip / c.slip_length)
          if st.sliding else c.friction)
    if ft <= mu * phi:  # stick: inside the cone
        return (sx, sy, sz), (ux, uy, uz), False, delta
    a = ft - mu * phi  # > 0; slide: towards the frictionless force, to the cone's edge
    tau = a / (a + mu * fc)
    s = 1.0 - tau
    fx, fy, fz = s * sx - tau * fc * Nx, s * sy - tau * fc * Ny, s * sz - tau * fc * Nz
    u2x, u2y, u2z = mul3(Kti, fx, fy, fz)
    return (fx, fy, fz), (u2x / q, u2y / q, u2z / q), True, delta
