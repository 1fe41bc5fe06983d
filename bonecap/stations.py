"""Whole-body MRI stations: order, register the overlaps, normalise intensity (build-subject stage 1).

A whole body is imaged as several overlapping axial stations. Between two
stations the patient moves a little (a few mm, about a degree), and each
station has its own receiver gain. This module puts the stations into one
world frame and onto one intensity scale:

- :func:`order_stations` -- head to feet, with checks (axial, overlapping);
- :func:`register_stations` -- the small rigid motion (6 DoF) of each
  consecutive overlap by intensity registration, chained into one frame;
- :func:`normalise_intensity` -- scale factors between stations from the
  overlaps.

Frames and conventions
----------------------
- Points are in the **LPS** world of the DICOM headers, mm (``+x`` left,
  ``+y`` posterior, ``+z`` superior). ``Volume.affine`` is ``voxel_to_lps``.
- The header of each station gives its *nominal* geometry. If the body lay
  moved by ``T_s`` during station ``s`` (``p_nominal = T_s @ p_body``), the
  registration returns a correction ``C_s`` with ``C_s @ T_s = G`` for every
  station: corrected affines ``C_s @ affine_s`` put every station's voxels on
  one body frame ``G``, which is fixed up to the gauge below.
- **Gauge.** Overlaps only show the motion of one station *relative* to the
  next; a rigid motion common to all stations is invisible. With
  ``reference=k`` station ``k`` keeps its header geometry (``C_k = I``). By
  default (``reference=None``) the common motion is chosen so that the
  corrections are as small as possible overall: ``G`` is the rigid
  least-squares fit (Kabsch) that brings the corrected corners of every
  station's field of view back onto their nominal positions. The patient's
  motions between stations are independent and unbiased, so their average
  is the best available estimate of "no motion"; a reference station
  would instead carry that station's own motion into every other one.

References
----------
- Lucas BD, Kanade T. An iterative image registration technique with an
  application to stereo vision. *IJCAI* 1981, 674-679 (Gauss-Newton image
  alignment).
- Baker S, Matthews I. Lucas-Kanade 20 years on: a unifying framework.
  *Int J Comput Vis* 56(3):221-255, 2004 (compositional updates).
- Kabsch W. A solution for the best rotation to relate two sets of vectors.
  *Acta Crystallogr A* 32:922-923, 1976 (the gauge fit).
- Nyul LG, Udupa JK. On standardizing the MR image intensity scale.
  *Magn Reson Med* 42(6):1072-1081, 1999 (intensity standardisation).
"""

from __future__ import annotations

import math
import time
from typing import Any, Sequence

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from bonecap.model import Volume

__all__ = ["order_stations", "register_stations", "normalise_intensity", "station_z_range"]

_EZ = np.array([0.0, 0.0, 1.0])


def _name(v: Volume, i: int) -> str:
    md = v.metadata or {}
    for key in ("station", "series_description", "name"):
        if md.get(key):
            return str(md[key])
    if md.get("series_number") is not None:
        return f"series {md['series_number']}"
    return f"station #{i}"


def station_z_range(volume: Volume) -> tuple[float, float]:
    """LPS z of the lowest and highest slice centre of an axial station (mm).

    Parameters
    ----------
    volume : Volume
        Affine ``voxel_to_lps``; taken at the in-plane centre of the grid.

    Returns
    -------
    (z_low, z_high) : float
    """
    I, J, K = volume.shape
    ends = volume.index_to_world(np.array([[(I - 1) / 2, (J - 1) / 2, 0.0], [(I - 1) / 2, (J - 1) / 2, K - 1.0]]))
    return float(min(ends[:, 2])), float(max(ends[:, 2]))


def _check_axial(volumes: Sequence[Volume], max_obliquity_deg: float) -> None:
    for n, v in enumerate(volumes):
        if not isinstance(v, Volume):
            raise ValueError(f"station {n} is a {type(v).__name__}, not a Volume")
        if min(v.shape) < 1 or v.shape[2] < 2:
            raise ValueError(f"{_name(v, n)}: a station needs at least 2 slices, got shape {v.shape}")
        d = v.direction
        normal = d[:, 2]
        tilt = math.degrees(math.acos(min(1.0, abs(float(normal @ _EZ)))))
        if tilt > max_obliquity_deg:
            axis = "LPS"[int(np.argmax(np.abs(normal)))]
            plane = {"L": "sagittal", "P": "coronal", "S": "axial"}[axis]
            raise ValueError(
                f"{_name(v, n)}: not an axial station (slice normal {np.round(normal, 3).tolist()} is "
                f"{tilt:.1f} deg from LPS z, a {plane} stack); whole-body stations must be axial within "
                f"{max_obliquity_deg:g} deg: leave this series out (a localiser?) or reslice it axially")


def order_stations(volumes: Sequence[Volume], *, min_overlap_mm: float = 10.0, max_obliquity_deg: float = 5.0,
                   allow_gaps: bool = False) -> list[Volume]:
    """Order whole-body stations head to feet and check that they fit together.

    Parameters
    ----------
    volumes : sequence of Volume
        The stations, any order, each an axial stack (affine ``voxel_to_lps``,
        LPS mm). Slices may run either way along z.
    min_overlap_mm : float
        Consecutive stations must overlap by at least this much along z
        (between slice centres), enough slices to register.
    max_obliquity_deg : float
        Largest angle allowed between a station's slice normal and LPS z.
    allow_gaps : bool
        Accept consecutive stations that overlap too little (their relative
        geometry is then kept nominal by :func:`register_stations`).

    Returns
    -------
    list of Volume
        The same objects, from the highest (head, largest LPS z) to the
        lowest.

    Raises
    ------
    ValueError
        No volumes, a station that is not axial (sagittal, coronal or strongly
        oblique), or two consecutive stations overlapping by less than
        ``min_overlap_mm`` (named, with their z ranges).

    Notes
    -----
    A station in another orientation is refused, not resampled: whole-body
    protocols are axial, so a sagittal or coronal series among them is
    almost always another acquisition (a localiser, a dedicated joint scan),
    and reslicing it onto an axial grid would hand the per-slice contour
    rules interpolated slices as if they were measured ones.
    """
    vols = list(volumes)
    if not vols:
        raise ValueError("order_stations needs at least one station")
    if not float(min_overlap_mm) >= 0:
        raise ValueError(f"min_overlap_mm must be >= 0, got {min_overlap_mm}")
    _check_axial(vols, float(max_obliquity_deg))
    ranges = [station_z_range(v) for v in vols]
    order = sorted(range(len(vols)), key=lambda n: (-ranges[n][1], -ranges[n][0]))
    if not allow_gaps:
        for a, b in zip(order[:-1], order[1:]):
            overlap = ranges[b][1] - ranges[a][0]
            if overlap < min_overlap_mm:
                what = "a gap of" if overlap < 0 else "an overlap of only"
                raise ValueError(
                    f"stations {_name(vols[a], a)} (z {ranges[a][0]:.1f}..{ranges[a][1]:.1f} mm) and "
                    f"{_name(vols[b], b)} (z {ranges[b][0]:.1f}..{ranges[b][1]:.1f} mm) leave {what} "
                    f"{abs(overlap):.1f} mm between slice centres (need >= {min_overlap_mm:g} mm to register); "
                    f"pass allow_gaps=True to keep their nominal geometry")
    return [vols[n] for n in order]


# --------------------------------------------------------------------------- #
# interpolation
# --------------------------------------------------------------------------- #
def _trilinear(vol: np.ndarray, idx: np.ndarray, grad: bool = True):
    """Trilinear value (and its exact index-space gradient) of ``vol`` at fractional indices ``idx`` (N, 3).

    Own implementation rather than ``map_coordinates`` because Gauss-Newton
    needs the gradient *of the same interpolant* as the value: a gradient from
    another scheme moves the fixed point away from the optimum.
    Indices outside ``[0, n-1]`` are clamped; callers mask them.
    """
    shp = np.asarray(vol.shape)
    i0 = np.clip(np.floor(idx).astype(np.int64), 0, shp - 2)
    f = np.clip(idx - i0, 0.0, 1.0)
    flat = vol.ravel()
    st = np.array(vol.strides) // vol.itemsize
    base = i0 @ st
    c = [flat[base + a * st[0] + b * st[1] + d * st[2]] for a in (0, 1) for b in (0, 1) for d in (0, 1)]
    c000, c001, c010, c011, c100, c101, c110, c111 = c
    fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
    c00 = c000 + (c100 - c000) * fx
    c01 = c001 + (c101 - c001) * fx
    c10 = c010 + (c110 - c010) * fx
    c11 = c011 + (c111 - c011) * fx
    c0 = c00 + (c10 - c00) * fy
    c1 = c01 + (c11 - c01) * fy
    val = c0 + (c1 - c0) * fz
    if not grad:
        return val
    gz = c1 - c0
    gy = (c10 - c00) * (1 - fz) + (c11 - c01) * fz
    d00, d01, d10, d11 = c100 - c000, c101 - c001, c110 - c010, c111 - c011
    gx = ((d00 * (1 - fy) + d10 * fy) * (1 - fz) + (d01 * (1 - fy) + d11 * fy) * fz)
    return val, np.stack([gx, gy, gz], axis=1)


def _inside(idx: np.ndarray, shape) -> np.ndarray:
    return np.all((idx >= 0) & (idx <= np.asarray(shape) - 1), axis=1)


def _otsu(values: np.ndarray) -> float:
    """Air/tissue threshold: Otsu on log intensity.

    On linear values Otsu splits fat from the rest when air is not the largest class (a full
    field of view); in log the air-tissue gap (noise floor ~20 vs >1000) is the widest.
    """
    from skimage.filters import threshold_otsu

    v = np.asarray(values, float)
    v = v[np.isfinite(v) & (v > 0)]
    if v.size == 0 or v.max() == v.min():
        return float(v.max()) if v.size else 0.0
    return float(np.exp(threshold_otsu(np.log(v))))


def _rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _angle_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(T[:3, :3]).as_rotvec())))


# --------------------------------------------------------------------------- #
# pairwise registration
# --------------------------------------------------------------------------- #
def _overlap_samples(fixed: Volume, moving: Volume, stride_mm: float, margin_mm: float):
    """Voxels of ``fixed`` (native slices, in-plane stride) inside ``moving``'s field of view, near the body."""
    fz = fixed.index_to_world(np.c_[np.zeros((fixed.shape[2], 2)), np.arange(fixed.shape[2])])[:, 2]
    mlo, mhi = station_z_range(moving)
    ks = np.nonzero((fz >= mlo + margin_mm) & (fz <= mhi - margin_mm))[0]
    if ks.size == 0:
        return None
    px = fixed.spacing[:2]
    si, sj = (max(1, int(round(stride_mm / p))) for p in px)
    ii, jj = np.arange(0, fixed.shape[0], si), np.arange(0, fixed.shape[1], sj)
    I, J, Kk = np.meshgrid(ii, jj, ks, indexing="ij")
    idx = np.stack([I.ravel(), J.ravel(), Kk.ravel()], axis=1).astype(float)
    world = fixed.index_to_world(idx)
    midx = moving.world_to_index(world)
    # Stay off the moving FOV's in-plane border by the margin too.
    mpx = moving.spacing
    lo = np.array([margin_mm / mpx[0], margin_mm / mpx[1], 0.0])
    hi = np.asarray(moving.shape, float) - 1 - lo
    keep = np.all((midx >= lo) & (midx <= hi), axis=1)
    return idx[keep].astype(np.int64), world[keep], ks


def _body_near(fixed_data: np.ndarray, ks: np.ndarray, idx: np.ndarray, spacing: np.ndarray, thr: float,
               dilate_mm: float) -> np.ndarray:
    """Sample points inside the body of the fixed station or within ``dilate_mm`` of it (edges give signal).

    Done on a grid subsampled to about 2 mm in-plane, with a square neighbourhood: the margin is
    coarse anyway, and a full-resolution round dilation costs more than the registration.
    """
    st = max(1, int(round(2.0 / float(spacing[0]))))
    sub = fixed_data[::st, ::st][:, :, ks] > thr
    # A square in-plane neighbourhood (separable maximum filter: cheap); slices stay apart.
    r = max(1, int(round(dilate_mm / (st * float(spacing[0])))))
    near = ndimage.maximum_filter(sub.view(np.uint8), size=(2 * r + 1, 2 * r + 1, 1)).view(bool)
    kpos = np.searchsorted(ks, idx[:, 2])
    ii = np.minimum(np.rint(idx[:, 0] / st).astype(np.int64), near.shape[0] - 1)
    jj = np.minimum(np.rint(idx[:, 1] / st).astype(np.int64), near.shape[1] - 1)
    return near[ii, jj, kpos]


def _register_pair(fixed: Volume, moving: Volume, *, levels: Sequence[tuple[float, float]], max_iter: int,
                   margin_mm: float, tol_mm: float, max_samples: int) -> dict[str, Any]:
    """Rigid ``M`` (fixed nominal LPS -> moving nominal LPS) maximising NCC on the overlap.

    Gauss-Newton (Levenberg-Marquardt damped) on ``sum w (g(x) U(M x) + b - F(x))^2`` where ``F`` is the
    fixed station on its own slices, ``U`` the moving one interpolated, and
    ``g`` a gain linear in position: the two stations' smooth bias fields
    differ across the overlap, which a constant gain (plain NCC) would push
    into the geometry.
    """
    # Crop both volumes to the overlap (with a margin) once; smoothing is in-plane only:
    # the slices are thick and few, smoothing across them would erase the z signal.
    flo, fhi = station_z_range(fixed)
    mlo, mhi = station_z_range(moving)
    zlo, zhi = max(flo, mlo) - 15.0, min(fhi, mhi) + 15.0

    def crop(v: Volume) -> tuple[np.ndarray, np.ndarray]:
        kz = v.index_to_world(np.c_[np.zeros((v.shape[2], 2)), np.arange(v.shape[2])])[:, 2]
        ks = np.nonzero((kz >= zlo) & (kz <= zhi))[0]
        k0, k1 = int(ks.min()), int(ks.max()) + 1
        shift = np.eye(4)
        shift[2, 3] = k0
        return np.asarray(v.data[:, :, k0:k1], np.float32), v.affine @ shift

    fdata, faff = crop(fixed)
    mdata, maff = crop(moving)
    fvol = Volume(fdata, faff)
    mvol = Volume(mdata, maff)
    samples = {stride: _overlap_samples(fvol, mvol, stride, margin_mm) for stride, _ in levels}
    if any(v is None for v in samples.values()):
        raise ValueError("no overlap slices")
    ks_all = next(iter(samples.values()))[2]
    thr = _otsu(fdata[:, :, ks_all][::2, ::2].ravel())
    m_inv = np.linalg.inv(maff)
    A3inv = m_inv[:3, :3]
    R = np.eye(3)
    t = np.zeros(3)
    history = []
    c = None
    ncc0 = ncc1 = float("nan")
    n_used = 0
    for stride_mm, sigma_mm in levels:
        sig_f = [sigma_mm / s for s in fvol.spacing[:2]] + [0.0]
        sig_m = [sigma_mm / s for s in mvol.spacing[:2]] + [0.0]
        fs = ndimage.gaussian_filter(fdata, sig_f) if sigma_mm > 0 else fdata
        ms = ndimage.gaussian_filter(mdata, sig_m) if sigma_mm > 0 else mdata
        ms = np.ascontiguousarray(ms, dtype=np.float64)
        idx, x, ks = samples[stride_mm]
        keep = _body_near(fdata, ks, idx, fvol.spacing, thr, dilate_mm=max(6.0, 2 * stride_mm))
        idx, x = idx[keep], x[keep]
        if len(x) > max_samples:
            # A fixed, spread-out subset: Gauss-Newton cost is linear in the samples, the
            # accuracy barely changes beyond a few ten thousand (benchmarks/bench_stations.py).
            idx, x = idx[::int(math.ceil(len(x) / max_samples))], x[::int(math.ceil(len(x) / max_samples))]
        if len(x) < 50:
            raise ValueError(f"only {len(x)} overlap samples near the body")
        F = fs[idx[:, 0], idx[:, 1], idx[:, 2]].astype(np.float64)
        if c is None:
            c = x.mean(axis=0)
        L = float(np.max(np.ptp(x, axis=0))) or 1.0
        xc = x - c
        ramp = xc / L
        lin = np.array([1.0, 0.0, 0.0, 0.0, 0.0])          # gain g0, gx, gy, gz; offset b
        first = True
        best = None                                         # (cost, R, t, lin, J, r)
        lam = 1e-4
        for it in range(max_iter):
            v = xc @ R.T
            y = v + c + t
            midx = y @ A3inv.T + m_inv[:3, 3]
            w = _inside(midx, ms.shape).astype(np.float64)
            U, gi = _trilinear(ms, midx)
            gw = gi @ A3inv                                   # world gradient: A^-T grad_idx, as rows
            if first:
                # Gain and offset by linear least squares before the first geometric step.
                Al = np.c_[U, U[:, None] * ramp, np.ones_like(U)] * w[:, None]
                lin = np.linalg.lstsq(Al, F * w, rcond=None)[0]
                first = False
                if not history:
                    ncc0 = _ncc(U[w > 0], F[w > 0])
            gain = lin[0] + ramp @ lin[1:4]
            r = (gain * U + lin[4] - F) * w
            cost = float(r @ r)
            if best is not None and best[0] - 1e-5 * best[0] < cost < best[0]:
                # Accepted but the cost barely moves: the rest is interpolation ripple, not signal.
                best = (cost, R, t, lin) + best[4:]
                break
            if best is None or cost < best[0]:
                Jg = gain[:, None] * gw
                J = np.c_[np.cross(v, Jg), Jg, U, U[:, None] * ramp, np.ones_like(U)] * w[:, None]
                best = (cost, R, t, lin, J, r, w)
                lam = max(lam / 3, 1e-7)
            else:
                # Levenberg-Marquardt: a step that raised the cost is undone and retried shorter
                # (trilinear interpolation is only piecewise smooth, so plain Gauss-Newton may overshoot).
                lam *= 10
                if lam > 1e3:
                    break
            _, R0, t0, lin0, J, r, _ = best
            H = J.T @ J
            H[np.diag_indices_from(H)] *= 1.0 + lam
            delta = -np.linalg.solve(H, J.T @ r)
            dw, dt = delta[:3], delta[3:6]
            R = Rotation.from_rotvec(dw).as_matrix() @ R0
            t = t0 + dt
            lin = lin0 + delta[6:]
            step = float(np.linalg.norm(dt) + np.linalg.norm(dw) * L / 2)
            history.append(step)
            if step < tol_mm:
                break
        _, R, t, lin, _, _, w = best
        n_used = int((w > 0).sum())
    # NCC at the end, on the finest level's samples.
    y = xc @ R.T + c + t
    midx = y @ A3inv.T + m_inv[:3, 3]
    w = _inside(midx, ms.shape)
    U = _trilinear(ms, midx, grad=False)
    ncc1 = _ncc(U[w], F[w])
    # y = R (x - c) + c + t  ->  M = [R, c + t - R c]
    M = _rigid(R, c + t - R @ c)
    return {"transform": M, "ncc_before": ncc0, "ncc_after": ncc1, "iterations": len(history),
            "n_samples": n_used, "overlap_centre": c}


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    d = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b / d) if d > 0 else float("nan")


def _fov_corners(v: Volume) -> np.ndarray:
    I, J, K = v.shape
    c = np.array([[a, b, d] for a in (0, I - 1) for b in (0, J - 1) for d in (0, K - 1)], float)
    return v.index_to_world(c)


def _kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Rigid ``T`` minimising ``sum |T src - dst|^2`` (Kabsch 1976)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    H = (src - cs).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return _rigid(R, cd - R @ cs)


def register_stations(volumes: Sequence[Volume], *, reference: int | None = None, min_overlap_mm: float = 10.0,
                      allow_gaps: bool = False, levels: Sequence[tuple[float, float]] = ((7.2, 4.0), (3.6, 1.5)),
                      max_iter: int = 40, margin_mm: float = 4.0, tol_mm: float = 0.01, max_samples: int = 20000,
                      max_obliquity_deg: float = 5.0) -> tuple[list[Volume], list[dict[str, Any]]]:
    """Recover each station's small rigid motion from the overlaps and put all stations in one frame.

    Parameters
    ----------
    volumes : sequence of Volume
        Axial stations (any order; :func:`order_stations` sorts and checks
        them), affines ``voxel_to_lps`` in LPS mm as the headers give them.
    reference : int, optional
        Index (head to feet, after ordering) of the station whose header
        geometry is kept. Default: the least-total-correction gauge (module
        docstring).
    min_overlap_mm : float
        Minimum overlap between slice centres (see :func:`order_stations`).
    allow_gaps : bool
        Keep the nominal relative geometry across overlaps that are too small
        instead of raising; the report says so (``registered`` False).
    levels : sequence of (stride_mm, sigma_mm)
        Coarse-to-fine schedule: in-plane sampling step of the overlap and
        in-plane Gaussian smoothing (never across slices, which are thick).
    max_iter : int
        Gauss-Newton iterations per level.
    margin_mm : float
        Overlap samples stay this far inside the other station's FOV.
    tol_mm : float
        Stop when a step moves the overlap by less than this.
    max_samples : int
        At most this many overlap samples per level (evenly thinned).
    max_obliquity_deg : float
        See :func:`order_stations`.

    Returns
    -------
    volumes : list of Volume
        Head to feet, same data (not copied), corrected affines
        ``C_s @ affine_s``; metadata gains ``station_correction`` (``C_s``,
        4x4 nominal LPS -> corrected LPS).
    reports : list of dict
        Per station: ``name``, ``correction`` (4x4), ``shift_mm`` (how far
        the correction moves the station's FOV centre), ``rotation_deg``;
        and for the overlap with the station above (``None`` for the first):
        ``pair`` with ``transform`` (this station's nominal LPS -> the one
        above's), ``ncc_before``, ``ncc_after`` (plain NCC of the overlap
        samples at the nominal and the found geometry; the fit maximises the
        locally-gained version, so plain NCC can even drop a little where the
        two bias fields differ most), ``iterations``, ``n_samples``,
        ``registered``, ``seconds``.

    Raises
    ------
    ValueError
        See :func:`order_stations`; a bad ``reference``; an overlap without
        enough body to register (unless ``allow_gaps``).

    Notes
    -----
    Each overlap is aligned by Gauss-Newton with Levenberg-Marquardt damping
    (Lucas & Kanade 1981; Baker & Matthews 2004) on the intensities: the lower station is sampled on its
    own slices, the upper one interpolated trilinearly with its exact
    gradient, and a gain linear in position plus an offset absorb the
    stations' different gains and bias fields (least squares with such a
    gain is normalised cross-correlation made local). Body edges and bones
    carry the signal; sample points are kept within a few mm of the body.
    The relative motions are chained from the head, then the gauge is fixed.
    """
    ordered = order_stations(volumes, min_overlap_mm=min_overlap_mm, max_obliquity_deg=max_obliquity_deg,
                             allow_gaps=allow_gaps)
    n = len(ordered)
    if reference is not None and not (isinstance(reference, (int, np.integer)) and 0 <= reference < n):
        raise ValueError(f"reference must be a station index in 0..{n - 1} (head to feet), got {reference!r}")
    pairs: list[dict[str, Any] | None] = [None]
    chain = [np.eye(4)]
    for s in range(1, n):
        up, lo = ordered[s - 1], ordered[s]
        t0 = time.perf_counter()
        overlap = station_z_range(lo)[1] - station_z_range(up)[0]
        info: dict[str, Any]
        try:
            if overlap < min_overlap_mm:
                raise ValueError(f"overlap {overlap:.1f} mm < {min_overlap_mm:g} mm")
            info = _register_pair(lo, up, levels=levels, max_iter=max_iter, margin_mm=margin_mm, tol_mm=tol_mm,
                                  max_samples=int(max_samples))
            info["registered"] = True
        except ValueError as exc:
            if not allow_gaps:
                raise ValueError(f"cannot register {_name(lo, s)} to {_name(up, s - 1)}: {exc}") from None
            info = {"transform": np.eye(4), "registered": False, "reason": str(exc),
                    "ncc_before": float("nan"), "ncc_after": float("nan"), "iterations": 0, "n_samples": 0}
        info["seconds"] = time.perf_counter() - t0
        pairs.append(info)
        # M maps this station's nominal frame into the one above's nominal frame.
        chain.append(chain[-1] @ info["transform"])
    if reference is None:
        src = np.concatenate([_fov_corners(v) @ C[:3, :3].T + C[:3, 3] for v, C in zip(ordered, chain)])
        dst = np.concatenate([_fov_corners(v) for v in ordered])
        G = _kabsch(src, dst)
    else:
        G = np.linalg.inv(chain[int(reference)])
    out, reports = [], []
    for s, (v, C0) in enumerate(zip(ordered, chain)):
        C = G @ C0
        centre = v.index_to_world((np.asarray(v.shape, float) - 1) / 2)
        md = dict(v.metadata or {})
        md["station_correction"] = C.tolist()
        out.append(Volume(v.data, C @ v.affine, md))
        reports.append({"name": _name(v, s), "correction": C,
                        "shift_mm": float(np.linalg.norm(C[:3, :3] @ centre + C[:3, 3] - centre)),
                        "rotation_deg": _angle_deg(C), "pair": pairs[s]})
    return out, reports


# --------------------------------------------------------------------------- #
# intensity
# --------------------------------------------------------------------------- #
def _pair_ratio(upper: Volume, lower: Volume, stride_mm: float, erode_mm: float) -> tuple[float, int]:
    """Median of ``upper / lower`` over matched overlap voxels well inside the body of both."""
    got = _overlap_samples(lower, upper, stride_mm, margin_mm=2.0)
    if got is None:
        return float("nan"), 0
    idx, world, ks = got
    L = lower.data[idx[:, 0], idx[:, 1], idx[:, 2]].astype(float)
    U = ndimage.map_coordinates(np.asarray(upper.data, np.float32), upper.world_to_index(world).T, order=1)
    tl = _otsu(lower.data[:, :, ks][::2, ::2].ravel())
    # Stay away from the body's edge: a sub-voxel misalignment there changes the ratio wildly.
    body = lower.data[:, :, ks] > tl
    r = max(1, int(round(erode_mm / float(lower.spacing[0]))))
    body = ndimage.minimum_filter(body.view(np.uint8), size=(2 * r + 1, 2 * r + 1, 1)).view(bool)
    inner = body[idx[:, 0], idx[:, 1], np.searchsorted(ks, idx[:, 2])]
    tu = _otsu(U)
    ok = inner & (U > tu) & (L > tl)
    if ok.sum() < 20:
        return float("nan"), int(ok.sum())
    return float(np.median(U[ok] / L[ok])), int(ok.sum())


def normalise_intensity(volumes: Sequence[Volume], *, reference: int | None = None, stride_mm: float = 3.6,
                        erode_mm: float = 6.0) -> tuple[list[Volume], np.ndarray]:
    """Intensity scale of each station relative to a reference, from the overlaps.

    Parameters
    ----------
    volumes : sequence of Volume
        Stations head to feet (LPS mm), best already registered
        (:func:`register_stations`), so overlap voxels match.
    reference : int, optional
        Station whose scale is 1. Default: the geometric mean of all scales
        is 1 (no station privileged).
    stride_mm : float
        In-plane step of the matched overlap voxels.
    erode_mm : float
        Voxels nearer than this to the body's edge are left out.

    Returns
    -------
    volumes : list of Volume
        ``data / scale`` (float32); metadata gains ``intensity_scale``.
    scales : ndarray (n,)
        Estimated gain of each station relative to the reference: a tissue
        that reads ``v`` in the reference reads ``scales[s] * v`` in station
        ``s``.

    Raises
    ------
    ValueError
        Fewer than one volume, a bad ``reference``, or an overlap with too
        few matched body voxels.

    Notes
    -----
    Per overlap the ratio is the median of ``upper / lower`` over matched
    voxels inside the body of both (robust to tissue, noise and the few
    voxels a residual misalignment mixes), chained from the head. A smooth
    bias field that differs between the two stations in their overlap is
    indistinguishable from a gain there; the median takes its typical value.
    """
    vols = list(volumes)
    n = len(vols)
    if n == 0:
        raise ValueError("normalise_intensity needs at least one station")
    if reference is not None and not (isinstance(reference, (int, np.integer)) and 0 <= reference < n):
        raise ValueError(f"reference must be a station index in 0..{n - 1}, got {reference!r}")
    log_s = np.zeros(n)
    for s in range(1, n):
        ratio, count = _pair_ratio(vols[s - 1], vols[s], stride_mm, erode_mm)
        if not (np.isfinite(ratio) and ratio > 0):
            raise ValueError(f"{_name(vols[s], s)} and {_name(vols[s - 1], s - 1)}: only {count} matched body "
                             f"voxels in their overlap, cannot compare intensities")
        log_s[s] = log_s[s - 1] - math.log(ratio)
    log_s -= log_s.mean() if reference is None else log_s[int(reference)]
    scales = np.exp(log_s)
    out = []
    for v, sc in zip(vols, scales):
        md = dict(v.metadata or {})
        md["intensity_scale"] = float(sc)
        out.append(Volume((np.asarray(v.data, np.float32) / np.float32(sc)), v.affine.copy(), md))
    return out, scales
