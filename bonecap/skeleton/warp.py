"""The personal skeleton: the template warped onto a subject's bones (issue #5, stage 5).

Kojima et al. warped a generic skeleton onto the bones extracted from a
person's MRI with an affine transform plus Gaussian radial basis functions
(their *RBFT*). Here, per bone: a rigid ICP, then an affine ICP (for a
slender bone, the fibula, a rigid motion with one scale along the bone and one
across it: a general affine is ill-posed across a section a few pixels wide),
then corresponding surface samples (feature points, both ways so the warp cannot
fold the template onto part of the target), and an RBF interpolant
``scipy.interpolate.RBFInterpolator(kernel="gaussian", degree=1)`` whose
degree-1 polynomial is the affine part. The fit is refined coarse to fine
(narrower kernels, correspondences recomputed from the current warp). Its
residual at the feature points is checked (a kernel too wide for the points
makes the linear system numerically singular and the fit silently wrong) and
so is the Jacobian determinant (no folding).

Public API
----------
- :func:`rigid_icp` / :func:`affine_icp` / :func:`axial_icp`
  ``(source_points, target_mesh, init=None, ...) -> (T, residuals)``
- :func:`feature_points` ``(template_mesh, target_mesh, n=1000, ...) -> (src, dst)``
- :class:`Warp`, :func:`fit_warp` ``(src, dst, *, kernel_width_mm=40, smoothing=1e-3, ...) -> Warp``
- :func:`initial_transform` ``(template, targets) -> 4x4``
- :func:`warp_skeleton` ``(template, targets, *, init=None, ...) -> (Skeleton, report)``

Frames: the template's bones are in its world (``"model"``: X anterior, Y up,
Z right, mm); the targets (and the result) in the subject's world, normally
**LPS** mm. Every transform here maps template world -> target world.

References
----------
- Kojima et al. (the design's source paper): affine + Gaussian RBF transform
  (RBFT) of a generic skeleton onto MRI bones.
- Besl PJ, McKay ND. A method for registration of 3-D shapes. *IEEE PAMI*
  14(2):239-256, 1992 (ICP).
- Chen Y, Medioni G. Object modelling by registration of multiple range
  images. *Image Vis Comput* 10(3):145-155, 1992 (point-to-plane ICP).
- Umeyama S. Least-squares estimation of transformation parameters between
  two point patterns. *IEEE PAMI* 13(4):376-380, 1991.
- Fornefett M, Rohr K, Stiehl HS. Radial basis functions with compact support
  for elastic registration of medical images. *Image Vis Comput* 19:87-96,
  2001 (RBF warps, Jacobian determinant as the folding check).
- Higham NJ. Computing the polar decomposition -- with applications. *SIAM J
  Sci Stat Comput* 7(4):1160-1174, 1986 (the rigid part of an affine).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.interpolate import RBFInterpolator
from scipy.spatial import cKDTree

from bonecap.model import Bone, Mesh, Skeleton
from bonecap.parallel import fork_map
from bonecap.skeleton.isb import refresh_isb_frames
from bonecap.skeleton.kinematics import joint_groups

__all__ = ["rigid_icp", "affine_icp", "axial_icp", "feature_points", "Warp", "fit_warp", "initial_transform",
           "cover_extent", "warp_skeleton"]


# --------------------------------------------------------------------------- #
# small geometry
# --------------------------------------------------------------------------- #
def _apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def _check_points(name: str, p) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} holds NaN or infinite coordinates")
    return p


def _check_mesh(name: str, m) -> Mesh:
    if not isinstance(m, Mesh):
        raise ValueError(f"{name} must be a bonecap.model.Mesh, got {type(m).__name__}")
    if len(m.faces) == 0:
        raise ValueError(f"{name} has no faces")
    return m


def _kabsch(A: np.ndarray, B: np.ndarray, scale: bool = False, centred: bool = True) -> np.ndarray:
    """Least-squares rigid (or similarity) 4x4 with ``B ~ T A`` (Umeyama 1991); ``centred=False``: about
    the origin (no translation: vectors from a fixed centre, e.g. a joint)."""
    ca, cb = (A.mean(0), B.mean(0)) if centred else (np.zeros(3), np.zeros(3))
    H = (A - ca).T @ (B - cb)
    U, S, Vt = np.linalg.svd(H)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ D @ U.T
    s = float((S * np.diag(D)).sum() / max(((A - ca) ** 2).sum(), 1e-12)) if scale else 1.0
    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = cb - s * R @ ca
    return T


def _fit_affine(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Least-squares affine 4x4 with ``B ~ T A``."""
    Ah = np.hstack([A, np.ones((len(A), 1))])
    M, *_ = np.linalg.lstsq(Ah, B, rcond=None)
    T = np.eye(4)
    T[:3, :] = M.T
    return T


def _polar_rotation(L: np.ndarray) -> np.ndarray:
    """The rotation of the polar decomposition ``L = R S`` (Higham 1986), via the SVD."""
    U, _, Vt = np.linalg.svd(L)
    R = U @ Vt
    if np.linalg.det(R) < 0:  # a reflection would flip the bone frame's handedness
        U[:, -1] *= -1
        R = U @ Vt
    return R


class _Surface:
    """A target mesh with what the ICPs and correspondences ask of it (built once per mesh).

    ``unseen``: half-spaces ``(normal, offset)``, ``normal . p > offset``, where the target was not
    looked for (a segmentation's search ended there): no pair with a point there counts."""

    def __init__(self, mesh: Mesh, unseen=()):
        import pyvista as pv
        import trimesh

        self.mesh = mesh
        self.unseen = _check_unseen(unseen)
        self.tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        self.normals = np.asarray(self.tm.face_normals)
        self.poly = pv.PolyData(mesh.vertices, np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).ravel())
        # dense samples for nearest-neighbour ICP: vertices plus face centres (spacing ~ the edge length)
        self.samples = np.concatenate([mesh.vertices, self.tm.triangles_center])
        self.sample_normals = np.concatenate([np.asarray(self.tm.vertex_normals), self.normals])
        self.tree = cKDTree(self.samples)

    def seen(self, p: np.ndarray) -> np.ndarray:
        """Which points lie where the target was looked for (outside every ``unseen`` half-space)."""
        return ~_past(p, self.unseen)

    def closest(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest points on the surface and their face ids."""
        cells, pts = self.poly.find_closest_cell(p, return_closest_point=True)
        return np.asarray(pts, dtype=float).reshape(-1, 3), np.asarray(cells, dtype=np.int64).reshape(-1)


def _past(p: np.ndarray, halfspaces) -> np.ndarray:
    """Which points lie in any of the half-spaces ``(normal, offset)``: ``normal . p > offset``."""
    out = np.zeros(len(p), bool)
    for n, c in halfspaces:
        out |= p @ n > c
    return out


def _check_unseen(unseen) -> list[tuple[np.ndarray, float]]:
    out = []
    for h in unseen or ():
        try:
            n, c = h
            n, c = np.asarray(n, dtype=float).reshape(3), float(c)
        except (TypeError, ValueError):
            raise ValueError(f"an unseen half-space is (normal (3,), offset), got {h!r}") from None
        if not (np.isfinite(n).all() and np.isfinite(c) and np.linalg.norm(n) > 1e-9):
            raise ValueError(f"an unseen half-space needs a finite non-zero normal and offset, got {h!r}")
        k = float(np.linalg.norm(n))
        out.append((n / k, c / k))
    return out


def _as_surface(m, unseen=()) -> _Surface:
    if isinstance(m, _Surface):
        if unseen:
            raise ValueError("give unseen half-spaces with a mesh, not with a prepared surface (it has its own)")
        return m
    return _Surface(_check_mesh("target_mesh", m), unseen)


def _turn_jacobian(p: np.ndarray) -> np.ndarray:
    """(N, 3, 3): d(w x p)/dw for each point, the matrix ``-[p]x`` (a small turn w moves p by w x p)."""
    J = np.zeros((len(p), 3, 3))
    J[:, 0, 1], J[:, 0, 2], J[:, 1, 2] = p[:, 2], -p[:, 1], p[:, 0]
    J[:, 1, 0], J[:, 2, 0], J[:, 2, 1] = -p[:, 2], p[:, 1], -p[:, 0]
    return J


def _solve_step(m: np.ndarray, q: np.ndarray, n: np.ndarray, kind: str, w_point: float,
                rot_offset: np.ndarray | None = None, prior: float = 0.0, axis: np.ndarray | None = None
                ) -> np.ndarray:
    """One linearised ICP step: the update U (4x4) minimising
    ``sum (n . (U m - q))^2 + w_point^2 sum |U m - q|^2`` (point-to-plane, Chen & Medioni 1992, with a little
    point-to-point that fixes the directions a plane leaves free).

    ``kind``: ``"rigid"``, ``"affine"`` or ``"axial"`` (a rigid motion with one scale along ``axis`` and one
    across it, about the points' centroid: :func:`axial_icp`)."""
    N = len(m)
    if kind == "axial":
        # U m = c + t + R(w) S (m - c), S = I + alpha u u' + beta (I - u u'), linearised about the identity
        u = np.asarray(axis, float) / np.linalg.norm(axis)
        c = m.mean(axis=0)
        d = m - c
        sa = d @ u
        rr = d - np.outer(sa, u)
        Jp = np.column_stack([np.cross(d, n), n, sa * (n @ u), (n * rr).sum(1)])          # (N, 8)
        rp = (n * (q - m)).sum(1)
        Jq = np.concatenate([_turn_jacobian(d), np.broadcast_to(np.eye(3), (N, 3, 3)), (sa[:, None] * u)[:, :, None],
                             rr[:, :, None]], axis=2).reshape(3 * N, 8)
        J = np.vstack([Jp, w_point * Jq])
        r = np.concatenate([rp, w_point * (q - m).ravel()])
        x = np.linalg.solve(J.T @ J, J.T @ r)
        from scipy.spatial.transform import Rotation

        uu = np.outer(u, u)
        A = Rotation.from_rotvec(x[:3]).as_matrix() @ (np.eye(3) + x[6] * uu + x[7] * (np.eye(3) - uu))
        U = np.eye(4)
        U[:3, :3] = A
        U[:3, 3] = c + x[3:6] - A @ c
        return U
    if kind == "rigid":
        # U m ~ m + w x m + t: unknowns (w, t)
        Jp = np.hstack([np.cross(m, n), n])                                   # (N, 6)
        rp = (n * (q - m)).sum(1)
        Jq = np.concatenate([_turn_jacobian(m), np.broadcast_to(np.eye(3), (N, 3, 3))], axis=2).reshape(3 * N, 6)
        J = np.vstack([Jp, w_point * Jq])
        r = np.concatenate([rp, w_point * (q - m).ravel()])
        if prior > 0 and rot_offset is not None and axis is not None:
            # a weak pull of the spin about the long axis back to the initial pose: it decides only what the
            # surfaces leave free (a thin straight bone's spin); swings stay free
            JtJ = J.T @ J
            mu = prior * np.trace(JtJ[:3, :3]) / 3.0
            J = np.vstack([J, np.sqrt(mu) * np.concatenate([axis, np.zeros(3)])[None]])
            r = np.concatenate([r, [-np.sqrt(mu) * float(axis @ rot_offset)]])
        x = np.linalg.solve(J.T @ J, J.T @ r)  # normal equations: 6 unknowns, well conditioned by the point term
        from scipy.spatial.transform import Rotation

        U = np.eye(4)
        U[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
        U[:3, 3] = x[3:]
        return U
    # affine: U m = W [m, 1], unknowns W (3x4) row-major
    phi = np.hstack([m, np.ones((N, 1))])
    Jp = (n[:, :, None] * phi[:, None, :]).reshape(N, 12)
    rp = (n * q).sum(1)
    Jq = (np.eye(3)[None, :, :, None] * phi[:, None, None, :]).reshape(3 * N, 12)
    J = np.vstack([Jp, w_point * Jq])
    r = np.concatenate([rp, w_point * q.ravel()])
    W = np.linalg.solve(J.T @ J, J.T @ r).reshape(3, 4)
    U = np.eye(4)
    U[:3, :] = W
    return U


def _icp(source: np.ndarray, target: _Surface, init: np.ndarray, kind: str, iterations: int, tol_mm: float,
         trim: float, prior: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial.transform import Rotation

    T = np.eye(4) if init is None else np.asarray(init, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"init must be a 4x4 transform, got shape {T.shape}")
    R0 = _polar_rotation(T[:3, :3])
    # the source's long axis (its principal direction), for the spin prior
    axis = np.linalg.eigh(np.cov((source - source.mean(0)).T))[1][:, -1]
    if kind == "rigid":
        # a similarity or affine start (e.g. initial_transform) gives its rotation: a rigid result stays rigid
        T = T.copy()
        T[:3, :3] = R0
    sel = np.arange(len(target.samples))
    if len(sel) > 3000:  # a subset is enough for the target -> source direction
        sel = sel[np.linspace(0, len(sel) - 1, 3000).astype(int)]
    tgt, tgt_n = target.samples[sel], target.sample_normals[sel]
    samples_seen = target.seen(target.samples)     # the target's samples do not move: once
    prev = np.inf
    for _ in range(int(iterations)):
        moved = _apply(T, source)
        d1, i1 = target.tree.query(moved)
        d2, i2 = cKDTree(moved).query(tgt)
        # both directions: source -> target alone lets a bigger target swallow the source, target -> source
        # alone lets a partial target pull the whole source onto itself; far pairs are dropped (trimmed ICP),
        # and pairs reaching where the target was not looked for (its end there is a cut, not the bone's)
        moved_seen = target.seen(moved)
        v1 = _enough(moved_seen & samples_seen[i1])
        v2 = _enough(samples_seen[sel] & moved_seen[i2])
        k1 = v1 & (d1 <= max(np.quantile(d1[v1], trim), 1e-9))
        k2 = v2 & (d2 <= max(np.quantile(d2[v2], trim), 1e-9))
        m = np.concatenate([moved[k1], moved[i2[k2]]])
        q = np.concatenate([target.samples[i1[k1]], tgt[k2]])
        n = np.concatenate([target.sample_normals[i1[k1]], tgt_n[k2]])
        off = Rotation.from_matrix(_polar_rotation(T[:3, :3]) @ R0.T).as_rotvec() if prior > 0 else None
        T = _solve_step(m, q, n, kind, 0.2, off, prior, _polar_rotation(T[:3, :3]) @ axis) @ T
        err = 0.5 * (d1[k1].mean() + d2[k2].mean())
        if abs(prev - err) < tol_mm:
            break
        prev = err
    moved = _apply(T, source)
    res = np.linalg.norm(target.closest(moved)[0] - moved, axis=1)
    return T, res[_seen_pairs(target, moved, moved)]


def _enough(ok: np.ndarray) -> np.ndarray:
    """The pairs ``ok`` keeps, or all of them if that leaves fewer than 10."""
    return ok if ok.sum() >= 10 else np.ones(len(ok), bool)


def _seen_pairs(target: _Surface, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairs with both ends where the target was looked for (all of them if that leaves fewer than 10)."""
    if not target.unseen:
        return np.ones(len(a), bool)
    return _enough(target.seen(a) & target.seen(b))


def rigid_icp(source_points, target_mesh, init=None, *, iterations: int = 60, tol_mm: float = 1e-3,
              trim: float = 0.9, rotation_prior: float = 0.0, unseen=()) -> tuple[np.ndarray, np.ndarray]:
    """Rigid ICP of points onto a mesh, correspondences both ways, point-to-plane (Besl & McKay 1992;
    Chen & Medioni 1992).

    Parameters
    ----------
    source_points : ndarray, shape (N, 3)
        Points in the source (template) world, mm.
    target_mesh : Mesh
        Surface in the target world (e.g. LPS), mm.
    init : ndarray (4, 4), optional
        Initial source -> target transform (identity by default; of a
        similarity or affine only the polar rotation and the translation are
        used). ICP is local: it needs the bone within ~20 deg and a fraction of
        its size.
    iterations : int
        Maximum number of iterations.
    tol_mm : float
        Stop when the mean matched distance changes less than this.
    trim : float
        Fraction of the matches kept each way (the nearest ones).
    rotation_prior : float
        Weight (relative to the mean rotational stiffness of the matches) of a
        pull of the spin about the source's long axis (its principal direction)
        back to ``init``'s. 0: none. A small value (1e-3) only decides what the
        surfaces leave free -- the spin of a thin, straight bone such as the
        fibula -- and leaves its swing to the surfaces.
    unseen : sequence of (normal (3,), offset)
        Half-spaces ``normal . p > offset`` of the target world where the
        target was not looked for (a segmentation's search ended short of the
        bone's end: its surface there is a cut). A pair with either point in
        one does not count, so the source is neither pulled onto the cut nor
        shrunk to it; what lies there is extrapolated.

    Returns
    -------
    T : ndarray (4, 4)
        ``source_to_target``, a rotation and translation.
    residuals : ndarray (N,) or (N_seen,)
        Distance (mm) of each moved source point to the target surface (of the
        points outside ``unseen`` only, when it is given).

    References
    ----------
    Besl & McKay 1992; Chen & Medioni 1992 (point-to-plane steps, with a 0.2-weighted
    point-to-point term for the directions a plane leaves free).
    """
    src = _check_points("source_points", source_points)
    if rotation_prior < 0:
        raise ValueError(f"rotation_prior must be >= 0, got {rotation_prior}")
    return _icp(src, _as_surface(target_mesh, unseen), init, "rigid", iterations, tol_mm, trim, rotation_prior)


def axial_icp(source_points, target_mesh, init=None, *, iterations: int = 60, tol_mm: float = 1e-3,
              trim: float = 0.9, unseen=()) -> tuple[np.ndarray, np.ndarray]:
    """ICP of a slender bone's points onto a mesh: a rigid motion with a scale along the bone and one across it.

    The affine stage of :func:`warp_skeleton` for a bone whose cross-section is
    a few pixels wide (:func:`_slender`, the fibula): a general affine's shears
    and stretches across such a bone are held by a section of ~15 mm only, and
    its fits came out stretched 1.2-1.7 times along a slant across the shaft on
    phantoms, which moved its landmarks several millimetres about the bone
    (the lateral malleolus) and tipped some over the plausibility limit.
    Two scales keep what a person's bone differs by (its length, its
    thickness); the RBF stage fits the rest of the shape.

    Same parameters and returns as :func:`affine_icp`; the long axis is the
    source points' principal direction, turned with the transform.
    """
    src = _check_points("source_points", source_points)
    return _icp(src, _as_surface(target_mesh, unseen), init, "axial", iterations, tol_mm, trim)


#: A bone is slender (:func:`_slender`) when the spread of its points across its long axis (the second
#: singular value) is below this fraction of the spread along it: the template's fibula 0.046, the next
#: slenderest long bones (ulna, radius) 0.09-0.10, femur and tibia 0.11-0.13.
SLENDER_RATIO = 0.06


def _slender(points: np.ndarray) -> bool:
    """Whether a bone's points are slender enough for :func:`axial_icp` in place of the affine ICP."""
    sv = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return bool(sv[1] < SLENDER_RATIO * sv[0])


def affine_icp(source_points, target_mesh, init=None, *, iterations: int = 60, tol_mm: float = 1e-3,
               trim: float = 0.9, unseen=()) -> tuple[np.ndarray, np.ndarray]:
    """Affine ICP of points onto a mesh, correspondences both ways.

    Same parameters as :func:`rigid_icp`; start it from the rigid result (an
    affine ICP from far away can shear the bone onto the wrong part).

    Returns
    -------
    T : ndarray (4, 4)
        ``source_to_target``, a general affine map.
    residuals : ndarray (N,) or (N_seen,)
        Distance (mm) of each moved source point to the target surface.
    """
    src = _check_points("source_points", source_points)
    return _icp(src, _as_surface(target_mesh, unseen), init, "affine", iterations, tol_mm, trim)


# --------------------------------------------------------------------------- #
# feature points
# --------------------------------------------------------------------------- #
def _barycentric(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    import trimesh

    return trimesh.triangles.points_to_barycentric(tri, p)


def _even_samples(tm, n: int, seed: int):
    """About ``n`` evenly spread surface samples (Poisson-disk rejection) and their faces."""
    import logging

    import trimesh

    # rejection leaves somewhat fewer than asked: that is fine here, and not worth trimesh's warning
    logger = logging.getLogger("trimesh.sample")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        return trimesh.sample.sample_surface_even(tm, n, seed=seed)
    finally:
        logger.setLevel(level)


def _correspondences(moving: Mesh, target: _Surface, n: int, max_angle_deg: float, seed: int,
                     moving_surface: _Surface | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs (face of ``moving``, barycentric coordinates, point on ``target``), both ways.

    Half the pairs start on ``moving`` (evenly spread samples -> their closest
    target point), half on the target (-> closest point of ``moving``); pairs
    whose normals disagree by more than ``max_angle_deg`` (the other side of a
    thin bone) or whose distance is an outlier are dropped, and the moving-side
    points are thinned to a minimum spacing so no two nearly coincident source
    points ask for different targets (which makes an interpolant fold).
    """
    ms = moving_surface if moving_surface is not None else _Surface(moving)
    half = max(int(n) // 2, 4)
    p_m, f_m = _even_samples(ms.tm, half, seed)
    q_m, c_m = target.closest(p_m)
    p_t, f_t = _even_samples(target.tm, half, seed + 1)
    q_t, c_t = ms.closest(p_t)
    faces = np.concatenate([np.asarray(f_m, dtype=np.int64), c_t])
    src = np.concatenate([p_m, q_t])
    dst = np.concatenate([q_m, p_t])
    n_src = ms.normals[faces]
    n_dst = np.concatenate([target.normals[c_m], target.normals[np.asarray(f_t, dtype=np.int64)]])
    keep = (n_src * n_dst).sum(1) >= np.cos(np.deg2rad(max_angle_deg))
    keep &= _seen_pairs(target, src, dst)
    d = np.linalg.norm(dst - src, axis=1)
    if keep.any():
        med = np.median(d[keep])
        keep &= d <= max(3.0 * med, med + 5.0)
    faces, src, dst = faces[keep], src[keep], dst[keep]
    # thin the source side: one pair per cell of about half the mean sample spacing
    spacing = 0.5 * np.sqrt(ms.tm.area / max(half, 1))
    _, first = np.unique(np.floor(src / spacing).astype(np.int64), axis=0, return_index=True)
    first = np.sort(first)
    faces, src, dst = faces[first], src[first], dst[first]
    bary = _barycentric(ms.tm.triangles[faces], src)
    return faces, bary, dst


def feature_points(template_mesh: Mesh, target_mesh: Mesh, n: int = 1000, *, max_angle_deg: float = 60.0,
                   seed: int = 0, unseen=()) -> tuple[np.ndarray, np.ndarray]:
    """Corresponding surface points of two roughly aligned meshes (the warp's feature points).

    Call it after ICP: both meshes in the same frame (the target's, e.g. LPS).
    Half the pairs are evenly spread samples of the template with their
    closest target point, half are target samples with their closest template
    point (symmetric: the template cannot fold onto part of the target, and
    target parts the template misses still pull it). Pairs whose surface
    normals differ by more than ``max_angle_deg`` or whose distance is an
    outlier are dropped; template points are thinned so that none are nearly
    coincident.

    Parameters
    ----------
    template_mesh, target_mesh : Mesh
        In one frame, mm.
    n : int
        Number of samples drawn (about half each way); the result has at most
        this many pairs. Keep it <= 1-2 thousand per bone (RBF memory).
    max_angle_deg : float
        Normal agreement for a pair to count.
    seed : int
        Seed of the even surface sampling (deterministic).
    unseen : sequence of (normal (3,), offset)
        Half-spaces where the target was not looked for (see :func:`rigid_icp`):
        no pair has a point there.

    Returns
    -------
    src, dst : ndarray (M, 3)
        Points on the template and their counterparts on the target.
    """
    _check_mesh("template_mesh", template_mesh)
    if int(n) < 8:
        raise ValueError(f"n must be at least 8 feature points, got {n}")
    _, _, dst = _corr = _correspondences(template_mesh, _as_surface(target_mesh, unseen), n, max_angle_deg, seed)
    faces, bary, _ = _corr
    tri = template_mesh.vertices[template_mesh.faces[faces]]
    src = np.einsum("nk,nkd->nd", bary, tri)
    return src, dst


# --------------------------------------------------------------------------- #
# the warp
# --------------------------------------------------------------------------- #
@dataclass
class Warp:
    """An affine + Gaussian RBF map ``x -> rbf(pre(x))`` (Kojima et al.'s RBFT).

    Attributes
    ----------
    rbf : scipy.interpolate.RBFInterpolator
        Gaussian kernel, degree-1 polynomial (the affine part).
    pre : ndarray (4, 4)
        An affine applied before the RBF (e.g. the affine ICP); identity by default.
    kernel_width_mm : float
        Gaussian width ``w``: the kernel is ``exp(-(r / w)^2)`` (``epsilon = 1 / w``).
    smoothing : float
    src, dst : ndarray (M, 3)
        Feature points (``src`` after ``pre``) and their targets.
    residual_mm : ndarray (M,)
        ``|warp(src) - dst|`` at the feature points: near 0 for an interpolating
        fit (``smoothing = 0``). A large residual means the fit failed (a kernel
        too wide for the points' spread: the system is numerically singular).
    """

    rbf: RBFInterpolator
    pre: np.ndarray
    kernel_width_mm: float
    smoothing: float
    src: np.ndarray
    dst: np.ndarray
    residual_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __call__(self, points) -> np.ndarray:
        """Map points ``(N, 3)`` of the source frame to the target frame."""
        p = _check_points("points", points)
        if len(p) == 0:
            return p.copy()
        return self.rbf(_apply(self.pre, p))

    def jacobian(self, points) -> np.ndarray:
        """The 3x3 Jacobian of the map at each point, ``(N, 3) -> (N, 3, 3)``.

        Analytic: ``d/dx exp(-eps^2 |x - y|^2) = -2 eps^2 (x - y) exp(...)``
        plus the affine part, chained with ``pre``.
        """
        p = _apply(self.pre, _check_points("points", points))
        r = self.rbf
        y, eps, C = r.y, float(r.epsilon), r._coeffs
        n_c = len(y)
        powers = np.asarray(r.powers)
        J = np.zeros((len(p), 3, 3))
        # the polynomial part: monomials of (x - shift) / scale of degree <= 1
        for m, pw in enumerate(powers):
            if pw.sum() == 1:
                d = int(np.argmax(pw))
                J[:, :, d] += C[n_c + m] / r._scale[d]
        # sum_i c_i (x - y_i)_d K_i = x_d (K C) - K (y_d C): matrix products only
        CY = np.hstack([C[:n_c]] + [y[:, d:d + 1] * C[:n_c] for d in range(3)])   # (N, 12)
        yy = (y ** 2).sum(1)
        for s0 in range(0, len(p), 4000):
            x = p[s0:s0 + 4000]
            r2 = np.maximum((x ** 2).sum(1)[:, None] + yy[None, :] - 2.0 * x @ y.T, 0.0)
            KC = np.exp(-(eps ** 2) * r2) @ CY                                     # (n, 12)
            for d in range(3):
                J[s0:s0 + 4000, :, d] += (-2.0 * eps ** 2) * (x[:, d:d + 1] * KC[:, :3] - KC[:, 3 * d + 3:3 * d + 6])
        return J @ self.pre[:3, :3]

    def min_jacobian_det(self, points) -> float:
        """Smallest Jacobian determinant over the points: > 0 means the warp does not fold there."""
        p = _check_points("points", points)
        if len(p) == 0:
            raise ValueError("min_jacobian_det needs at least one point")
        return float(np.linalg.det(self.jacobian(p)).min())


def fit_warp(src, dst, *, kernel_width_mm: float = 40.0, smoothing: float = 1e-3, pre=None,
             max_residual_mm: float | None = 1.0) -> Warp:
    """Fit the affine + Gaussian RBF warp that takes feature points ``src`` to ``dst``.

    Parameters
    ----------
    src, dst : ndarray (M, 3)
        Feature points (in the frame after ``pre``) and their targets, mm;
        at least 4 not coplanar (the affine part).
    kernel_width_mm : float
        Width ``w`` of the Gaussian ``exp(-(r / w)^2)``; ``epsilon = 1 / w``.
        It should be a few times the feature-point spacing and well below the
        bone's size: too wide and the kernel matrix is numerically singular
        (the fit fails silently -- caught by ``max_residual_mm``).
    smoothing : float
        Added to the kernel matrix's diagonal (0: interpolate exactly); a
        little regularises noisy correspondences.
    pre : ndarray (4, 4), optional
        An affine applied to input points before the RBF (stored in the Warp).
    max_residual_mm : float or None
        Raise if the 95th percentile of the residual at the feature points
        exceeds this; ``None`` skips the check (the residual is still stored).

    Returns
    -------
    Warp

    Raises
    ------
    ValueError
        On mismatched or too few points, a non-positive width or negative
        smoothing, or when the residual check fails.

    References
    ----------
    Kojima et al. (RBFT); scipy ``RBFInterpolator`` (Gaussian kernel needs
    ``epsilon``; ``degree=1`` adds the affine part).
    """
    src = _check_points("src", src)
    dst = _check_points("dst", dst)
    if src.shape != dst.shape:
        raise ValueError(f"src and dst must have the same shape, got {src.shape} and {dst.shape}")
    if len(src) < 4:
        raise ValueError(f"fit_warp needs at least 4 feature points (the affine part), got {len(src)}")
    if not kernel_width_mm > 0:
        raise ValueError(f"kernel_width_mm must be positive, got {kernel_width_mm}")
    if smoothing < 0:
        raise ValueError(f"smoothing must be >= 0, got {smoothing}")
    pre = np.eye(4) if pre is None else np.asarray(pre, dtype=float)
    if pre.shape != (4, 4):
        raise ValueError(f"pre must be a 4x4 transform, got shape {pre.shape}")
    rbf = RBFInterpolator(src, dst, kernel="gaussian", epsilon=1.0 / float(kernel_width_mm), degree=1,
                          smoothing=float(smoothing))
    res = np.linalg.norm(rbf(src) - dst, axis=1)
    warp = Warp(rbf, pre, float(kernel_width_mm), float(smoothing), src, dst, res)
    if max_residual_mm is not None:
        p95 = float(np.percentile(res, 95))
        if not p95 <= max_residual_mm:
            extent = float(np.ptp(src, axis=0).max())
            raise ValueError(
                f"the RBF warp misses its feature points (95th percentile residual {p95:.2f} mm > "
                f"{max_residual_mm} mm): a kernel {kernel_width_mm:g} mm wide is too wide for {len(src)} "
                f"points spread over {extent:.0f} mm (numerically singular), or the smoothing is too strong")
    return warp


# --------------------------------------------------------------------------- #
# the skeleton
# --------------------------------------------------------------------------- #
def initial_transform(template: Skeleton, targets: dict[str, Mesh], bones=None) -> np.ndarray:
    """A rough template world -> target world similarity from the bones' centroids.

    The centroid of each bone's template mesh (template world, ``"model"``) is
    matched to the centroid of its target mesh (e.g. LPS), a least-squares
    similarity (Umeyama 1991). It needs no pose knowledge, only three or more
    bones present in both that are not on one line (pelvis, femora, spine,
    sternum, skull...). Limbs that lie differently (the MRI pose) make it rough:
    the per-bone ICPs refine it.

    Parameters
    ----------
    template : Skeleton
    targets : dict of str -> Mesh
    bones : list of str, optional
        Bones to use (default: every bone with a mesh in both).

    Returns
    -------
    ndarray (4, 4)
    """
    names = [n for n in (bones or template.bones) if n in targets and n in template.bones
             and template.bones[n].mesh is not None]
    if len(names) < 3:
        raise ValueError(f"initial_transform needs at least 3 bones in both the template and the targets, "
                         f"got {names}")
    A = np.array([template.world_mesh(n).vertices.mean(0) for n in names])
    B = np.array([targets[n].vertices.mean(0) for n in names])
    if np.linalg.matrix_rank(A - A.mean(0), tol=1.0) < 2:
        raise ValueError("the bones' centroids lie on a line: the rotation about it is undetermined")
    return _kabsch(A, B, scale=True)


def _default_widths(extent: float, spacing: float) -> list[float]:
    """Coarse-to-fine Gaussian widths for a bone of size ``extent`` with feature points ``spacing`` apart.

    The first kernel carries the bone-scale bending, the last the local shape.
    Widths stay within ~1.5-4 feature spacings: wider and the kernel matrix is
    numerically singular (the fit misses its points), narrower and each point
    pulls a spike of its own.
    """
    return [min(0.3 * extent, 4.0 * spacing), min(0.15 * extent, 2.5 * spacing), min(0.08 * extent, 1.5 * spacing)]


def cover_extent(T: np.ndarray, src_world: np.ndarray, target_vertices: np.ndarray, *, tol_mm: float = 2.0,
                 max_stretch: float = 1.12, directions=None) -> tuple[np.ndarray, dict[str, Any] | None]:
    """Stretch an elongated bone's affine along its long axis until it covers its target's extent.

    A long bone's shaft is a cylinder: along its own axis an ICP is held only
    by the bone's ends. Where an end of the extraction is a cut (the search
    ended before the bone did: :func:`bonecap.build_mri.unseen_ends`), the
    pairs there do not count, so nothing holds the template's length at that
    end, and a template shorter than the subject's bone stays short: the
    affine leaves it ending before the extraction does, and the narrow RBF
    kernels of a thin bone then pull out its tip alone. On phantoms the
    fibula's lateral malleolus came out 17-21 mm up its shaft (its head, 21 mm
    down), and with it the ISB origin of the tibia, the fibula and the foot
    (the malleoli's midpoint, :mod:`bonecap.skeleton.isb`), 10-12 mm off.

    The extraction is bone wherever it lies, so its extent along the axis is a
    lower bound on the bone's: the affine is followed by a scaling along the
    axis (anchored at the end that already covers) so that the template reaches
    each end of the target it fell short of by more than ``tol_mm``. Only for
    bones whose extraction does not run on into a neighbour (the caller
    decides: build-subject gives the fibulae, not a femur, whose head's search
    runs into the pelvis); or, with ``directions``, for a bone's marrow.

    Parameters
    ----------
    T : ndarray (4, 4)
        The affine, template world -> target world.
    src_world : ndarray (N, 3)
        The template bone's vertices in template world.
    target_vertices : ndarray (M, 3)
        The target's vertices (target world).
    tol_mm : float
        Shortfalls up to this are left to the RBF.
    max_stretch : float
        A larger stretch is not applied (the target holds something else).
    directions : sequence of ndarray (3,), optional
        Cover only the ends lying toward one of these directions (target world;
        an end whose outward axis makes less than 60 deg with one). None: both.
        With the template's marrow (its inner surface) as ``src_world``, a
        bone whose extraction ends where its marrow does (the ulna, short of
        its styloid) has its marrow stretched to reach it at that end
        (:func:`warp_skeleton`'s ``cover_marrow``).

    Returns
    -------
    T : ndarray (4, 4)
        The covering affine (``T`` itself when nothing is to cover).
    report : dict or None
        ``{"lo_mm", "hi_mm", "stretch"}``: how far each end moved along the
        axis, and the scale; ``{"skipped": why}`` when the stretch was refused;
        None when nothing was short (or the bone is not elongated).
    """
    T = np.asarray(T, float)
    base = _apply(T, _check_points("src_world", src_world))
    tv = _check_points("target_vertices", target_vertices)
    c = base.mean(axis=0)
    u = _long_axis(base)
    if u is None:                    # not a long bone: its ends are not along one axis
        return T, None
    sb = (base - c) @ u
    # the target's vertices near the bone's axis only (a stray piece beside it says nothing of its length)
    radial = np.linalg.norm((base - c) - np.outer(sb, u), axis=1).max()
    tr = tv - c
    st = tr @ u
    near = np.linalg.norm(tr - np.outer(st, u), axis=1) <= 2.0 * radial
    if not near.any():
        return T, None
    st = st[near]
    lo, hi = float(sb.min()), float(sb.max())
    if directions is None:
        lo_ok = hi_ok = True
    else:
        dots = [float(np.asarray(d, float) @ u) / max(float(np.linalg.norm(d)), 1e-12) for d in directions]
        lo_ok, hi_ok = any(x < -0.5 for x in dots), any(x > 0.5 for x in dots)
    new_lo = float(st.min()) if lo_ok and lo - st.min() > tol_mm else lo
    new_hi = float(st.max()) if hi_ok and st.max() - hi > tol_mm else hi
    if new_lo == lo and new_hi == hi:
        return T, None
    a = (new_hi - new_lo) / (hi - lo)
    if a > max_stretch:
        return T, {"skipped": f"the target reaches {a:.2f}x the bone's length along its axis"}
    # p' = p + [(a - 1) s + new_lo - a lo] u, s = (p - c) . u: the ends go to new_lo and new_hi
    S = np.eye(4)
    S[:3, :3] += (a - 1.0) * np.outer(u, u)
    S[:3, 3] = (new_lo - a * lo) * u - (a - 1.0) * u * float(u @ c)
    return S @ T, {"lo_mm": round(lo - new_lo, 2), "hi_mm": round(new_hi - hi, 2), "stretch": round(a, 4)}


#: How far (mm) a bone's warp may end short of the length its ``length_from`` neighbour gives it before it
#: is warped again with that end cut and the neighbour's length (:func:`warp_skeleton`). Both estimates
#: have their spread. On ten phantom radii (seeds 0-2, both protocols) the direct warp ended within 2 mm of
#: the true tip on eight and 7.2-7.3 mm short on two (the template's tip paired with the extraction's end
#: cap, 9-14 mm short of the styloid); the ulna's affine put the radius's end 4.9 mm nearer to 4.2 mm
#: farther than the direct warp where that was right, 6.7 and 8.6 mm farther where it was not.
LENGTH_FROM_MARGIN_MM = 5.5

#: The trimmed ICP's kept fraction for :func:`_warp_one`'s second rigid start (elongated bones).
TRIMMED_START = 0.9
#: How much smaller (fraction) the second start's affine residual must be to replace the first.
SECOND_START_MARGIN = 0.1


def _long_axis(points: np.ndarray) -> np.ndarray | None:
    """A long bone's axis (unit, its principal direction), or None when its principal extent is not at
    least three times the next (:func:`cover_extent`, :func:`_warp_one`)."""
    _, sv, vt = np.linalg.svd(points - points.mean(axis=0), full_matrices=False)
    return vt[0] if sv[0] >= 3.0 * sv[1] else None


def _warp_one(name: str, src_world: np.ndarray, faces: np.ndarray, target: _Surface, init: np.ndarray,
              n_features: int, widths: list[float] | None, smoothing: float, max_residual_mm: float,
              n_icp: int, seed: int, rotation_prior: float, check_pts: np.ndarray,
              cover: bool = False, marrow: np.ndarray | None = None,
              reach: tuple[np.ndarray, list] | None = None) -> dict[str, Any]:
    """rigid ICP -> affine ICP -> coarse-to-fine RBF for one bone; template world -> target world.

    An elongated bone gets a second rigid start, trimmed (:data:`TRIMMED_START`), whose affine
    replaces the first where its residual is :data:`SECOND_START_MARGIN` smaller (report ``flags``).

    ``check_pts`` (template world) are where the Jacobian must stay positive: the bone's outer and
    inner surface vertices. ``cover``: stretch the affine along the bone's axis to its target's extent
    (:func:`cover_extent`); the plain affine ICP stays the affine-only baseline (``T_affine_icp``).
    ``marrow`` (template world, the bone's inner surface's vertices): stretch the affine so that the
    marrow reaches the extraction's cut ends (``target.unseen``; :func:`cover_extent`'s ``directions``).
    ``reach`` ``(points, half-spaces)``: the bone's vertices where a measured neighbour's affine puts them
    (target world) and the half-spaces of the end cut for it (also in ``target.unseen``): stretch the affine
    so that the bone reaches as far as those points toward that cut, and hold it there past the cut
    (``warp_skeleton``'s ``length_from``; the target's other cuts play no part in it)."""
    sub = src_world[np.linspace(0, len(src_world) - 1, min(n_icp, len(src_world))).astype(int)]
    # The rigid stage keeps every pair (no trimming): a long bone placed off along its own axis -- a
    # template shorter or longer than the subject's -- is held there only by its ends, and the pairs at
    # the ends (the target's end sticking out past the template's, the template's past the target's)
    # are the farthest ones, the very pairs a trimmed ICP drops: the shaft, a cylinder, leaves the slide
    # free. Trimmed, phantoms' radii and tibiae stayed 12-28 mm off along their axes. The target is the
    # bone's own extraction (checked, and cut where its search ended): the affine stage trims its outliers.
    T_rigid, _ = rigid_icp(sub, target, init, rotation_prior=rotation_prior, trim=1.0)
    # a slender bone's affine is a rigid motion with two scales (axial_icp): a general one is ill-posed across it
    affine_fit = axial_icp if _slender(src_world) else affine_icp
    T_aff, res_aff = affine_fit(sub, target, T_rigid)
    flags: list[str] = []
    if _long_axis(src_world) is not None:
        # ... but the untrimmed pairs also pull the bone toward whatever its extraction ran on into: a
        # radius's search runs into the carpals (17-26 mm past its styloid on phantoms), and once the rigid
        # fit had slid a radius 8 mm along its axis that way, the affine stretched it onto the carpals
        # (20 mm long, its ISB origin at the styloid with it). The ICP has two minima there; a trimmed
        # start finds the other, and the template lying on its extraction decides between them: the
        # affine's residual (template -> extraction, which the run-on part does not lower), kept only
        # when clearly smaller (SECOND_START_MARGIN), so a bone the untrimmed start holds stays where it was.
        T_rt, _ = rigid_icp(sub, target, init, rotation_prior=rotation_prior, trim=TRIMMED_START)
        # the two starts within 1 mm RMS of each other: the same minimum, nothing to choose
        if np.sqrt(np.mean(np.sum((_apply(T_rt, sub) - _apply(T_rigid, sub)) ** 2, axis=1))) > 1.0:
            T_at, res_t = affine_fit(sub, target, T_rt)
            if np.mean(res_t) < (1.0 - SECOND_START_MARGIN) * np.mean(res_aff):
                flags.append(f"trimmed rigid start kept: affine residual {np.mean(res_aff):.2f} -> "
                             f"{np.mean(res_t):.2f} mm")
                T_rigid, T_aff, res_aff = T_rt, T_at, res_t
    T_icp, covered = T_aff, None
    if cover:
        T_aff, covered = cover_extent(T_aff, src_world, target.mesh.vertices)
    if marrow is not None and len(target.unseen):
        # at a cut end the extraction is the marrow's last sections: the template's marrow must reach them
        T_aff, covered_m = cover_extent(T_aff, marrow, target.mesh.vertices, directions=[n for n, _ in target.unseen])
        if covered_m is not None:
            covered = {**(covered or {}), "marrow": covered_m}
    # the length cut's half-spaces alone (the target's other cuts, a search's end, play no part here)
    length_cut = [] if reach is None else _check_unseen(reach[1])
    if length_cut:
        # past a cut nothing of the extraction holds the bone's length but the affine's axial scale, which
        # the extraction's short end sets: the neighbour's affine says how far the bone goes on there
        T_aff, covered_n = cover_extent(T_aff, src_world, reach[0], directions=[n for n, _ in length_cut])
        if covered_n is not None:
            covered = {**(covered or {}), "neighbour": covered_n}
    base = Mesh(_apply(T_aff, src_world), faces, "target")  # the template after the affine ("A-space")
    extent = float(np.ptp(base.vertices, axis=0).max())
    spacing = float(np.sqrt(base.to_trimesh().area / max(n_features, 8)))
    widths = list(widths) if widths else _default_widths(extent, spacing)
    held = np.zeros((0, 3))
    if covered is not None and "neighbour" in covered:
        # The RBF's own linear part is fitted to the feature points, all short of the cut: it re-takes the
        # axial scale the extraction's short end sets, and its extrapolation past the cut pulled a tip the
        # neighbour's stretch had placed 7 mm back (the demo subject's left radius, cut and stretched). Past
        # the cut the stretched affine is the estimate: the bone's vertices there, about a feature spacing
        # apart (one per cube of that size), are held where it puts them. (Not when the cut affine reached
        # the neighbour's length by itself: on the two radii where that was so, holding moved the wrist's
        # centre 0.4 mm farther off and the styloid 0.5 mm, against the RBF's extrapolation.)
        past = base.vertices[_past(base.vertices, length_cut)]
        _, first = np.unique(np.floor(past / spacing).astype(np.int64), axis=0, return_index=True)
        held = past[np.sort(first)]
        covered["neighbour"]["held_past_cut"] = int(len(held))
    current = base
    warp = None
    for it, w in enumerate(widths):
        faces_i, bary, dst = _correspondences(current, target, n_features, 60.0, seed + 7 * it)
        src = np.einsum("nk,nkd->nd", bary, base.vertices[base.faces[faces_i]])
        src, dst = np.concatenate([src, held]), np.concatenate([dst, held])
        # a fold comes from a few contradicting correspondences (a neck or a crest the affine left
        # apart): more smoothing lets the fit pass them by; the residual check still guards the fit
        cand, why = None, ""
        for sm in (smoothing, 10.0 * smoothing):
            try:
                c = fit_warp(src, dst, kernel_width_mm=w, smoothing=sm, pre=T_aff, max_residual_mm=max_residual_mm)
            except ValueError as e:
                why = str(e)
                continue
            det = c.min_jacobian_det(check_pts)
            if det > 0.05:
                cand = c
                break
            why = f"folds (min Jacobian det {det:.3f})"
        if cand is None:
            flags.append(f"width {w:.0f} mm not used: {why}")
            continue
        warp = cand
        current = Mesh(warp(src_world), faces, "target")
    return {"T_rigid": T_rigid, "T_affine": T_aff, "T_affine_icp": T_icp, "covered": covered, "warp": warp,
            "affine_residual_mm": res_aff, "flags": flags, "n_features": 0 if warp is None else len(warp.src)}


def _implausible(start: np.ndarray, r: dict[str, Any], max_turn_deg: float, max_res_mm: float,
                 centre: np.ndarray | None = None, max_shift_mm: float = np.inf) -> str:
    """Why a bone's ICP result cannot be the bone (empty string when it can)."""
    if centre is not None and np.isfinite(max_shift_mm):
        shift = float(np.linalg.norm(_apply(r["T_rigid"], centre[None])[0] - _apply(np.asarray(start, float),
                                                                                  centre[None])[0]))
        if shift > max_shift_mm:
            return f"the rigid fit moved it {shift:.0f} mm from its placed pose"
    R0 = _polar_rotation(np.asarray(start, float)[:3, :3])
    dR = R0.T @ r["T_rigid"][:3, :3]
    turn = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    if turn > max_turn_deg:
        return f"the rigid fit turned it {turn:.0f} deg from its placed pose"
    sv = np.linalg.svd(r["T_affine"][:3, :3] @ np.linalg.inv(np.asarray(start, float)[:3, :3]), compute_uv=False)
    if sv.max() > 1.6 or sv.min() < 0.6:
        return f"the affine fit stretched it by {sv.min():.2f}-{sv.max():.2f}"
    res = float(np.mean(r["affine_residual_mm"]))
    if res > max_res_mm:
        return f"affine residual {res:.1f} mm > {max_res_mm:g} mm"
    return ""


def warp_skeleton(template: Skeleton, targets: dict[str, Mesh], *, init=None, n_features: int = 600,
                  kernel_widths_mm=None, smoothing: float = 1e-3, max_residual_mm: float = 1.5,
                  rotation_prior: float = 1e-3, world: str = "lps", seed: int = 0,
                  max_turn_deg: float = 45.0, max_affine_residual_mm: float = 6.0,
                  start_from: str = "ancestor", max_shift_mm: float = np.inf,
                  rigid_bodies=None, fixed=None, unseen=None,
                  refine_chain=None, cover=(), cover_marrow=(),
                  length_from=None) -> tuple[Skeleton, dict[str, Any]]:
    """The personal skeleton: every template bone warped onto its target (affine + Gaussian RBF).

    Per bone with a target mesh, in parent-before-child order: rigid ICP
    (initialised from the parent's rigid result and the template's relative
    pose, or from ``init`` for the root; a long bone also from a trimmed start,
    the one whose affine lies closer on its target kept), affine ICP, then the RBF warp fitted
    to feature points (:func:`feature_points`, both ways) coarse to fine
    (kernel widths 0.3, 0.15 and 0.08 x the bone's size, capped at 4, 2.5 and
    1.5 feature-point spacings; correspondences recomputed from the previous
    warp each time). A width whose fit misses its feature points or folds the
    bone (Jacobian determinant <= 0.05 at a vertex of its outer or inner
    surface, even with 10x the smoothing) is not used: the previous warp stays
    (or the affine, if no width passed), and the report's ``flags`` say so.

    Outputs per bone:

    - **mesh** (and ``inner_mesh``) and **landmarks**: the warp of the template's.
    - **bone_to_world**: ISB orientation kept -- the rotation is the polar
      rotation of the affine ICP's linear part times the template bone's
      rotation; the origin is the warped template origin. Then, where the
      template's frame is defined by landmarks (femur, tibia and the foot,
      humerus, ulna, radius: :mod:`bonecap.skeleton.isb`), its origin is
      rebuilt from the warped landmarks (report: ``frame_rebuilt``, the
      change in mm).
    - **joint centres**: a joint shared by several bones (same name, or a
      side-suffixed name like ``sacroiliac_r``/``sacroiliac``, at the same
      template place) gets **one** position: the weighted mean of where the
      warps of the bones that have their own target put it, weights
      ``1 / (5 mm + d)^2`` with ``d`` the joint centre's distance to that
      bone's template surface (a warp is reliable near its own bone: both
      sides of a hip or knee count about equally, while a sacrum's
      extrapolation to the pubic symphysis hardly counts against the hip
      bones'). Bones carried by neighbours take it as it is. Joint axes
      follow each bone's Jacobian.

    Bones without a target (missed or broken by the MRI) are carried by their
    neighbours: an affine fitted to the warped joint centres they share with
    bones that have a target; with fewer than 4 such points, the nearest
    warped relative's affine corrected onto them (3 points: a rigid fit; 2:
    the smallest rotation turning the joint-to-joint direction and a stretch
    to its length; 1: a shift), so they stay joined.

    Parameters
    ----------
    template : Skeleton
        World ``"model"`` (or any); meshes in bone frames.
    targets : dict of str -> Mesh
        Bone name -> its surface in the target world (LPS mm).
    init : ndarray (4, 4), optional
        Rough template world -> target world transform (from matching a few
        joint centres or :func:`initial_transform`; default: that).
    n_features : int
        Feature points drawn per bone and refinement step (<= 1-2 thousand).
    kernel_widths_mm : sequence of float, optional
        The coarse-to-fine widths for every bone (default: per bone size).
    smoothing : float
        RBF smoothing (see :func:`fit_warp`).
    max_residual_mm : float
        Residual check of every fit (95th percentile, mm).
    rotation_prior : float
        See :func:`rigid_icp`: keeps the spin a surface leaves undecided (a
        fibula about its axis) at the parent-carried start (bones started from
        ``init``, with no warped ancestor, get none: ``init`` is rough).
    world : str
        Name of the target world, written to the result's ``world``.
    seed : int
        Seed of the surface sampling.
    max_turn_deg, max_affine_residual_mm : float
        A bone whose rigid fit turns it more than ``max_turn_deg`` from its
        start, whose affine stretches it below 0.6 or above 1.6, or whose
        affine residual exceeds ``max_affine_residual_mm`` is not warped onto
        that target (it is probably another bone, or two merged) and is
        carried by its neighbours instead; the report says why.
    max_shift_mm : float
        Likewise for a rigid fit that moves the bone's centre farther than this.
    rigid_bodies : sequence of sequence of str, optional
        Groups of bones rigidly attached to each other (default: the
        template's ``metadata["rigid_bodies"]``, the pelvis for bonecap's
        template). A group none of whose bones has a target is carried as one
        rigid body onto all the joints it shares with the others.
    fixed : dict of str -> ndarray (4, 4), optional
        Bones placed by other means, each with its template world -> target
        world map (build-subject: the skull and mandible fitted to the head's
        skin). They are carried with it, and their joints anchor the chain of
        carried bones below them: the chain (the vertebrae between the skull
        and the pelvis carried onto the hips) is carried up from its anchored
        end, then the mismatch at the fixed bone is spread along it linearly
        in arc length over its joints and the chain is carried again, so a
        spine longer or shorter than the template's proportions meets both ends.
    refine_chain : callable, optional
        ``refine_chain(joint_bones, points) -> (points or None, report)``: given
        each joint of such a chain (bottom to top) as the names of the bones
        it joins and the joints where the linear spread put them (world),
        returns better places for them (build-subject: the discs the MRI shows,
        :func:`bonecap.segmentation.spine.spine_levels`), or None to keep the
        spread. The first and last joints stay with the anchor and the fixed
        bone. Its reports are the warp report's ``chains``.
    cover : collection of str
        Bones whose extraction's extent along their long axis bounds their
        length from below (its ends do not run on into a neighbour): their
        affine is stretched along the axis to cover it before the RBF
        (:func:`cover_extent`; report: ``covered``). build-subject gives the
        fibulae.
    cover_marrow : collection of str
        Bones whose extraction ends where their marrow does at their cut ends
        (``unseen``): the template's marrow (its inner surface) is stretched
        along the axis to reach the extraction there (report: ``covered``'s
        ``marrow``). build-subject gives the ulnae, whose styloids hold no
        marrow.
    length_from : dict of str -> (str, sequence of (normal (3,), offset)), optional
        Bone -> (a neighbour with its own target, half-spaces): the bone's
        extraction may end short of the bone past those half-spaces (an end
        the slice rules do not resolve), and the neighbour's affine applied
        to the template bone (the template's proportion to the neighbour)
        says how far it goes on. The
        bone is warped as usual; where its warp then ends more than
        :data:`LENGTH_FROM_MARGIN_MM` short of the neighbour's (along its axis,
        toward the half-spaces), it is warped again with that end cut (the
        half-spaces added to ``unseen``), its affine stretched to the
        neighbour's length there where it falls short of it
        (:func:`cover_extent`) and then its vertices past the cut held where
        that affine puts them. Report: ``length_from``
        (``neighbour``, ``short_mm``, ``used``) and, when used, ``covered``'s
        ``neighbour`` (the stretch, when the cut bone's affine fell short of
        the neighbour's length by more than :func:`cover_extent`'s 2 mm, and
        ``held_past_cut``, the vertices then held). Only where the neighbour's
        own warp is plausible.
        build-subject gives each radius its ulna (:data:`bonecap.build_mri.LENGTH_FROM`).
    start_from : {"ancestor", "placed"}
        Where each bone's rigid ICP starts: from its nearest warped ancestor's
        result (a template in another pose than the targets), or from
        ``init`` itself for every bone (a template already placed bone by
        bone near the targets, as build-subject does). With ``"placed"``, a
        bone carried by its neighbours that would move or turn beyond the
        own targets' bounds (``max_shift_mm``, ``max_turn_deg``) is kept where
        it was placed (source "placed template"); a bone hanging below an own
        target through bones without one (a foot below its tibia) starts from
        that target's rigid correction, as it was placed with it; when every joint it is
        carried onto was placed by an own target, by a bone carried onto
        such joints alone (down a chain), or by the chain between a fixed
        bone and its anchor (spread, or put where ``refine_chain`` says), the
        shift bound is twice ``max_shift_mm``: those joints passed the bounds
        themselves or were measured, and a long bone's end moves farther than
        its centre.
    unseen : dict of str -> sequence of (normal (3,), offset), optional
        Per bone, half-spaces of the target world where its target was not
        looked for (``normal . p > offset``): a slice-wise search that ended
        short of the bone's end leaves a cut there, which the ICPs and the
        feature points must not take for the bone's end (it would shrink the
        bone to it); the template's part beyond is extrapolated by the
        affine and the RBF (see :func:`rigid_icp`).

    Returns
    -------
    skeleton : Skeleton
        ``world=world``; same bones, parents and names.
    report : dict
        ``bones``: per bone ``source`` ("own target" / "neighbours"),
        ``n_features``, ``residual_mean_mm``/``residual_max_mm`` (at the feature
        points), ``min_jacobian_det`` (over the bone's vertices),
        ``affine_residual_mean_mm`` (template after the affine ICP to target),
        ``kernel_width_mm``, ``flags``, ``unseen`` (the half-spaces given, as
        normal and offset), ``covered`` (:func:`cover_extent`'s report, when it
        stretched); ``transforms``: per bone the affine ICP (template world ->
        target world, the affine-only baseline; without ``cover``'s stretch);
        ``seconds``.

    References
    ----------
    Kojima et al. (RBFT); Besl & McKay 1992; Higham 1986.
    """
    if not isinstance(template, Skeleton):
        raise ValueError(f"template must be a Skeleton, got {type(template).__name__}")
    unknown = sorted(set(targets) - set(template.bones))
    if unknown:
        raise ValueError(f"targets name bones that are not in the template: {unknown}")
    for n, m in targets.items():
        _check_mesh(f"target {n!r}", m)
    own = [n for n in template.bones if n in targets and template.bones[n].mesh is not None]
    if not own:
        raise ValueError("no template bone with a mesh has a target: nothing to warp onto")
    t_start = time.perf_counter()
    if start_from not in ("ancestor", "placed"):
        raise ValueError(f"start_from must be 'ancestor' or 'placed', got {start_from!r}")
    if init is None:
        init = initial_transform(template, targets) if len(own) >= 3 else np.eye(4)
    init = np.asarray(init, dtype=float)
    if init.shape != (4, 4):
        raise ValueError(f"init must be a 4x4 transform, got {init.shape}")

    cuts = {n: _check_unseen(h) for n, h in (unseen or {}).items()}
    unknown = sorted(set(cuts) - set(targets))
    if unknown:
        raise ValueError(f"unseen names bones without a target: {unknown}")
    results: dict[str, dict[str, Any]] = {}
    rejected: dict[str, str] = {}
    rigid_of: dict[str, np.ndarray] = {}
    index = {name: i for i, name in enumerate(template.bones)}

    length_from = {b: (nb, _check_unseen(h)) for b, (nb, h) in (length_from or {}).items()}
    named = {b for b, (nb, _) in length_from.items()} | {nb for nb, _ in length_from.values()}
    unknown = sorted(n for n in named if n not in template.bones)
    if unknown:
        raise ValueError(f"length_from names bones that are not in the template: {unknown}")
    if any(not h for _, h in length_from.values()):
        raise ValueError("length_from needs at least one half-space per bone (the end it may fall short at)")

    def template_vertices(name: str) -> np.ndarray:
        bone = template.bones[name]
        return _apply(bone.bone_to_world, bone.mesh.vertices)

    def mapped(r: dict[str, Any], p: np.ndarray) -> np.ndarray:
        """Points (template world) through a bone's warp result: its RBF, or its affine where none passed."""
        return r["warp"](p) if r["warp"] is not None else _apply(r["T_affine"], p)

    def why_not(name: str, start: np.ndarray, r: dict[str, Any]) -> str:
        """Why the bone's warp ``r`` from ``start`` cannot be the bone (:func:`_implausible`; '' when it can)."""
        return _implausible(start, r, max_turn_deg, max_affine_residual_mm, template_vertices(name).mean(axis=0),
                            max_shift_mm)

    def reach_of(name: str, done_so_far: dict[str, dict[str, Any]],
                 start: np.ndarray | None = None) -> np.ndarray | None:
        """The bone's template vertices where its ``length_from`` neighbour's affine puts them (or None);
        ``start``: the neighbour's, to check its result (results not checked yet)."""
        nb = length_from[name][0] if name in length_from else None
        r = done_so_far.get(nb)
        if r is None or (start is not None and why_not(nb, start, r)):
            return None
        # the neighbour's affine, not its RBF: the template's proportion, without the local corrections of
        # the neighbour's own surface (whose kernels reach a few cm across to this bone)
        return _apply(r["T_affine"], template_vertices(name))

    def short_of(name: str, r: dict[str, Any], reach: np.ndarray) -> float:
        """How far (mm) the bone's warp ``r`` ends short of ``reach`` along its axis, toward its length cut."""
        got = mapped(r, template_vertices(name))
        u = _long_axis(reach)
        if u is None:
            return 0.0
        # each half-space's end (a bone cut at both ends: the larger shortfall)
        return max(float((reach @ v).max() - (got @ v).max())
                   for v in (u if u @ n >= 0 else -u for n, _ in length_from[name][1]))

    def length_check(name: str, r: dict[str, Any], done_so_far: dict[str, dict[str, Any]],
                     start: np.ndarray | None) -> tuple[np.ndarray | None, dict[str, Any]]:
        """``(reach, report)``: the neighbour's reach when the bone's warp falls short of it, else None."""
        nb = length_from[name][0]
        reach = reach_of(name, done_so_far, start)
        if reach is None:
            return None, {"neighbour": nb, "short_mm": None, "used": False,
                          "why": f"no plausible warp of {nb} (no target, rejected, or not warped before {name})"}
        short = short_of(name, r, reach)
        rep = {"neighbour": nb, "short_mm": round(short, 2), "used": short > LENGTH_FROM_MARGIN_MM}
        return ((reach, length_from[name][1]) if rep["used"] else None), rep

    def warp_bone(name: str, start: np.ndarray, prior: float,
                  reach: tuple[np.ndarray, list] | None = None) -> dict[str, Any]:
        """One bone's warp; with ``reach`` (:func:`length_check`'s), its ``length_from`` end cut and stretched to it."""
        bone = template.bones[name]
        src_world = template_vertices(name)
        inner = None if bone.inner_mesh is None else _apply(bone.bone_to_world, bone.inner_mesh.vertices)
        check = src_world if inner is None else np.concatenate([src_world, inner])
        # every other vertex while fitting (spacing ~3-5 mm, below the narrowest kernel); the report
        # checks them all
        check = check[::2]
        unseen_here = list(cuts.get(name, ())) + (list(reach[1]) if reach is not None else [])
        return _warp_one(name, src_world, bone.mesh.faces, _Surface(targets[name], unseen_here), start,
                         n_features,
                         kernel_widths_mm, smoothing, max_residual_mm, 800, seed + 101 * index[name], prior,
                         check, cover=name in cover, marrow=inner if name in cover_marrow else None,
                         reach=reach)

    checks: dict[str, tuple[tuple[np.ndarray, list] | None, dict[str, Any]]] = {}

    def checked(name: str, first: dict[str, Any], again: dict[str, Any], start: np.ndarray) -> dict[str, Any]:
        """The warp with the length cut, ``again``, unless it is not plausibly the bone: then ``first``."""
        why = why_not(name, start, again)
        if not why:
            return again
        checks[name][1].update(used=False, why=f"the warp with the cut end was rejected ({why}); the first kept")
        return first

    if start_from == "placed":
        # a template already placed bone by bone (build-subject poses its limbs toward the MRI's)
        # starts every bone where it is -- an ancestor's ICP error must not tilt its children -- so
        # the bones are independent: warped in worker processes, the largest first so that the
        # workers finish together (each bone's sampling seed is its own: the same result in any order)
        todo = sorted(own, key=lambda n: -len(template.bones[n].mesh.vertices))
        done = dict(zip(todo, fork_map(lambda n: warp_bone(n, init, rotation_prior), todo)))
        # a bone that ended short of its length_from neighbour's length: again, its end cut, in a second round
        checks = {n: length_check(n, done[n], done, init) for n in own if n in length_from}
        again = [n for n, (reach, _) in checks.items() if reach is not None]
        for n, r2 in zip(again, fork_map(lambda n: warp_bone(n, init, rotation_prior, checks[n][0]), again)):
            done[n] = checked(n, done[n], r2, init)
    for name, bone in template.bones.items():
        if name not in targets or bone.mesh is None:
            continue
        if start_from == "placed":
            start, r = init, done[name]
        else:
            # the nearest ancestor with a rigid result carries the template's relative pose (a child
            # of a rotated parent starts rotated with it: limbs posed otherwise than the template
            # converge)
            a = bone.parent
            while a is not None and a not in rigid_of:
                a = template.bones[a].parent
            start = init if a is None else rigid_of[a]
            r = warp_bone(name, start, rotation_prior if a is not None else 0.0)
            if name in length_from:
                # (results holds the plausible warps only; a neighbour later in the template's order is not used)
                checks[name] = length_check(name, r, results, None)
                if checks[name][0] is not None:
                    r = checked(name, r, warp_bone(name, start, rotation_prior if a is not None else 0.0,
                                                   checks[name][0]), start)
        # a target that only fits the bone turned over or stretched is not this
        # bone (two bones merged, a neighbour taken for it): carry the bone from
        # its neighbours instead of warping it onto the wrong shape
        why = why_not(name, start, r)
        if why:
            rejected[name] = why
            continue
        results[name] = r
        rigid_of[name] = r["T_rigid"]

    def own_map(name: str, p: np.ndarray) -> np.ndarray:
        return mapped(results[name], p)

    # joint centres: one position per joint
    groups = joint_groups(template)
    joint_pos: dict[tuple[str, str], np.ndarray] = {}
    trees: dict[str, cKDTree] = {}
    for g in groups:
        own_g = [(b, k) for b, k in g if b in results]
        if not own_g:
            continue
        pts, wts = [], []
        for b, k in own_g:
            c0 = template.bones[b].landmark_in_world(k)
            pts.append(own_map(b, c0[None])[0])
            if b not in trees:
                trees[b] = cKDTree(_apply(template.bones[b].bone_to_world, template.bones[b].mesh.vertices))
            # a warp is trustworthy near its bone's surface: weight by 1 / (5 mm + distance)^2, so a
            # pubic symphysis listed by the sacrum comes from the hip bones that reach it
            wts.append(1.0 / (5.0 + trees[b].query(c0)[0]) ** 2)
        c = np.average(np.array(pts), axis=0, weights=np.array(wts))
        for e in g:
            joint_pos[e] = c

    # bones without a target: an affine from the joints they share with warped bones. A rigid body
    # of several bones (the pelvis: sacrum and both hip bones) none of which has a target is carried
    # as one, onto all the joints it shares with the rest: carried bone by bone, the sacrum (no warped
    # neighbour) stayed where it was placed and pinned each hip bone's sacroiliac joint, so each hip
    # bone turned about it toward its femur's hip centre (10 deg off on a phantom)
    if rigid_bodies is None:
        rigid_bodies = template.metadata.get("rigid_bodies", [])
    body_of: dict[str, tuple[str, ...]] = {}
    for g in rigid_bodies:
        g = tuple(b for b in g if b in template.bones)
        if len(g) > 1 and not any(b in results for b in g):
            for b in g:
                body_of[b] = g
    fixed = {} if fixed is None else {n: np.asarray(T, dtype=float) for n, T in fixed.items()}
    for n, T in fixed.items():
        if n not in template.bones or T.shape != (4, 4):
            raise ValueError(f"fixed: {n!r} must be a template bone with a 4x4 transform")
        if n in results:
            raise ValueError(f"fixed: {n!r} has its own target; a bone is either warped or fixed")
    known = dict(joint_pos)                   # joints placed by warped bones

    group_of = {e: g for g in groups for e in g}

    def follow(b: str, M: np.ndarray, joint_pos: dict) -> None:
        """Bone ``b`` moved by ``M``: its joints not placed yet, and every bone's listing of them, go with it."""
        for k in template.bones[b].joint_centres:
            if (b, k) not in joint_pos:
                p = _apply(M, template.bones[b].landmark_in_world(k)[None])[0]
                for e in group_of[(b, k)]:
                    joint_pos.setdefault(e, p)

    def carry_all(joint_pos: dict, keep: frozenset = frozenset(), trust: frozenset = frozenset()
                  ) -> tuple[dict[str, np.ndarray], list[str]]:
        """Every bone without a result carried (or fixed), in template order; fills ``joint_pos``.
        Bones in ``keep`` keep their carried rotation (moved and stretched onto their joints only);
        joints in ``trust`` are trusted as own targets' are."""
        carried: dict[str, np.ndarray] = {}
        kept_placed: list[str] = []
        # joints placed by own targets, or by bones carried onto such joints alone (down a chain: the talus
        # onto its tibia's ankle, then the calcaneus onto the talus's subtalar joint)
        trusted = set(known) | set(trust)
        for name, bone in template.bones.items():
            if name in results or name in carried:
                continue
            if name in fixed:                 # placed by other means (the skull on the head's skin)
                carried[name] = fixed[name]
                follow(name, fixed[name], joint_pos)
                continue
            body = body_of.get(name, (name,))
            A, B, own = [], [], []
            from_warped = True          # every joint it is carried onto is trusted
            for b in body:
                for k in template.bones[b].joint_centres:
                    if (b, k) in joint_pos:
                        A.append(template.bones[b].landmark_in_world(k))
                        B.append(joint_pos[(b, k)])
                        from_warped &= (b, k) in trusted
                        own.append((b, k) in known)
            # the start, corrected below onto its warped joints: a placed template's bone where it was placed,
            # but a bone hanging below an own target (a foot below its tibia, a hand below its radius) was
            # placed with it (the limbs are re-posed as subtrees) and shares its placement's error: it turns
            # with the ancestor's rigid correction, keeping the template's joint angle, where its one joint
            # would only move it (the warped tibiae turned 2-3 deg from their placement on phantoms, and the
            # feet, left as placed, lay that far from their shanks' frames)
            anc = _warped_ancestor(template, name, results, fixed) if start_from == "placed" and len(body) == 1 \
                else None
            if anc is not None:
                M = np.asarray(results[anc]["T_rigid"], float)
            elif start_from == "placed":
                M = init
            else:
                rel = _nearest_relative(template, name, results, carried)
                M = init if rel is None else rel
            # two joints say little of a bone's turn when they lie close together on it: less than a
            # third of its size apart (a scapula's two, 35-40 mm on 150), it is only moved onto them
            ext = [_apply(template.bones[b].bone_to_world, template.bones[b].mesh.vertices)
                   for b in body if template.bones[b].mesh is not None]
            size = float(np.linalg.norm(np.ptp(np.concatenate(ext), axis=0))) if ext else 0.0
            keep_rot = (len(body) > 1 and start_from == "placed") or name in keep
            M = _carry(M, np.array(A).reshape(-1, 3), np.array(B).reshape(-1, 3), rigid=len(body) > 1,
                       keep_rotation=keep_rot, min_baseline_mm=0.0 if keep_rot else size / 3.0,
                       pin=np.array(own, bool))
            if start_from == "placed" and any(template.bones[b].mesh is not None for b in body):
                # joints borrowed from badly warped neighbours must not throw a placed
                # bone across the body: beyond the same bounds as an own target, keep it placed
                fake = {"T_rigid": np.eye(4), "T_affine": M, "affine_residual_mm": np.zeros(1)}
                c = np.concatenate(ext).mean(axis=0)
                moved = float(np.linalg.norm(_apply(M, c[None])[0] - _apply(init, c[None])[0]))
                R_M = _polar_rotation(M[:3, :3]) @ _polar_rotation(init[:3, :3]).T
                turn = float(np.degrees(np.arccos(np.clip((np.trace(R_M) - 1) / 2, -1, 1))))
                # trusted joints (own targets passed these bounds themselves) are followed twice as far:
                # a talus placed 45 mm off its warped tibia's ankle (a phantom whose shank is longer than
                # the placement's) was kept there, and its foot with it, 45 mm from the ankle
                limit = max_shift_mm * (2.0 if A and from_warped else 1.0)
                if moved > limit or turn > max_turn_deg or _implausible(init, fake, 180.0, np.inf):
                    M = np.asarray(init, float).copy()
                    kept_placed.extend(body)
                    from_warped = False
            for b in body:
                carried[b] = M
            # the joints it shares only with other carried bones follow it
            before = set(joint_pos)
            for b in body:
                follow(b, M, joint_pos)
            if A and from_warped:
                trusted.update(set(joint_pos) - before)
        return carried, kept_placed

    carried, kept_placed = carry_all(joint_pos)
    # A chain of carried bones between a fixed bone and the first anchored ancestor (the cervical,
    # thoracic and lumbar vertebrae between the skull fitted to the head's skin and the pelvis carried
    # onto the hips) was carried up from the bottom alone, with the template's proportions: its top
    # missed the fixed bone by the person's difference in spine length. The mismatch is spread along
    # the chain (linearly in arc length over its joints) and the bones are carried again, keeping the
    # rotations they were carried with: the spread is a smooth shift, and turning each vertebra onto
    # its shifted joints tilted them by its slope (0.2 deg on a phantom whose vertebrae were right).
    chains = _chains_to_fixed(template, fixed, results, body_of, known, group_of)
    chain_reports = []
    if chains:
        seeded = dict(known)
        # The chain's joints lie between two placed ends (the pelvis carried onto the hips, the skull on
        # the head's skin), spread between them or put on the discs the MRI shows: trusted as own targets'
        # joints are. Untrusted, a lumbar spine 26 mm shorter than the template's spread (a phantom's,
        # the chain's discs all matched) moved its vertebrae more than the 40 mm bound from where the
        # template was placed, and l5-t7 were kept there, 29-32 mm from the truth, while t6-t1 above
        # them, moved less, lay within 0.4-2.6 mm.
        chain_joints: set = set()
        for chain, _ in chains:
            pts = np.array([joint_pos[g[0]] for g in chain])          # as carried: bottom to top
            top_bone, top_joint = next((b, k) for b, k in chain[-1] if b in fixed)
            top = _apply(fixed[top_bone], template.bones[top_bone].landmark_in_world(top_joint)[None])[0]
            arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
            frac = arc / max(arc[-1], 1e-9)
            spread = pts + frac[:, None] * (top - pts[-1])
            if refine_chain is not None:
                # the image's own word on where the joints between the ends lie (the discs the MRI shows)
                moved, rep = refine_chain([sorted({b for b, _ in g}) for g in chain], spread)
                chain_reports.append({"joints": [g[0][1] for g in chain], **rep})
                if moved is not None:
                    spread[1:-1] = np.asarray(moved, float)[1:-1]
            # the bottom joint is left to its anchor (carried again the same way); the others move
            for g, p in zip(chain[1:], spread[1:]):
                for e in g:
                    seeded[e] = p
                    chain_joints.add(e)
        joint_pos = seeded
        carried, kept_placed = carry_all(joint_pos, frozenset(b for _, bones in chains for b in bones),
                                         frozenset(chain_joints))

    def bone_map(name: str, p: np.ndarray) -> np.ndarray:
        return own_map(name, p) if name in results else _apply(carried[name], p)

    def bone_affine(name: str) -> np.ndarray:
        return results[name]["T_affine"] if name in results else carried[name]

    def bone_rotation(name: str) -> np.ndarray:
        # own target: the rigid ICP's rotation (the affine's polar rotation can pick up a spin the shear
        # trades for); carried: the polar rotation of the fitted affine
        return results[name]["T_rigid"][:3, :3] if name in results else _polar_rotation(carried[name][:3, :3])

    new_bones: dict[str, Bone] = {}
    report_bones: dict[str, Any] = {}
    for name, bone in template.bones.items():
        A = bone_affine(name)
        R = bone_rotation(name) @ bone.bone_to_world[:3, :3]
        o = bone_map(name, bone.bone_to_world[:3, 3][None])[0]
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, o
        Tinv = np.linalg.inv(T)

        def to_bone(p_world: np.ndarray) -> np.ndarray:
            return _apply(Tinv, p_world)

        def mp(m: Mesh | None) -> Mesh | None:
            if m is None:
                return None
            return Mesh(to_bone(bone_map(name, _apply(bone.bone_to_world, m.vertices))), m.faces.copy(), name)

        jc = {}
        for k, v in bone.joint_centres.items():
            p = joint_pos.get((name, k))
            if p is None:
                p = bone_map(name, _apply(bone.bone_to_world, v[None]))[0]
            jc[k] = to_bone(p[None])[0]
        lm = {k: to_bone(bone_map(name, _apply(bone.bone_to_world, v[None])))[0] for k, v in bone.landmarks.items()}
        axes = {}
        for k, ax in bone.joint_axes.items():
            c = _apply(bone.bone_to_world, (bone.joint_centres.get(k, np.zeros(3)))[None])
            J = results[name]["warp"].jacobian(c)[0] if name in results and results[name]["warp"] is not None \
                else A[:3, :3]
            axes[k] = R.T @ (J @ (bone.bone_to_world[:3, :3] @ ax))
        meta = dict(bone.metadata)
        meta["personalized"] = "own target" if name in results else "fixed" if name in fixed else "neighbours"
        new_bones[name] = Bone(name=name, parent=bone.parent, mesh=mp(bone.mesh), bone_to_world=T,
                               joint_centres=jc, joint_axes=axes, landmarks=lm, inner_mesh=mp(bone.inner_mesh),
                               metadata=meta)
        if name in results:
            r = results[name]
            w = r["warp"]
            verts = _apply(bone.bone_to_world, bone.mesh.vertices)
            if bone.inner_mesh is not None:
                verts = np.concatenate([verts, _apply(bone.bone_to_world, bone.inner_mesh.vertices)])
            report_bones[name] = {
                "source": "own target",
                "n_features": r["n_features"],
                "residual_mean_mm": float(w.residual_mm.mean()) if w is not None else None,
                "residual_max_mm": float(w.residual_mm.max()) if w is not None else None,
                "min_jacobian_det": float(w.min_jacobian_det(verts)) if w is not None
                else float(np.linalg.det(A[:3, :3])),
                "affine_residual_mean_mm": float(r["affine_residual_mm"].mean()),
                "kernel_width_mm": w.kernel_width_mm if w is not None else None,
                "flags": r["flags"],
            }
            if r.get("covered"):
                report_bones[name]["covered"] = r["covered"]
            if name in checks:
                report_bones[name]["length_from"] = checks[name][1]
            cut_here = list(cuts.get(name, ())) + (list(length_from[name][1]) if checks.get(name, (None, {}))[1]
                                                   .get("used") else [])
            if cut_here:
                report_bones[name]["unseen"] = [[*np.round(n, 4).tolist(), round(c, 2)] for n, c in cut_here]
        else:
            report_bones[name] = {"source": ("fixed (given)" if name in fixed else
                                             "placed template (neighbours' joints out of bounds)"
                                             if name in kept_placed else "neighbours")
                                  + (f" (own target rejected: {rejected[name]})" if name in rejected else ""),
                                  "n_features": 0, "residual_mean_mm": None,
                                  "residual_max_mm": None, "min_jacobian_det": float(np.linalg.det(A[:3, :3])),
                                  "affine_residual_mean_mm": None, "kernel_width_mm": None, "flags": []}
    meta = dict(template.metadata)
    meta["personalized"] = {"method": "rigid ICP, affine ICP, Gaussian RBF (Kojima et al. RBFT)",
                            "n_features": n_features, "smoothing": smoothing, "init": init.tolist()}
    out = Skeleton(bones=new_bones, world=world, metadata=meta)
    # the frames were carried as rigid bodies; origins rebuilt from the warped landmarks mean what the
    # template's mean (the tibia's origin, between tibia and fibula, drifted by 15-25 mm otherwise)
    out, reframed = refresh_isb_frames(out, template)
    for name, change in reframed.items():
        report_bones[name]["frame_rebuilt"] = {k: round(v, 3) for k, v in change.items()}
    report = {"bones": report_bones,
              # the affine-only baseline: a bone's plain affine ICP (before cover_extent's stretch)
              "transforms": {n: (results[n].get("T_affine_icp", results[n]["T_affine"]) if n in results
                                 else bone_affine(n)).tolist() for n in template.bones},
              "init": init.tolist(), "seconds": time.perf_counter() - t_start}
    if chain_reports:
        report["chains"] = chain_reports
    return out, report


def _carry(M: np.ndarray, A: np.ndarray, B: np.ndarray, rigid: bool = False,
           keep_rotation: bool = False, min_baseline_mm: float = 0.0,
           pin: np.ndarray | None = None) -> np.ndarray:
    """Correct a relative's affine ``M`` so the template joint centres ``A`` land on their warped places ``B``.

    4+ points spanning 3-D: the least-squares affine (``rigid``: ``M`` followed
    by the least-squares rigid correction -- a body of several bones keeps its
    shape, its joints to the rest are few and far apart). Otherwise ``M``
    followed by the smallest correction: 3 points, a rigid fit (Umeyama); 2,
    the rotation turning the joint-to-joint direction onto the warped one and
    a stretch along it to the warped length, about their midpoint; 1, a shift.
    ``keep_rotation`` leaves out the rotation of the 2-point case: ``M`` is a
    placement that already turned the bone, and two joints say less about its
    orientation than the placement did (a pelvis's two hip centres lie 1-3 deg
    off its symmetric template's left-right axis in a person; turned onto them,
    a pelvis placed within 0.1 deg came out 3 deg off on a phantom).
    Two joints closer together than ``min_baseline_mm`` give a shift only:
    over a short baseline a few millimetres of joint error are a large turn
    and stretch of the whole bone (a scapula's acromioclavicular and
    glenohumeral centres, 35-40 mm apart on a blade of 150 mm: turned 8-11
    deg and stretched by 1.27 on phantoms whose scapulae sat as the
    template's on the thorax). The shift puts the joints in ``pin`` (a
    boolean mask over the points: those an own target placed, the
    glenohumeral centre on its warped humerus) on their places, else the
    joints' midpoint on theirs.
    """
    k = len(A)
    if k == 0:
        return M
    if not rigid and k >= 4 and np.linalg.matrix_rank(A - A.mean(0), tol=1.0) == 3:
        return _fit_affine(A, B)
    MA = _apply(M, A)
    C = np.eye(4)
    if k >= 3 and np.linalg.matrix_rank(MA - MA.mean(0), tol=1.0) >= 2:
        C = _kabsch(MA, B)
    elif k >= 2 and np.linalg.norm(MA[-1] - MA[0]) >= min_baseline_mm:
        u, v = MA[-1] - MA[0], B[-1] - B[0]
        stretch = float(np.linalg.norm(v) / max(np.linalg.norm(u), 1e-9))
        u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
        ax, c = np.cross(u, v), float(u @ v)
        if np.linalg.norm(ax) > 1e-9 and not keep_rotation:
            from scipy.spatial.transform import Rotation

            C[:3, :3] = Rotation.from_rotvec(ax / np.linalg.norm(ax) * np.arccos(np.clip(c, -1, 1))).as_matrix()
        # the length between the two joints is known: stretch along it (the relative's affine scaled its own
        # bone, not this one)
        C[:3, :3] = C[:3, :3] @ (np.eye(3) + (stretch - 1.0) * np.outer(u, u))
        C[:3, 3] = B.mean(0) - C[:3, :3] @ MA.mean(0)
    else:
        sel = np.ones(k, bool) if pin is None or not np.any(pin) else np.asarray(pin, bool)
        C[:3, 3] = B[sel].mean(0) - MA[sel].mean(0)
    return C @ M


def _chains_to_fixed(sk: Skeleton, fixed: dict, results: dict, body_of: dict, known: dict,
                     group_of: dict) -> list[tuple[list[list[tuple[str, str]]], list[str]]]:
    """The joints of each chain of carried bones below a fixed bone, bottom to top, and its bones.

    From a fixed bone down its ancestors (the skull, c1, c2, ... l5) to the first
    that is anchored: warped, fixed, or one of a rigid body with at least two
    joints placed by warped bones (the pelvis on the femora's hip centres). A
    chain is returned as the joint groups between consecutive bones, from the
    anchor's joint to the fixed bone's, with the bones between (neither the
    fixed bone nor the anchor); none when the fixed bone's parent is anchored
    already or no anchor lies below.
    """
    def anchored(b: str) -> bool:
        if b in results or b in fixed:
            return True
        body = body_of.get(b)
        return body is not None and sum((bb, k) in known for bb in body for k in sk.bones[bb].joint_centres) >= 2

    chains = []
    for f in fixed:
        seq = [f]
        b = sk.bones[f].parent
        while b is not None and not anchored(b):
            seq.append(b)
            b = sk.bones[b].parent
        if b is None or len(seq) < 2:
            continue
        seq.append(b)
        joints = []
        for child, parent in zip(seq[:-1], seq[1:]):
            shared = {id(group_of[(child, k)]): group_of[(child, k)] for k in sk.bones[child].joint_centres
                      if any(e[0] == parent for e in group_of[(child, k)])}
            if len(shared) != 1:
                break
            joints.append(shared.popitem()[1])
        else:
            chains.append((joints[::-1], seq[1:-1]))
    return chains


def _warped_ancestor(sk: Skeleton, name: str, results: dict, fixed: dict) -> str | None:
    """The nearest ancestor of ``name`` with an own target, reached through bones without one (and not
    fixed); None if there is none."""
    a = sk.bones[name].parent
    while a is not None:
        if a in results:
            return a
        if a in fixed:
            return None
        a = sk.bones[a].parent
    return None


def _nearest_relative(sk: Skeleton, name: str, results: dict, carried: dict) -> np.ndarray | None:
    """The affine of the nearest ancestor (else child) that was warped or carried."""
    a = sk.bones[name].parent
    while a is not None:
        if a in results:
            return results[a]["T_affine"]
        if a in carried:
            return carried[a]
        a = sk.bones[a].parent
    for n, b in sk.bones.items():
        if b.parent == name and n in results:
            return results[n]["T_affine"]
    return None
