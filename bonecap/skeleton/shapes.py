"""Parametric shape primitives and implicit-field meshing for the generic skeleton.

Every bone of :mod:`bonecap.skeleton.generic` is authored as an *implicit field*:
a union (sharp or smooth), difference or intersection of primitives, each with an
approximate signed distance function (negative inside, in mm). The field is sampled
on a regular grid around the bone and turned into a triangle mesh with marching
cubes, Taubin-smoothed and decimated. This is the robust way to get closed,
consistently wound meshes out of unions of overlapping parts: the mesh is the
boundary of a set, so it cannot have holes or self-intersections.

The same field gives the *inner* (endosteal / cancellous) surface: the level set
``field + thickness(p) = 0``, with a spatially varying cortical thickness.

Primitives evaluate only inside their own bounding box (grown by a band): outside
it their value is taken as ``+band``. That keeps a long, curved part (a rib) cheap
on a large grid.

Conventions: points are ``(N, 3)`` float arrays in mm; rotation matrices hold the
primitive's local axes as *columns* (``p_world = R @ p_local + centre``).
"""

from __future__ import annotations

import gc

import numpy as np

__all__ = [
    "smin", "smax", "Primitive", "Sphere", "Ellipsoid", "EllipticCylinder", "RoundCone",
    "Tube", "Plate", "polygon_sdf_2d", "RoundBox", "HalfSpace", "Intersect", "Shell", "ShapeBuilder", "Field",
    "frame_from_axes", "rotation_about", "unit", "surface_extreme", "finish_mesh",
]

_EPS = 1e-9


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, _EPS)


def rotation_about(axis, angle_deg: float) -> np.ndarray:
    """Rotation matrix of ``angle_deg`` about ``axis`` (right-hand rule)."""
    a = unit(axis)
    t = np.radians(angle_deg)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def frame_from_axes(primary, secondary, order: str = "yz") -> np.ndarray:
    """Right-handed rotation whose axis ``order[0]`` is along ``primary`` and
    axis ``order[1]`` lies in the plane of ``primary`` and ``secondary``.

    Returns a 3x3 matrix whose columns are the x, y, z axes.
    """
    idx = {"x": 0, "y": 1, "z": 2}
    i, j = idx[order[0]], idx[order[1]]
    k = 3 - i - j
    a = unit(primary)
    b = unit(np.asarray(secondary, float) - np.dot(secondary, a) * a)
    R = np.zeros((3, 3))
    R[:, i] = a
    R[:, j] = b
    c = np.cross(a, b)
    # (i, j, k) cyclic -> k = i x j; otherwise k = j x i
    R[:, k] = c if (j - i) % 3 == 1 else -c
    return R


def smin(a, b, k: float):
    """Polynomial smooth minimum (union with a fillet of radius ~k)."""
    if k <= 0:
        return np.minimum(a, b)
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def smax(a, b, k: float):
    """Polynomial smooth maximum (intersection / difference with a fillet)."""
    return -smin(-a, -b, k)


def _ellipsoid_sdf(q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Approximate signed distance to an axis-aligned ellipsoid (Quilez's bound).

    ``q`` (N, d) local coordinates, ``r`` (d,) or (N, d) radii. Exact on a sphere,
    first-order accurate near the surface of an ellipsoid.
    """
    k0 = np.sqrt(np.sum((q / r) ** 2, axis=-1))
    k1 = np.sqrt(np.sum((q / (r * r)) ** 2, axis=-1))
    d = k0 * (k0 - 1.0) / np.maximum(k1, _EPS)
    # at the very centre the bound degenerates to 0/0: use -min radius
    centre = k1 < 1e-6
    if np.any(centre):
        rmin = np.min(r, axis=-1) if np.ndim(r) > 1 else np.min(r)
        d = np.where(centre, -rmin if np.ndim(r) == 1 else -rmin, d)
    return d


class Primitive:
    """Base class: a bounding box ``lo``, ``hi`` and an approximate SDF."""

    lo: np.ndarray
    hi: np.ndarray
    infinite = False

    def sdf(self, p: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def parts(self) -> list["Primitive"]:
        """Sub-primitives evaluated separately (sharp union) -- itself by default."""
        return [self]


class Sphere(Primitive):
    def __init__(self, centre, radius: float):
        self.c = np.asarray(centre, float)
        self.r = float(radius)
        self.lo, self.hi = self.c - self.r, self.c + self.r

    def sdf(self, p):
        return np.linalg.norm(p - self.c, axis=1) - self.r


class Ellipsoid(Primitive):
    """Ellipsoid with semi-axes ``radii`` along the columns of ``R``."""

    def __init__(self, centre, radii, R=None):
        self.c = np.asarray(centre, float)
        self.r = np.asarray(radii, float)
        self.R = np.eye(3) if R is None else np.asarray(R, float)
        ext = np.abs(self.R) @ self.r
        self.lo, self.hi = self.c - ext, self.c + ext

    def sdf(self, p):
        q = (p - self.c) @ self.R
        return _ellipsoid_sdf(q, self.r)


class EllipticCylinder(Primitive):
    """Elliptic cylinder along local y (half-height ``h``), radii ``rx``, ``rz``,
    with edges rounded by ``rounding`` mm (a vertebral body, a disc of bone)."""

    def __init__(self, centre, rx: float, h: float, rz: float, R=None, rounding: float = 2.0):
        self.c = np.asarray(centre, float)
        self.R = np.eye(3) if R is None else np.asarray(R, float)
        self.rx, self.h, self.rz, self.rd = float(rx), float(h), float(rz), float(rounding)
        ext = np.abs(self.R) @ np.array([rx, h, rz])
        self.lo, self.hi = self.c - ext, self.c + ext

    def sdf(self, p):
        q = (p - self.c) @ self.R
        rd = self.rd
        d2 = _ellipsoid_sdf(q[:, [0, 2]], np.array([self.rx - rd, self.rz - rd]))
        dy = np.abs(q[:, 1]) - (self.h - rd)
        a = np.maximum(d2, 0.0)
        b = np.maximum(dy, 0.0)
        return np.minimum(np.maximum(d2, dy), 0.0) + np.sqrt(a * a + b * b) - rd


class RoundBox(Primitive):
    """Box of half extents ``half`` (local axes = columns of ``R``), edges rounded."""

    def __init__(self, centre, half, R=None, rounding: float = 1.0):
        self.c = np.asarray(centre, float)
        self.R = np.eye(3) if R is None else np.asarray(R, float)
        self.half = np.asarray(half, float)
        self.rd = float(rounding)
        ext = np.abs(self.R) @ self.half
        self.lo, self.hi = self.c - ext, self.c + ext

    def sdf(self, p):
        q = np.abs((p - self.c) @ self.R) - (self.half - self.rd)
        out = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        return out + np.minimum(q.max(axis=1), 0.0) - self.rd


class HalfSpace(Primitive):
    """The half space ``(p - point) . normal <= 0`` (normal points outwards)."""

    infinite = True

    def __init__(self, point, normal):
        self.o = np.asarray(point, float)
        self.n = unit(normal)
        self.lo = np.full(3, -np.inf)
        self.hi = np.full(3, np.inf)

    def sdf(self, p):
        return (p - self.o) @ self.n


class RoundCone(Primitive):
    """Capsule from ``a`` to ``b`` whose radius goes linearly from ``ra`` to ``rb``."""

    def __init__(self, a, b, ra: float, rb: float):
        self.a = np.asarray(a, float)
        self.b = np.asarray(b, float)
        self.ra, self.rb = float(ra), float(rb)
        r = max(self.ra, self.rb)
        self.lo = np.minimum(self.a, self.b) - r
        self.hi = np.maximum(self.a, self.b) + r

    def sdf(self, p):
        ab = self.b - self.a
        L2 = max(float(ab @ ab), _EPS)
        t = np.clip((p - self.a) @ ab / L2, 0.0, 1.0)
        c = self.a + t[:, None] * ab
        return np.linalg.norm(p - c, axis=1) - (self.ra + t * (self.rb - self.ra))


class _EllipticSegment(Primitive):
    """One segment of a :class:`Tube`: elliptical section swept along a line
    segment, the section frame and radii interpolated linearly, ellipsoidal caps."""

    def __init__(self, a, b, e1a, e1b, ra, rb):
        self.a = np.asarray(a, float)
        self.b = np.asarray(b, float)
        self.u = self.b - self.a
        self.L = max(float(np.linalg.norm(self.u)), _EPS)
        self.uh = self.u / self.L
        self.e1a = np.asarray(e1a, float)
        self.e1b = np.asarray(e1b, float)
        self.const_frame = bool(np.allclose(self.e1a, self.e1b))
        self.ra = np.asarray(ra, float)
        self.rb = np.asarray(rb, float)
        # bounding box of the swept ellipses plus the end caps
        r = max(self.ra.max(), self.rb.max())
        rc = max(self.ra.min(), self.rb.min())
        ext = r * np.sqrt(np.clip(1.0 - self.uh ** 2, 0.0, 1.0)) + rc * np.abs(self.uh)
        self.lo = np.minimum(self.a, self.b) - ext
        self.hi = np.maximum(self.a, self.b) + ext

    def sdf(self, p):
        f32 = np.float32
        d0 = (p - self.a).astype(f32)
        uh = self.uh.astype(f32)
        s = d0 @ uh
        sc = np.clip(s, 0.0, f32(self.L))
        axial = s - sc
        t = sc / f32(self.L)
        d = d0 - sc[:, None] * uh[None, :]
        if self.const_frame:
            e1 = self.e1a - (self.e1a @ self.uh) * self.uh
            e1 = (e1 / np.linalg.norm(e1)).astype(f32)
            e2 = np.cross(self.uh, e1).astype(f32)
            q1 = d @ e1
            q2 = d @ e2
        else:
            e1 = self.e1a[None, :].astype(f32) * (1 - t)[:, None] + self.e1b[None, :].astype(f32) * t[:, None]
            e1 -= (e1 @ uh)[:, None] * uh[None, :]
            e1 /= np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), f32(1e-6))
            e2 = np.cross(uh[None, :], e1)
            q1 = np.einsum("ij,ij->i", d, e1)
            q2 = np.einsum("ij,ij->i", d, e2)
        r1 = f32(self.ra[0]) + t * f32(self.rb[0] - self.ra[0])
        r2 = f32(self.ra[1]) + t * f32(self.rb[1] - self.ra[1])
        rc = np.minimum(r1, r2)
        a1, a2, a3 = q1 / r1, q2 / r2, axial / rc
        k0 = np.sqrt(a1 * a1 + a2 * a2 + a3 * a3)
        b1, b2, b3 = a1 / r1, a2 / r2, a3 / rc
        k1 = np.sqrt(b1 * b1 + b2 * b2 + b3 * b3)
        out = k0 * (k0 - 1.0) / np.maximum(k1, f32(1e-6))
        return np.where(k1 < 1e-6, -rc, out)


class Tube(Primitive):
    """A bar of elliptical section swept along a polyline (a rib, a bone shaft).

    Parameters
    ----------
    nodes : (K, 3)
        Centreline points.
    radii : (K, 2) or (K,)
        Semi-axes of the section at each node: along ``e1`` and along
        ``tangent x e1`` (a single value gives a round section).
    e1 : (3,) or (K, 3), optional
        Direction of the first semi-axis at each node (projected perpendicular to
        the local tangent). Defaults to any perpendicular direction.
    """

    def __init__(self, nodes, radii, e1=None):
        self.nodes = np.asarray(nodes, float)
        K = len(self.nodes)
        radii = np.asarray(radii, float)
        if radii.ndim == 1:
            radii = np.stack([radii, radii], axis=1)
        self.radii = radii
        tang = np.gradient(self.nodes, axis=0)
        tang = unit(tang)
        if e1 is None:
            ref = np.array([0.0, 0.0, 1.0]) if abs(tang[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
            e1 = np.repeat(ref[None, :], K, axis=0)
        e1 = np.asarray(e1, float)
        if e1.ndim == 1:
            e1 = np.repeat(e1[None, :], K, axis=0)
        e1 = e1 - np.sum(e1 * tang, axis=1, keepdims=True) * tang
        self.e1 = unit(e1)
        self._segs = [
            _EllipticSegment(self.nodes[i], self.nodes[i + 1], self.e1[i], self.e1[i + 1],
                             self.radii[i], self.radii[i + 1])
            for i in range(K - 1)
        ]
        self.lo = np.min([s.lo for s in self._segs], axis=0)
        self.hi = np.max([s.hi for s in self._segs], axis=0)

    def parts(self):
        return list(self._segs)

    def sdf(self, p):
        return np.min([s.sdf(p) for s in self._segs], axis=0)


def polygon_sdf_2d(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Exact signed distance from 2-D points (N, 2) to a closed polygon (M, 2), negative inside."""
    P = np.asarray(pts, float)
    V = np.asarray(poly, float)
    W = np.roll(V, -1, axis=0)
    # coordinates as separate contiguous vectors: the per-edge work is a few fused passes
    # over N values instead of (N, 2) matrix products (~3x faster on the plates' tables)
    X = np.ascontiguousarray(P[:, 0])
    Y = np.ascontiguousarray(P[:, 1])
    best = np.full(len(P), np.inf)
    inside = np.zeros(len(P), bool)
    qx, qy, t, tmp = (np.empty(len(P)) for _ in range(4))
    for a, b in zip(V, W):
        ex, ey = b - a
        np.subtract(X, a[0], out=qx)
        np.subtract(Y, a[1], out=qy)
        np.multiply(qx, ex, out=t)
        t += qy * ey
        t *= 1.0 / max(ex * ex + ey * ey, _EPS)
        np.clip(t, 0.0, 1.0, out=t)
        # squared distance to the segment: |q - t e|^2
        np.multiply(t, ex, out=tmp)
        np.subtract(qx, tmp, out=qx)
        np.multiply(t, ey, out=tmp)
        np.subtract(qy, tmp, out=qy)
        np.multiply(qx, qx, out=tmp)
        tmp += qy * qy
        np.minimum(best, tmp, out=best)
        # even-odd crossing rule
        cond = (a[1] > Y) != (b[1] > Y)
        xint = a[0] + (Y - a[1]) * (ex / (ey if abs(ey) >= _EPS else _EPS))
        inside ^= cond & (X < xint)
    d = np.sqrt(best)
    return np.where(inside, -d, d)


class Plate(Primitive):
    """A thick plate: the Minkowski sum of a ball of radius ``half_thickness`` with a flat
    2-D region (``outline`` shrunk by the half thickness) lifted by a height field.

    The plate lives in the plane through ``origin`` spanned by ``e1``, ``e2`` (normal
    ``e1 x e2``). ``outline`` (M, 2) is the plate's outline in (u, v) = plane
    coordinates; ``half_thickness`` and ``height`` are scalars or vectorised functions
    ``f(u, v)``. Everything is tabulated once on a 2-D grid (``res`` mm), so the field
    costs a few bilinear look-ups per point. Exact for a flat plate of constant
    thickness; the edges are rounded.
    """

    def __init__(self, origin, e1, e2, outline, half_thickness=1.5, height=None, res: float = 0.5,
                 band: float = 12.0):
        self.o = np.asarray(origin, float)
        self.e1 = unit(e1)
        self.e2 = unit(np.asarray(e2, float) - (np.asarray(e2, float) @ self.e1) * self.e1)
        self.n = np.cross(self.e1, self.e2)
        poly = np.asarray(outline, float)
        hfun = half_thickness if callable(half_thickness) else (lambda u, v, h=float(half_thickness): np.full(np.shape(u), h))
        zfun = height if callable(height) else (lambda u, v: np.zeros(np.shape(u)))
        lo2 = poly.min(axis=0)
        hi2 = poly.max(axis=0)
        h_probe = hfun(*np.meshgrid(np.linspace(lo2[0], hi2[0], 9), np.linspace(lo2[1], hi2[1], 9), indexing="ij"))
        hmax = float(np.max(h_probe))
        margin = band + hmax + 2.0
        self.u0 = lo2 - margin
        nu, nv = (np.ceil((hi2 - lo2 + 2 * margin) / res).astype(int) + 1)
        self.res = float(res)
        us = self.u0[0] + res * np.arange(nu)
        vs = self.u0[1] + res * np.arange(nv)
        UU, VV = np.meshgrid(us, vs, indexing="ij")
        sd = polygon_sdf_2d(np.stack([UU.ravel(), VV.ravel()], 1), poly).reshape(nu, nv)
        Uc = np.clip(UU, lo2[0], hi2[0])
        Vc = np.clip(VV, lo2[1], hi2[1])
        self.t_h = np.asarray(hfun(Uc, Vc), float).reshape(nu, nv).astype(np.float32)
        self.t_z = np.asarray(zfun(Uc, Vc), float).reshape(nu, nv).astype(np.float32)
        self.t_sd = (sd + self.t_h).astype(np.float32)          # outline shrunk by the half thickness
        self.shape2 = (nu, nv)
        zmax = float(np.abs(self.t_z).max()) + float(self.t_h.max())
        corners = [self.o + u * self.e1 + v * self.e2 + s * zmax * self.n
                   for u in (lo2[0], hi2[0]) for v in (lo2[1], hi2[1]) for s in (-1, 1)]
        self.lo = np.min(corners, axis=0)
        self.hi = np.max(corners, axis=0)

    def _lookup(self, tables, u, v):
        fu = np.clip((u - self.u0[0]) / self.res, 0, self.shape2[0] - 1.001)
        fv = np.clip((v - self.u0[1]) / self.res, 0, self.shape2[1] - 1.001)
        i = fu.astype(np.int64)
        j = fv.astype(np.int64)
        a = (fu - i).astype(np.float32)
        b = (fv - j).astype(np.float32)
        out = []
        for T in tables:
            out.append((T[i, j] * (1 - a) + T[i + 1, j] * a) * (1 - b) + (T[i, j + 1] * (1 - a) + T[i + 1, j + 1] * a) * b)
        return out

    def sdf(self, p):
        q = (p - self.o).astype(np.float32)
        u = q @ self.e1.astype(np.float32)
        v = q @ self.e2.astype(np.float32)
        w = q @ self.n.astype(np.float32)
        sd, h, z = self._lookup((self.t_sd, self.t_h, self.t_z), u, v)
        w = w - z
        ds = np.maximum(sd, 0.0)
        return np.sqrt(ds * ds + w * w) - h


class Intersect(Primitive):
    """Intersection of primitives (e.g. a sphere clipped by a half space)."""

    def __init__(self, *prims: Primitive, k: float = 0.0):
        self.prims = prims
        self.k = float(k)
        finite = [p for p in prims if not p.infinite]
        self.lo = np.max([p.lo for p in finite], axis=0)
        self.hi = np.min([p.hi for p in finite], axis=0)

    def sdf(self, p):
        d = self.prims[0].sdf(p)
        for q in self.prims[1:]:
            d = smax(d, q.sdf(p), self.k)
        return d


class Shell(Primitive):
    """A hollow version of ``prim``: a wall of ``thickness`` mm inside its surface."""

    def __init__(self, prim: Primitive, thickness: float):
        self.prim = prim
        self.t = float(thickness)
        self.lo, self.hi = prim.lo, prim.hi

    def sdf(self, p):
        d = self.prim.sdf(p)
        return np.maximum(d, -d - self.t)


# ---------------------------------------------------------------------------
# building a field on a grid


class Field:
    """A sampled scalar field: ``values[i, j, k]`` at ``origin + voxel * (i, j, k)``."""

    def __init__(self, values: np.ndarray, origin: np.ndarray, voxel: float):
        self.values = values
        self.origin = np.asarray(origin, float)
        self.voxel = float(voxel)

    def points(self) -> np.ndarray:
        nx, ny, nz = self.values.shape
        g = np.meshgrid(*(self.origin[i] + self.voxel * np.arange(n) for i, n in enumerate((nx, ny, nz))),
                        indexing="ij")
        return np.stack([a.ravel() for a in g], axis=1)


class ShapeBuilder:
    """Accumulates CSG operations on primitives, then samples them on a grid.

    ``add(prim, k)`` smooth union (fillet ~k mm), ``cut(prim, k)`` difference,
    ``clip(prim, k)`` intersection. A list of primitives given to ``add``/``cut``
    is first united sharply, then combined.
    """

    def __init__(self, voxel: float = 1.0, band: float | None = None):
        self.voxel = float(voxel)
        self.band = band
        self.ops: list[tuple[str, list[Primitive], float]] = []

    def add(self, prims, k: float = 0.0) -> "ShapeBuilder":
        self.ops.append(("add", _as_list(prims), float(k)))
        return self

    def cut(self, prims, k: float = 0.0) -> "ShapeBuilder":
        self.ops.append(("cut", _as_list(prims), float(k)))
        return self

    def clip(self, prims, k: float = 0.0) -> "ShapeBuilder":
        self.ops.append(("clip", _as_list(prims), float(k)))
        return self

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        los = [p.lo for op, ps, _ in self.ops if op == "add" for p in ps]
        his = [p.hi for op, ps, _ in self.ops if op == "add" for p in ps]
        return np.min(los, axis=0), np.max(his, axis=0)

    def evaluate(self, pts: np.ndarray, band: float) -> np.ndarray:
        """The field at ``pts`` (N, 3), clamped above at ``band``."""
        pts = np.asarray(pts, float)
        P = pts[:, None, :]
        return self._eval_blocks(P, pts, pts, band)[:, 0]

    def _eval_blocks(self, P, blo, bhi, band):
        """Evaluate on points grouped in blocks: ``P`` (nB, M, 3) with per-block
        bounding boxes ``blo``, ``bhi`` (nB, 3) used to skip distant primitives."""
        nB, M = P.shape[:2]
        F = np.full((nB, M), band, dtype=np.float32)
        for op, prims, k in self.ops:
            if op == "clip":
                G = self._group_values(prims, P, blo, bhi, band)
                F = smax(F, G, k).astype(np.float32)
                continue
            grow = band + k
            glo = np.min([p.lo for p in prims], axis=0) - grow
            ghi = np.max([p.hi for p in prims], axis=0) + grow
            sel = np.nonzero(np.all((bhi >= glo) & (blo <= ghi), axis=1))[0]
            if len(sel) == 0:
                continue
            G = self._group_values(prims, P[sel], blo[sel], bhi[sel], band)
            if op == "add":
                F[sel] = smin(F[sel], G, k)
            else:
                F[sel] = smax(F[sel], -G, k)
        return F

    @staticmethod
    def _group_values(prims, P, blo, bhi, band):
        nB, M = P.shape[:2]
        G = np.full((nB, M), band, dtype=np.float32)
        for prim in prims:
            for part in prim.parts():
                if part.infinite:
                    val = part.sdf(P.reshape(-1, 3)).reshape(nB, M)
                    np.minimum(G, np.minimum(val, band).astype(np.float32), out=G)
                    continue
                sel = np.nonzero(np.all((bhi >= part.lo - band) & (blo <= part.hi + band), axis=1))[0]
                if len(sel) == 0:
                    continue
                val = part.sdf(P[sel].reshape(-1, 3)).reshape(len(sel), M)
                G[sel] = np.minimum(G[sel], np.minimum(val, band).astype(np.float32))
        return G

    def sample(self, margin: float | None = None, band: float | None = None, depth: float = 0.0,
               block: int = 4) -> Field:
        """Sample the field on a grid covering every added primitive.

        A coarse pass at block centres finds the blocks that can hold the surface
        (or the inner surface down to ``depth`` mm inside); only those are sampled
        finely, the others keep the coarse value.
        """
        v = self.voxel
        B = int(block)
        halfdiag = np.sqrt(3.0) * 0.5 * (B - 1) * v
        tol = 1.6 * halfdiag + v
        band = max(self.band or 0.0, 4.0 * v, tol + 2.0) if band is None else band
        margin = 2.0 * v + 1.0 if margin is None else margin
        lo, hi = self.bounds()
        # snap the grid to a global lattice of step v: the same shape is sampled at the
        # same points whatever the other parts of the bone extend to
        lo = np.floor((lo - margin) / v) * v
        hi = hi + margin
        nb = np.ceil((hi - lo) / (v * B)).astype(int) + 1
        shape = nb * B
        origin = lo
        # coarse pass
        cidx = np.meshgrid(*(np.arange(n) for n in nb), indexing="ij")
        centres = origin + v * (B * np.stack([c.ravel() for c in cidx], axis=1) + 0.5 * (B - 1))
        Fc = self.evaluate(centres, band).reshape(tuple(nb))
        active = (Fc < tol) & (Fc > -(depth + tol))
        # every fine voxel starts at its block's coarse value: written through a (nb, B) x 3 view,
        # one grid and no temporaries (a chain of np.repeat made three, the largest twice the grid)
        F = np.empty(tuple(shape), dtype=np.float32)
        F.reshape(nb[0], B, nb[1], B, nb[2], B)[...] = Fc[:, None, :, None, :, None]
        act = np.argwhere(active)
        if len(act):
            off = np.stack(np.meshgrid(np.arange(B), np.arange(B), np.arange(B), indexing="ij"), -1).reshape(-1, 3)
            # in chunks of blocks: every point's value depends on that point alone, and the
            # primitives' float64 temporaries (~10 arrays of the chunk) stay at about 15 MB
            # (262 144 points a chunk held ~60 MB in each meshing worker, for no speed)
            chunk = max(1, 65_536 // len(off))
            for a0 in range(0, len(act), chunk):
                ac = act[a0:a0 + chunk]
                idx = ac[:, None, :] * B + off[None, :, :]          # (nA, B^3, 3)
                P = origin + v * idx
                blo = origin + v * (ac * B)
                bhi = blo + v * (B - 1)
                vals = self._eval_blocks(P, blo, bhi, band)
                idx = idx.reshape(-1, 3)
                F[idx[:, 0], idx[:, 1], idx[:, 2]] = vals.ravel()
        assert tuple(F.shape) == tuple(shape)
        return Field(F, origin, v)


def _as_list(prims) -> list[Primitive]:
    if isinstance(prims, Primitive):
        return [prims]
    return list(prims)


# ---------------------------------------------------------------------------
# meshing


def _marching_cubes(values: np.ndarray, level: float, origin, voxel):
    """Iso-surface of a grid ``values[i, j, k]`` at ``origin + voxel * (i, j, k)``.

    Uses VTK's flying edges (several times faster than scikit-image), falling back
    to ``skimage.measure.marching_cubes``. The grid is padded with a border above
    ``level`` so every surface is closed. Returns ``(verts, faces)`` or None.
    """
    top = max(float(values.max()), level + 1.0)
    # Fortran order: VTK's image data runs x fastest, so the padded grid goes to VTK without
    # a reordered copy and without a deep copy (two grids fewer at the peak of a worker)
    pad = np.full(tuple(np.asarray(values.shape) + 2), np.float32(top), dtype=np.float32, order="F")
    pad[1:-1, 1:-1, 1:-1] = values
    # grid values (almost) at the level make (nearly) coincident vertices that later merge
    # into non-manifold edges: push them 1e-3 mm off the level
    # (a few slabs at a time: |pad - level| of the whole grid were two more grids at a worker's peak,
    # ~35 MB for the scapula at the default phantom's resolution; slabs of the last axis are contiguous
    # in Fortran order)
    step = max(1, (1 << 20) // max(1, pad.shape[0] * pad.shape[1]))
    for k in range(0, pad.shape[2], step):
        slab = pad[:, :, k:k + step]
        near = np.abs(slab - np.float32(level)) < np.float32(1e-3)
        slab[near] = np.float32(level) + np.where(slab[near] >= level, np.float32(1e-3), np.float32(-1e-3))
    del near
    if pad.min() >= level:
        return None
    org = np.asarray(origin, float) - voxel
    try:
        from vtkmodules.util import numpy_support as ns
        from vtkmodules.vtkCommonDataModel import vtkImageData
        from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D

        img = vtkImageData()
        img.SetDimensions(*pad.shape)
        img.SetSpacing(voxel, voxel, voxel)
        img.SetOrigin(*org)
        # a view of ``pad`` (alive until this function returns, after the filter has run)
        arr = ns.numpy_to_vtk(pad.ravel(order="K"), deep=False)
        img.GetPointData().SetScalars(arr)
        fe = vtkFlyingEdges3D()
        fe.SetInputData(img)
        fe.SetValue(0, level)
        fe.ComputeNormalsOff()
        fe.ComputeGradientsOff()
        fe.ComputeScalarsOff()
        fe.Update()
        out = fe.GetOutput()
        verts = ns.vtk_to_numpy(out.GetPoints().GetData()).astype(float)
        polys = ns.vtk_to_numpy(out.GetPolys().GetConnectivityArray()).reshape(-1, 3).astype(np.int64)
        return verts, polys
    except Exception:  # pragma: no cover - VTK missing or broken
        from skimage.measure import marching_cubes

        verts, faces, _n, _v = marching_cubes(pad, level=level, spacing=(voxel,) * 3, allow_degenerate=False)
        # (i, j, k) = (x, y, z): the grid is built with ij indexing, no axis reversal needed
        return verts + org, faces


def finish_mesh(verts: np.ndarray, faces: np.ndarray, target_faces: int, smooth_iterations: int = 6,
                min_component_volume: float = 0.0, return_dense: bool = False):
    """Clean, orient, smooth and decimate a marching-cubes surface.

    Returns ``(vertices, faces)`` of a closed, consistently wound mesh with outward
    normals (positive volume), about ``target_faces`` triangles (plus the smoothed,
    undecimated vertices when ``return_dense``); raises ``RuntimeError`` when no
    closed mesh could be produced.
    """
    import trimesh

    m = trimesh.Trimesh(verts, faces, process=False)
    m.update_faces(m.nondegenerate_faces())
    m.remove_unreferenced_vertices()
    # drop numerical specks and too small pieces; component volumes in one vectorised pass
    min_component_volume = max(min_component_volume, 1.0)
    labels = trimesh.graph.connected_component_labels(m.face_adjacency, node_count=len(m.faces))
    tri = m.vertices[m.faces]
    fvol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    del tri                                   # (9 doubles a face, not needed past here)
    cvol = np.bincount(labels, weights=fvol)
    keep_c = np.abs(cvol) >= min_component_volume
    if not np.any(keep_c):
        return None
    if not np.all(keep_c):
        m.update_faces(keep_c[labels])
        m.remove_unreferenced_vertices()
    if cvol[keep_c].sum() < 0:
        m.invert()
    if smooth_iterations:
        trimesh.smoothing.filter_taubin(m, lamb=0.5, nu=0.53, iterations=smooth_iterations)
    dense = np.asarray(m.vertices, float).copy()
    best = m
    n = len(m.faces)
    if target_faces and n > target_faces:
        best = _decimate_closed(m, target_faces)
        if best is None:
            # decimate the connected components one by one (small pieces collapse
            # into non-manifold shapes when decimated together with big ones)
            comps = m.split(only_watertight=False)
            parts = []
            for comp in comps:
                tgt = max(int(target_faces * len(comp.faces) / n), 160)
                part = comp if len(comp.faces) <= tgt else _decimate_closed(comp, tgt)
                if part is None and comp.is_watertight and comp.is_winding_consistent:
                    # A closed piece that no decimator keeps closed stays at full
                    # resolution: more triangles, but never an open bone.
                    part = comp
                if part is None:
                    raise RuntimeError("decimation could not keep the surface closed")
                parts.append(part)
            best = trimesh.util.concatenate(parts)
            # the dense surface, its pieces and their caches (reference cycles) go before the checks
            # build edge groups of their own (the hip bone's inner surface: ~20 MB)
            del comps, parts, part, comp, m
            gc.collect()
    if not (best.is_watertight and best.is_winding_consistent):
        raise RuntimeError("meshing produced an open or inconsistently wound surface")
    if return_dense:
        return np.asarray(best.vertices, float), np.asarray(best.faces, np.int64), dense
    return np.asarray(best.vertices, float), np.asarray(best.faces, np.int64)


def _decimate_closed(m, target_faces: int):
    """Quadric decimation to about ``target_faces`` that keeps the mesh closed, or None."""
    import fast_simplification
    import trimesh

    n = len(m.faces)
    if n <= target_faces:
        return m
    for factor in (1.0, 0.93, 1.07, 0.86, 1.15, 0.8):
        tgt = int(target_faces * factor)
        red = 1.0 - tgt / n
        if red <= 0:
            continue
        v2, f2 = fast_simplification.simplify(m.vertices.astype(np.float32), m.faces.astype(np.int32),
                                              target_reduction=red, agg=7)
        d = trimesh.Trimesh(v2.astype(float), f2, process=True)
        d.remove_unreferenced_vertices()
        if d.is_watertight and d.is_winding_consistent and d.volume > 0:
            return d
        # a trimesh object and its caches form reference cycles: a failed try is freed now, not at the
        # collector's next full pass (six tries on the hip bone's inner surface held ~25 MB)
        del d, v2, f2
        gc.collect()
    return _decimate_vtk(m, target_faces)


def _decimate_vtk(m, target_faces: int):
    """Fallback: VTK's topology-preserving decimation (never opens or pinches the
    surface, may stop above the target)."""
    import trimesh
    from vtkmodules.util import numpy_support as ns
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
    from vtkmodules.vtkFiltersCore import vtkDecimatePro

    pts = vtkPoints()
    pts.SetData(ns.numpy_to_vtk(np.ascontiguousarray(m.vertices, dtype=np.float64), deep=True))
    cells = vtkCellArray()
    conn = ns.numpy_to_vtkIdTypeArray(np.ascontiguousarray(m.faces.ravel(), dtype=np.int64), deep=True)
    offs = ns.numpy_to_vtkIdTypeArray(np.arange(0, 3 * len(m.faces) + 1, 3, dtype=np.int64), deep=True)
    cells.SetData(offs, conn)
    poly = vtkPolyData()
    poly.SetPoints(pts)
    poly.SetPolys(cells)
    dec = vtkDecimatePro()
    dec.SetInputData(poly)
    dec.SetTargetReduction(1.0 - target_faces / len(m.faces))
    dec.PreserveTopologyOn()
    dec.SplittingOff()
    dec.BoundaryVertexDeletionOff()
    dec.SetMaximumError(1e9)
    dec.Update()
    out = dec.GetOutput()
    v = ns.vtk_to_numpy(out.GetPoints().GetData()).astype(float)
    f = ns.vtk_to_numpy(out.GetPolys().GetConnectivityArray()).reshape(-1, 3).astype(np.int64)
    d = trimesh.Trimesh(v, f, process=True)
    d.remove_unreferenced_vertices()
    if d.is_watertight and d.is_winding_consistent and d.volume > 0 and len(d.faces) <= 1.25 * target_faces:
        return d
    return None


def field_to_mesh(field: Field, target_faces: int, level: float = 0.0, offset: np.ndarray | None = None,
                  smooth_iterations: int = 6, min_component_volume: float = 0.0, opening: bool = False,
                  return_dense: bool = False):
    """Mesh the level set ``field + offset = level`` (``offset`` a scalar or a grid of the
    same shape). ``opening`` first removes inside parts thinner than about two voxels
    (a grey-level opening of the inside), which keeps cancellous cores free of slivers."""
    vals = field.values if offset is None else field.values + offset
    if opening:
        from scipy import ndimage

        inside = np.argwhere(vals < level) if np.ndim(vals) == 3 else None
        if inside is not None and len(inside):
            lo = np.maximum(inside.min(axis=0) - 3, 0)
            hi = np.minimum(inside.max(axis=0) + 4, np.array(vals.shape))
            sl = tuple(slice(a, b) for a, b in zip(lo, hi))
            vals = np.array(vals, dtype=np.float32, copy=True)
            vals[sl] = ndimage.minimum_filter(ndimage.maximum_filter(vals[sl], size=3), size=3)
    r = _marching_cubes(vals, level, field.origin, field.voxel)
    if r is None:
        return None
    return finish_mesh(r[0], r[1], target_faces, smooth_iterations, min_component_volume, return_dense)


def surface_extreme(vertices: np.ndarray, seed, direction, radius: float = 15.0) -> np.ndarray:
    """The surface vertex within ``radius`` of ``seed`` furthest along ``direction``.

    The usual way to define a palpable landmark (the most lateral point of the
    lateral epicondyle...). A seed deep inside a thick bone (a shaft's axis on a
    coarse mesh) can have no vertex within ``radius``: then the window is the
    cylinder of that radius along ``direction`` through the seed (the most
    lateral point at the seed's level), and only if that is empty too the
    nearest vertex. (The nearest vertex alone put a femur's "lateral" shaft
    landmark on its medial side when the mesh was coarse.)
    """
    V = np.asarray(vertices, float)
    seed = np.asarray(seed, float)
    d = unit(direction)
    rel = V - seed
    near = np.linalg.norm(rel, axis=1) <= radius
    if not np.any(near):
        near = np.linalg.norm(rel - np.outer(rel @ d, d), axis=1) <= radius
    if not np.any(near):
        return V[np.argmin(np.linalg.norm(rel, axis=1))].copy()
    cand = V[near]
    return cand[np.argmax((cand - seed) @ d)].copy()
