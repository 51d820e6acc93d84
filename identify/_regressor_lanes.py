"""The compiled regressor kernel of :func:`identify.dynamics.regressor`, lane-wise.

The recursion of one sample is scalar arithmetic on 3-vectors: too little to fill a SIMD
register. So a block of ``LANES`` samples goes through the recursion together, joint by
joint, every quantity held as an array over the lanes (``w[r, m]``) and every step a
branch-free loop over the lanes with a scalar body, which the compiler vectorises (the
joint type enters as a 0/1 factor; sine and cosine are polynomials, not libm calls). The
rows of block (j, i) (eq. 17) go straight into ``out``. Chunks of ``CHUNK`` samples run in
parallel, each with its scratch allocated once.
"""

from __future__ import annotations

import numba
import numpy as np

LANES = 128
CHUNK = 1024

_jit = numba.njit(cache=True, fastmath=True, error_model="numpy", boundscheck=False)
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


@_jit
def _joint_step(i, revolute, a0, ac, a_s, p0, pc, ps, t0, uu, qi, qdi, qddi, a, p, rho, w, dw, dv, rho_prev, b, rf, rn, d):  # type: ignore[no-untyped-def]
    """Joint i for every lane: A, rho, the forward recursion (eqs. 1-6), B, carried rows.
    Branch-free loops over the lanes (the joint type is a 0/1 factor), so they vectorise."""
    nl = qi.shape[0]
    tx, ty, tz = t0[i, 0], t0[i, 1], t0[i, 2]
    ux, uy, uz = uu[i, 0], uu[i, 1], uu[i, 2]
    rv = 1.0 if revolute[i] else 0.0
    pv = 1.0 - rv
    # A and p: affine in (cos q, sin q) for a revolute joint, in q for a prismatic one
    if revolute[i]:
        _sincos(qi, d[0], d[1], nl)
    else:
        for m in range(nl):
            d[0, m] = qi[m]
            d[1, m] = 0.0
    for r in range(3):
        for k in range(3):
            c0, cc, cs = a0[i, r, k], ac[i, r, k], a_s[i, r, k]
            for m in range(nl):
                a[r, k, m] = c0 + rv * (d[0, m] * cc + d[1, m] * cs)
        c0, cc, cs = p0[i, r], pc[i, r], ps[i, r]
        for m in range(nl):
            p[r, m] = c0 + d[0, m] * cc + d[1, m] * cs
    for m in range(nl):
        a00, a01, a02 = a[0, 0, m], a[0, 1, m], a[0, 2, m]
        a10, a11, a12 = a[1, 0, m], a[1, 1, m], a[1, 2, m]
        a20, a21, a22 = a[2, 0, m], a[2, 1, m], a[2, 2, m]
        px, py, pz = p[0, m], p[1, m], p[2, m]
        # rho = A^T (t0 - p): the joint point in frame i
        dx, dy, dz = tx - px, ty - py, tz - pz
        rx = a00 * dx + a10 * dy + a20 * dz
        ry = a01 * dx + a11 * dy + a21 * dz
        rz = a02 * dx + a12 * dy + a22 * dz
        wx, wy, wz = w[0, m], w[1, m], w[2, m]
        ex, ey, ez = dw[0, m], dw[1, m], dw[2, m]
        # acceleration of the joint point: dv + dw x t0 + w x (w x t0), then into frame i
        cx, cy, cz = wy * tz - wz * ty, wz * tx - wx * tz, wx * ty - wy * tx
        vx = dv[0, m] + (ey * tz - ez * ty) + (wy * cz - wz * cy)
        vy = dv[1, m] + (ez * tx - ex * tz) + (wz * cx - wx * cz)
        vz = dv[2, m] + (ex * ty - ey * tx) + (wx * cy - wy * cx)
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
        zx, zy, zz = ux * qdi[m], uy * qdi[m], uz * qdi[m]
        wx, wy, wz = owx + rv * zx, owy + rv * zy, owz + rv * zz
        ex = oex + rv * ((owy * zz - owz * zy) + ux * qddi[m])
        ey = oey + rv * ((owz * zx - owx * zz) + uy * qddi[m])
        ez = oez + rv * ((owx * zy - owy * zx) + uz * qddi[m])
        dvx += pv * (ux * qddi[m] + 2.0 * (wy * zz - wz * zy))
        dvy += pv * (uy * qddi[m] + 2.0 * (wz * zx - wx * zz))
        dvz += pv * (uz * qddi[m] + 2.0 * (wx * zy - wy * zx))
        # dv -= dw x rho + w x (w x rho): the origin of frame i
        cx, cy, cz = wy * rz - wz * ry, wz * rx - wx * rz, wx * ry - wy * rx
        dvx -= (ey * rz - ez * ry) + (wy * cz - wz * cy)
        dvy -= (ez * rx - ex * rz) + (wz * cx - wx * cz)
        dvz -= (ex * ry - ey * rx) + (wx * cy - wy * cx)
        w[0, m], w[1, m], w[2, m] = wx, wy, wz
        dw[0, m], dw[1, m], dw[2, m] = ex, ey, ez
        dv[0, m], dv[1, m], dv[2, m] = dvx, dvy, dvz
        # B = [dw x] + w w^T - |w|^2 E
        w2 = wx * wx + wy * wy + wz * wz
        b[0, 0, m] = wx * wx - w2
        b[0, 1, m] = wx * wy - ez
        b[0, 2, m] = wx * wz + ey
        b[1, 0, m] = wy * wx + ez
        b[1, 1, m] = wy * wy - w2
        b[1, 2, m] = wy * wz - ex
        b[2, 0, m] = wz * wx - ey
        b[2, 1, m] = wz * wy + ex
        b[2, 2, m] = wz * wz - w2
        # the shift that carries rows from the last joint point to this one: A rho + p - rho_prev
        d[0, m] = a00 * rx + a01 * ry + a02 * rz + px - rho_prev[0, m]
        d[1, m] = a10 * rx + a11 * ry + a12 * rz + py - rho_prev[1, m]
        d[2, m] = a20 * rx + a21 * ry + a22 * rz + pz - rho_prev[2, m]
        rho_prev[0, m], rho_prev[1, m], rho_prev[2, m] = rx, ry, rz
        rho[0, m], rho[1, m], rho[2, m] = rx, ry, rz
    # carried rows <- rows R_i: rf' = A^T (rf + rn x d), rn' = A^T rn
    for j in range(i):
        for m in range(nl):
            a00, a01, a02 = a[0, 0, m], a[0, 1, m], a[0, 2, m]
            a10, a11, a12 = a[1, 0, m], a[1, 1, m], a[1, 2, m]
            a20, a21, a22 = a[2, 0, m], a[2, 1, m], a[2, 2, m]
            gx, gy, gz = d[0, m], d[1, m], d[2, m]
            nx, ny, nz = rn[j, 0, m], rn[j, 1, m], rn[j, 2, m]
            fx = rf[j, 0, m] + ny * gz - nz * gy
            fy = rf[j, 1, m] + nz * gx - nx * gz
            fz = rf[j, 2, m] + nx * gy - ny * gx
            rf[j, 0, m] = a00 * fx + a10 * fy + a20 * fz
            rf[j, 1, m] = a01 * fx + a11 * fy + a21 * fz
            rf[j, 2, m] = a02 * fx + a12 * fy + a22 * fz
            rn[j, 0, m] = a00 * nx + a10 * ny + a20 * nz
            rn[j, 1, m] = a01 * nx + a11 * ny + a21 * nz
            rn[j, 2, m] = a02 * nx + a12 * ny + a22 * nz
    uvec = (ux, uy, uz)
    for r in range(3):
        for m in range(nl):
            rf[i, r, m] = pv * uvec[r]
            rn[i, r, m] = rv * uvec[r]


@_jit
def _rows(i, nl, rho, w, dw, dv, b, rf, rn, out):  # type: ignore[no-untyped-def]
    """Block (j, i) of eq. 17 for every j <= i and lane, straight into ``out[lane, j, 10 i + col]``;
    the blocks below the diagonal are zero."""
    c0 = 10 * i
    for j in range(i + 1):
        for m in range(nl):
            fn0, fn1, fn2 = rn[j, 0, m], rn[j, 1, m], rn[j, 2, m]
            rx, ry, rz = rho[0, m], rho[1, m], rho[2, m]
            # the row taken about the origin of frame i: rf + rho x fn
            x0 = rf[j, 0, m] + ry * fn2 - rz * fn1
            x1 = rf[j, 1, m] + rz * fn0 - rx * fn2
            x2 = rf[j, 2, m] + rx * fn1 - ry * fn0
            d0, d1, d2 = dv[0, m], dv[1, m], dv[2, m]
            wx, wy, wz = w[0, m], w[1, m], w[2, m]
            ex, ey, ez = dw[0, m], dw[1, m], dw[2, m]
            out[m, j, c0 + 0] = x0 * d0 + x1 * d1 + x2 * d2
            out[m, j, c0 + 1] = b[0, 0, m] * x0 + b[1, 0, m] * x1 + b[2, 0, m] * x2 + (d1 * fn2 - d2 * fn1)
            out[m, j, c0 + 2] = b[0, 1, m] * x0 + b[1, 1, m] * x1 + b[2, 1, m] * x2 + (d2 * fn0 - d0 * fn2)
            out[m, j, c0 + 3] = b[0, 2, m] * x0 + b[1, 2, m] * x1 + b[2, 2, m] * x2 + (d0 * fn1 - d1 * fn0)
            y0 = fn1 * wz - fn2 * wy
            y1 = fn2 * wx - fn0 * wz
            y2 = fn0 * wy - fn1 * wx
            out[m, j, c0 + 4] = ex * fn0 + wx * y0
            out[m, j, c0 + 5] = ey * fn0 + ex * fn1 + wy * y0 + wx * y1
            out[m, j, c0 + 6] = ez * fn0 + ex * fn2 + wz * y0 + wx * y2
            out[m, j, c0 + 7] = ey * fn1 + wy * y1
            out[m, j, c0 + 8] = ez * fn1 + ey * fn2 + wz * y1 + wy * y2
            out[m, j, c0 + 9] = ez * fn2 + wz * y2
    for j in range(i + 1, out.shape[1]):
        for m in range(nl):
            for c in range(10):
                out[m, j, c0 + c] = 0.0


@numba.njit(cache=True, parallel=True, fastmath=True, error_model="numpy", boundscheck=False)
def regressor_kernel(revolute, a0, ac, a_s, p0, pc, ps, t0, u, g, qt, qdt, qddt, out):  # type: ignore[no-untyped-def]
    """``out[k]`` = the regressor of sample k (eqs. 16-18); ``qt`` etc. are (N, n), joint-major;
    the joint constants are :func:`identify.dynamics._joint_constants`'s."""
    nj, n = qt.shape
    nchunks = (n + CHUNK - 1) // CHUNK
    for chunk in numba.prange(nchunks):
        # scratch for one block of lanes, allocated once per chunk
        a = np.empty((3, 3, LANES))
        p = np.empty((3, LANES))
        d = np.empty((3, LANES))
        b = np.empty((3, 3, LANES))
        rho = np.empty((3, LANES))
        w = np.empty((3, LANES))
        dw = np.empty((3, LANES))
        dv = np.empty((3, LANES))
        rho_prev = np.empty((3, LANES))
        rf = np.empty((nj, 3, LANES))
        rn = np.empty((nj, 3, LANES))
        for k0 in range(chunk * CHUNK, min(n, chunk * CHUNK + CHUNK), LANES):
            nl = min(LANES, n - k0)
            for r in range(3):
                for m in range(nl):
                    w[r, m] = 0.0
                    dw[r, m] = 0.0
                    dv[r, m] = g[r]
                    rho_prev[r, m] = 0.0
            for i in range(nj):
                _joint_step(i, revolute, a0, ac, a_s, p0, pc, ps, t0, u, qt[i, k0:k0 + nl], qdt[i, k0:k0 + nl], qddt[i, k0:k0 + nl],
                            a, p, rho, w, dw, dv, rho_prev, b, rf, rn, d)
                _rows(i, nl, rho, w, dw, dv, b, rf, rn, out[k0:k0 + nl])
