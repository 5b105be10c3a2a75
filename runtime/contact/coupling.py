r"""Step 3, several contacts solved together through the body.

The compliance C (3s x 3s) has as diagonal blocks the local laws' own, D_l = K̃_l⁻¹ (so that s = 1 is exactly
the single contact), and as off-diagonal ones the displacement at x_l per unit force at x_k from the Green's
functions, C_lk = Σ_i Σ_m φ_i(x_l) φ_m(x_k) ζ_m(i) (symmetrised).  Block Gauss–Seidel: each contact applies
the law (:func:`pmask.runtime.contact.law.local_law`) to the displacement left to it, ū_l − Σ_{k≠l} C_lk f_k,
friction in the same local law (as SOFA's LCP does).  A contact whose penetration that leaves is ≤ 0 takes no
force this tick (the LCP's complementarity: the others' pushes carried the surface away from its tool) but
stays in contact while its own probe is inside.  Frictionless contacts start from the exact solution of the
coupled normal problem (the Delassus system), and their first sweep is Jacobi (each law on what the start
leaves it), which is what the laws then confirm; a pair pressing on the law's first branch, the laws' own
solution then, takes their results from the start with no sweep (:func:`pair_solved`).

Why the full K̃⁻¹ on the diagonal: with contacts that press through each other the off-diagonal blocks are of
the diagonal's size (a grasp's two jaws: 0.026 against 0.036 m/N), and the whole matrix is then positive
definite only if each diagonal block is the full compliance.  A law that decoupled the normal from the
tangential directions (k_n along N, one k_t across) made it indefinite at 35 % of the diagonal in random pairs
and triples on the kidney, and the sweeps diverged (a grasp at μ = 1 gave infinite forces); with K̃⁻¹ the
smallest eigenvalue stayed above 2.5 % of the diagonal, like the finite-element compliance itself (1.6 %).

The native core's ``core/coupling.c`` is the same code operation for operation.
"""
from __future__ import annotations

from pmask.runtime.contact.law import GEO_KI, GEO_LAM, GEO_k, increment_stiffness, local_law
from pmask.runtime.contact.linalg3 import mul3
from pmask.runtime.contact.state import GS_SWEEPS


def solve(c, states, active, geo, ubar):
    """The contact law for every active contact, the several coupled by block Gauss-Seidel on the compliance
    (one sweep when uncoupled).  Returns {l: ((f, ū', sliding, δ), ū left to l)}."""
    coupling = coupling_blocks(c, states, active) if c.coupled and len(active) > 1 else None
    start = None
    if coupling and c._frictionless:
        force, start, phi = normal_start(active, geo, ubar, coupling, states)
        solved = pair_solved(states, geo, active, force, start, phi) if phi else None
        if solved is not None:  # the pair's start is its laws' solution: no sweep
            for l in active:
                states[l].law_force = force[l]
            return solved
    else:
        force = {l: states[l].law_force for l in active}  # warm start: last tick's forces
    result = {}
    for sweep in range(GS_SWEEPS if coupling else 1):
        change, size = 0.0, 0.0
        # from the exact frictionless start the first sweep is Jacobi (every ū' from the start, so in the native
        # core the laws do not wait on one another; the bench's side-by-side ratio measures it); the start solves
        # their normal problem, so that sweep only confirms it.  A pair's start gives its ū' itself.
        left = None
        if coupling and sweep == 0 and c._frictionless:
            left = start or {l: less_coupling(ubar[l], l, active, coupling, force) for l in active}
        for l in active:
            if left is not None:
                ux, uy, uz = left[l]
            elif coupling:
                ux, uy, uz = less_coupling(ubar[l], l, active, coupling, force)
            else:
                ux, uy, uz = ubar[l]
            res = local_law(c, states[l], geo[l], ux, uy, uz)
            old = force[l]
            force[l] = res[0]
            result[l] = (res, (ux, uy, uz))
            change = max(change, abs(res[0][0] - old[0]), abs(res[0][1] - old[1]), abs(res[0][2] - old[2]))
            size = max(size, abs(res[0][0]), abs(res[0][1]), abs(res[0][2]))
        if change <= 1e-13 * size:
            break
    for l in active:
        states[l].law_force = force[l]
    return result


def less_coupling(u, l, active, coupling, force):
    """ū_l − Σ_{k≠l} C_lk f_k: the displacement left to contact l by the others' forces through the body."""
    ux, uy, uz = u
    for k in active:
        if k != l:
            C, (gx, gy, gz) = coupling[(l, k)], force[k]
            ux -= C[0] * gx + C[1] * gy + C[2] * gz
            uy -= C[3] * gx + C[4] * gy + C[5] * gz
            uz -= C[6] * gx + C[7] * gy + C[8] * gz
    return ux, uy, uz


def normal_start(active, geo, ubar, coupling, states=None):
    """Frictionless contacts' start for the sweeps: the normal forces φ (f_l = −φ_l N_l) that solve the coupled
    normal problem, the linear complementarity problem φ ≥ 0, w = δ̄ − A φ ≤ 0 on the released contacts and
    A φ = δ̄ on the pressing ones, with A_ll = 1/k (the law's own normal compliance, Nᵀ K̃⁻¹ N; past δ* 1/k*
    with δ̄ less δ* (1 − k/k*)), A_lk = N_lᵀ C_lk N_k and δ̄_l = −N_l · ū_l (the Delassus system, symmetric
    positive definite).

    Murty's least-index principal pivoting (Murty 1974; finite for a P-matrix such as A): solve A φ = δ̄ on
    the pressing set by Gaussian elimination without pivoting (:func:`solve_spd`), then release the first
    pressing contact that pulls (φ < 0) or press the first released one that would go in (w > 0), until
    neither is left.  With every contact pressing (the usual case) this is one solve; with one pulled away
    by the others it is the exact solution too, and the sweeps stop after one (the clipped solve they
    started from before took 40-47 sweeps to converge to 1e-13 for four contacts, 60 for eight, counted by hand
    on the bench's trace).  After :data:`PIVOTS` ``s`` pivots the last solve, clipped at zero, goes to the
    sweeps as it is.

    Returns (the forces {l: f_l}, for a pair pressing what each leaves the other {l: ū_l − C_lk f_k} and
    its two φ, else None and None)."""
    s = len(active)
    A = [[0.0] * s for _ in range(s)]
    r = [0.0] * s
    stiff = [0.0] * s
    for x, l in enumerate(active):
        Nx, Ny, Nz = geo[l][0], geo[l][1], geo[l][2]
        ux, uy, uz = ubar[l]
        r[x] = -(Nx * ux + Ny * uy + Nz * uz)
        st = None if states is None else states[l]
        if st is not None and st.frozen:  # φ = k δ* + λ k* (δ − δ*)
            k, ks = geo[l][GEO_k], increment_stiffness(st, geo[l][GEO_LAM])
            A[x][x] = 1.0 / ks
            r[x] = r[x] - st.frozen_depth * (1.0 - k / ks)
            stiff[x] = ks
        else:
            A[x][x] = 1.0 / geo[l][GEO_k]
            stiff[x] = geo[l][GEO_k]
        for y in range(x + 1, s):  # A is symmetric (C_kl = C_lkᵀ): each pair once
            k = active[y]
            C = coupling[(l, k)]
            Mx, My, Mz = geo[k][0], geo[k][1], geo[k][2]
            cx = C[0] * Mx + C[1] * My + C[2] * Mz
            cy = C[3] * Mx + C[4] * My + C[5] * Mz
            cz = C[6] * Mx + C[7] * My + C[8] * Mz
            A[x][y] = A[y][x] = Nx * cx + Ny * cy + Nz * cz
    if s == 2:  # a pair pressing (a grasp's two jaws): each row times its stiffness, one division on the way
        (s0, s1), c01 = stiff, A[0][1]
        e0, e1, g0, g1 = s0 * r[0], s1 * r[1], c01 * s0, c01 * s1
        d = 1.0 - g0 * g1  # the Schur complement's pivot, 1/k_1 − A_01² k_0, times k_1
        if s0 > 0.0 and s1 > 0.0 and d > 0.0:
            x1 = (e1 - g1 * e0) / d
            x0 = e0 - g0 * x1
            if x0 >= 0.0 and x1 >= 0.0:  # and what each leaves the other: ū_l − C_lk f_k = ū_l + φ_k C_lk N_k
                (l, k), N, M = active, geo[active[0]], geo[active[1]]
                C, (ul, uk) = coupling[(l, k)], (ubar[l], ubar[k])
                cx = C[0] * M[0] + C[1] * M[1] + C[2] * M[2]  # C_lk N_k, as A_lk's
                cy = C[3] * M[0] + C[4] * M[1] + C[5] * M[2]
                cz = C[6] * M[0] + C[7] * M[1] + C[8] * M[2]
                wx = C[0] * N[0] + C[3] * N[1] + C[6] * N[2]  # C_kl N_l = C_lkᵀ N_l
                wy = C[1] * N[0] + C[4] * N[1] + C[7] * N[2]
                wz = C[2] * N[0] + C[5] * N[1] + C[8] * N[2]
                force = {l: (-x0 * N[0], -x0 * N[1], -x0 * N[2]), k: (-x1 * M[0], -x1 * M[1], -x1 * M[2])}
                return force, {l: (ul[0] + x1 * cx, ul[1] + x1 * cy, ul[2] + x1 * cz),
                               k: (uk[0] + x0 * wx, uk[1] + x0 * wy, uk[2] + x0 * wz)}, (x0, x1)
    pressing = [True] * s
    phi = None
    for _ in range(PIVOTS * s):
        idx = [x for x in range(s) if pressing[x]]
        sol = solve_spd([[A[i][j] for j in idx] for i in idx], [r[i] for i in idx])
        if sol is None:
            phi = None
            break
        phi = [0.0] * s
        for t, i in enumerate(idx):
            phi[i] = sol[t]
        flip = -1
        for x in range(s):
            if pressing[x]:
                if phi[x] < 0.0:
                    flip = x
                    break
            else:
                w = r[x]
                for y in range(s):
                    if pressing[y]:
                        w = w - A[x][y] * phi[y]
                if w > 0.0:
                    flip = x
                    break
        if flip < 0:
            break
        pressing[flip] = not pressing[flip]
    out = {}
    for x, l in enumerate(active):
        p = 0.0 if phi is None else max(phi[x], 0.0)
        Nx, Ny, Nz = geo[l][0], geo[l][1], geo[l][2]
        out[l] = (-p * Nx, -p * Ny, -p * Nz)
    return out, None, None


def pair_solved(states, geo, active, force, start, phi):
    """A frictionless pair pressing (both φ > 0) on the law's first branch (δ_l = −N_l · ū'_l > 0, neither past
    δ*): the start is the two laws' solution (f_l = −φ_l N_l, φ_l = k_l δ_l to round-off), so their results
    are taken from it, {l: ((f_l, K̃_l⁻¹ f_l, sliding, δ_l), ū'_l)} as :func:`solve` returns them, and no
    sweep runs (the law's chain δ → k δ → f is then off the native pair's tick); else None (the laws run on
    ū', a Jacobi sweep)."""
    (l, k), (x0, x1) = active, phi
    if not (x0 > 0.0 and x1 > 0.0):
        return None
    out = {}
    for m in (l, k):
        Nx, Ny, Nz = geo[m][0], geo[m][1], geo[m][2]
        ux, uy, uz = start[m]
        delta = -(Nx * ux + Ny * uy + Nz * uz)
        if not delta > 0.0 or states[m].frozen:
            return None
        f = force[m]
        out[m] = ((f, mul3(geo[m][GEO_KI], *f), True, delta), (ux, uy, uz))
    return out


#: the frictionless start's pivots, at most this many times the number of contacts (Murty's rule ends far sooner:
#: 1 for contacts that all press, 2-3 where one is pulled away)
PIVOTS = 4


def coupling_blocks(c, states, active):
    """C_lk (symmetrised, 9 floats row-major) for every ordered pair of active contacts: Σ_x Σ_y φ_x φ_y P_xy
    over the pair's vertex-pair blocks (:meth:`pmask.runtime.contact.ContactSurface.pair_blocks` of their mesh
    triangles, φ their barycentrics there), which are kept in ``c._pair_blocks`` while both contacts stay on the
    same mesh triangles (on a subdivided surface a contact crosses many of its triangles inside one of the mesh's).
    The C core also keeps the blocks of the vertex pairs a move keeps (a move to a neighbouring triangle keeps six of
    the nine); the values are the same, so the forces are too."""
    srf = c.surface
    cache = c._pair_blocks
    out = {}
    for a in active:
        for b in active:
            if a < b:
                ta, tb = states[a].tri, states[b].tri
                ma, mb = srf._parent[ta], srf._parent[tb]
                hit = cache.get((a, b))
                if hit is None or hit[0] != ma or hit[1] != mb:
                    hit = cache[(a, b)] = (ma, mb, srf.pair_blocks(ma, mb))
                P, (a0, a1, a2), (b0, b1, b2) = hit[2], states[a].b, states[b].b
                if srf._mapped:  # a subdivided surface: φ on the mesh triangles, where ζ lives
                    _, a0, a1, a2 = srf.mesh_point(ta, a0, a1, a2)
                    _, b0, b1, b2 = srf.mesh_point(tb, b0, b1, b2)
                # S_k = Σ_xy w_xy P_xy,k as three row sums t_x = Σ_y w_xy P_xy,k (block xy at 9 (3x + y)), then
                # (t_0 + t_1) + t_2, as the C's (whose tick waits on the chain of adds); a zero weight adds ±0,
                # which leaves a sum as it was (P is finite)
                w0, w1, w2, w3, w4 = a0 * b0, a0 * b1, a0 * b2, a1 * b0, a1 * b1
                w5, w6, w7, w8 = a1 * b2, a2 * b0, a2 * b1, a2 * b2
                S = [(w0 * P[k] + w1 * P[9 + k] + w2 * P[18 + k]) + (w3 * P[27 + k] + w4 * P[36 + k] + w5 * P[45 + k])
                     + (w6 * P[54 + k] + w7 * P[63 + k] + w8 * P[72 + k]) for k in range(9)]
                out[(a, b)] = S
                out[(b, a)] = [S[3 * j + i] for i in range(3) for j in range(3)]
    return out


def solve_spd(A, r):
    """x with A x = r by Gaussian elimination without pivoting (A symmetric positive definite), in place;
    None if a pivot is not positive.  The native core runs the same operations in the same order."""
    s = len(r)
    for k in range(s):
        p = A[k][k]
        if not p > 0.0:
            return None
        for i in range(k + 1, s):
            q = A[i][k] / p
            for j in range(k + 1, s):
                A[i][j] = A[i][j] - q * A[k][j]
            r[i] = r[i] - q * r[k]
    x = [0.0] * s
    for i in range(s - 1, -1, -1):
        acc = r[i]
        for j in range(i + 1, s):
            acc = acc - A[i][j] * x[j]
        x[i] = acc / A[i][i]
    return x
