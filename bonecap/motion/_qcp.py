"""The weighted rigid fit of :mod:`bonecap.motion.lsq`, compiled: one loop over fits and frames.

:func:`bonecap.motion.lsq._fit_qcp` fits thousands of small problems at once (every frame of every
segment of a colour, a few to a dozen points each). Written with numpy, each of its ~150 array
operations is a pass over all of them with its own temporaries and its own call overhead: on a
phantom trial of 180 frames the fits were most of the solve time, and the call overhead most of
the fits (about 1 ms a call whether it held one segment or seven). Here one compiled loop (numba)
visits each frame once and keeps the sums, the characteristic polynomial and the eigenvector in
registers.

The mathematics is Horn's (1987) unit-quaternion solution with the largest eigenvalue of the
4 x 4 key matrix found by Newton's method on its characteristic polynomial (Theobald 2005, QCP),
the eigenvector as the best-conditioned row of the adjugate of ``N - lambda I`` -- the steps and the
validity rule of the numpy version it replaced (session 42: the solver's poses on the phantoms'
trials agreed to rounding, 1e-12 in rotation and 3e-11 mm; ``tests/test_motion_lsq.py`` checks the
fit against an SVD fit, noise-free points far from the lab origin and strided inputs). The sums are
taken about the weighted centroids (a frame's few points visited three times: weights, centroids,
centred sums): the numpy version subtracted the centroids' products from uncentred sums to save a
pass over its arrays, which lost ~3 of 16 digits.

References
----------
.. [1] Horn BKP (1987). Closed-form solution of absolute orientation using unit quaternions.
   J Opt Soc Am A 4(4):629-642.
.. [2] Theobald DL (2005). Rapid calculation of RMSDs using a quaternion-based characteristic
   polynomial. Acta Cryst A61:478-480.
"""

from __future__ import annotations

import numpy as np
from numba import njit


def _compiled(signature: str):
    """``numba.njit(signature)``, its machine code cached on disk where numba finds a writable place.

    numba caches beside this module or in the user's cache directory (``NUMBA_CACHE_DIR``); with
    neither writable (a read-only install run by a user without a writable home) it refuses to
    compile a ``cache=True`` function at all. Such a process compiles without the cache (~3 s)
    instead of failing to import the motion solver.
    """
    def decorate(fn):
        try:
            return njit(signature, cache=True, nogil=True)(fn)
        except RuntimeError:            # "cannot cache function ...: no locator available"
            return njit(signature, cache=False, nogil=True)(fn)
    return decorate


@_compiled("float64(float64, float64, float64, float64, float64, float64, float64, float64, float64)")
def _det3(a00, a01, a02, a10, a11, a12, a20, a21, a22):
    return (a00 * (a11 * a22 - a12 * a21) - a01 * (a10 * a22 - a12 * a20)
            + a02 * (a10 * a21 - a11 * a20))


# an explicit signature: called with constant indices, numba would compile one version per constant
@_compiled("float64(float64[:, ::1], int64, int64)")
def _cofactor(A, i, j):
    """Cofactor (i, j) of the 4 x 4 matrix ``A``."""
    # the rows and columns left: k, skipping the one removed
    r0 = 1 if i == 0 else 0
    r1 = 2 if i <= 1 else 1
    r2 = 3 if i <= 2 else 2
    c0 = 1 if j == 0 else 0
    c1 = 2 if j <= 1 else 1
    c2 = 3 if j <= 2 else 2
    d = _det3(A[r0, c0], A[r0, c1], A[r0, c2],
              A[r1, c0], A[r1, c1], A[r1, c2],
              A[r2, c0], A[r2, c1], A[r2, c2])
    return d if (i + j) % 2 == 0 else -d


# explicit signatures: one compiled version each, compiled (or loaded from the cache) when this module
# is imported; the fit's inputs are made contiguous by its caller, the pseudo-markers' targets are views
# into padded buffers, contiguous or not (a contiguous array is accepted where any layout is)
@_compiled("void(float64[:, :, ::1], float64[:, :, :, ::1], float64[:, :, ::1], int64, float64, "
           "float64[:, :, :, ::1], float64[:, :, ::1], boolean[:, ::1])")
def qcp_fits(P, Q, w, newton_steps, min_spread, R, t, valid):
    """Weighted rigid fits ``P -> Q`` for ``G`` point sets over ``F`` frames, in place.

    Parameters
    ----------
    P : ndarray (G, K, 3)
        Local points of each fit (padding points carry weight 0).
    Q : ndarray (G, F, 3, K)
        Lab points, coordinates first, finite (a missing point has weight 0).
    w : ndarray (G, F, K)
        Weights >= 0.
    newton_steps : int
        Most Newton steps on the characteristic polynomial (it stops at rounding level, 3-4 steps).
    min_spread : float
        Collinearity limit, ``sqrt(l1 l2 + l1 l3 + l2 l3) / (l1 + l2 + l3)`` of the weighted local
        scatter's eigenvalues (the ``sqrt(s2 / s1)`` rule of :mod:`bonecap.motion.rigid`).
    R : ndarray (G, F, 3, 3), t : ndarray (G, F, 3), valid : ndarray (G, F) of bool
        Filled: ``q ~ R p + t``; ``valid`` where at least three points carry weight, they are
        not collinear, and the eigenvector is defined.
    """
    G, F = Q.shape[0], Q.shape[1]
    K = Q.shape[3]
    # the compiled loop does not check its indices: disagreeing shapes would read past the arrays
    if (P.shape[0] != G or P.shape[1] != K or P.shape[2] != 3 or Q.shape[2] != 3 or w.shape[0] != G
            or w.shape[1] != F or w.shape[2] != K or R.shape[0] != G or R.shape[1] != F
            or t.shape[0] != G or t.shape[1] != F or valid.shape[0] != G or valid.shape[1] != F):
        raise ValueError("qcp_fits: the shapes of P, Q, w and the outputs do not agree")
    N = np.empty((4, 4))
    A = np.empty((4, 4))
    for g in range(G):
        for f in range(F):
            W = 0.0
            n_pos = 0
            for k in range(K):
                wk = w[g, f, k]
                W += wk
                if wk != 0.0:
                    n_pos += 1
            inv_w = 1.0 / W if W > 0.0 else 1.0
            cpx = cpy = cpz = cqx = cqy = cqz = 0.0
            for k in range(K):
                wk = w[g, f, k] * inv_w
                cpx += wk * P[g, k, 0]
                cpy += wk * P[g, k, 1]
                cpz += wk * P[g, k, 2]
                cqx += wk * Q[g, f, 0, k]
                cqy += wk * Q[g, f, 1, k]
                cqz += wk * Q[g, f, 2, k]
            # centred sums: S_ab = sum w (p - cp)_a (q - cq)_b, C the local scatter, qq the lab's
            Sxx = Sxy = Sxz = Syx = Syy = Syz = Szx = Szy = Szz = 0.0
            Cxx = Cxy = Cxz = Cyy = Cyz = Czz = 0.0
            qq = 0.0
            for k in range(K):
                wk = w[g, f, k] * inv_w
                if wk == 0.0:
                    continue
                px = P[g, k, 0] - cpx
                py = P[g, k, 1] - cpy
                pz = P[g, k, 2] - cpz
                qx = Q[g, f, 0, k] - cqx
                qy = Q[g, f, 1, k] - cqy
                qz = Q[g, f, 2, k] - cqz
                Sxx += wk * px * qx
                Sxy += wk * px * qy
                Sxz += wk * px * qz
                Syx += wk * py * qx
                Syy += wk * py * qy
                Syz += wk * py * qz
                Szx += wk * pz * qx
                Szy += wk * pz * qy
                Szz += wk * pz * qz
                Cxx += wk * px * px
                Cxy += wk * px * py
                Cxz += wk * px * pz
                Cyy += wk * py * py
                Cyz += wk * py * pz
                Czz += wk * pz * pz
                qq += wk * (qx * qx + qy * qy + qz * qz)
            trC = Cxx + Cyy + Czz
            e2 = 0.5 * (trC * trC - (Cxx * Cxx + Cyy * Cyy + Czz * Czz
                                      + 2.0 * (Cxy * Cxy + Cxz * Cxz + Cyz * Cyz)))
            ok = n_pos >= 3 and trC > 0.0
            if ok:
                ok = np.sqrt(max(e2, 0.0)) / trC >= min_spread

            N[0, 0] = Sxx + Syy + Szz
            N[0, 1] = Syz - Szy
            N[0, 2] = Szx - Sxz
            N[0, 3] = Sxy - Syx
            N[1, 1] = Sxx - Syy - Szz
            N[1, 2] = Sxy + Syx
            N[1, 3] = Szx + Sxz
            N[2, 2] = -Sxx + Syy - Szz
            N[2, 3] = Syz + Szy
            N[3, 3] = -Sxx - Syy + Szz
            for i in range(4):
                for j in range(i):
                    N[i, j] = N[j, i]
            # l^4 + c2 l^2 + c1 l + c0 (trace N = 0); Newton from the upper bound (trC + qq) / 2
            # decreases monotonically onto the largest root
            c2 = -2.0 * (Sxx * Sxx + Sxy * Sxy + Sxz * Sxz + Syx * Syx + Syy * Syy + Syz * Syz
                         + Szx * Szx + Szy * Szy + Szz * Szz)
            c1 = -8.0 * _det3(Sxx, Sxy, Sxz, Syx, Syy, Syz, Szx, Szy, Szz)
            c0 = 0.0
            for j in range(4):
                c0 += N[0, j] * _cofactor(N, 0, j)
            lam = 0.5 * (trC + qq)
            for _ in range(newton_steps):
                l2 = lam * lam
                fv = l2 * l2 + c2 * l2 + c1 * lam + c0
                df = 4.0 * l2 * lam + 2.0 * c2 * lam + c1
                step = fv / df if df != 0.0 else 0.0
                lam -= step
                if not abs(step) > 1e-13 * abs(lam):
                    break
            for i in range(4):
                for j in range(4):
                    A[i, j] = N[i, j] - lam if i == j else N[i, j]
            # A is symmetric of rank 3 at the root: adj(A) = c q q^T; its largest diagonal
            # entry picks the best-conditioned row
            best = 0
            dbest = -1.0
            for i in range(4):
                d = abs(_cofactor(A, i, i))
                if d > dbest:
                    dbest = d
                    best = i
            q0 = _cofactor(A, best, 0)
            q1 = _cofactor(A, best, 1)
            q2 = _cofactor(A, best, 2)
            q3 = _cofactor(A, best, 3)
            qn = np.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
            if not qn > 0.0:
                ok = False
                qn = 1.0
            a0 = q0 / qn
            b = q1 / qn
            c = q2 / qn
            d = q3 / qn
            R[g, f, 0, 0] = a0 * a0 + b * b - c * c - d * d
            R[g, f, 0, 1] = 2.0 * (b * c - a0 * d)
            R[g, f, 0, 2] = 2.0 * (b * d + a0 * c)
            R[g, f, 1, 0] = 2.0 * (b * c + a0 * d)
            R[g, f, 1, 1] = a0 * a0 - b * b + c * c - d * d
            R[g, f, 1, 2] = 2.0 * (c * d - a0 * b)
            R[g, f, 2, 0] = 2.0 * (b * d - a0 * c)
            R[g, f, 2, 1] = 2.0 * (c * d + a0 * b)
            R[g, f, 2, 2] = a0 * a0 - b * b - c * c + d * d
            t[g, f, 0] = cqx - (R[g, f, 0, 0] * cpx + R[g, f, 0, 1] * cpy + R[g, f, 0, 2] * cpz)
            t[g, f, 1] = cqy - (R[g, f, 1, 0] * cpx + R[g, f, 1, 1] * cpy + R[g, f, 1, 2] * cpz)
            t[g, f, 2] = cqz - (R[g, f, 2, 0] * cpx + R[g, f, 2, 1] * cpy + R[g, f, 2, 2] * cpz)
            valid[g, f] = ok


@_compiled("void(float64[:, :, :], float64[:, :], float64[:], float64, float64[:, :, :], float64[:, :], int64)")
def place_points(T, pts, wts, scale, Q, W, slot):
    """Joint pseudo-markers of :mod:`bonecap.motion.lsq`: ``pts`` carried by ``T`` into target slots.

    Parameters
    ----------
    T : ndarray (F, 4, 4)
        The neighbour's pose per frame (its frame -> lab), NaN where it is not solved.
    pts : ndarray (n, 3)
        The points in the neighbour's frame (mm).
    wts : ndarray (n,)
        Their weights; ``scale`` multiplies them (0: a neighbour that must not pull).
    Q : ndarray (F, 3, K), W : ndarray (F, K)
        The fit's targets (coordinates first) and weights: slots ``slot .. slot + n - 1`` are
        filled, with weight 0 and target 0 in frames where ``T`` is not finite.
    """
    F = T.shape[0]
    n = pts.shape[0]
    # the compiled loop does not check its indices: a wrong slot would write past the fit's slots
    if (Q.shape[0] != F or W.shape[0] != F or slot < 0 or slot + n > Q.shape[2] or slot + n > W.shape[1]
            or wts.shape[0] != n or pts.shape[1] != 3 or Q.shape[1] != 3):
        raise ValueError("place_points: shapes or slots do not agree")
    for f in range(F):
        good = True
        for i in range(3):
            for j in range(4):
                if not np.isfinite(T[f, i, j]):
                    good = False
        for m in range(n):
            if good:
                for i in range(3):
                    Q[f, i, slot + m] = (T[f, i, 0] * pts[m, 0] + T[f, i, 1] * pts[m, 1]
                                         + T[f, i, 2] * pts[m, 2] + T[f, i, 3])
                W[f, slot + m] = wts[m] * scale
            else:
                for i in range(3):
                    Q[f, i, slot + m] = 0.0
                W[f, slot + m] = 0.0


def warm_up() -> None:
    """Run each kernel once on a tiny input: a check that the compiled code loaded and runs.

    The kernels are compiled when this module is first imported after an install (~3 s; numba caches
    the machine code beside the module) and loaded from that cache by every later process (~0.3 s,
    ~0.65 s with numba's own import). ``bonecap animate`` imports this module and calls this before
    its trials, timed apart, so that a trial's ``solve_seconds`` is its own solve.
    """
    G, F, K = 1, 2, 3
    R, t, valid = np.empty((G, F, 3, 3)), np.empty((G, F, 3)), np.empty((G, F), np.bool_)
    qcp_fits(np.zeros((G, K, 3)), np.zeros((G, F, 3, K)), np.zeros((G, F, K)), 1, 1e-3, R, t, valid)
    Q, W = np.zeros((F, 3, K + 1))[:, :, :K], np.zeros((F, K + 1))[:, :K]
    place_points(np.full((F, 4, 4), np.nan), np.zeros((1, 3)), np.ones(1), 1.0, Q, W, 0)
