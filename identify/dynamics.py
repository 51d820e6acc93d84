"""Newton-Euler dynamics, classic (eqs. 1-9) and Khosla's linear-in-parameters form (10-18).

All functions are batched over samples: ``q, qd, qdd`` are ``(n_samples, n_joints)``.
The recursions run over the joints only; nothing loops over samples in Python.

Quantities of link ``i`` are expressed in link frame ``i`` (Khosla's choice). Each joint
``i`` has a reference point ``rho_i`` on its axis; the wrench ``g_i = [f_i; n_i]`` that link
``i-1`` exerts on link ``i`` is taken about ``rho_i``. For standard DH ``rho_i = -p_i`` (the
origin of frame ``i-1``), and ``K_i``, ``R_{i+1}`` below are the paper's matrices letter
for letter; for modified DH and URDF joints the same formulas hold with their own ``rho_i``.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from .robot import Robot, inertia_matrix
from .spatial import Array, axis_rotation, skew


@dataclass(frozen=True)
class LinkMotion:
    """Forward recursion (eqs. 1-3) for one link, over all samples.

    ``A``: (n, 3, 3) rotation from frame i to frame i-1 (Khosla's ``A_i``);
    ``P``: (n, 3) origin of frame i in frame i-1; ``w, dw, dv``: (n, 3) angular velocity,
    angular acceleration, linear acceleration of the frame origin (gravity included as a
    base acceleration), all in frame i; ``rho``: (n, 3) the joint-axis reference point in
    frame i; ``axis``: (3,) the joint axis in frame i.
    """

    A: Array
    P: Array
    w: Array
    dw: Array
    dv: Array
    rho: Array
    axis: Array
    revolute: bool


def _t(a: Array, x: Array) -> Array:
    """``A^T x`` batched: (n, 3, 3), (n, 3) -> (n, 3)."""
    return np.einsum("nba,nb->na", a, x)


def _m(a: Array, x: Array) -> Array:
    """``A x`` batched."""
    return np.einsum("nab,nb->na", a, x)


def _cross(a: Array, b: Array) -> Array:
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def check_joint_arrays(robot: Robot, q: Array, qd: Array, qdd: Array) -> tuple[Array, Array, Array]:
    """Coerce to float (n, N) arrays and check their shapes agree with the robot."""
    arrays = []
    for label, x in (("q", q), ("qd", qd), ("qdd", qdd)):
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if x.ndim != 2 or x.shape[1] != robot.n_joints:
            raise ValueError(f"{label} must be (n_samples, {robot.n_joints}), got {x.shape}")
        arrays.append(x)
    if not arrays[0].shape == arrays[1].shape == arrays[2].shape:
        raise ValueError(f"q, qd, qdd shapes differ: {[a.shape for a in arrays]}")
    return arrays[0], arrays[1], arrays[2]


def forward_recursion(robot: Robot, q: Array, qd: Array, qdd: Array) -> list[LinkMotion]:
    """Velocities and accelerations of every link frame, base to tip (eqs. 1-3).

    .. math::
        \\omega_i = A_i^T \\omega_{i-1} + \\sigma_i u_i \\dot q_i, \\qquad
        \\dot\\omega_i = A_i^T \\dot\\omega_{i-1}
            + \\sigma_i (u_i \\ddot q_i + (A_i^T \\omega_{i-1}) \\times u_i \\dot q_i)

    and the origin's acceleration through the point on the joint axis, fixed in both links
    (for standard DH this is Khosla's eq. 3 with ``rho_i = -p_i``). The base is at rest in
    the gravitational field: ``dv_0 = -gravity``.
    """
    q, qd, qdd = check_joint_arrays(robot, q, qd, qdd)
    n = q.shape[0]
    w = np.zeros((n, 3))
    dw = np.zeros((n, 3))
    dv = np.broadcast_to(-robot.gravity, (n, 3)).copy()
    motions = []
    for i, joint in enumerate(robot.joints):
        r0, t0 = joint.pre[:3, :3], joint.pre[:3, 3]
        r1, t1 = joint.post[:3, :3], joint.post[:3, 3]
        u = r1.T @ joint.axis  # joint axis in link frame i (fixed by either motion)
        if joint.revolute:
            rq = axis_rotation(joint.axis, q[:, i])
            a = r0 @ rq @ r1
            p = t0 + (r0 @ (rq @ t1).T).T
        else:
            a = np.broadcast_to(r0 @ r1, (n, 3, 3))
            p = t0 + (r0 @ (t1[:, None] + joint.axis[:, None] * q[:, i])).T
        rho = _t(a, t0 - p)  # joint frame origin (on the axis) in frame i
        w_prev, dw_prev = _t(a, w), _t(a, dw)
        # acceleration of the axis point, computed as a point of link i-1
        acc_axis = _t(a, dv + _cross(dw, t0) + _cross(w, _cross(w, np.broadcast_to(t0, (n, 3)))))
        if joint.revolute:
            w = w_prev + u * qd[:, i : i + 1]
            dw = dw_prev + u * qdd[:, i : i + 1] + _cross(w_prev, u * qd[:, i : i + 1])
            dv = acc_axis - _cross(dw, rho) - _cross(w, _cross(w, rho))
        else:
            w, dw = w_prev, dw_prev
            uqd = u * qd[:, i : i + 1]
            dv = acc_axis - _cross(dw, rho) - _cross(w, _cross(w, rho)) + u * qdd[:, i : i + 1]
            dv = dv + 2.0 * _cross(w, uqd)
        motions.append(LinkMotion(a, p, w, dw, dv, rho, u, joint.revolute))
    return motions


def selection_vector(motion: LinkMotion) -> Array:
    """Eq. (17): the row of ``g_i`` that is the joint torque (revolute) or force."""
    s = np.zeros(6)
    if motion.revolute:
        s[3:] = motion.axis
    else:
        s[:3] = motion.axis
    return s


def inverse_dynamics(robot: Robot, q: Array, qd: Array, qdd: Array, link_inertials: list[tuple[float, Array, Array]] | None = None) -> Array:
    """Classic Newton-Euler inverse dynamics, eqs. (1)-(9), nonlinear in ``s_i``.

    ``link_inertials`` is a list of ``(mass, com (3,), inertia about COM (3, 3))`` per link,
    defaulting to the robot's modeled values. Returns ``tau`` (n, N).

    .. math::
        F_i = m_i \\dot v^*_i, \\quad N_i = I_i \\dot\\omega_i + \\omega_i \\times I_i \\omega_i,
        \\quad f_i = A_{i+1} f_{i+1} + F_i,
        \\quad n_i = A_{i+1} n_{i+1} + P_{i+1} \\times A_{i+1} f_{i+1} + N_i + s_i \\times F_i

    with moments about the origin of frame i; ``tau_i`` is taken about the joint axis.
    """
    if link_inertials is None:
        link_inertials = []
        for joint in robot.joints:
            if joint.inertial is None:
                raise ValueError(f"joint {joint.name}: no modeled inertial values")
            link_inertials.append(
                (joint.inertial.mass_kg, np.asarray(joint.inertial.com_m), inertia_matrix(joint.inertial.inertia_kgm2))
            )
    motions = forward_recursion(robot, q, qd, qdd)
    n = q.shape[0] if np.ndim(q) == 2 else 1
    tau = np.zeros((n, robot.n_joints))
    f_next = np.zeros((n, 3))
    n_next = np.zeros((n, 3))
    for i in reversed(range(robot.n_joints)):
        mo = motions[i]
        mass, s, inertia = link_inertials[i]
        s = np.broadcast_to(np.asarray(s, dtype=float), (n, 3))
        acc_com = _cross(mo.dw, s) + _cross(mo.w, _cross(mo.w, s)) + mo.dv  # (4)
        force = mass * acc_com  # (5)
        moment = mo.dw @ inertia.T + _cross(mo.w, mo.w @ inertia.T)  # (6)
        if i + 1 < robot.n_joints:
            nxt = motions[i + 1]
            f_child = _m(nxt.A, f_next)
            n_child = _m(nxt.A, n_next) + _cross(nxt.P, f_child)
        else:
            f_child = np.zeros((n, 3))
            n_child = np.zeros((n, 3))
        f_i = f_child + force  # (7)
        n_i = n_child + moment + _cross(s, force)  # (8), about the origin of frame i
        if mo.revolute:  # (9), about the joint axis
            tau[:, i] = (n_i - _cross(mo.rho, f_i)) @ mo.axis
        else:
            tau[:, i] = f_i @ mo.axis
        f_next, n_next = f_i, n_i
    return tau


def _dot_matrix(x: Array) -> Array:
    """Khosla's ``[. x]``: ``I x = [. x] [Ixx Ixy Ixz Iyy Iyz Izz]^T``; (n, 3) -> (n, 3, 6)."""
    n = x.shape[0]
    out = np.zeros((n, 3, 6))
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = x[:, 0], x[:, 1], x[:, 2]
    out[:, 1, 1], out[:, 1, 3], out[:, 1, 4] = x[:, 0], x[:, 1], x[:, 2]
    out[:, 2, 2], out[:, 2, 4], out[:, 2, 5] = x[:, 0], x[:, 1], x[:, 2]
    return out


def kinematic_matrix(motion: LinkMotion) -> Array:
    """Khosla's kinematic matrix ``K_i`` (n, 6, 10): ``G_i = K_i phi_i`` about ``rho_i``.

    .. math::
        K_i = \\begin{bmatrix} \\dot v_i & [\\dot\\omega_i\\times] + [\\omega_i\\times]^2 & 0 \\\\
        [p_i\\times]\\dot v_i & -[\\dot v_i\\times] + [p_i\\times]([\\dot\\omega_i\\times]
        + [\\omega_i\\times]^2) & [.\\dot\\omega_i] + [\\omega_i\\times][.\\omega_i] \\end{bmatrix}

    with ``p_i = -rho_i`` (Khosla, after eq. 17).
    """
    n = motion.w.shape[0]
    sw, sdw, sdv, sp = skew(motion.w), skew(motion.dw), skew(motion.dv), skew(-motion.rho)
    b = sdw + sw @ sw
    k = np.zeros((n, 6, 10))
    k[:, :3, 0] = motion.dv
    k[:, :3, 1:4] = b
    k[:, 3:, 0] = _m(sp, motion.dv)
    k[:, 3:, 1:4] = -sdv + sp @ b
    k[:, 3:, 4:] = _dot_matrix(motion.dw) + sw @ _dot_matrix(motion.w)
    return k


def pseudo_rotation(motion: LinkMotion, rho_parent: Array) -> Array:
    """Khosla's pseudo-rotation ``R_i`` (n, 6, 6): ``g_{i-1} = R_i g_i + G_{i-1}`` (eq. 16).

    .. math:: R_i = \\begin{bmatrix} A_i & 0 \\\\ [d\\times] A_i & A_i \\end{bmatrix},
        \\quad d = c_i - \\rho_{i-1}

    with ``c_i`` the axis point of joint i in frame i-1 (zero for standard DH, so that
    ``d = p_{i-1}`` as in the paper).
    """
    n = motion.A.shape[0]
    c = _m(motion.A, motion.rho) + motion.P
    r = np.zeros((n, 6, 6))
    r[:, :3, :3] = motion.A
    r[:, 3:, 3:] = motion.A
    r[:, 3:, :3] = skew(c - rho_parent) @ motion.A
    return r


def regressor_blocks(robot: Robot, q: Array, qd: Array, qdd: Array) -> Array:
    """``M`` assembled literally from ``K_i`` and ``R_i`` (eqs. 16-18); slow, for checking."""
    motions = forward_recursion(robot, q, qd, qdd)
    n, nj = q.shape
    out = np.zeros((n, nj, 10 * nj))
    for j in range(nj):
        row = np.broadcast_to(selection_vector(motions[j]), (n, 6))
        for i in range(j, nj):
            if i > j:
                row = np.einsum("nk,nkl->nl", row, pseudo_rotation(motions[i], motions[i - 1].rho))
            out[:, j, 10 * i : 10 * i + 10] = np.einsum("nk,nkl->nl", row, kinematic_matrix(motions[i]))
    return out


def regressor(robot: Robot, q: Array, qd: Array, qdd: Array, out: Array | None = None) -> Array:
    """The block upper-triangular matrix ``M(q, qd, qdd)`` of ``tau = M phi`` (eq. 18).

    Returns (n_samples, N, 10 N) in C order. Block ``(j, i)`` is ``s_j^T R_{j+1} ... R_i K_i``
    (eqs. 16-17): the rows ``s_j^T R^j_i`` of all joints ``j <= i`` are carried together from
    link to link and multiplied into ``K_i`` in closed form, which is :func:`regressor_blocks`
    without the zeros of ``K_i``. A compiled kernel (:mod:`identify.kernels.regressor_lanes`) runs
    it on blocks of samples in SIMD lanes, the blocks of a large call on several threads. ``out``
    (n, N, 10 N), possibly a view into a wider array, receives the result when given.
    """
    q, qd, qdd = check_joint_arrays(robot, q, qd, qdd)
    n, nj = q.shape
    if out is None:
        out = np.empty((n, nj, 10 * nj))
    elif out.shape != (n, nj, 10 * nj):
        raise ValueError(f"out has shape {out.shape}, expected {(n, nj, 10 * nj)}")
    layout = _out_layout(out)
    if layout is None:  # not rows of doubles: compute, then let numpy copy (and cast)
        out[...] = regressor(robot, q, qd, qdd)
        return out
    revolute, a0, ac, a_s, p0, pc, ps, t0, u, g = _constants(robot)
    from .kernels.regressor_lanes import regressor_rows

    row_stride, seg_len, seg_stride, first_aligned = layout
    regressor_rows(revolute, a0, ac, a_s, p0, pc, ps, t0, u, g,
                   np.ascontiguousarray(q), np.ascontiguousarray(qd), np.ascontiguousarray(qdd),
                   out, row_stride, seg_len, seg_stride, first_aligned)
    return out


def _out_layout(out: Array) -> tuple[int, int, int, Array] | None:
    """How the kernel writes ``out``: (row stride, segment length, segment stride, first
    cache-line-aligned column per segment or -1), in elements; None when ``out`` is not
    made of contiguous rows of doubles the kernel can address."""
    _, nj, width = out.shape
    item, address = out.itemsize, out.ctypes.data
    if out.dtype != np.float64 or address % item or any(st % item for st in out.strides) or out.strides[2] != item:
        return None
    row, seg, _ = (st // item for st in out.strides)
    if out.flags.c_contiguous:
        row, seg_len, seg, segments = nj * width, nj * width, 0, 1
    else:
        seg_len, segments = width, nj
    first = np.full(segments, -1, dtype=np.int64)
    if row % 8 == 0:  # a segment's column starts at the same place in a cache line in every row
        first[:] = (-(address // item + np.arange(segments) * seg)) % 8
    return row, seg_len, seg, first


_CONSTANTS: weakref.WeakKeyDictionary[Robot, tuple[tuple[bytes, ...], tuple[Array, ...]]] = weakref.WeakKeyDictionary()


def _constants(robot: Robot) -> tuple[Array, ...]:
    """The kernel's per-robot inputs (joint types, :func:`_joint_constants`, base acceleration),
    computed once per robot: recomputing them took longer than the kernel on the few hundred
    samples of a design's candidate. Kept with a fingerprint of the joints' arrays, so that a
    robot whose arrays were changed in place gets them anew."""
    key = tuple(x.tobytes() for j in robot.joints for x in (np.asarray(j.pre), np.asarray(j.axis), np.asarray(j.post)))
    key += (bytes(j.revolute for j in robot.joints), np.asarray(robot.gravity, float).tobytes())
    hit = _CONSTANTS.get(robot)
    if hit is not None and hit[0] == key:
        return hit[1]
    values = (np.array([j.revolute for j in robot.joints]), *_joint_constants(robot), -np.asarray(robot.gravity, dtype=float))
    _CONSTANTS[robot] = (key, values)
    return values


def _joint_constants(robot: Robot) -> tuple[Array, ...]:
    """What of joint i's transform ``[r0|t0] J(e, q) [r1|t1]`` does not depend on q.

    Rodrigues, ``Rq = c E + s [e x] + (1 - c) e e^T``, makes the rotation and the origin of
    a revolute joint affine in ``(c, s)``: ``A = A0 + c Ac + s As``, ``p = p0 + c pc + s ps``;
    a prismatic joint has ``A = A0`` and ``p = p0 + q pc``. ``u`` is the axis in frame i.
    """
    nj = robot.n_joints
    a0, ac, a_s = np.zeros((nj, 3, 3)), np.zeros((nj, 3, 3)), np.zeros((nj, 3, 3))
    p0, pc, ps, t0, u = (np.zeros((nj, 3)) for _ in range(5))
    for i, j in enumerate(robot.joints):
        e = np.asarray(j.axis, float).reshape(3)
        r0, t0[i] = np.asarray(j.pre, float)[:3, :3], np.asarray(j.pre, float)[:3, 3]
        r1, t1 = np.asarray(j.post, float)[:3, :3], np.asarray(j.post, float)[:3, 3]
        u[i] = r1.T @ e
        if j.revolute:
            ex = np.array([[0.0, -e[2], e[1]], [e[2], 0.0, -e[0]], [-e[1], e[0], 0.0]])
            a0[i] = np.outer(r0 @ e, r1.T @ e)
            ac[i] = r0 @ r1 - a0[i]
            a_s[i] = r0 @ ex @ r1
            p0[i] = t0[i] + r0 @ e * (e @ t1)
            pc[i] = r0 @ (t1 - e * (e @ t1))
            ps[i] = r0 @ np.cross(e, t1)
        else:
            a0[i] = r0 @ r1
            p0[i] = t0[i] + r0 @ t1
            pc[i] = r0 @ e
    return a0, ac, a_s, p0, pc, ps, t0, u
