"""Warp kernels of the MLS-MPM substep (orchestration lives in :mod:`sync4d.sim.mpm_warp.solver`).

One substep is three launches (Hu et al. 2018, MLS-MPM; paper Sec. 3.1 and appendix A.1):

1. :func:`p2g` (particles): fixed-corotated Kirchhoff stress fused with the APIC/MLS particle-to-grid
   scatter of momentum and mass (quadratic B-spline weights).
2. :func:`grid_update` (nodes): momentum -> velocity, gravity, walls near the grid edge, fixed region.
3. :func:`g2p` (particles): gather velocity and the affine matrix C, F <- (I + dt C) F, x <- x + dt v.

Conventions: positions in metres, the grid node (i, j, k) sits at ``origin + (i, j, k) * dx``. A grid
cell of P2G output holds ``vec4(m v_x, m v_y, m v_z, m)`` so one scatter per node does mass and momentum.
Multi-field MPM (:mod:`sync4d.sim.mpm_warp.fields`): with F velocity fields the grids are F grids stacked
along x, node (i, j, k) of field f at x-index ``f nx + i``; each particle scatters into and gathers from its
own field; the grid update bonds fields at the joints of parts in different fields. One field is the plain
single-grid MLS-MPM, the same arithmetic.

All three are differentiated, including the grid mass (by the hand-written adjoints below; P2G and G2P also
have Warp's generated ones, the grid update, whose loop over fields is unrolled, only its own): the grid
update divides by the node mass, and that division is what carries the gradient of the weights back
to the particle positions (PhysDreamer's solver treats the node mass as a constant and its gradients go
wrong after ~20 substeps). Array stores and atomic adds are not replayed in the adjoint (Warp's
``skip_replay``), so running an adjoint kernel never disturbs the forward grid.

Guards: a particle whose stencil would leave the grid (or whose position is NaN/inf) is clamped to a
valid stencil so no kernel ever reads or writes out of bounds, and the substep index is recorded with
``atomic_min`` into ``status[0]``; the orchestration turns that into ``SimulationDiverged``.
"""

from __future__ import annotations

import warp as wp

from sync4d.sim.mpm_warp.fields import MAX_FIELDS as MAX_FIELDS_

# Differentiable kernels; the CPU backend compiles them with optimisation (level 0 runs ~80x slower).
wp.set_module_options({"enable_backward": True})

# Newton iterations of the polar decomposition (see rotation_part).
POLAR_ITERS = wp.constant(4)
# Newton is trusted when det F exceeds this and R^T R is within this of I after the iterations; otherwise
# (large or inverted deformations, rare in practice) the rotation comes from the SVD.
POLAR_MIN_J = wp.constant(0.2)
POLAR_TOL = wp.constant(1.0e-4)
STATUS_OK = wp.constant(2147483647)
# The most velocity fields the grid update handles (its loops over fields are unrolled to this).
MAX_FIELDS = wp.constant(MAX_FIELDS_)


@wp.func
def inverse_transpose(X: wp.mat33):
    """(X^-T, det X) from the cofactor matrix (cheaper than wp.inverse + transpose)."""
    c00 = X[1, 1] * X[2, 2] - X[1, 2] * X[2, 1]
    c01 = X[1, 2] * X[2, 0] - X[1, 0] * X[2, 2]
    c02 = X[1, 0] * X[2, 1] - X[1, 1] * X[2, 0]
    c10 = X[0, 2] * X[2, 1] - X[0, 1] * X[2, 2]
    c11 = X[0, 0] * X[2, 2] - X[0, 2] * X[2, 0]
    c12 = X[0, 1] * X[2, 0] - X[0, 0] * X[2, 1]
    c20 = X[0, 1] * X[1, 2] - X[0, 2] * X[1, 1]
    c21 = X[0, 2] * X[1, 0] - X[0, 0] * X[1, 2]
    c22 = X[0, 0] * X[1, 1] - X[0, 1] * X[1, 0]
    det = X[0, 0] * c00 + X[0, 1] * c01 + X[0, 2] * c02
    return wp.mat33(c00, c01, c02, c10, c11, c12, c20, c21, c22) * (1.0 / det), det


@wp.func
def rotation_part(F: wp.mat33) -> wp.mat33:
    """Rotation R of the polar decomposition F = R S (R proper, S symmetric positive definite).

    Newton's iteration X <- (X + X^-T) / 2 from X = F maps each singular value s to (s + 1/s) / 2, which
    converges quadratically; four unrolled iterations (differentiated by Warp's autodiff) reach float32
    accuracy for stretches within about [0.6, 1.6] at ~30 ns, against ~350 ns for ``wp.svd3``. Outside
    that range (R^T R off I by more than POLAR_TOL) or for nearly flat or inverted F (det F <=
    POLAR_MIN_J, where Newton would head for a reflection) R = U V^T from ``wp.svd3`` (det U = det V = 1).
    """
    R = F
    ok = wp.determinant(F) > POLAR_MIN_J
    if ok:
        for _it in range(POLAR_ITERS):
            Rit, d = inverse_transpose(R)
            R = 0.5 * (R + Rit)
        E = wp.transpose(R) * R - wp.identity(n=3, dtype=float)
        # largest entry of the symmetric R^T R - I
        diag = wp.max(wp.max(wp.abs(E[0, 0]), wp.abs(E[1, 1])), wp.abs(E[2, 2]))
        off = wp.max(wp.max(wp.abs(E[0, 1]), wp.abs(E[0, 2])), wp.abs(E[1, 2]))
        err = wp.max(diag, off)
        ok = err < POLAR_TOL
    if not ok:
        U, sig, V = wp.svd3(F)
        R = U * wp.transpose(V)
    return R


@wp.func
def kirchhoff_stress_of(F: wp.mat33, R: wp.mat33, mu: float, lam: float) -> wp.mat33:
    """THE fixed-corotated Kirchhoff stress tau = 2 mu (F - R) F^T + lam (J - 1) J I  [Pa].

    The one place the constitutive law is written: P2G, P2G's adjoint (which rebuilds tau from the stored
    rotation) and the test kernel :func:`kirchhoff_stress` all call it, so a test of this function is a
    test of what the simulator integrates. ``R`` is the polar rotation of ``F`` (:func:`rotation_part`).
    """
    J = wp.determinant(F)
    return 2.0 * mu * (F - R) * wp.transpose(F) + wp.identity(n=3, dtype=float) * (lam * (J - 1.0) * J)


@wp.func
def kirchhoff_fixed_corotated(F: wp.mat33, mu: float, lam: float) -> wp.mat33:
    """:func:`kirchhoff_stress_of` with the polar rotation computed from ``F`` [Pa]."""
    return kirchhoff_stress_of(F, rotation_part(F), mu, lam)


@wp.func
def kirchhoff_adjoint(F: wp.mat33, R: wp.mat33, mu: float, lam: float, adj_tau: wp.mat33) -> wp.mat33:
    """dL/dF of the fixed-corotated Kirchhoff stress given dL/dtau (hand-written, exact polar derivative).

    tau = 2 mu (F F^T - R F^T) + lam (J^2 - J) I. For F = R S the rotation varies as dR = R [w]x with
    (tr(S) I - S) w = axial(R^T dF - dF^T R), so <Rbar, dR> = <R [y]x, dF> with
    y = (tr(S) I - S)^-1 axial(R^T Rbar) and axial(M) = (M32 - M23, M13 - M31, M21 - M12).
    """
    G = adj_tau
    adj_F = 2.0 * mu * ((G + wp.transpose(G)) * F - wp.transpose(G) * R)
    Rbar = -2.0 * mu * (G * F)
    # J = det F: dJ = J tr(F^-1 dF), i.e. dJ/dF = cofactor(F)
    FinvT, J = inverse_transpose(F)
    trG = G[0, 0] + G[1, 1] + G[2, 2]
    adj_F = adj_F + (lam * (2.0 * J - 1.0) * trG * J) * FinvT
    M = wp.transpose(R) * Rbar
    mvec = wp.vec3(M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1])
    S = wp.transpose(R) * F
    S = 0.5 * (S + wp.transpose(S))
    K = wp.identity(n=3, dtype=float) * (S[0, 0] + S[1, 1] + S[2, 2]) - S
    Kit, detK = inverse_transpose(K)
    y = wp.vec3(0.0)
    # K's eigenvalues are sums of two singular values: singular only for flat/inverted F (skip that term)
    if wp.abs(detK) > 1.0e-12:
        y = wp.transpose(Kit) * mvec
    Y = wp.mat33(0.0, -y[2], y[1], y[2], 0.0, -y[0], -y[1], y[0], 0.0)
    return adj_F + R * Y


@wp.func
def bspline_weights(fx: wp.vec3):
    """Quadratic B-spline weights per axis: returns (wx, wy, wz), wx[a] the weight of node base+a along x.

    fx is the position in cells from the stencil base, in [0.5, 1.5) per axis.
    """
    a = wp.vec3(1.5) - fx
    b = fx - wp.vec3(1.0)
    c = fx - wp.vec3(0.5)
    w0 = 0.5 * wp.cw_mul(a, a)
    w1 = wp.vec3(0.75) - wp.cw_mul(b, b)
    w2 = 0.5 * wp.cw_mul(c, c)
    wx = wp.vec3(w0[0], w1[0], w2[0])
    wy = wp.vec3(w0[1], w1[1], w2[1])
    wz = wp.vec3(w0[2], w1[2], w2[2])
    return wx, wy, wz


@wp.func
def stencil_base(p: wp.vec3, nx: int, ny: int, nz: int):
    """Lower stencil node of a particle at p (grid units) and whether the 3x3x3 stencil fits the grid.

    NaN/inf positions fail every comparison and get the (valid) base 0, so memory stays safe.
    """
    fb = wp.vec3(wp.floor(p[0] - 0.5), wp.floor(p[1] - 0.5), wp.floor(p[2] - 0.5))
    ok = True
    bx = int(0)
    by = int(0)
    bz = int(0)
    if fb[0] >= 0.0 and fb[0] <= float(nx - 3):
        bx = int(fb[0])
    else:
        ok = False
    if fb[1] >= 0.0 and fb[1] <= float(ny - 3):
        by = int(fb[1])
    else:
        ok = False
    if fb[2] >= 0.0 and fb[2] <= float(nz - 3):
        bz = int(fb[2])
    else:
        ok = False
    return bx, by, bz, ok


@wp.kernel
def p2g(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    mass: wp.array(dtype=float),
    volume: wp.array(dtype=float),
    field: wp.array(dtype=wp.int32),
    mu: float,
    lam: float,
    origin: wp.vec3,
    dx: float,
    inv_dx: float,
    dt: float,
    nx: int,
    ny: int,
    nz: int,
    substep: int,
    store_rotation: int,
    bond: wp.array(dtype=float),
    bonding: int,
    grid: wp.array3d(dtype=wp.vec4),
    status: wp.array(dtype=wp.int32),
    rotation: wp.array(dtype=wp.mat33),
    bond_grid: wp.array3d(dtype=float),
):
    """Particle-to-grid scatter with the stress fused in (MLS-MPM).

    Per node i: m_i += w m_p;  (m v)_i += w (m_p v_p + A_p (x_i - x_p)) with the MLS affine matrix
    A_p = m_p C_p - dt V_p^0 (4 / dx^2) tau_p (its stress part is the paper's grid-update force term).

    Args:
        x, v: (P,) positions [m] and velocities [m/s].
        C, F: (P,) APIC affine matrices [1/s] and deformation gradients.
        mass, volume: (P,) particle masses [kg] and initial volumes V_p^0 [m^3].
        field: (P,) each particle's velocity field f (:mod:`fields`): node i of f at x-index f nx + i.
        mu, lam: Lame parameters [Pa].
        origin: world position of node (0, 0, 0) [m]; dx, inv_dx: cell size [m] and its inverse.
        dt: substep [s]; nx, ny, nz: nodes per axis; substep: index recorded on failure.
        store_rotation: 1 to also write each particle's polar rotation R (the backward pass rebuilds a
            substep's grid and then needs R again in :func:`p2g_adjoint`), 0 to skip it.
        bond, bonding: (P,) 1 for a particle flagged at its joint (read only when ``bonding`` is 1).
        grid: (F nx, ny, nz) zeroed accumulator of vec4(m v, m) [kg m/s, kg] per field (output).
        status: (1,) int, min substep index at which a particle left the grid or became non-finite.
        rotation: (P,) polar rotation of F (output, written only with ``store_rotation``).
        bond_grid: (F nx, ny, nz) zeroed flagged mass [kg] (output with ``bonding``; switches, no gradient).
    """
    p = wp.tid()
    xp = x[p]
    gp = (xp - origin) * inv_dx
    bx, by, bz, ok = stencil_base(gp, nx, ny, nz)
    if not ok:
        wp.atomic_min(status, 0, substep)
    fx = gp - wp.vec3(float(bx), float(by), float(bz))
    wx, wy, wz = bspline_weights(fx)

    m = mass[p]
    fo = field[p] * nx
    flagged = bonding != 0 and bond[p] > 0.0  # bond holds P entries whatever ``bonding``
    Fp = F[p]
    R = rotation_part(Fp)
    if store_rotation != 0:
        rotation[p] = R
    tau = kirchhoff_stress_of(Fp, R, mu, lam)
    A = m * C[p] - (dt * volume[p] * 4.0 * inv_dx * inv_dx) * tau
    # (x_i - x_p) = dx (node - fx): split so the loop only adds columns of A.
    mom0 = m * v[p] - dx * (A * fx)
    Ax = dx * wp.vec3(A[0, 0], A[1, 0], A[2, 0])
    Ay = dx * wp.vec3(A[0, 1], A[1, 1], A[2, 1])
    Az = dx * wp.vec3(A[0, 2], A[1, 2], A[2, 2])

    for a in range(3):
        for b in range(3):
            for c in range(3):
                w = wx[a] * wy[b] * wz[c]
                mom = mom0 + float(a) * Ax + float(b) * Ay + float(c) * Az
                wp.atomic_add(grid, fo + bx + a, by + b, bz + c, wp.vec4(w * mom[0], w * mom[1], w * mom[2], w * m))
                if flagged:
                    wp.atomic_add(bond_grid, fo + bx + a, by + b, bz + c, w * m)


@wp.func
def boundary_mask(
    i: int,
    j: int,
    k: int,
    n0: int,
    n1: int,
    n2: int,
    vi: wp.vec3,
    wall: int,
    sticky: int,
    origin: wp.vec3,
    dx: float,
    fixed_lo: wp.vec3,
    fixed_hi: wp.vec3,
    use_fixed: int,
) -> wp.vec3:
    """Per-component 0/1 mask the boundary conditions apply to a node velocity ``vi`` (before masking).

    Walls: nodes within ``wall`` of a face; sticky walls zero the whole velocity, slip walls the outward
    component only. Nodes inside the fixed box are held still. Shared by the grid update and its adjoint.
    """
    mx = 1.0
    my = 1.0
    mz = 1.0
    if sticky != 0:
        if i < wall or i >= n0 - wall or j < wall or j >= n1 - wall or k < wall or k >= n2 - wall:
            mx = 0.0
            my = 0.0
            mz = 0.0
    else:
        if (i < wall and vi[0] < 0.0) or (i >= n0 - wall and vi[0] > 0.0):
            mx = 0.0
        if (j < wall and vi[1] < 0.0) or (j >= n1 - wall and vi[1] > 0.0):
            my = 0.0
        if (k < wall and vi[2] < 0.0) or (k >= n2 - wall and vi[2] > 0.0):
            mz = 0.0
    if use_fixed != 0:
        xi = origin + dx * wp.vec3(float(i), float(j), float(k))
        if (
            xi[0] >= fixed_lo[0]
            and xi[0] <= fixed_hi[0]
            and xi[1] >= fixed_lo[1]
            and xi[1] <= fixed_hi[1]
            and xi[2] >= fixed_lo[2]
            and xi[2] <= fixed_hi[2]
        ):
            mx = 0.0
            my = 0.0
            mz = 0.0
    return wp.vec3(mx, my, mz)


@wp.func
def node_sum(grids: wp.array4d(dtype=wp.vec4), i: int, j: int, k: int) -> wp.vec4:
    """Node (i, j, k) of the per-thread P2G grids summed: grids[0] + grids[1] + ... (one grid: itself)."""
    g = grids[0, i, j, k]
    for t in range(1, grids.shape[0]):
        g = g + grids[t, i, j, k]
    return g


@wp.func
def bonded(bonds: wp.array4d(dtype=float), i: int, j: int, k: int, m: float, share: float) -> bool:
    """Whether a field with node mass ``m`` at x-index i (field-major) carries flagged mass >= share m there."""
    s = bonds[0, i, j, k]
    for t in range(1, bonds.shape[0]):
        s = s + bonds[t, i, j, k]
    return s >= share * m


@wp.func
def field_nodes(
    grids: wp.array4d(dtype=wp.vec4),
    bonds: wp.array4d(dtype=float),
    nx: int,
    num_fields: int,
    bonding: int,
    i: int,
    j: int,
    k: int,
    mass_eps: float,
    share: float,
):
    """Physical node (i, j, k) of every field, read once: (G, on, ps, ms, ns) with row f of G field f's
    vec4(m v, m), on[f] = 1 for a field bonded there (:func:`bonded`, mass > eps, only with ``bonding``) and
    the bonded fields' summed momentum ps, mass ms and count ns."""
    G = wp.mat44(0.0)
    on = wp.vec4(0.0)
    ps = wp.vec3(0.0)
    ms = float(0.0)
    ns = int(0)
    for f in range(MAX_FIELDS):
        if f < num_fields:
            g = node_sum(grids, f * nx + i, j, k)
            G[f] = g
            if bonding != 0 and g[3] > mass_eps:
                if bonded(bonds, f * nx + i, j, k, g[3], share):
                    on[f] = 1.0
                    ps = ps + wp.vec3(g[0], g[1], g[2])
                    ms = ms + g[3]
                    ns = ns + 1
    return G, on, ps, ms, ns


@wp.kernel(enable_backward=False)
def grid_update(
    grids: wp.array4d(dtype=wp.vec4),
    bonds: wp.array4d(dtype=float),
    i0: int,
    nx: int,
    num_fields: int,
    bonding: int,
    bond_share: float,
    gravity: wp.vec3,
    dt: float,
    mass_eps: float,
    wall: int,
    sticky: int,
    origin: wp.vec3,
    dx: float,
    fixed_lo: wp.vec3,
    fixed_hi: wp.vec3,
    use_fixed: int,
    grid_v: wp.array3d(dtype=wp.vec3),
):
    """Node velocities v_i = (m v)_i / m_i + dt g per field, bonds, then boundary conditions (:func:`boundary_mask`).

    Launched over the slab of physical nodes i0 <= i < i0 + dim[0] (the whole grid, or one thread's share); each
    launch point updates node (i, j, k) of every field (stored at x-index f nx + i). Differentiated by
    :func:`grid_update_adjoint` (no generated adjoint).

    Args:
        grids: (T, F nx, ny, nz) vec4(m v, m) from :func:`p2g`, one grid per thread that scattered
            (summed here, so the threads never write the same node).
        bonds: (T, F nx, ny, nz) each field's flagged mass from :func:`p2g` (read only with ``bonding``).
        i0: first x-index of the slab this launch covers; nx: physical nodes along x; num_fields: F.
        bonding: 1 to bond fields: at a node where two or more fields carry flagged mass of at least
            ``bond_share`` of their own mass, those fields all take their common velocity
            sum (m v) / sum m + dt g (momentum conserving); 0: fields are independent.
        gravity: [m/s^2]; dt: substep [s].
        mass_eps: nodes lighter than this [kg] are empty (avoids 1/m blow-ups in value and gradient).
        wall: nodes within this many of a face are walls; sticky: 1 zeroes the whole velocity there,
            0 only the outward normal component (slip).
        origin, dx: node (0, 0, 0) [m] and cell size [m] (to place the fixed region).
        fixed_lo, fixed_hi: world box [m] whose nodes are held at zero velocity when use_fixed is 1.
        grid_v: (F nx, ny, nz) node velocities [m/s] (output).
    """
    i, j, k = wp.tid()
    i = i + i0
    G, on, ps, ms, ns = field_nodes(grids, bonds, nx, num_fields, bonding, i, j, k, mass_eps, bond_share)
    for f in range(MAX_FIELDS):
        if f < num_fields:
            g = G[f]
            m = g[3]
            vi = wp.vec3(0.0)
            if m > mass_eps:
                vi = wp.vec3(g[0], g[1], g[2]) / m + dt * gravity
                if ns > 1 and on[f] > 0.0:
                    vi = ps / ms + dt * gravity
                mask = boundary_mask(
                    i, j, k, nx, grids.shape[2], grids.shape[3], vi, wall, sticky, origin, dx, fixed_lo, fixed_hi,
                    use_fixed,
                )  # fmt: skip
                vi = wp.cw_mul(vi, mask)
            grid_v[f * nx + i, j, k] = vi


@wp.func
def adj_sum(adj_grid_v: wp.array4d(dtype=wp.vec3), i: int, j: int, k: int) -> wp.vec3:
    """Node (i, j, k) of the per-thread G2P-adjoint grids summed."""
    av = adj_grid_v[0, i, j, k]
    for t in range(1, adj_grid_v.shape[0]):
        av = av + adj_grid_v[t, i, j, k]
    return av


@wp.kernel(enable_backward=False)
def grid_update_adjoint(
    grids: wp.array4d(dtype=wp.vec4),
    bonds: wp.array4d(dtype=float),
    i0: int,
    nx: int,
    num_fields: int,
    bonding: int,
    bond_share: float,
    gravity: wp.vec3,
    dt: float,
    mass_eps: float,
    wall: int,
    sticky: int,
    origin: wp.vec3,
    dx: float,
    fixed_lo: wp.vec3,
    fixed_hi: wp.vec3,
    use_fixed: int,
    adj_grid_v: wp.array4d(dtype=wp.vec3),
    adj_grid: wp.array3d(dtype=wp.vec4),
):
    """Hand-written adjoint of :func:`grid_update`: dL/d(m v)_i and dL/dm_i from dL/dv_i, per field.

    A free field: v = M (p / m + dt g) with p = (m v)_i and the boundary mask M (piecewise constant):
    dL/dp = M dL/dv / m and dL/dm = -(M dL/dv) . p / m^2. The node mass gets its gradient here; it is
    what carries the weights' position dependence back correctly over many substeps. Bonded fields S share
    v = M (P / M_S + dt g) with P = sum p_f, M_S = sum m_f over S: each gets dL/dp_f = A / M_S and
    dL/dm_f = -(A / M_S) . P / M_S with A = sum over S of M dL/dv_f (the bond switch itself is piecewise
    constant). ``adj_grid`` (F nx, ny, nz) is written, not accumulated (no zeroing needed). ``grids`` and
    ``adj_grid_v`` (T, F nx, ny, nz) hold one grid per thread (P2G's and G2P-adjoint's scatters), summed here;
    the slab is as in :func:`grid_update`.
    """
    i, j, k = wp.tid()
    i = i + i0
    G, on, ps, ms, ns = field_nodes(grids, bonds, nx, num_fields, bonding, i, j, k, mass_eps, bond_share)
    a_s = wp.vec3(0.0)
    if ns > 1:
        vs = ps / ms + dt * gravity
        mask_s = boundary_mask(
            i, j, k, nx, grids.shape[2], grids.shape[3], vs, wall, sticky, origin, dx, fixed_lo, fixed_hi, use_fixed
        )  # fmt: skip
        for f in range(MAX_FIELDS):
            if f < num_fields and on[f] > 0.0:
                a_s = a_s + wp.cw_mul(adj_sum(adj_grid_v, f * nx + i, j, k), mask_s)
    for f in range(MAX_FIELDS):
        if f < num_fields:
            g = G[f]
            m = g[3]
            out = wp.vec4(0.0)
            if m > mass_eps:
                if ns > 1 and on[f] > 0.0:
                    ap = a_s / ms
                    out = wp.vec4(ap[0], ap[1], ap[2], -wp.dot(ap, ps) / ms)
                else:
                    p = wp.vec3(g[0], g[1], g[2])
                    inv_m = 1.0 / m
                    vi = p * inv_m + dt * gravity
                    mask = boundary_mask(
                        i, j, k, nx, grids.shape[2], grids.shape[3], vi, wall, sticky, origin, dx, fixed_lo, fixed_hi,
                        use_fixed,
                    )  # fmt: skip
                    a = wp.cw_mul(adj_sum(adj_grid_v, f * nx + i, j, k), mask)
                    ap = a * inv_m
                    out = wp.vec4(ap[0], ap[1], ap[2], -wp.dot(ap, p) * inv_m)
            adj_grid[f * nx + i, j, k] = out


@wp.kernel
def g2p(
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    grid_v: wp.array3d(dtype=wp.vec3),
    field: wp.array(dtype=wp.int32),
    nx: int,
    origin: wp.vec3,
    inv_dx: float,
    dt: float,
    substep: int,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    C_out: wp.array(dtype=wp.mat33),
    F_out: wp.array(dtype=wp.mat33),
    status: wp.array(dtype=wp.int32),
):
    """Grid-to-particle gather: v_p = sum w v_i, C_p = (4/dx^2) sum w v_i (x_i - x_p)^T, F, x update.

    Args:
        x, F: (P,) positions [m] and deformation gradients at the start of the substep.
        grid_v: (F nx, ny, nz) node velocities [m/s] of every field from :func:`grid_update`.
        field: (P,) each particle's field (it gathers from that field only); nx: physical nodes along x.
        origin, inv_dx: node (0, 0, 0) [m] and inverse cell size [1/m]; dt: substep [s].
        substep: index recorded in ``status`` when a particle ends off the grid or non-finite.
        x_out, v_out, C_out, F_out: (P,) the next state (outputs; never the input arrays).
        status: (1,) int failure record (see :func:`p2g`).
    """
    p = wp.tid()
    xp = x[p]
    gp = (xp - origin) * inv_dx
    ny = grid_v.shape[1]
    nz = grid_v.shape[2]
    bx, by, bz, ok = stencil_base(gp, nx, ny, nz)
    fx = gp - wp.vec3(float(bx), float(by), float(bz))
    wx, wy, wz = bspline_weights(fx)
    fo = field[p] * nx

    vp = wp.vec3(0.0)
    B = wp.mat33(0.0)
    for a in range(3):
        for b in range(3):
            for c in range(3):
                w = wx[a] * wy[b] * wz[c]
                wv = w * grid_v[fo + bx + a, by + b, bz + c]
                vp = vp + wv
                B = B + wp.outer(wv, wp.vec3(float(a), float(b), float(c)))
    # sum_i w v_i (node - fx)^T in cell units; (4/dx^2) (x_i - x_p) = (4/dx) (node - fx).
    Cp = (4.0 * inv_dx) * (B - wp.outer(vp, fx))
    xn = xp + dt * vp
    Fn = (wp.identity(n=3, dtype=float) + dt * Cp) * F[p]
    x_out[p] = xn
    v_out[p] = vp
    C_out[p] = Cp
    F_out[p] = Fn
    gn = (xn - origin) * inv_dx
    bnx, bny, bnz, okn = stencil_base(gn, nx, ny, nz)
    if not okn or not wp.isfinite(vp) or not wp.isfinite(Fn):
        wp.atomic_min(status, 0, substep)


@wp.func
def bspline_dweights(fx: wp.vec3):
    """Derivatives d w / d fx of :func:`bspline_weights`, per axis: (dwx, dwy, dwz)."""
    d0 = fx - wp.vec3(1.5)
    d1 = -2.0 * (fx - wp.vec3(1.0))
    d2 = fx - wp.vec3(0.5)
    return wp.vec3(d0[0], d1[0], d2[0]), wp.vec3(d0[1], d1[1], d2[1]), wp.vec3(d0[2], d1[2], d2[2])


@wp.kernel(enable_backward=False)
def p2g_adjoint(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    mass: wp.array(dtype=float),
    volume: wp.array(dtype=float),
    field: wp.array(dtype=wp.int32),
    mu: float,
    lam: float,
    origin: wp.vec3,
    dx: float,
    inv_dx: float,
    dt: float,
    nx: int,
    ny: int,
    nz: int,
    rotation: wp.array(dtype=wp.mat33),
    adj_grid: wp.array3d(dtype=wp.vec4),
    adj_x: wp.array(dtype=wp.vec3),
    adj_v: wp.array(dtype=wp.vec3),
    adj_C: wp.array(dtype=wp.mat33),
    adj_F: wp.array(dtype=wp.mat33),
):
    """Hand-written adjoint of :func:`p2g` (one gather pass; Warp's generated one is ~4x slower).

    With G_i = dL/d(m v, m)_i and mom_i = mom0 + A (node - fx) dx:
    dL/dmom0 = sum w G_i, dL/dA = dx sum w G_i (node - fx)^T, dL/dw_i = G_i . (mom_i, m); the weights'
    derivatives give dL/dx, dL/dtau = -dt V (4/dx^2) dL/dA gives dL/dF through :func:`kirchhoff_adjoint`.
    Writes dL/dv and dL/dC, adds to dL/dx and dL/dF (G2P's adjoint wrote them first); fields as in P2G.
    """
    p = wp.tid()
    gp = (x[p] - origin) * inv_dx
    bx, by, bz, ok = stencil_base(gp, nx, ny, nz)
    fo = field[p] * nx
    fx = gp - wp.vec3(float(bx), float(by), float(bz))
    wx, wy, wz = bspline_weights(fx)
    dwx, dwy, dwz = bspline_dweights(fx)
    m = mass[p]
    Fp = F[p]
    R = rotation[p]  # stored by the P2G that rebuilt this substep's grid (same F)
    tau = kirchhoff_stress_of(Fp, R, mu, lam)
    k_tau = dt * volume[p] * 4.0 * inv_dx * inv_dx
    A = m * C[p] - k_tau * tau
    mom0 = m * v[p] - dx * (A * fx)
    Ax = dx * wp.vec3(A[0, 0], A[1, 0], A[2, 0])
    Ay = dx * wp.vec3(A[0, 1], A[1, 1], A[2, 1])
    Az = dx * wp.vec3(A[0, 2], A[1, 2], A[2, 2])
    s0 = wp.vec3(0.0)
    sa = wp.vec3(0.0)
    sb = wp.vec3(0.0)
    sc = wp.vec3(0.0)
    gwx = wp.vec3(0.0)
    gwy = wp.vec3(0.0)
    gwz = wp.vec3(0.0)
    for a in range(3):
        for b in range(3):
            for c in range(3):
                G = adj_grid[fo + bx + a, by + b, bz + c]
                gv = wp.vec3(G[0], G[1], G[2])
                wyz = wy[b] * wz[c]
                w = wx[a] * wyz
                mom = mom0 + float(a) * Ax + float(b) * Ay + float(c) * Az
                gw = wp.dot(gv, mom) + G[3] * m
                wg = w * gv
                s0 = s0 + wg
                sa = sa + float(a) * wg
                sb = sb + float(b) * wg
                sc = sc + float(c) * wg
                gwx[a] = gwx[a] + wyz * gw
                gwy[b] = gwy[b] + wx[a] * wz[c] * gw
                gwz[c] = gwz[c] + wx[a] * wy[b] * gw
    # dL/dA: columns from the node offsets, minus the fx part of mom0
    adj_A = dx * (wp.matrix_from_cols(sa, sb, sc) - wp.outer(s0, fx))
    adj_fx = -dx * (wp.transpose(A) * s0) + wp.vec3(wp.dot(gwx, dwx), wp.dot(gwy, dwy), wp.dot(gwz, dwz))
    adj_x[p] = adj_x[p] + inv_dx * adj_fx
    adj_v[p] = m * s0
    adj_C[p] = m * adj_A
    adj_F[p] = adj_F[p] + kirchhoff_adjoint(Fp, R, mu, lam, -k_tau * adj_A)


@wp.kernel(enable_backward=False)
def g2p_adjoint(
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    grid_v: wp.array3d(dtype=wp.vec3),
    field: wp.array(dtype=wp.int32),
    nx: int,
    origin: wp.vec3,
    inv_dx: float,
    dt: float,
    adj_x_out: wp.array(dtype=wp.vec3),
    adj_v_out: wp.array(dtype=wp.vec3),
    adj_C_out: wp.array(dtype=wp.mat33),
    adj_F_out: wp.array(dtype=wp.mat33),
    adj_grid_v: wp.array3d(dtype=wp.vec3),
    adj_x: wp.array(dtype=wp.vec3),
    adj_F: wp.array(dtype=wp.mat33),
):
    """Hand-written adjoint of :func:`g2p` (one pass over the stencil).

    From x' = x + dt v_p, F' = (I + dt C_p) F, C_p = (4/dx) (B - v_p fx^T), B = sum w v_i node^T:
    dL/dC_p = dL/dC' + dt dL/dF' F^T, dL/dv_p = dL/dv' + dt dL/dx' - (4/dx) dL/dC_p fx, and each node gets
    dL/dv_i += w (dL/dv_p + (4/dx) dL/dC_p node) (scattered into ``adj_grid_v``, which must be zeroed).
    Writes dL/dx and dL/dF of the substep's input state (P2G's adjoint adds its parts afterwards). Fields
    as in :func:`g2p`.
    """
    p = wp.tid()
    gp = (x[p] - origin) * inv_dx
    ny = grid_v.shape[1]
    nz = grid_v.shape[2]
    bx, by, bz, ok = stencil_base(gp, nx, ny, nz)
    fo = field[p] * nx
    fx = gp - wp.vec3(float(bx), float(by), float(bz))
    wx, wy, wz = bspline_weights(fx)
    dwx, dwy, dwz = bspline_dweights(fx)

    Fp = F[p]
    aF = adj_F_out[p]
    aC = adj_C_out[p] + dt * (aF * wp.transpose(Fp))
    ax_out = adj_x_out[p]
    aB = (4.0 * inv_dx) * aC
    av = adj_v_out[p] + dt * ax_out - aB * fx
    aBx = wp.vec3(aB[0, 0], aB[1, 0], aB[2, 0])
    aBy = wp.vec3(aB[0, 1], aB[1, 1], aB[2, 1])
    aBz = wp.vec3(aB[0, 2], aB[1, 2], aB[2, 2])

    vp = wp.vec3(0.0)
    bxa = wp.vec3(0.0)
    bya = wp.vec3(0.0)
    bza = wp.vec3(0.0)
    gwx = wp.vec3(0.0)
    gwy = wp.vec3(0.0)
    gwz = wp.vec3(0.0)
    for a in range(3):
        for b in range(3):
            for c in range(3):
                vi = grid_v[fo + bx + a, by + b, bz + c]
                wyz = wy[b] * wz[c]
                w = wx[a] * wyz
                g = av + float(a) * aBx + float(b) * aBy + float(c) * aBz
                wp.atomic_add(adj_grid_v, fo + bx + a, by + b, bz + c, w * g)
                gw = wp.dot(vi, g)
                wv = w * vi
                vp = vp + wv
                bxa = bxa + float(a) * wv
                bya = bya + float(b) * wv
                bza = bza + float(c) * wv
                gwx[a] = gwx[a] + wyz * gw
                gwy[b] = gwy[b] + wx[a] * wz[c] * gw
                gwz[c] = gwz[c] + wx[a] * wy[b] * gw
    Cp = (4.0 * inv_dx) * (wp.matrix_from_cols(bxa, bya, bza) - wp.outer(vp, fx))
    adj_F[p] = wp.transpose(wp.identity(n=3, dtype=float) + dt * Cp) * aF
    # fx enters C_p through -(4/dx) v_p fx^T and every weight
    adj_fx = -(wp.transpose(aB) * vp) + wp.vec3(wp.dot(gwx, dwx), wp.dot(gwy, dwy), wp.dot(gwz, dwz))
    adj_x[p] = ax_out + inv_dx * adj_fx


@wp.kernel
def kirchhoff_stress(F: wp.array(dtype=wp.mat33), mu: float, lam: float, tau: wp.array(dtype=wp.mat33)):
    """(P,) fixed-corotated Kirchhoff stress [Pa] of each F (for tests and for timing the stress alone)."""
    p = wp.tid()
    tau[p] = kirchhoff_fixed_corotated(F[p], mu, lam)


@wp.kernel(enable_backward=False)
def kirchhoff_stress_adjoint(
    F: wp.array(dtype=wp.mat33),
    mu: float,
    lam: float,
    adj_tau: wp.array(dtype=wp.mat33),
    adj_F: wp.array(dtype=wp.mat33),
):
    """(P,) dL/dF from dL/dtau by :func:`kirchhoff_adjoint` (tests compare it with Warp's generated adjoint)."""
    p = wp.tid()
    adj_F[p] = kirchhoff_adjoint(F[p], rotation_part(F[p]), mu, lam, adj_tau[p])


# ----------------------------------------------------------------------------------------------------
# The drive held through the frame (complementary dynamics, Zhang et al. 2020, in velocity and position
# form): after every G2P, the particles' deviation from the rig (each particle the blend of its parts' driven
# motions) is removed within the rig's degrees of freedom (a translation and a small rotation per part, a
# least-squares fit in the mass metric), from positions and velocities; what the rig does not control stays with
# the physics. Adjoints: hand-written for drive_apply and drive_sums (checked against finite differences in the tests);
# drive_solve is a symmetric matrix product and is its own adjoint.
# ----------------------------------------------------------------------------------------------------


@wp.func
def skew(w: wp.vec3) -> wp.mat33:
    """[w]x: the matrix with [w]x a = w x a."""
    return wp.mat33(0.0, -w[2], w[1], w[2], 0.0, -w[0], -w[1], w[0], 0.0)


@wp.func
def rotation_from_vector(w: wp.vec3) -> wp.mat33:
    """exp([w]x) by Rodrigues' formula (a series near zero, where its adjoint stays finite)."""
    K = skew(w)
    t2 = wp.dot(w, w)
    if t2 < 1.0e-10:
        return wp.identity(n=3, dtype=float) + K + 0.5 * K * K
    t = wp.sqrt(t2)
    return wp.identity(n=3, dtype=float) + (wp.sin(t) / t) * K + ((1.0 - wp.cos(t)) / t2) * K * K


@wp.kernel
def drive_sums(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    slot_part: wp.array2d(dtype=wp.int32),
    slot_weight: wp.array2d(dtype=float),
    slot_offset: wp.array2d(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    turn: wp.array(dtype=wp.mat33),
    centre: wp.array(dtype=wp.vec3),
    linear: wp.array(dtype=wp.vec3),
    angular: wp.array(dtype=wp.vec3),
    sums: wp.array2d(dtype=wp.vec3),
):
    """Per part b, the rig's generalised forces J^T M u of the particles' deviation from the rig.

    Args:
        x, v: (P,) positions [m] and velocities [m/s] after G2P.
        slot_part, slot_weight, slot_offset: (P, 4) each particle's blended parts (< 0: an empty slot), their
            weights and the rest offsets from those parts' rest mass centroids [m].
        mass: (P,) [kg]. turn: (B,) the drive's rest -> now rotation; centre: (B,) the driven centroid [m];
        linear, angular: (B,) the drive's centroid velocity [m/s] and angular velocity [rad/s].
        sums: (B, 4) accumulates sum m w_b u, sum m w_b r_b x u, sum m w_b e, sum m w_b r_b x e, with r_b = turn_b
            offset_b, u = x - sum_b w_b (centre_b + r_b) and e = v - sum_b w_b (linear_b + angular_b x r_b)
            (must be zeroed).
    """
    p = wp.tid()
    if slot_part[p, 0] < 0:
        return
    x_rig = wp.vec3(0.0)
    v_rig = wp.vec3(0.0)
    for k in range(4):
        b = slot_part[p, k]
        if b >= 0:
            r = turn[b] * slot_offset[p, k]
            x_rig = x_rig + slot_weight[p, k] * (centre[b] + r)
            v_rig = v_rig + slot_weight[p, k] * (linear[b] + wp.cross(angular[b], r))
    u = x[p] - x_rig
    e = v[p] - v_rig
    for k in range(4):
        b = slot_part[p, k]
        if b >= 0:
            r = turn[b] * slot_offset[p, k]
            m = mass[p] * slot_weight[p, k]
            wp.atomic_add(sums, b, 0, m * u)
            wp.atomic_add(sums, b, 1, m * wp.cross(r, u))
            wp.atomic_add(sums, b, 2, m * e)
            wp.atomic_add(sums, b, 3, m * wp.cross(r, e))


@wp.kernel
def drive_solve(
    solve: wp.array2d(dtype=float),
    turn: wp.array(dtype=wp.mat33),
    sums: wp.array2d(dtype=wp.vec3),
    theta: wp.array2d(dtype=wp.vec3),
):
    """theta = G solve G^T sums per (part b, column j): j = 0, 1 the translation [m] and rotation vector [rad] of the
    positions' fit, 2, 3 those of the velocities'; G turns each part's rotation unknowns into the world by ``turn``
    (``solve`` works in the parts' turned frames, :func:`drive.normal_matrix`). G solve G^T is symmetric, so the
    same product takes dL/dtheta back to dL/dsums."""
    b, j = wp.tid()
    q = j // 2
    row = 6 * b + 3 * (j % 2)
    out = wp.vec3(0.0)
    for c in range(sums.shape[0]):
        for kind in range(2):
            g = sums[c, 2 * q + kind]
            if kind == 1:
                g = wp.transpose(turn[c]) * g
            col = 6 * c + 3 * kind
            for i in range(3):
                out[i] = out[i] + solve[row + i, col] * g[0] + solve[row + i, col + 1] * g[1] + solve[row + i, col + 2] * g[2]
    if j % 2 == 1:
        out = turn[b] * out
    theta[b, j] = out


@wp.kernel
def sum_slices(parts: wp.array3d(dtype=wp.vec3), total: wp.array2d(dtype=wp.vec3)):
    """total[b, k] = sum over t of parts[t, b, k] (the threads' partial sums)."""
    b, k = wp.tid()
    s = wp.vec3(0.0)
    for t in range(parts.shape[0]):
        s = s + parts[t, b, k]
    total[b, k] = s


@wp.kernel
def drive_apply(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    slot_part: wp.array2d(dtype=wp.int32),
    slot_weight: wp.array2d(dtype=float),
    slot_offset: wp.array2d(dtype=wp.vec3),
    turn: wp.array(dtype=wp.mat33),
    theta: wp.array2d(dtype=wp.vec3),
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    C_out: wp.array(dtype=wp.mat33),
    F_out: wp.array(dtype=wp.mat33),
):
    """Remove the rig's fit of the deviation (:func:`drive_solve`'s ``theta``) from every particle: its blend of
    the parts' t + w x r from positions and velocities; the blended rotation of the velocities' fit also leaves the
    affine matrix C, and F turns with the positions' blended rotation.

    Args:
        x, v, C, F: (P,) the state after G2P; slot_part, slot_weight, slot_offset, turn: as in :func:`drive_sums`;
        theta: (B, 4) the fits of :func:`drive_solve`.
        x_out, v_out, C_out, F_out: (P,) the corrected state (never the input arrays).
    """
    p = wp.tid()
    dx = wp.vec3(0.0)
    dv = wp.vec3(0.0)
    w_x = wp.vec3(0.0)
    w_v = wp.vec3(0.0)
    for k in range(4):
        b = slot_part[p, k]
        if b >= 0:
            r = turn[b] * slot_offset[p, k]
            w = slot_weight[p, k]
            dx = dx + w * (theta[b, 0] + wp.cross(theta[b, 1], r))
            dv = dv + w * (theta[b, 2] + wp.cross(theta[b, 3], r))
            w_x = w_x + w * theta[b, 1]
            w_v = w_v + w * theta[b, 3]
    x_out[p] = x[p] - dx
    v_out[p] = v[p] - dv
    C_out[p] = C[p] - skew(w_v)
    F_out[p] = rotation_from_vector(-w_x) * F[p]



@wp.func
def rodrigues_coefficients(t2: float) -> wp.vec4:
    """(a, b, a'/t, b'/t) of exp([w]x) = I + a(t) [w]x + b(t) [w]x^2 at t^2 = |w|^2 (the series near zero)."""
    if t2 < 1.0e-10:
        return wp.vec4(1.0, 0.5, -1.0 / 3.0, -1.0 / 12.0)
    t = wp.sqrt(t2)
    st = wp.sin(t)
    ct = wp.cos(t)
    return wp.vec4(st / t, (1.0 - ct) / t2, (t * ct - st) / (t2 * t), (t * st - 2.0 * (1.0 - ct)) / (t2 * t2))


@wp.func
def rotation_vector_gradient(w: wp.vec3, H: wp.mat33, c: wp.vec4) -> wp.vec3:
    """d/dw of <H, exp([w]x)> (Frobenius product), ``c`` = :func:`rodrigues_coefficients` of |w|^2: with
    [w]x^2 = w w^T - t^2 I the product is tr H + a (w . s) + b (w^T H w - t^2 tr H), s = vee(H - H^T)."""
    s = wp.vec3(H[2, 1] - H[1, 2], H[0, 2] - H[2, 0], H[1, 0] - H[0, 1])
    t2 = wp.dot(w, w)
    tr = H[0, 0] + H[1, 1] + H[2, 2]
    quad = wp.dot(w, H * w) - t2 * tr
    return c[0] * s + (c[2] * wp.dot(w, s) + c[3] * quad) * w + c[1] * ((H + wp.transpose(H)) * w - 2.0 * tr * w)


@wp.kernel
def drive_apply_adjoint(
    F_out: wp.array(dtype=wp.mat33),
    slot_part: wp.array2d(dtype=wp.int32),
    slot_weight: wp.array2d(dtype=float),
    slot_offset: wp.array2d(dtype=wp.vec3),
    turn: wp.array(dtype=wp.mat33),
    theta: wp.array2d(dtype=wp.vec3),
    adj_x_out: wp.array(dtype=wp.vec3),
    adj_v_out: wp.array(dtype=wp.vec3),
    adj_C_out: wp.array(dtype=wp.mat33),
    adj_F_out: wp.array(dtype=wp.mat33),
    adj_x: wp.array(dtype=wp.vec3),
    adj_v: wp.array(dtype=wp.vec3),
    adj_C: wp.array(dtype=wp.mat33),
    adj_F: wp.array(dtype=wp.mat33),
    adj_theta: wp.array2d(dtype=wp.vec3),
):
    """The adjoint of :func:`drive_apply`: dL/d(state after G2P) and dL/dtheta (accumulated; must be zeroed) from
    dL/d(corrected state). Only F's correction is non-linear; its input F is recovered from the corrected one
    (F = exp([w_x]x) F_out), so the state after G2P need not be recomputed.

    Args:
        F_out: (P,) the corrected deformation gradients; slot_part ... theta: as in :func:`drive_apply`.
        adj_x_out, adj_v_out, adj_C_out, adj_F_out: (P,) dL/d of the corrected state.
        adj_x, adj_v, adj_C, adj_F: (P,) written: dL/d of the state after G2P (x and v before the moments' share).
        adj_theta: (B, 4) accumulates dL/dtheta.
    """
    p = wp.tid()
    w_x = wp.vec3(0.0)
    w_v = wp.vec3(0.0)
    for k in range(4):
        b = slot_part[p, k]
        if b >= 0:
            w_x = w_x + slot_weight[p, k] * theta[b, 1]
            w_v = w_v + slot_weight[p, k] * theta[b, 3]
    ax = adj_x_out[p]
    av = adj_v_out[p]
    aC = adj_C_out[p]
    aF = adj_F_out[p]
    # F_out = exp(-[w_x]x) F: d/dw_x of <aF, exp(-[w_x]x) F> = -(d/du of <aF F^T, exp([u]x)> at u = -w_x)
    c = rodrigues_coefficients(wp.dot(w_x, w_x))
    K = skew(w_x)
    undo = wp.identity(n=3, dtype=float) + c[0] * K + c[1] * K * K  # exp([w_x]x), the inverse of the correction
    adj_x[p] = ax
    adj_v[p] = av
    adj_C[p] = aC
    adj_F[p] = undo * aF
    F_mid = undo * F_out[p]
    g_x = -rotation_vector_gradient(-w_x, aF * wp.transpose(F_mid), c)
    # C_out = C - [w_v]x: d<aC, [w]x>/dw = vee(aC - aC^T)
    g_v = -wp.vec3(aC[2, 1] - aC[1, 2], aC[0, 2] - aC[2, 0], aC[1, 0] - aC[0, 1])
    for k in range(4):
        b = slot_part[p, k]
        if b >= 0:
            r = turn[b] * slot_offset[p, k]
            w = slot_weight[p, k]
            wp.atomic_add(adj_theta, b, 0, -w * ax)
            wp.atomic_add(adj_theta, b, 1, w * (wp.cross(ax, r) + g_x))
            wp.atomic_add(adj_theta, b, 2, -w * av)
            wp.atomic_add(adj_theta, b, 3, w * (wp.cross(av, r) + g_v))


@wp.kernel
def drive_sums_adjoint(
    slot_part: wp.array2d(dtype=wp.int32),
    slot_weight: wp.array2d(dtype=float),
    slot_offset: wp.array2d(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    turn: wp.array(dtype=wp.mat33),
    adj_sums: wp.array2d(dtype=wp.vec3),
    adj_x: wp.array(dtype=wp.vec3),
    adj_v: wp.array(dtype=wp.vec3),
):
    """The adjoint of :func:`drive_sums` in x and v (the moments are linear in them): adds dL/dx and dL/dv.

    Args:
        slot_part ... turn: as in :func:`drive_sums`; adj_sums: (B, 4) dL/d of the summed moments.
        adj_x, adj_v: (P,) accumulate.
    """
    p = wp.tid()
    gu = wp.vec3(0.0)
    ge = wp.vec3(0.0)
    for k in range(4):
        b = slot_part[p, k]
        if b >= 0:
            r = turn[b] * slot_offset[p, k]
            m = mass[p] * slot_weight[p, k]
            # d/du of A . (r x u) = A x r
            gu = gu + m * (adj_sums[b, 0] + wp.cross(adj_sums[b, 1], r))
            ge = ge + m * (adj_sums[b, 2] + wp.cross(adj_sums[b, 3], r))
    adj_x[p] = adj_x[p] + gu
    adj_v[p] = adj_v[p] + ge
