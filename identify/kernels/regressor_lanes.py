"""The compiled regressor kernel of :func:`identify.dynamics.regressor`, lane-wise.

The recursion of one sample is scalar arithmetic on 3-vectors: too little to fill a SIMD
register. So a block of ``LANES`` samples goes through the recursion together, joint by
joint, every quantity a row of lanes and every step a branch-free loop over all the lanes
with a scalar body, which the compiler vectorises (the joint type enters as a 0/1 factor;
sine and cosine are polynomials, not libm calls). The lane state lives in one array with
rows at fixed offsets, so the compiler can prove that the loops' reads and writes do not
overlap; with separate arrays it could not, and left the longest loops scalar.

The block's rows of eq. 17 collect in a (column, lane) table; 8 x 8 tiles of it are
transposed in registers into ``out``, whose rows are a sample each, with non-temporal
stores when the rows are whole cache lines: the output is far larger than the caches, and
ordinary stores would first read every line they are about to overwrite.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from .threads import THREADS, pool

LANES = 128
CHUNK = 1024
SERIAL_BELOW = 4 * CHUNK
"""Calls on fewer samples run the kernel in the calling thread alone (:func:`regressor_rows`)."""

# rows of the lane state ``s[row * L + lane]``; _Q, _QD, _QDD are also the rows of ``motion[i]``
_Q, _QD, _QDD = 0, 1, 2
_COS, _SIN = 3, 4  # of q for a revolute joint; (q, 0) for a prismatic one
_A = 5  # the rotation A[r, k] at _A + 3 r + k
_P = 14  # the origin p
_W, _DW, _DV = 17, 20, 23  # w, dw, dv (eqs. 1-6)
_RHO = 26  # rho of the joint last visited
_D = 29  # the shift that carries rows from the last joint point to this one
_B = 32  # B[r, k] = ([dw x] + w w^T - |w|^2 E)[r, k] at _B + 3 r + k
_NSTATE = 41

# numba caches the compiled kernels beside this file, keyed by its path and time stamp; a cache
# written when this package was the top-level ``identify`` (before it installed as
# ``armid.identify``) names the old module, so this file changed with the rename to make any
# such cache stale rather than fail to load ("No module named 'identify'")
_inline = numba.njit(cache=True, fastmath=True, error_model="numpy", boundscheck=False, inline="always")
# no reassociation here: the Cody-Waite reduction's order of subtraction is its accuracy
_exact = numba.njit(cache=True, fastmath={"contract", "nsz", "arcp"}, error_model="numpy", boundscheck=False)

_PIO2_HI, _PIO2_LO, _TWO_OVER_PI = 1.57079632673412561417e00, 6.07710050650619224932e-11, 0.63661977236758134308
_S = (-1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04,
      2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10)
_C = (4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05,
      -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11)


@_exact
def _sincos(x, c_out, s_out, nl):  # type: ignore[no-untyped-def]
    """cos and sin of ``x[:nl]``, branch-free so that the loop vectorises (libm's are calls):
    Cody-Waite reduction by pi/2, fdlibm's kernel polynomials on [-pi/4, pi/4], quadrant by
    selection; within 2 ulp for |x| < 1e5 rad (tested against numpy)."""
    for m in range(nl):
        k = np.floor(x[m] * _TWO_OVER_PI + 0.5)
        r = (x[m] - k * _PIO2_HI) - k * _PIO2_LO
        z = r * r
        sr = r + r * z * (_S[0] + z * (_S[1] + z * (_S[2] + z * (_S[3] + z * (_S[4] + z * _S[5])))))
        cr = 1.0 - 0.5 * z + z * z * (_C[0] + z * (_C[1] + z * (_C[2] + z * (_C[3] + z * (_C[4] + z * _C[5])))))
        n = np.int64(k) & 3
        sw = n & 1
        c = sr if sw else cr
        s = cr if sw else sr
        c_out[m] = -c if (n == 1 or n == 2) else c
        s_out[m] = -s if n >= 2 else s


def _vector_pointer(builder, context, aryty, array, index):  # type: ignore[no-untyped-def]
    data = context.make_array(aryty)(context, builder, array).data
    return builder.bitcast(builder.gep(data, [index]), ir.VectorType(ir.DoubleType(), 8).as_pointer())


def _transpose8(nontemporal: bool):  # type: ignore[no-untyped-def]
    """An intrinsic: ``dst.flat[di + r * ds + c] = src.flat[si + c * ss + r]`` for r, c < 8,
    through registers (three rounds of shuffles). With ``nontemporal`` the eight stores bypass
    the cache and ``dst.flat[di]`` must be 64-byte aligned."""
    lo, hi = [0, 8, 2, 10, 4, 12, 6, 14], [1, 9, 3, 11, 5, 13, 7, 15]
    pairs_lo, pairs_hi = [0, 1, 8, 9, 4, 5, 12, 13], [2, 3, 10, 11, 6, 7, 14, 15]
    halves_lo, halves_hi = [0, 1, 2, 3, 8, 9, 10, 11], [4, 5, 6, 7, 12, 13, 14, 15]

    @intrinsic
    def transpose(typingctx, dst, di, ds, src, si, ss):  # type: ignore[no-untyped-def]
        if not all(isinstance(a, types.Array) and a.dtype == types.float64 for a in (dst, src)):
            return None  # the tiles are of doubles
        sig = types.void(dst, types.intp, types.intp, src, types.intp, types.intp)

        def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
            dst_v, di_v, ds_v, src_v, si_v, ss_v = args
            i64 = ir.IntType(64)

            def mask(m):  # type: ignore[no-untyped-def]
                return ir.Constant(ir.VectorType(ir.IntType(32), 8), m)

            v = []
            for c in range(8):
                index = builder.add(si_v, builder.mul(ss_v, ir.Constant(i64, c)))
                v.append(builder.load(_vector_pointer(builder, context, signature.args[3], src_v, index), align=8))
            t = []
            for k in range(0, 8, 2):
                t += [builder.shuffle_vector(v[k], v[k + 1], mask(lo)), builder.shuffle_vector(v[k], v[k + 1], mask(hi))]
            u = [None] * 8
            for k in (0, 1, 4, 5):
                u[k] = builder.shuffle_vector(t[k], t[k + 2], mask(pairs_lo))
                u[k + 2] = builder.shuffle_vector(t[k], t[k + 2], mask(pairs_hi))
            rows = [None] * 8
            for k in range(4):
                rows[k] = builder.shuffle_vector(u[k], u[k + 4], mask(halves_lo))
                rows[k + 4] = builder.shuffle_vector(u[k], u[k + 4], mask(halves_hi))
            for r in range(8):
                index = builder.add(di_v, builder.mul(ds_v, ir.Constant(i64, r)))
                ptr = _vector_pointer(builder, context, signature.args[0], dst_v, index)
                if nontemporal:
                    store = builder.store(rows[r], ptr, align=64)
                    store.set_metadata("nontemporal", builder.module.add_metadata([ir.Constant(ir.IntType(32), 1)]))
                else:
                    builder.store(rows[r], ptr, align=8)
            return context.get_dummy_value()

        return sig, codegen

    return transpose


_transpose8_stream = _transpose8(nontemporal=True)
_transpose8_store = _transpose8(nontemporal=False)


@intrinsic
def _store_fence(typingctx):  # type: ignore[no-untyped-def]
    """Orders the non-temporal stores before anything after (they are weakly ordered)."""

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        builder.fence("seq_cst")
        return context.get_dummy_value()

    return types.void(), codegen


L = LANES  # the stride of a row of lanes, a constant so that the compiler sees rows apart


@_inline
def _joint_step(i, revolute, a0, ac, a_s, p0, pc, ps, t0, uu, motion, s, carried):  # type: ignore[no-untyped-def]
    """Joint i for every lane: A, rho, the forward recursion (eqs. 1-6), B, carried rows.
    Branch-free loops over the lanes (the joint type is a 0/1 factor), so they vectorise.
    ``s[row * L + lane]`` is the lane state; ``motion[i]`` joint i's q, qd, qdd rows;
    ``carried[j]`` the rows rf (0-2) and rn (3-5) of joint j carried to this link. Its three
    parts are inlined into one body, as when they were written as one. The joint type's factor
    ``rv`` (1 revolute, 0 prismatic) is taken here once and passed on: taken again in each part,
    the compiler left some lane loops scalar (a third fewer packed-double instructions)."""
    rv = 1.0 if revolute[i] else 0.0
    _joint_transform(i, revolute[i], rv, a0, ac, a_s, p0, pc, ps, motion, s)
    _forward_recursion(i, rv, t0, uu, s)
    _carry_rows(i, rv, uu, s, carried)


@_inline
def _joint_transform(i, revolute, rv, a0, ac, a_s, p0, pc, ps, motion, s):  # type: ignore[no-untyped-def]
    """Joint i's rotation A and origin p for every lane, and its qd, qdd into the lane state:
    A and p are affine in (cos q, sin q) for a revolute joint, in q for a prismatic one."""
    mi = motion[i]
    if revolute:
        _sincos(mi[_Q * L:_Q * L + L], s[_COS * L:_COS * L + L], s[_SIN * L:_SIN * L + L], L)
    else:
        for m in range(L):
            s[_COS * L + m] = mi[_Q * L + m]
            s[_SIN * L + m] = 0.0
    for r in range(3):
        for k in range(3):
            c0, cc, cs = a0[i, r, k], ac[i, r, k], a_s[i, r, k]
            for m in range(L):
                s[(_A + 3 * r + k) * L + m] = c0 + rv * (s[_COS * L + m] * cc + s[_SIN * L + m] * cs)
        c0, cc, cs = p0[i, r], pc[i, r], ps[i, r]
        for m in range(L):
            s[(_P + r) * L + m] = c0 + s[_COS * L + m] * cc + s[_SIN * L + m] * cs
    for m in range(L):
        s[_QD * L + m] = mi[_QD * L + m]
        s[_QDD * L + m] = mi[_QDD * L + m]


@_inline
def _forward_recursion(i, rv, t0, uu, s):  # type: ignore[no-untyped-def]
    """Khosla's forward recursion (eqs. 1-6) from the last joint point into frame i for every
    lane: rho = A^T (t0 - p), w, dw and dv with the joint's own motion, then
    B = [dw x] + w w^T - |w|^2 E and the shift that carries rows from the last joint point here."""
    tx, ty, tz = t0[i, 0], t0[i, 1], t0[i, 2]
    ux, uy, uz = uu[i, 0], uu[i, 1], uu[i, 2]
    pv = 1.0 - rv
    for m in range(L):
        a00, a01, a02 = s[_A * L + m], s[(_A + 1) * L + m], s[(_A + 2) * L + m]
        a10, a11, a12 = s[(_A + 3) * L + m], s[(_A + 4) * L + m], s[(_A + 5) * L + m]
        a20, a21, a22 = s[(_A + 6) * L + m], s[(_A + 7) * L + m], s[(_A + 8) * L + m]
        px, py, pz = s[_P * L + m], s[(_P + 1) * L + m], s[(_P + 2) * L + m]
        qd, qdd = s[_QD * L + m], s[_QDD * L + m]
        # rho = A^T (t0 - p): the joint point in frame i
        dx, dy, dz = tx - px, ty - py, tz - pz
        rx = a00 * dx + a10 * dy + a20 * dz
        ry = a01 * dx + a11 * dy + a21 * dz
        rz = a02 * dx + a12 * dy + a22 * dz
        wx, wy, wz = s[_W * L + m], s[(_W + 1) * L + m], s[(_W + 2) * L + m]
        ex, ey, ez = s[_DW * L + m], s[(_DW + 1) * L + m], s[(_DW + 2) * L + m]
        # acceleration of the joint point: dv + dw x t0 + w x (w x t0), then into frame i
        cx, cy, cz = wy * tz - wz * ty, wz * tx - wx * tz, wx * ty - wy * tx
        vx = s[_DV * L + m] + (ey * tz - ez * ty) + (wy * cz - wz * cy)
        vy = s[(_DV + 1) * L + m] + (ez * tx - ex * tz) + (wz * cx - wx * cz)
        vz = s[(_DV + 2) * L + m] + (ex * ty - ey * tx) + (wx * cy - wy * cx)
        dvx = a00 * vx + a10 * vy + a20 * vz
        dvy = a01 * vx + a11 * vy + a21 * vz
        dvz = a02 * vx + a12 * vy + a22 * vz
        # w, dw into frame i, plus the joint's own motion (revolute: rv = 1, prismatic: pv = 1)
        owx = a00 * wx + a10 * wy + a20 * wz
        owy = a01 * wx + a11 * wy + a21 * wz
        owz = a02 * wx + a12 * wy + a22 * wz
        oex = a00 * ex + a10 * ey + a20 * ez
        oey = a01 * ex + a11 * ey + a21 * ez
        oez = a02 * ex + a12 * ey + a22 * ez
        zx, zy, zz = ux * qd, uy * qd, uz * qd
        wx, wy, wz = owx + rv * zx, owy + rv * zy, owz + rv * zz
        ex = oex + rv * ((owy * zz - owz * zy) + ux * qdd)
        ey = oey + rv * ((owz * zx - owx * zz) + uy * qdd)
        ez = oez + rv * ((owx * zy - owy * zx) + uz * qdd)
        dvx += pv * (ux * qdd + 2.0 * (wy * zz - wz * zy))
        dvy += pv * (uy * qdd + 2.0 * (wz * zx - wx * zz))
        dvz += pv * (uz * qdd + 2.0 * (wx * zy - wy * zx))
        # dv -= dw x rho + w x (w x rho): the origin of frame i
        cx, cy, cz = wy * rz - wz * ry, wz * rx - wx * rz, wx * ry - wy * rx
        dvx -= (ey * rz - ez * ry) + (wy * cz - wz * cy)
        dvy -= (ez * rx - ex * rz) + (wz * cx - wx * cz)
        dvz -= (ex * ry - ey * rx) + (wx * cy - wy * cx)
        s[_W * L + m], s[(_W + 1) * L + m], s[(_W + 2) * L + m] = wx, wy, wz
        s[_DW * L + m], s[(_DW + 1) * L + m], s[(_DW + 2) * L + m] = ex, ey, ez
        s[_DV * L + m], s[(_DV + 1) * L + m], s[(_DV + 2) * L + m] = dvx, dvy, dvz
        # B = [dw x] + w w^T - |w|^2 E
        w2 = wx * wx + wy * wy + wz * wz
        s[_B * L + m] = wx * wx - w2
        s[(_B + 1) * L + m] = wx * wy - ez
        s[(_B + 2) * L + m] = wx * wz + ey
        s[(_B + 3) * L + m] = wy * wx + ez
        s[(_B + 4) * L + m] = wy * wy - w2
        s[(_B + 5) * L + m] = wy * wz - ex
        s[(_B + 6) * L + m] = wz * wx - ey
        s[(_B + 7) * L + m] = wz * wy + ex
        s[(_B + 8) * L + m] = wz * wz - w2
        # the shift that carries rows from the last joint point to this one: A rho + p - rho_prev
        s[_D * L + m] = a00 * rx + a01 * ry + a02 * rz + px - s[_RHO * L + m]
        s[(_D + 1) * L + m] = a10 * rx + a11 * ry + a12 * rz + py - s[(_RHO + 1) * L + m]
        s[(_D + 2) * L + m] = a20 * rx + a21 * ry + a22 * rz + pz - s[(_RHO + 2) * L + m]
        s[_RHO * L + m], s[(_RHO + 1) * L + m], s[(_RHO + 2) * L + m] = rx, ry, rz


@_inline
def _carry_rows(i, rv, uu, s, carried):  # type: ignore[no-untyped-def]
    """The rows of the joints before i carried through R_i (eq. 16: rf' = A^T (rf + rn x d),
    rn' = A^T rn), and joint i's own rows started: its axis, as a force row for a prismatic
    joint and a moment row for a revolute one."""
    ux, uy, uz = uu[i, 0], uu[i, 1], uu[i, 2]
    pv = 1.0 - rv
    for j in range(i):
        c = carried[j]
        for m in range(L):
            a00, a01, a02 = s[_A * L + m], s[(_A + 1) * L + m], s[(_A + 2) * L + m]
            a10, a11, a12 = s[(_A + 3) * L + m], s[(_A + 4) * L + m], s[(_A + 5) * L + m]
            a20, a21, a22 = s[(_A + 6) * L + m], s[(_A + 7) * L + m], s[(_A + 8) * L + m]
            gx, gy, gz = s[_D * L + m], s[(_D + 1) * L + m], s[(_D + 2) * L + m]
            nx, ny, nz = c[3 * L + m], c[4 * L + m], c[5 * L + m]
            fx = c[m] + ny * gz - nz * gy
            fy = c[L + m] + nz * gx - nx * gz
            fz = c[2 * L + m] + nx * gy - ny * gx
            c[m] = a00 * fx + a10 * fy + a20 * fz
            c[L + m] = a01 * fx + a11 * fy + a21 * fz
            c[2 * L + m] = a02 * fx + a12 * fy + a22 * fz
            c[3 * L + m] = a00 * nx + a10 * ny + a20 * nz
            c[4 * L + m] = a01 * nx + a11 * ny + a21 * nz
            c[5 * L + m] = a02 * nx + a12 * ny + a22 * nz
    c = carried[i]
    uvec = (ux, uy, uz)
    for r in range(3):
        for m in range(L):
            c[r * L + m] = pv * uvec[r]
            c[(3 + r) * L + m] = rv * uvec[r]


@_inline
def _rows(i, nj, s, carried, table):  # type: ignore[no-untyped-def]
    """Block (j, i) of eq. 17 for every j <= i and lane, into ``table[(10 nj j + 10 i + col) L + lane]``;
    the blocks below the diagonal stay zero."""
    for j in range(i + 1):
        c = carried[j]
        c0 = 10 * nj * j + 10 * i
        t = table[c0 * L:(c0 + 10) * L]
        for m in range(L):
            fn0, fn1, fn2 = c[3 * L + m], c[4 * L + m], c[5 * L + m]
            rx, ry, rz = s[_RHO * L + m], s[(_RHO + 1) * L + m], s[(_RHO + 2) * L + m]
            # the row taken about the origin of frame i: rf + rho x fn
            x0 = c[m] + ry * fn2 - rz * fn1
            x1 = c[L + m] + rz * fn0 - rx * fn2
            x2 = c[2 * L + m] + rx * fn1 - ry * fn0
            d0, d1, d2 = s[_DV * L + m], s[(_DV + 1) * L + m], s[(_DV + 2) * L + m]
            wx, wy, wz = s[_W * L + m], s[(_W + 1) * L + m], s[(_W + 2) * L + m]
            ex, ey, ez = s[_DW * L + m], s[(_DW + 1) * L + m], s[(_DW + 2) * L + m]
            b00, b01, b02 = s[_B * L + m], s[(_B + 1) * L + m], s[(_B + 2) * L + m]
            b10, b11, b12 = s[(_B + 3) * L + m], s[(_B + 4) * L + m], s[(_B + 5) * L + m]
            b20, b21, b22 = s[(_B + 6) * L + m], s[(_B + 7) * L + m], s[(_B + 8) * L + m]
            t[m] = x0 * d0 + x1 * d1 + x2 * d2
            t[L + m] = b00 * x0 + b10 * x1 + b20 * x2 + (d1 * fn2 - d2 * fn1)
            t[2 * L + m] = b01 * x0 + b11 * x1 + b21 * x2 + (d2 * fn0 - d0 * fn2)
            t[3 * L + m] = b02 * x0 + b12 * x1 + b22 * x2 + (d0 * fn1 - d1 * fn0)
            y0 = fn1 * wz - fn2 * wy
            y1 = fn2 * wx - fn0 * wz
            y2 = fn0 * wy - fn1 * wx
            t[4 * L + m] = ex * fn0 + wx * y0
            t[5 * L + m] = ey * fn0 + ex * fn1 + wy * y0 + wx * y1
            t[6 * L + m] = ez * fn0 + ex * fn2 + wz * y0 + wx * y2
            t[7 * L + m] = ey * fn1 + wy * y1
            t[8 * L + m] = ez * fn1 + ey * fn2 + wz * y1 + wy * y2
            t[9 * L + m] = ez * fn2 + wz * y2


@_inline
def _write_out(table, nl, k0, out, row_stride, seg_len, seg_stride, first_aligned):  # type: ignore[no-untyped-def]
    """The block's lanes into the rows ``k0 + lane`` of ``out``, the flat (1-D) memory of the
    result from its first element on: row k's elements lie at ``k * row_stride +
    seg * seg_stride + col`` in segments of ``seg_len`` contiguous columns (one segment of
    10 N^2 when the result is C-contiguous, N of 10 N when it is a view into a wider array).
    8 x 8 tiles go through registers; ``first_aligned[seg]`` >= 0 is a column whose address
    is a cache line's in every row, and the tiles from it go out non-temporally."""
    for seg in range(first_aligned.shape[0]):
        fa = first_aligned[seg]
        start = max(fa, 0)
        stop = start + (seg_len - start) // 8 * 8
        t0 = seg * seg_len  # the table row of the segment's first column
        m0 = 0
        while m0 + 8 <= nl:
            base = (k0 + m0) * row_stride + seg * seg_stride
            for col in range(start, stop, 8):
                if fa >= 0:
                    _transpose8_stream(out, base + col, row_stride, table, (t0 + col) * L + m0, L)
                else:
                    _transpose8_store(out, base + col, row_stride, table, (t0 + col) * L + m0, L)
            for m in range(m0, m0 + 8):
                row = (k0 + m) * row_stride + seg * seg_stride
                for col in range(start):
                    out[row + col] = table[(t0 + col) * L + m]
                for col in range(stop, seg_len):
                    out[row + col] = table[(t0 + col) * L + m]
            m0 += 8
        for m in range(m0, nl):
            row = (k0 + m) * row_stride + seg * seg_stride
            for col in range(seg_len):
                out[row + col] = table[(t0 + col) * L + m]


@numba.njit(cache=True, nogil=True, fastmath=True, error_model="numpy", boundscheck=False)
def regressor_kernel(revolute, a0, ac, a_s, p0, pc, ps, t0, u, g, q, qd, qdd, out, row_stride, seg_len, seg_stride, first_aligned,
                     first_chunk, stop_chunk):  # type: ignore[no-untyped-def]
    """Rows of ``out`` = the regressor of samples k (eqs. 16-18), for (n, N) ``q``, ``qd``,
    ``qdd``, over the chunks ``first_chunk <= k // CHUNK < stop_chunk``; the joint constants
    are :func:`identify.dynamics._joint_constants`'s; ``out`` is the result's flat memory,
    laid out as :func:`_write_out` says. Without the GIL, so that threads share the chunks
    (:func:`regressor_rows`)."""
    n, nj = q.shape
    ncol = 10 * nj * nj
    for chunk in range(first_chunk, stop_chunk):
        # scratch for one block of lanes, allocated once per chunk
        s = np.empty(_NSTATE * L)
        motion = np.zeros((nj, 3 * L))  # lanes past the end of the data keep finite values
        carried = np.empty((nj, 6 * L))
        table = np.zeros(ncol * L)  # the blocks below the diagonal stay zero
        for k0 in range(chunk * CHUNK, min(n, chunk * CHUNK + CHUNK), L):
            nl = min(L, n - k0)
            for m in range(nl):
                for i in range(nj):
                    motion[i, _Q * L + m] = q[k0 + m, i]
                    motion[i, _QD * L + m] = qd[k0 + m, i]
                    motion[i, _QDD * L + m] = qdd[k0 + m, i]
            for r in range(3):
                for m in range(L):
                    s[(_W + r) * L + m] = 0.0
                    s[(_DW + r) * L + m] = 0.0
                    s[(_DV + r) * L + m] = g[r]
                    s[(_RHO + r) * L + m] = 0.0
            for i in range(nj):
                _joint_step(i, revolute, a0, ac, a_s, p0, pc, ps, t0, u, motion, s, carried)
                _rows(i, nj, s, carried, table)
            _write_out(table, nl, k0, out, row_stride, seg_len, seg_stride, first_aligned)
        _store_fence()


def regressor_rows(revolute, a0, ac, a_s, p0, pc, ps, t0, u, g, q, qd, qdd, out, row_stride, seg_len, seg_stride, first_aligned):  # type: ignore[no-untyped-def]
    """:func:`regressor_kernel` into ``out`` (n, N, 10 N), possibly a view into a wider
    array: the chunks shared out among ``THREADS`` threads (this one and a pool's), in this
    thread alone below ``SERIAL_BELOW`` samples.

    The kernel was a numba ``parallel=True`` function (prange over the chunks). Its parallel
    machinery tripled the compilation on a fresh machine (66 s against 27 s measured on this
    2-core machine at load average 11), and waking its threads cost more than a few chunks
    of work: 160 samples took 17 ms on two threads and 0.08 ms on one at load average 9,
    7,840 samples 9.6 ms and 3.8 ms. So the kernel is serial and releases the GIL, and
    threads take contiguous shares of the chunks only for large calls.

    The kernel gets ``out`` as its flat memory (a 1-D view from the first element to the
    last), so that a C-contiguous result and a view into a stacked regressor are one type
    to numba: one compilation, not two (10-28 s each measured here under load)."""
    n = q.shape[0]
    if n == 0:
        return
    span = (n - 1) * row_stride + (first_aligned.shape[0] - 1) * seg_stride + seg_len
    flat = np.lib.stride_tricks.as_strided(out, shape=(span,), strides=(out.itemsize,))
    args = (revolute, a0, ac, a_s, p0, pc, ps, t0, u, g, q, qd, qdd, flat, row_stride, seg_len, seg_stride, first_aligned)
    nchunks = (n + CHUNK - 1) // CHUNK
    threads = min(THREADS, nchunks) if n >= SERIAL_BELOW else 1
    bounds = [nchunks * k // threads for k in range(threads + 1)]
    others = [pool("regressor").submit(regressor_kernel, *args, bounds[k], bounds[k + 1]) for k in range(1, threads)]
    regressor_kernel(*args, bounds[0], bounds[1])
    for f in others:
        f.result()
