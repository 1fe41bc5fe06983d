"""Weighted least-squares rigid fit of marker clusters, batched over frames and bones.

Given the positions of a bone's markers in the bone's own frame (``local``)
and where the cameras saw them in the lab (``measured``), find the rotation
``R`` and translation ``t`` that minimise

.. math::

    \\sum_i w_i \\, \\lVert R\\,p_i + t - q_i \\rVert^2 ,

the problem of Söderkvist & Wedin (1993). The solution is closed form: ``t``
maps the weighted centroid of the local markers onto that of the measured
ones, and ``R`` comes from the singular value decomposition of the weighted
cross-covariance matrix ``H = sum_i w_i (p_i - p̄)(q_i - q̄)^T = U S V^T`` as
``R = V diag(1, 1, d) U^T`` with ``d = sign(det(V U^T))``, the correction of
Umeyama (1991) that keeps ``R`` a proper rotation (``det R = +1``) instead of
a reflection when the data are planar or very noisy (Kabsch 1976 lacks it).

Everything is numpy over a leading batch axis: one call to
:func:`numpy.linalg.svd` on a ``(..., 3, 3)`` stack fits every frame (and every
bone) at once; there is no Python loop per frame.

Conventions
-----------
- Lengths in millimetres.
- A pose is a 4x4 homogeneous transform ``local_to_lab``: it maps a point
  given in the bone (local/model) frame to the lab frame,
  ``q_lab = T @ [p_local, 1]``.
- Missing markers are ``NaN`` in ``measured``. A marker takes part in a fit
  only where its local **and** measured positions are finite and its weight
  is positive; every other marker has weight 0 for that fit.
- Where a pose cannot be solved, its transform is all ``NaN`` and its
  ``valid`` flag is ``False``; nothing raises for missing data. Wrong shapes
  and negative or infinite weights raise :class:`ValueError`.

When is a pose solvable?
------------------------
A fit is *valid* when

1. at least ``min_markers`` (>= 3) markers take part, and
2. those markers are not (near-)collinear. The test uses the singular values
   ``s1 >= s2 >= s3`` of ``H`` (computed with normalised weights, so they
   are in mm^2): the fit is valid when ``sqrt(s2 / s1) >= min_spread_ratio``
   (default ``1e-3``). For noise-free data ``s1, s2, s3`` are the
   eigenvalues of the weighted scatter matrix of the local markers, so
   ``sqrt(s2 / s1)`` is the ratio of the markers' RMS spread across their
   main axis to their RMS spread along it; the rotation about the main axis
   is undetermined when it is 0 and its error grows like ``1 / sqrt(s2)``
   (Söderkvist & Wedin 1993). Collinear local markers make ``H`` exactly of
   rank 1 whatever the noise in ``measured``, so they are always caught.
   Three non-collinear markers (a plane, ``s3 = 0``) are enough.

The ratio is returned as ``RigidFit.spread_ratio`` so that callers who know
their noise level can apply a stricter threshold.

References
----------
.. [1] Söderkvist I, Wedin P-Å (1993). Determining the movements of the
   skeleton using well-configured markers. J Biomech 26(12):1473-1477.
.. [2] Kabsch W (1976). A solution for the best rotation to relate two sets
   of vectors. Acta Cryst A32:922-923.
.. [3] Umeyama S (1991). Least-squares estimation of transformation
   parameters between two point patterns. IEEE TPAMI 13(4):376-380.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "RigidFit",
    "BoneFits",
    "fit_rigid",
    "fit_rigid_bones",
    "apply_transform",
    "rotation_angle_deg",
]

DEFAULT_MIN_SPREAD_RATIO = 1e-3


@dataclass(frozen=True)
class RigidFit:
    """Result of :func:`fit_rigid` for a batch of shape ``(...)``.

    Attributes
    ----------
    transforms : ndarray, shape (..., 4, 4)
        ``local_to_lab`` transforms (mm): ``q_lab = T @ [p_local, 1]``. All
        ``NaN`` where ``valid`` is ``False``.
    valid : ndarray of bool, shape (...)
        ``True`` where enough non-collinear markers took part (see the module
        documentation for the exact test).
    residuals : ndarray, shape (..., M)
        Distance in mm between each measured marker and where the fitted
        transform puts its local position. ``NaN`` where the marker is missing
        or the fit is invalid. Visible markers of weight 0 still get a
        residual (useful to judge an outlier that was left out).
    rms : ndarray, shape (...)
        Weighted root-mean-square residual over the markers that took part,
        ``sqrt(sum w_i r_i^2 / sum w_i)`` in mm -- the minimised objective;
        ``NaN`` where invalid.
    n_used : ndarray of int, shape (...)
        Number of markers that took part (finite, positive weight).
    spread_ratio : ndarray, shape (...)
        ``sqrt(s2 / s1)`` of the cross-covariance singular values (0 when
        ``s1`` is 0); the collinearity measure compared to ``min_spread_ratio``.
    """

    transforms: np.ndarray
    valid: np.ndarray
    residuals: np.ndarray
    rms: np.ndarray
    n_used: np.ndarray
    spread_ratio: np.ndarray

    @property
    def local_to_lab(self) -> np.ndarray:
        """Alias of :attr:`transforms`, named after the frames it maps."""
        return self.transforms


@dataclass(frozen=True)
class BoneFits:
    """Result of :func:`fit_rigid_bones` for ``F`` frames, ``B`` bones, ``M`` markers.

    Attributes
    ----------
    bones : list of str
        Bone names, parallel to axis 1 of ``transforms`` (the key order of
        ``local_by_bone``).
    transforms : ndarray, shape (F, B, 4, 4)
        ``bone_to_lab`` transforms (mm); ``NaN`` where not solvable.
    valid : ndarray of bool, shape (F, B)
    residuals : ndarray, shape (F, M)
        Per trial marker, the distance in mm between the measured marker and
        where the fitted pose of **its first bone** (in ``bones`` order) puts
        it. ``NaN`` where the marker is missing, that bone's fit is invalid,
        or the marker belongs to no bone.
    rms : ndarray, shape (F, B)
        Weighted RMS residual of each bone's fit (mm).
    n_used : ndarray of int, shape (F, B)
        Markers that took part in each bone's fit.
    marker_bone : ndarray of int, shape (M,)
        Index into ``bones`` of the bone whose residual ``residuals`` reports
        for each marker; ``-1`` for markers on no bone.

    Notes
    -----
    ``bones``, ``transforms``, ``valid`` and ``residuals`` are what
    :class:`bonecap.model.Motion` takes (with the trial's times and labels).
    """

    bones: list[str]
    transforms: np.ndarray
    valid: np.ndarray
    residuals: np.ndarray
    rms: np.ndarray
    n_used: np.ndarray
    marker_bone: np.ndarray


# --------------------------------------------------------------------------- helpers


def _det3(A: np.ndarray) -> np.ndarray:
    """Determinant of a (..., 3, 3) stack by cofactors (faster than LU for 3x3)."""
    return (
        A[..., 0, 0] * (A[..., 1, 1] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 1])
        - A[..., 0, 1] * (A[..., 1, 0] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 0])
        + A[..., 0, 2] * (A[..., 1, 0] * A[..., 2, 1] - A[..., 1, 1] * A[..., 2, 0])
    )


def _check_points(name: str, a, frame: str) -> np.ndarray:
    try:
        a = np.asarray(a, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be an array of numbers, got {type(a).__name__}: {exc}") from None
    if a.ndim < 2 or a.shape[-1] != 3:
        raise ValueError(
            f"{name} must have shape (..., M, 3) (marker positions in the {frame} frame, mm), "
            f"got shape {a.shape}")
    return a


def _check_weights(weights, n_markers: int, what: str) -> np.ndarray:
    try:
        w = np.asarray(weights, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"weights must be an array of numbers: {exc}") from None
    if w.ndim < 1 or w.shape[-1] != n_markers:
        raise ValueError(
            f"weights must have shape ({n_markers},) or (..., {n_markers}) -- one per {what} -- "
            f"got shape {w.shape}")
    if np.isinf(w).any():
        raise ValueError("weights must be finite (use 0 to leave a marker out, NaN is also read as 0)")
    if (w < 0).any():
        raise ValueError(f"weights must be non-negative, got a minimum of {np.nanmin(w)}")
    return np.where(np.isnan(w), 0.0, w)


def _check_min_markers(min_markers) -> int:
    if (isinstance(min_markers, bool) or not isinstance(min_markers, (int, np.integer))
            or min_markers < 3):
        raise ValueError(
            f"min_markers must be an integer >= 3 (a rotation needs 3 non-collinear markers), "
            f"got {min_markers!r}")
    return int(min_markers)


def _check_ratio(min_spread_ratio) -> float:
    r = float(min_spread_ratio)
    if not (0.0 <= r <= 1.0):
        raise ValueError(f"min_spread_ratio must lie in [0, 1], got {min_spread_ratio!r}")
    return r


# --------------------------------------------------------------------------- core


def _fit_core(local: np.ndarray, measured: np.ndarray, w: np.ndarray,
              min_markers: int, min_spread_ratio: float) -> RigidFit:
    """The batched fit on checked arrays; all three broadcast to ``batch + (M, ...)``."""
    visible = np.isfinite(measured).all(axis=-1) & np.isfinite(local).all(axis=-1)  # (..., M)
    w_eff = np.where(visible & (w > 0), w, 0.0)
    n_used = np.count_nonzero(w_eff, axis=-1)
    W = w_eff.sum(axis=-1)
    wn = w_eff / np.where(W > 0, W, 1.0)[..., None]  # normalised: sums to 1 (or 0)

    vis3 = visible[..., None]
    P = np.where(vis3, local, 0.0)
    Q = np.where(vis3, measured, 0.0)
    wrow = wn[..., None, :]  # (..., 1, M)
    cp = (wrow @ P)[..., 0, :]  # weighted centroids (..., 3)
    cq = (wrow @ Q)[..., 0, :]
    Pc = P - cp[..., None, :]
    Qc = Q - cq[..., None, :]
    H = np.swapaxes(Pc * wn[..., None], -1, -2) @ Qc  # sum_i w_i p_i q_i^T, (..., 3, 3)

    batch = H.shape[:-2]
    finite = np.isfinite(H).all(axis=(-2, -1))
    H_safe = np.where(finite[..., None, None], H, np.eye(3))
    U, S, Vt = np.linalg.svd(H_safe)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(S[..., 0] > 0, np.sqrt(np.clip(S[..., 1], 0.0, None) / S[..., 0]), 0.0)
    ratio = np.where(finite & (n_used > 0), ratio, 0.0)
    valid = (n_used >= min_markers) & (ratio >= min_spread_ratio) & (ratio > 0) & finite

    d = np.where(_det3(U) * _det3(Vt) < 0, -1.0, 1.0)
    D = np.ones(batch + (3,))
    D[..., 2] = d
    V = np.swapaxes(Vt, -1, -2)
    R = (V * D[..., None, :]) @ np.swapaxes(U, -1, -2)
    t = cq - (R @ cp[..., None])[..., 0]

    T = np.zeros(batch + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    T[~valid] = np.nan

    # residual = |R (p - p̄) + q̄ - q| computed from centred data (no cancellation
    # of lab-scale coordinates); NaN for missing markers and invalid fits.
    diff = Pc @ np.swapaxes(R, -1, -2) - Qc
    res = np.sqrt(np.einsum("...i,...i->...", diff, diff))
    res = np.where(visible & valid[..., None], res, np.nan)
    with np.errstate(invalid="ignore"):
        rms = np.sqrt(np.einsum("...m,...m->...", wn, np.where(w_eff > 0, res, 0.0) ** 2))
    rms = np.where(valid, rms, np.nan)
    return RigidFit(transforms=T, valid=valid, residuals=res, rms=rms,
                    n_used=n_used, spread_ratio=ratio)


def fit_rigid(local, measured, weights=None, min_markers: int = 3, *,
              min_spread_ratio: float = DEFAULT_MIN_SPREAD_RATIO) -> RigidFit:
    """Weighted least-squares ``local_to_lab`` rigid transform of a marker cluster.

    Parameters
    ----------
    local : array_like, shape (M, 3) or (..., M, 3)
        Marker positions in the bone's own (local/model) frame, mm. Broadcast
        against ``measured`` over the leading axes (one cluster for all
        frames, or one per frame).
    measured : array_like, shape (..., M, 3)
        The same markers measured in the lab frame, mm; ``NaN`` (any
        non-finite coordinate) where a marker is missing.
    weights : array_like, shape (M,) or (..., M), optional
        Non-negative weights, broadcast like the leading axes. Only their
        ratios matter. ``NaN`` is read as 0; a weight of 0 leaves a marker
        out of the fit (it still gets a residual). Default: all 1.
    min_markers : int, default 3
        Fewest markers that must take part (finite, positive weight) for a
        fit to be valid; at least 3.
    min_spread_ratio : float, default 1e-3
        Collinearity threshold: the fit is invalid when
        ``sqrt(s2 / s1) < min_spread_ratio``, with ``s1 >= s2`` the two
        largest singular values of the weighted cross-covariance ``H`` (for
        noise-free data, the ratio of the markers' RMS spread across their
        main axis to that along it). See the module documentation.

    Returns
    -------
    RigidFit
        ``transforms`` (..., 4, 4) ``local_to_lab`` (``NaN`` where invalid),
        ``valid`` (...), ``residuals`` (..., M) mm, ``rms`` (...) mm,
        ``n_used`` (...), ``spread_ratio`` (...); ``...`` is the broadcast of
        the leading axes of ``local``, ``measured`` and ``weights``.

    Raises
    ------
    ValueError
        On shapes that are not (..., M, 3), marker counts that disagree,
        leading axes that do not broadcast, negative or infinite weights, or
        ``min_markers < 3``.

    Notes
    -----
    ``t = q̄ - R p̄`` with weighted centroids, and ``R = V diag(1, 1, d) U^T``
    from ``H = sum w_i (p_i - p̄)(q_i - q̄)^T = U S V^T``,
    ``d = sign(det(V U^T))`` [3]_. The fit is equivariant: fitting data
    moved by a rigid ``G`` in the lab returns ``G @ T``.

    References
    ----------
    .. [1] Söderkvist I, Wedin P-Å (1993). Determining the movements of the
       skeleton using well-configured markers. J Biomech 26(12):1473-1477.
    .. [2] Kabsch W (1976). Acta Cryst A32:922-923.
    .. [3] Umeyama S (1991). IEEE TPAMI 13(4):376-380.
    """
    local = _check_points("local", local, "bone (local)")
    measured = _check_points("measured", measured, "lab")
    M = measured.shape[-2]
    if local.shape[-2] != M:
        raise ValueError(
            f"local has {local.shape[-2]} markers (shape {local.shape}) but measured has {M} "
            f"(shape {measured.shape}); axis -2 must match")
    if M == 0:
        raise ValueError("fit_rigid needs at least one marker column, got M = 0")
    min_markers = _check_min_markers(min_markers)
    min_spread_ratio = _check_ratio(min_spread_ratio)
    w = np.ones(M) if weights is None else _check_weights(weights, M, "marker")
    try:
        batch = np.broadcast_shapes(local.shape[:-2], measured.shape[:-2], w.shape[:-1])
    except ValueError:
        raise ValueError(
            f"leading (batch) axes do not broadcast: local {local.shape[:-2]}, "
            f"measured {measured.shape[:-2]}, weights {w.shape[:-1]}") from None
    local = np.broadcast_to(local, batch + (M, 3))
    measured = np.broadcast_to(measured, batch + (M, 3))
    w = np.broadcast_to(w, batch + (M,))
    return _fit_core(local, measured, w, min_markers, min_spread_ratio)


def fit_rigid_bones(local_by_bone: Mapping[str, np.ndarray],
                    marker_index_by_bone: Mapping[str, Sequence[int]],
                    measured, weights=None, min_markers: int = 3, *,
                    min_spread_ratio: float = DEFAULT_MIN_SPREAD_RATIO) -> BoneFits:
    """Fit every bone in every frame with one batched SVD.

    Each bone's marker cluster is padded with zero-weight markers to the
    largest cluster size ``Mmax``, so all ``F x B`` fits run as a single
    :func:`fit_rigid` call on ``(F, B, Mmax, 3)`` arrays.

    Parameters
    ----------
    local_by_bone : mapping of str -> array_like, shape (M_b, 3)
        Each bone's markers in that bone's own frame (mm). Its key order is
        the bone order of the result.
    marker_index_by_bone : mapping of str -> sequence of int
        For each bone (same keys), the ``M_b`` indices into axis 1 of
        ``measured`` of its markers, parallel to the rows of
        ``local_by_bone[bone]``. A marker may belong to several bones.
    measured : array_like, shape (F, M, 3)
        Trial marker positions in the lab frame, mm, ``NaN`` in gaps (as in
        :attr:`bonecap.model.Trial.points`).
    weights : array_like, shape (M,) or (F, M), optional
        Non-negative per-marker (per-frame) weights; see :func:`fit_rigid`.
    min_markers : int, default 3
        Fewest markers needed for a valid fit of a bone in a frame.
    min_spread_ratio : float, default 1e-3
        Collinearity threshold, see :func:`fit_rigid`.

    Returns
    -------
    BoneFits
        ``bones`` (B), ``transforms`` (F, B, 4, 4) ``bone_to_lab``,
        ``valid`` (F, B), ``residuals`` (F, M) -- for a marker on several
        bones, the residual of its **first** bone in ``bones`` order, NaN for
        markers on no bone --, ``rms`` (F, B), ``n_used`` (F, B) and
        ``marker_bone`` (M,).

    Raises
    ------
    ValueError
        On mismatched keys, index lists whose length differs from the local
        cluster, out-of-range or repeated indices, a bone with fewer than
        ``min_markers`` markers, or bad shapes.

    References
    ----------
    .. [1] Söderkvist I, Wedin P-Å (1993). J Biomech 26(12):1473-1477.
    """
    measured = np.asarray(measured, dtype=float)
    if measured.ndim != 3 or measured.shape[2] != 3:
        raise ValueError(
            f"measured must have shape (frames, markers, 3) in the lab frame, got {measured.shape}")
    F, M, _ = measured.shape
    min_markers = _check_min_markers(min_markers)
    bones = [str(b) for b in local_by_bone]
    if not bones:
        raise ValueError("local_by_bone is empty: give at least one bone")
    if set(map(str, marker_index_by_bone)) != set(bones):
        missing = sorted(set(bones) - set(map(str, marker_index_by_bone)))
        extra = sorted(set(map(str, marker_index_by_bone)) - set(bones))
        raise ValueError(
            f"marker_index_by_bone must have the keys of local_by_bone; "
            f"missing {missing}, unexpected {extra}")
    index_by_name = {str(k): v for k, v in marker_index_by_bone.items()}

    locals_, indices = [], []
    for key, name in zip(local_by_bone, bones):
        loc = np.asarray(local_by_bone[key], dtype=float)
        if loc.ndim != 2 or loc.shape[1] != 3:
            raise ValueError(
                f"local_by_bone[{name!r}] must have shape (M_b, 3) in the bone frame, got {loc.shape}")
        if not np.isfinite(loc).all():
            raise ValueError(f"local_by_bone[{name!r}] has non-finite marker positions")
        idx = np.asarray(index_by_name[name])
        if idx.ndim != 1 or (idx.size and not np.issubdtype(idx.dtype, np.integer)):
            raise ValueError(
                f"marker_index_by_bone[{name!r}] must be a flat list of integer marker indices, "
                f"got {index_by_name[name]!r}")
        idx = idx.astype(np.intp)
        if len(idx) != len(loc):
            raise ValueError(
                f"bone {name!r}: {len(loc)} local markers but {len(idx)} marker indices")
        if len(idx) < min_markers:
            raise ValueError(
                f"bone {name!r} has {len(idx)} markers; a rigid fit needs at least "
                f"min_markers = {min_markers}")
        if idx.min() < 0 or idx.max() >= M:
            raise ValueError(
                f"bone {name!r}: marker indices must lie in [0, {M - 1}] (measured has {M} markers), "
                f"got {idx.tolist()}")
        if len(np.unique(idx)) != len(idx):
            raise ValueError(f"bone {name!r}: repeated marker index in {idx.tolist()}")
        locals_.append(loc)
        indices.append(idx)

    B = len(bones)
    Mmax = max(len(i) for i in indices)
    local_pad = np.zeros((B, Mmax, 3))
    index_pad = np.zeros((B, Mmax), dtype=np.intp)
    in_bone = np.zeros((B, Mmax), dtype=bool)
    for b, (loc, idx) in enumerate(zip(locals_, indices)):
        local_pad[b, : len(idx)] = loc
        index_pad[b, : len(idx)] = idx
        in_bone[b, : len(idx)] = True

    if weights is None:
        w_trial = np.ones((1, M))
    else:
        w_trial = _check_weights(weights, M, "trial marker")
        if w_trial.ndim == 1:
            w_trial = w_trial[None]
        elif w_trial.shape != (F, M):
            raise ValueError(f"weights must have shape ({M},) or ({F}, {M}), got {w_trial.shape}")

    meas_g = measured[:, index_pad]  # (F, B, Mmax, 3)
    w_g = w_trial[:, index_pad] * in_bone  # (F or 1, B, Mmax); padding -> weight 0
    w_g = np.broadcast_to(w_g, (F, B, Mmax))
    local_b = np.broadcast_to(local_pad, (F, B, Mmax, 3))
    fit = _fit_core(local_b, meas_g, w_g, min_markers, _check_ratio(min_spread_ratio))

    # per trial marker: residual on its first bone
    marker_bone = np.full(M, -1, dtype=np.intp)
    marker_slot = np.zeros(M, dtype=np.intp)
    for b in range(B - 1, -1, -1):  # later bones first, so the first bone wins
        marker_bone[indices[b]] = b
        marker_slot[indices[b]] = np.arange(len(indices[b]))
    residuals = np.full((F, M), np.nan)
    on_bone = marker_bone >= 0
    residuals[:, on_bone] = fit.residuals[:, marker_bone[on_bone], marker_slot[on_bone]]
    return BoneFits(bones=bones, transforms=fit.transforms, valid=fit.valid,
                    residuals=residuals, rms=fit.rms, n_used=fit.n_used,
                    marker_bone=marker_bone)


# --------------------------------------------------------------------------- utilities


def apply_transform(T, points) -> np.ndarray:
    """Map points by homogeneous transforms: ``p_b = R p_a + t`` for ``T = a_to_b``.

    Parameters
    ----------
    T : array_like, shape (..., 4, 4)
        ``a_to_b`` transforms (e.g. ``local_to_lab`` from :func:`fit_rigid`).
    points : array_like, shape (..., N, 3)
        Points in frame *a*; leading axes broadcast against those of ``T``.

    Returns
    -------
    ndarray, shape (..., N, 3)
        The points in frame *b*. ``NaN`` transforms give ``NaN`` points.
    """
    T = np.asarray(T, dtype=float)
    points = np.asarray(points, dtype=float)
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise ValueError(f"T must have shape (..., 4, 4), got {T.shape}")
    if points.ndim < 2 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., N, 3), got {points.shape}")
    try:
        return points @ np.swapaxes(T[..., :3, :3], -1, -2) + T[..., None, :3, 3]
    except ValueError:
        raise ValueError(
            f"leading axes of T {T.shape[:-2]} and points {points.shape[:-2]} do not broadcast") from None


def rotation_angle_deg(Ta, Tb) -> np.ndarray:
    """Angle in degrees of the rotation that takes pose ``Ta`` to pose ``Tb``.

    Parameters
    ----------
    Ta, Tb : array_like, shape (..., 4, 4) or (..., 3, 3)
        Transforms (or rotation matrices) mapping the same source frame to the
        same target frame (e.g. two ``local_to_lab`` estimates of one bone);
        leading axes broadcast.

    Returns
    -------
    ndarray, shape (...)
        The angle of ``Ra^T Rb`` in [0, 180] degrees; ``NaN`` where either
        input is ``NaN``.

    Notes
    -----
    Computed as ``atan2(|R - R^T|_F / (2 sqrt 2), (tr R - 1) / 2)``, which is
    accurate to machine precision near 0 and 180 degrees alike (``arccos``
    of the trace alone loses half the digits near 0).
    """
    Ra = np.asarray(Ta, dtype=float)
    Rb = np.asarray(Tb, dtype=float)
    for name, A in (("Ta", Ra), ("Tb", Rb)):
        if A.ndim < 2 or A.shape[-2:] not in ((4, 4), (3, 3)):
            raise ValueError(f"{name} must have shape (..., 4, 4) or (..., 3, 3), got {A.shape}")
    Ra, Rb = Ra[..., :3, :3], Rb[..., :3, :3]
    try:
        R = np.swapaxes(Ra, -1, -2) @ Rb
    except ValueError:
        raise ValueError(
            f"leading axes of Ta {Ra.shape[:-2]} and Tb {Rb.shape[:-2]} do not broadcast") from None
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    K = R - np.swapaxes(R, -1, -2)
    sin = np.sqrt(np.einsum("...ij,...ij->...", K, K)) / (2.0 * np.sqrt(2.0))
    return np.degrees(np.arctan2(sin, cos))
