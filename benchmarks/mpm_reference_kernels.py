"""The Warp kernels of the plain MLS-MPM reference (``benchmarks/mpm_reference.py``, which documents them).

Warp's kernel language writes array types as calls (``wp.array(dtype=wp.vec3)``), which mypy cannot read: this
module is exempt from mypy as ``sync4d.sim.mpm_warp.kernels`` is (pyproject.toml), and holds nothing else.
"""

import warp as wp


@wp.kernel
def ref_stress(F: wp.array(dtype=wp.mat33), mu: float, lam: float, tau: wp.array(dtype=wp.mat33)):
    """(P,) Kirchhoff stress [Pa] of fixed-corotated elasticity, rotation from the SVD."""
    p = wp.tid()
    Fp = F[p]
    U, sig, V = wp.svd3(Fp)
    R = U * wp.transpose(V)
    J = wp.determinant(Fp)
    tau[p] = 2.0 * mu * (Fp - R) * wp.transpose(Fp) + wp.identity(n=3, dtype=float) * (lam * J * (J - 1.0))


@wp.kernel
def ref_p2g(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    tau: wp.array(dtype=wp.mat33),
    mass: wp.array(dtype=float),
    volume: wp.array(dtype=float),
    origin: wp.vec3,
    dx: float,
    inv_dx: float,
    dt: float,
    grid_m: wp.array3d(dtype=float),
    grid_mv: wp.array3d(dtype=wp.vec3),
):
    """Scatter mass [kg] and APIC/MLS momentum [kg m/s] to the 27 stencil nodes (atomic adds)."""
    p = wp.tid()
    gp = (x[p] - origin) * inv_dx
    bx = int(wp.floor(gp[0] - 0.5))
    by = int(wp.floor(gp[1] - 0.5))
    bz = int(wp.floor(gp[2] - 0.5))
    fx = gp - wp.vec3(float(bx), float(by), float(bz))
    w0 = 0.5 * wp.cw_mul(wp.vec3(1.5) - fx, wp.vec3(1.5) - fx)
    w1 = wp.vec3(0.75) - wp.cw_mul(fx - wp.vec3(1.0), fx - wp.vec3(1.0))
    w2 = 0.5 * wp.cw_mul(fx - wp.vec3(0.5), fx - wp.vec3(0.5))
    wx = wp.vec3(w0[0], w1[0], w2[0])
    wy = wp.vec3(w0[1], w1[1], w2[1])
    wz = wp.vec3(w0[2], w1[2], w2[2])
    m = mass[p]
    affine = m * C[p] - (dt * volume[p] * 4.0 * inv_dx * inv_dx) * tau[p]
    mv = m * v[p]
    for i in range(3):
        for j in range(3):
            for k in range(3):
                weight = wx[i] * wy[j] * wz[k]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                wp.atomic_add(grid_mv, bx + i, by + j, bz + k, weight * (mv + affine * dpos))
                wp.atomic_add(grid_m, bx + i, by + j, bz + k, weight * m)


@wp.kernel
def ref_grid(
    grid_m: wp.array3d(dtype=float),
    grid_mv: wp.array3d(dtype=wp.vec3),
    gravity: wp.vec3,
    dt: float,
    mass_eps: float,
    wall: int,
    grid_v: wp.array3d(dtype=wp.vec3),
):
    """Node velocity [m/s] = momentum / mass + dt g; slip walls stop the outward component."""
    i, j, k = wp.tid()
    m = grid_m[i, j, k]
    vi = wp.vec3(0.0)
    if m > mass_eps:
        vi = grid_mv[i, j, k] / m + dt * gravity
        vx = vi[0]
        vy = vi[1]
        vz = vi[2]
        if (i < wall and vx < 0.0) or (i >= grid_m.shape[0] - wall and vx > 0.0):
            vx = 0.0
        if (j < wall and vy < 0.0) or (j >= grid_m.shape[1] - wall and vy > 0.0):
            vy = 0.0
        if (k < wall and vz < 0.0) or (k >= grid_m.shape[2] - wall and vz > 0.0):
            vz = 0.0
        vi = wp.vec3(vx, vy, vz)
    grid_v[i, j, k] = vi


@wp.kernel
def ref_g2p(
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    grid_v: wp.array3d(dtype=wp.vec3),
    origin: wp.vec3,
    inv_dx: float,
    dt: float,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    C_out: wp.array(dtype=wp.mat33),
    F_out: wp.array(dtype=wp.mat33),
):
    """Gather velocity [m/s] and the affine matrix C [1/s]; advance F and x into the next state's arrays."""
    p = wp.tid()
    gp = (x[p] - origin) * inv_dx
    bx = int(wp.floor(gp[0] - 0.5))
    by = int(wp.floor(gp[1] - 0.5))
    bz = int(wp.floor(gp[2] - 0.5))
    fx = gp - wp.vec3(float(bx), float(by), float(bz))
    w0 = 0.5 * wp.cw_mul(wp.vec3(1.5) - fx, wp.vec3(1.5) - fx)
    w1 = wp.vec3(0.75) - wp.cw_mul(fx - wp.vec3(1.0), fx - wp.vec3(1.0))
    w2 = 0.5 * wp.cw_mul(fx - wp.vec3(0.5), fx - wp.vec3(0.5))
    wx = wp.vec3(w0[0], w1[0], w2[0])
    wy = wp.vec3(w0[1], w1[1], w2[1])
    wz = wp.vec3(w0[2], w1[2], w2[2])
    vp = wp.vec3(0.0)
    Cp = wp.mat33(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                weight = wx[i] * wy[j] * wz[k]
                dpos = wp.vec3(float(i), float(j), float(k)) - fx  # in cells
                gv = grid_v[bx + i, by + j, bz + k]
                vp = vp + weight * gv
                Cp = Cp + (4.0 * inv_dx * weight) * wp.outer(gv, dpos)
    x_out[p] = x[p] + dt * vp
    v_out[p] = vp
    C_out[p] = Cp
    F_out[p] = (wp.identity(n=3, dtype=float) + dt * Cp) * F[p]
