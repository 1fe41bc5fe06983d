"""The rule-based bone-pose solver of Kojima et al. (section 8.1), written out so it can be tested.

The paper drives each bone from markers with three rules:

1. **Joint centres by relative-position preservation.** A joint centre is held
   in a frame built from its marker pair (or single marker) and the bone
   axis, with the subject's own offset from the markers to the MRI joint
   centre (:func:`marker_frame`, :func:`joint_centre_offset`,
   :func:`joint_centre_from_markers`).
2. **Bone direction by the atan/asin axis rules.** With the bone vector
   ``a = distal - proximal = [p, q, r]`` in the paper's Y-up lab,
   ``theta_z = atan(p / q)`` brought to 0-360 degrees by quadrant
   corrections and ``theta_x = asin(r / |a|)`` in -90..90 degrees; the bone's
   rest axis is +Y and ``R = Rz(-theta_z) Rx(theta_x) Ry(theta_y)`` so that
   ``R @ y = a / |a|`` (:func:`axis_angles`, :func:`paper_rotation`).
3. **Axial twist from a marker-pair vector against its static pose**
   (:func:`twist_angle`).

:func:`solve_bone` combines them into a bone pose per frame and maps it into
the skeleton's bone frame, ``T(t) @ inv(T_paper(static)) @ T_bone(static)``, so
the paper's poses compare with the least-squares solver's and with the truth.

Frames: inputs are in the **lab** frame of the trial (Z up for Vicon, or Y up
with ``lab_up="y"``); the paper's angles are defined in the lab turned Y-up,
``(x, y, z) -> (x, z, -y)`` (:func:`to_paper_frame`). Lengths in mm, angles
in degrees.

References
----------
Kojima et al., the MRI-based personal skeleton and motion-capture paper this
project follows (section 8.1: bone pose from markers).
"""

from __future__ import annotations

import numpy as np

__all__ = ["to_paper_frame", "from_paper_frame", "axis_angles", "paper_rotation", "minimal_rotation",
           "twist_angle", "marker_frame", "joint_centre_offset", "joint_centre_from_markers", "solve_bone"]

# (x, y, z) in a Z-up lab -> (x, z, -y) in the paper's Y-up frame.
_ZUP_TO_PAPER = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _lab_to_paper_matrix(lab_up: str) -> np.ndarray:
    if lab_up == "z":
        return _ZUP_TO_PAPER
    if lab_up == "y":
        return np.eye(3)
    raise ValueError(f"lab_up must be 'z' or 'y', got {lab_up!r}")


def to_paper_frame(v: np.ndarray, lab_up: str = "z") -> np.ndarray:
    """Express lab vectors ``(..., 3)`` in the paper's Y-up frame: ``(x, y, z) -> (x, z, -y)`` for a Z-up lab."""
    return np.asarray(v, dtype=float) @ _lab_to_paper_matrix(lab_up).T


def from_paper_frame(v: np.ndarray, lab_up: str = "z") -> np.ndarray:
    """Inverse of :func:`to_paper_frame`."""
    return np.asarray(v, dtype=float) @ _lab_to_paper_matrix(lab_up)


def _hold_previous(values: np.ndarray, ok: np.ndarray, fill: float) -> np.ndarray:
    """Replace ``values[~ok]`` by the last ``ok`` value before it (``fill`` before the first)."""
    idx = np.where(ok, np.arange(len(values)), -1)
    np.maximum.accumulate(idx, out=idx)
    return np.where(idx >= 0, values[np.maximum(idx, 0)], fill)


def axis_angles(a: np.ndarray, min_horizontal: float = 1e-6, theta_z0: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The paper's bone-direction angles for bone vectors in its Y-up frame.

    Parameters
    ----------
    a : ndarray, shape (F, 3) or (3,)
        ``distal - proximal`` = ``[p, q, r]`` in the paper's frame (see
        :func:`to_paper_frame`).
    min_horizontal : float
        Where ``sqrt(p**2 + q**2) <= min_horizontal * |a|`` the bone is
        vertical in the paper's p-q plane and ``theta_z`` is undefined: the
        previous frame's value is held (``theta_z0`` before the first).
    theta_z0 : float
        Value used for leading frames where ``theta_z`` is undefined.

    Returns
    -------
    theta_z : ndarray (F,)
        ``atan(p / q)`` in degrees brought to [0, 360) by the paper's quadrant
        corrections -- which are exactly ``atan2(p, q) mod 360``:
        ``[1, 1, 0] -> 45``, ``[1, 0, 0] -> 90``, ``[0, -1, 0] -> 180``,
        ``[-1, 0, 0] -> 270``, ``[-1, 1, 0] -> 315``. The paper lists
        "p < 0, q = 0 -> 360 degrees"; that is a typo for 270 (the direction
        ``[-1, 0, 0]`` is a quarter turn from ``[0, 1, 0]``, not a full one).
    theta_x : ndarray (F,)
        ``asin(r / |a|)`` in degrees, in [-90, 90] (``[0, 1, 1] -> 45``).
    """
    a = np.atleast_2d(np.asarray(a, dtype=float))
    if a.shape[-1] != 3:
        raise ValueError(f"bone vectors must have shape (F, 3), got {a.shape}")
    p, q, r = a[:, 0], a[:, 1], a[:, 2]
    norm = np.linalg.norm(a, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        theta_x = np.degrees(np.arcsin(np.clip(r / norm, -1.0, 1.0)))
    theta_z = np.mod(np.degrees(np.arctan2(p, q)), 360.0)
    defined = np.hypot(p, q) > min_horizontal * norm
    theta_z = _hold_previous(theta_z, defined & np.isfinite(theta_z), theta_z0)
    theta_z[~np.isfinite(norm) | (norm == 0)] = np.nan
    return theta_z, theta_x


def _rot(axis: int, deg: np.ndarray) -> np.ndarray:
    t = np.radians(np.asarray(deg, dtype=float))
    c, s = np.cos(t), np.sin(t)
    R = np.zeros(t.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[..., axis, axis] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s
    R[..., j, i] = s
    return R


def paper_rotation(theta_z: np.ndarray, theta_x: np.ndarray, theta_y: np.ndarray) -> np.ndarray:
    """``R = Rz(-theta_z) @ Rx(theta_x) @ Ry(theta_y)`` (degrees), batched; ``R @ [0, 1, 0]`` is the bone direction."""
    return _rot(2, -np.asarray(theta_z)) @ _rot(0, theta_x) @ _rot(1, theta_y)


def minimal_rotation(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation taking direction ``u`` to direction ``v`` (batched ``(..., 3)`` -> ``(..., 3, 3)``).

    Rodrigues' formula about ``u x v``; for opposite vectors (no unique
    answer) a half turn about an axis perpendicular to ``u`` is returned.
    """
    u = np.asarray(u, dtype=float)
    v = np.asarray(v, dtype=float)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    u, v = np.broadcast_arrays(u, v)
    w = np.cross(u, v)
    c = np.sum(u * v, axis=-1)
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        factor = np.where(c > -1 + 1e-12, 1.0 / (1.0 + c), 0.0)
    R = np.eye(3) + K + (K @ K) * factor[..., None, None]
    opposite = c <= -1 + 1e-12
    if np.any(opposite):
        # Half turn about any axis perpendicular to u.
        uo = u[opposite]
        helper = np.where(np.abs(uo[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        n = np.cross(uo, helper)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        R[opposite] = 2 * n[:, :, None] * n[:, None, :] - np.eye(3)
    return R


def twist_angle(static_axis: np.ndarray, static_twist: np.ndarray, axis: np.ndarray, twist: np.ndarray
                ) -> np.ndarray:
    """Signed axial twist (degrees) of a bone against its static pose.

    The static twist vector (e.g. RELP -> RELA) is carried by the minimal
    rotation that takes the static bone axis to the current one; it and the
    current twist vector are projected on the plane normal to the current
    axis, and the signed angle between them about the axis is returned
    (right-handed about ``axis``).

    Parameters
    ----------
    static_axis, static_twist : ndarray (3,)
        Bone axis and twist vector in the static trial (any common frame).
    axis, twist : ndarray (F, 3)
        The same vectors per frame, in that frame.
    """
    axis = np.atleast_2d(np.asarray(axis, dtype=float))
    twist = np.atleast_2d(np.asarray(twist, dtype=float))
    M = minimal_rotation(np.broadcast_to(static_axis, axis.shape), axis)
    carried = M @ np.asarray(static_twist, dtype=float)
    n = axis / np.linalg.norm(axis, axis=1, keepdims=True)

    def project(v):
        return v - np.sum(v * n, axis=1, keepdims=True) * n

    a, b = project(carried), project(twist)
    return np.degrees(np.arctan2(np.sum(np.cross(a, b) * n, axis=1), np.sum(a * b, axis=1)))


def marker_frame(origin: np.ndarray, toward: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """A right-handed frame ``(F, 4, 4)`` (frame -> lab) from markers and the bone axis.

    Origin at ``origin``; x along ``toward - origin`` (for a marker pair,
    ``origin`` is the pair's midpoint and ``toward`` one of its markers); y
    along the bone axis made orthogonal to x; z = x cross y.
    """
    origin = np.atleast_2d(np.asarray(origin, dtype=float))
    x = np.atleast_2d(np.asarray(toward, dtype=float)) - origin
    x = x / np.linalg.norm(x, axis=1, keepdims=True)
    y = np.atleast_2d(np.asarray(axis, dtype=float))
    y = y - np.sum(y * x, axis=1, keepdims=True) * x
    y = y / np.linalg.norm(y, axis=1, keepdims=True)
    z = np.cross(x, y)
    T = np.zeros(origin.shape[:1] + (4, 4))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = x, y, z, origin
    T[:, 3, 3] = 1.0
    return T


def joint_centre_offset(frame_static: np.ndarray, centre_static: np.ndarray) -> np.ndarray:
    """The subject's joint centre expressed in a static marker frame (mm): the offset to preserve."""
    T = np.asarray(frame_static, dtype=float).reshape(4, 4)
    return np.linalg.solve(T[:3, :3], np.asarray(centre_static, dtype=float) - T[:3, 3])


def joint_centre_from_markers(frames: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Joint centres per frame ``(F, 3)`` from marker frames ``(F, 4, 4)`` and a preserved offset."""
    return frames[:, :3, :3] @ np.asarray(offset, dtype=float) + frames[:, :3, 3]


def solve_bone(proximal: np.ndarray, distal: np.ndarray, twist_from: np.ndarray, twist_to: np.ndarray,
               static_index: int | tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
               bone_static: np.ndarray, lab_up: str = "z") -> dict[str, np.ndarray]:
    """One bone's pose per frame by the paper's rules.

    Parameters
    ----------
    proximal, distal : ndarray (F, 3)
        Proximal and distal joint centres in the lab (mm), e.g. from
        :func:`joint_centre_from_markers`.
    twist_from, twist_to : ndarray (F, 3)
        The twist marker pair in the lab.
    static_index : int or tuple
        The frame of these arrays that is the static pose, or the static
        ``(proximal, distal, twist_from, twist_to)`` positions (3,) each.
    bone_static : ndarray (4, 4)
        ``bone_to_lab`` of the skeleton's bone at the static pose (ISB frame).
    lab_up : {"z", "y"}
        The lab's vertical axis.

    Returns
    -------
    dict
        ``transforms`` (F, 4, 4) ``bone_to_lab`` in the skeleton's bone frame,
        ``theta_z``, ``theta_x``, ``theta_y`` (F,) the paper's angles in
        degrees (theta_y is the twist relative to the paper's own rest
        orientation), ``twist`` (F,) the twist against the static pose.
    """
    proximal, distal = np.atleast_2d(proximal), np.atleast_2d(distal)
    tw = np.atleast_2d(twist_to) - np.atleast_2d(twist_from)
    if isinstance(static_index, (int, np.integer)):
        sp, sd, stw = proximal[static_index], distal[static_index], tw[static_index]
    else:
        sp, sd, sf, st = (np.asarray(x, dtype=float) for x in static_index)
        stw = st - sf
    P = _lab_to_paper_matrix(lab_up)
    a = (distal - proximal) @ P.T
    a_s = (sd - sp) @ P.T
    tw_p, stw_p = tw @ P.T, stw @ P.T

    # Static orientation: the paper's rest twist is taken as zero at the static pose.
    tz_s, tx_s = axis_angles(a_s)
    R_static = paper_rotation(tz_s, tx_s, 0.0)[0]
    twist = twist_angle(a_s, stw_p, a, tw_p)
    # Current orientation: minimal rotation of the static axis onto the current one,
    # then the measured twist about the current axis.
    n = a / np.linalg.norm(a, axis=1, keepdims=True)
    R_twist = _axis_angle_matrix(n, np.radians(twist))
    R = R_twist @ minimal_rotation(np.broadcast_to(a_s, a.shape), a) @ R_static
    theta_z, theta_x = axis_angles(a, theta_z0=float(tz_s[0]))
    # Express R in the paper's decomposition: Ry(theta_y) = (Rz Rx)^T R.
    Ry = np.swapaxes(paper_rotation(theta_z, theta_x, np.zeros_like(theta_z)), -1, -2) @ R
    theta_y = np.degrees(np.arctan2(Ry[:, 0, 2], Ry[:, 0, 0]))

    T_paper = np.tile(np.eye(4), (len(a), 1, 1))
    T_paper[:, :3, :3] = P.T @ R @ P  # back into the lab frame
    T_paper[:, :3, 3] = proximal
    T_paper_static = np.eye(4)
    T_paper_static[:3, :3] = P.T @ R_static @ P
    T_paper_static[:3, 3] = sp
    transforms = T_paper @ np.linalg.solve(T_paper_static, np.asarray(bone_static, dtype=float))
    return {"transforms": transforms, "theta_z": theta_z, "theta_x": theta_x, "theta_y": theta_y,
            "twist": twist}


def _axis_angle_matrix(n: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotations by ``angle`` (rad) about unit axes ``n`` (batched Rodrigues)."""
    K = np.zeros(n.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -n[..., 2], n[..., 1], -n[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = n[..., 2], -n[..., 1], n[..., 0]
    s, c = np.sin(angle)[..., None, None], np.cos(angle)[..., None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)
