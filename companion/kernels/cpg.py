"""The flying skeleton's CPG motion generator (thesis sec. 4.3.1 and 4.4), as kernels: the CPG's
Runge-Kutta step and output, the expected physics' body step, and the link targets.

The specifications are :mod:`companion.motion.cpg` (:func:`~companion.motion.cpg.cpg_step`,
:func:`~companion.motion.cpg.cpg_output`) and :mod:`companion.motion.expected_physics`
(:func:`~companion.motion.expected_physics.body_wrench`,
:func:`~companion.motion.expected_physics.body_step`,
:func:`~companion.motion.expected_physics.link_targets`), for one CPG and one body (no batch
dimensions). Shared argument tuples:

* ``state = (a, a_dot, b, b_dot, phi)``: the CPG's amplitudes and biases (n, 2) and phases (n,);
* ``shape = (sigma_a, sigma_b, f, k_a, k_b, k_phi)``: shaping weights (n,), frequency and gains;
* ``coupling = (i, j, phi_ij)``: the coupled pairs (P,) (oscillator ``i`` follows ``j``);
* ``body = (p, v, R, w)``: the body's position and velocity (world, (3,)), attitude (3, 3) and
  body rate (3,);
* ``water = (k_axial, k_normal, mass, J)``: the drag factors ``rho A c_d / 2`` along and across a
  link, the body's mass and principal moments (3,).
"""

from __future__ import annotations

import math

import numpy as np

from .jit import jit
from .so3 import quat_exp, rotmat_quadratic

__all__ = ["cpg_step_kernel", "cpg_output_kernel", "body_step_kernel", "link_targets_kernel"]


@jit
def _derivative(a, ad, b, bd, phi, shape, coupling, A, B, out):
    """``out = (a', a_dot', b', b_dot', phi')`` of the CPG at ``(a, ad, b, bd, phi)``
    (:func:`~companion.motion.cpg.cpg_derivative`)."""
    sigma_a, sigma_b, f, k_a, k_b, k_phi = shape
    ci, cj, cphi = coupling
    o_a, o_ad, o_b, o_bd, o_phi = out
    n = phi.shape[0]
    for i in range(n):
        for c in range(2):
            o_a[i, c] = ad[i, c]
            o_ad[i, c] = k_a * (k_a / 4.0 * (sigma_a[i] * A[c] - a[i, c]) - ad[i, c])
            o_b[i, c] = bd[i, c]
            o_bd[i, c] = k_b * (k_b / 4.0 * (sigma_b[i] * B[c] - b[i, c]) - bd[i, c])
        o_phi[i] = 0.0
    for p in range(ci.shape[0]):
        o_phi[ci[p]] += math.sin(phi[cj[p]] - phi[ci[p]] - cphi[p])
    for i in range(n):
        o_phi[i] = 2.0 * math.pi * f + k_phi * o_phi[i]


@jit
def cpg_step_kernel(state, shape, coupling, A, B, dt):
    """One classical Runge-Kutta step of ``dt`` of ``state`` (updated in place), ``A`` and ``B``
    (2,) held over the step (:func:`~companion.motion.cpg.cpg_step`)."""
    a, ad, b, bd, phi = state
    n = phi.shape[0]
    ka, kad, kb, kbd, kphi = np.empty((4, n, 2)), np.empty((4, n, 2)), np.empty((4, n, 2)), np.empty((4, n, 2)), \
        np.empty((4, n))
    xa, xad, xb, xbd, xphi = np.empty((n, 2)), np.empty((n, 2)), np.empty((n, 2)), np.empty((n, 2)), np.empty(n)
    _derivative(a, ad, b, bd, phi, shape, coupling, A, B, (ka[0], kad[0], kb[0], kbd[0], kphi[0]))
    for s in range(1, 4):
        h = dt if s == 3 else 0.5 * dt
        for i in range(n):
            for c in range(2):
                xa[i, c] = a[i, c] + h * ka[s - 1, i, c]
                xad[i, c] = ad[i, c] + h * kad[s - 1, i, c]
                xb[i, c] = b[i, c] + h * kb[s - 1, i, c]
                xbd[i, c] = bd[i, c] + h * kbd[s - 1, i, c]
            xphi[i] = phi[i] + h * kphi[s - 1, i]
        _derivative(xa, xad, xb, xbd, xphi, shape, coupling, A, B, (ka[s], kad[s], kb[s], kbd[s], kphi[s]))
    h = dt / 6.0
    for s in range(4):
        w = h if s == 0 or s == 3 else 2.0 * h
        for i in range(n):
            for c in range(2):
                a[i, c] += w * ka[s, i, c]
                ad[i, c] += w * kad[s, i, c]
                b[i, c] += w * kb[s, i, c]
                bd[i, c] += w * kbd[s, i, c]
            phi[i] += w * kphi[s, i]


@jit
def _exp_into(rx, ry, rz, R):
    """``R`` (3, 3) <- ``Exp(r)`` (``so3_exp``: the quaternion, then its quadratic form)."""
    w, x, y, z = quat_exp(rx, ry, rz)
    R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2] = rotmat_quadratic(w, x, y, z)


@jit
def cpg_output_kernel(state, shape, coupling, A, B, out):
    """``out = (R_BL (n, 3, 3), omega_BL_L (n, 3))``: every link's attitude in the body frame and
    its body rate ``J_r(w_i) w_i'`` (:func:`~companion.motion.cpg.cpg_output`)."""
    a, ad, b, bd, phi = state
    R_bl, omega = out
    n = phi.shape[0]
    d = (np.empty((n, 2)), np.empty((n, 2)), np.empty((n, 2)), np.empty((n, 2)), np.empty(n))
    _derivative(a, ad, b, bd, phi, shape, coupling, A, B, d)
    for i in range(n):
        s, c = math.sin(phi[i]), math.cos(phi[i])
        u0 = b[i, 0] + a[i, 0] * s
        u1 = b[i, 1] + a[i, 1] * s
        ud0 = d[2][i, 0] + d[0][i, 0] * s + a[i, 0] * c * d[4][i]
        ud1 = d[2][i, 1] + d[0][i, 1] * s + a[i, 1] * c * d[4][i]
        w0, w1, w2 = 0.0, -u1, u0  # S(e1) [0; u]
        v0, v1, v2 = 0.0, -ud1, ud0
        theta = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        if theta < 1e-6:
            c1, c2 = 0.5 - theta * theta / 24.0, 1.0 / 6.0 - theta * theta / 120.0
        else:
            c1 = (1.0 - math.cos(theta)) / (theta * theta)
            c2 = (theta - math.sin(theta)) / (theta * theta * theta)
        # J_r v = v - c1 w x v + c2 w x (w x v)
        x0, x1, x2 = w1 * v2 - w2 * v1, w2 * v0 - w0 * v2, w0 * v1 - w1 * v0
        y0, y1, y2 = w1 * x2 - w2 * x1, w2 * x0 - w0 * x2, w0 * x1 - w1 * x0
        omega[i, 0] = v0 - c1 * x0 + c2 * y0
        omega[i, 1] = v1 - c1 * x1 + c2 * y1
        omega[i, 2] = v2 - c1 * x2 + c2 * y2
        _exp_into(w0, w1, w2, R_bl[i])


@jit
def _shape(R_bl, omega, half, r, rd):
    """Link centres ``r`` (n, 3) and their rates ``rd`` in the body frame, centroid at 0
    (:func:`~companion.motion.expected_physics.chain_shape`)."""
    n = R_bl.shape[0]
    for k in range(3):
        r[0, k] = 0.0
        rd[0, k] = 0.0
    for i in range(1, n):
        # the right-tip offsets R d and their rates R (omega x d), d = (half, 0, 0)
        for k in range(3):
            t0 = R_bl[i - 1, k, 0] * half + R_bl[i, k, 0] * half
            t1 = (R_bl[i - 1, k, 1] * omega[i - 1, 2] * half - R_bl[i - 1, k, 2] * omega[i - 1, 1] * half
                  + R_bl[i, k, 1] * omega[i, 2] * half - R_bl[i, k, 2] * omega[i, 1] * half)
            r[i, k] = r[i - 1, k] + t0
            rd[i, k] = rd[i - 1, k] + t1
    for k in range(3):
        mr, mrd = 0.0, 0.0
        for i in range(n):
            mr += r[i, k]
            mrd += rd[i, k]
        mr /= n
        mrd /= n
        for i in range(n):
            r[i, k] -= mr
            rd[i, k] -= mrd


@jit
def body_step_kernel(body, R_bl, omega, half, water, dt, iterations, out):
    """The drag on every link summed about the centre of mass (``body_wrench``), then one step of
    the body's dynamics with it (``body_step``): ``out = (p, v, R, w)`` the body after ``dt``."""
    p, v, R, w = body
    k_ax, k_n, mass, J = water
    p1, v1, R1, w1 = out
    n = R_bl.shape[0]
    r, rd = np.empty((n, 3)), np.empty((n, 3))
    _shape(R_bl, omega, half, r, rd)
    vb = np.empty(3)
    for k in range(3):
        vb[k] = R[0, k] * v[0] + R[1, k] * v[1] + R[2, k] * v[2]
    f = np.zeros(3)
    tau = np.zeros(3)
    for i in range(n):
        ri = r[i]
        u0 = vb[0] + (w[1] * ri[2] - w[2] * ri[1]) + rd[i, 0]
        u1 = vb[1] + (w[2] * ri[0] - w[0] * ri[2]) + rd[i, 1]
        u2 = vb[2] + (w[0] * ri[1] - w[1] * ri[0]) + rd[i, 2]
        l0 = R_bl[i, 0, 0] * u0 + R_bl[i, 1, 0] * u1 + R_bl[i, 2, 0] * u2  # R_BLi^T u
        l1 = R_bl[i, 0, 1] * u0 + R_bl[i, 1, 1] * u1 + R_bl[i, 2, 1] * u2
        l2 = R_bl[i, 0, 2] * u0 + R_bl[i, 1, 2] * u1 + R_bl[i, 2, 2] * u2
        sn = math.sqrt(l1 * l1 + l2 * l2)
        d0 = -k_ax * abs(l0) * l0
        d1 = -k_n * sn * l1
        d2 = -k_n * sn * l2
        fb0 = R_bl[i, 0, 0] * d0 + R_bl[i, 0, 1] * d1 + R_bl[i, 0, 2] * d2
        fb1 = R_bl[i, 1, 0] * d0 + R_bl[i, 1, 1] * d1 + R_bl[i, 1, 2] * d2
        fb2 = R_bl[i, 2, 0] * d0 + R_bl[i, 2, 1] * d1 + R_bl[i, 2, 2] * d2
        f[0] += fb0
        f[1] += fb1
        f[2] += fb2
        tau[0] += ri[1] * fb2 - ri[2] * fb1
        tau[1] += ri[2] * fb0 - ri[0] * fb2
        tau[2] += ri[0] * fb1 - ri[1] * fb0
    # the passive midpoint rule for the rotation
    for k in range(3):
        w1[k] = w[k]
    wm = np.empty(3)
    for _ in range(iterations):
        for k in range(3):
            wm[k] = 0.5 * (w[k] + w1[k])
        c0 = wm[1] * J[2] * wm[2] - wm[2] * J[1] * wm[1]
        c1 = wm[2] * J[0] * wm[0] - wm[0] * J[2] * wm[2]
        c2 = wm[0] * J[1] * wm[1] - wm[1] * J[0] * wm[0]
        w1[0] = w[0] + dt * (tau[0] - c0) / J[0]
        w1[1] = w[1] + dt * (tau[1] - c1) / J[1]
        w1[2] = w[2] + dt * (tau[2] - c2) / J[2]
    for k in range(3):
        wm[k] = 0.5 * (w[k] + w1[k])
    E = np.empty((3, 3))
    Em = np.empty((3, 3))
    _exp_into(dt * wm[0], dt * wm[1], dt * wm[2], E)
    _exp_into(0.5 * dt * wm[0], 0.5 * dt * wm[1], 0.5 * dt * wm[2], Em)
    for a in range(3):
        m = 0.0
        for b in range(3):
            R1[a, b] = R[a, 0] * E[0, b] + R[a, 1] * E[1, b] + R[a, 2] * E[2, b]
            Rm_ab = R[a, 0] * Em[0, b] + R[a, 1] * Em[1, b] + R[a, 2] * Em[2, b]
            m += Rm_ab * f[b]
        v1[a] = v[a] + dt * m / mass
        p1[a] = p[a] + 0.5 * dt * (v[a] + v1[a])


@jit
def link_targets_kernel(body, R_bl, omega, half, out):
    """Every link's target ``out = (p_w (n, 3), v_w (n, 3), R_wl (n, 3, 3), omega_l (n, 3))``
    (:func:`~companion.motion.expected_physics.link_targets`)."""
    p, v, R, w = body
    p_w, v_w, R_wl, omega_l = out
    n = R_bl.shape[0]
    r, rd = np.empty((n, 3)), np.empty((n, 3))
    _shape(R_bl, omega, half, r, rd)
    for i in range(n):
        ri = r[i]
        u0 = (w[1] * ri[2] - w[2] * ri[1]) + rd[i, 0]
        u1 = (w[2] * ri[0] - w[0] * ri[2]) + rd[i, 1]
        u2 = (w[0] * ri[1] - w[1] * ri[0]) + rd[i, 2]
        for a in range(3):
            for b in range(3):
                R_wl[i, a, b] = R[a, 0] * R_bl[i, 0, b] + R[a, 1] * R_bl[i, 1, b] + R[a, 2] * R_bl[i, 2, b]
            omega_l[i, a] = (R_bl[i, 0, a] * w[0] + R_bl[i, 1, a] * w[1] + R_bl[i, 2, a] * w[2]) + omega[i, a]
            p_w[i, a] = p[a] + (R[a, 0] * ri[0] + R[a, 1] * ri[1] + R[a, 2] * ri[2])
            v_w[i, a] = v[a] + (R[a, 0] * u0 + R[a, 1] * u1 + R[a, 2] * u2)
