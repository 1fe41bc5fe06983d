"""The paper solver for whole trials (Kojima et al. §8.1), wired to a subject.

:mod:`bonecap.motion.paper` holds the rules (axis angles, twist, marker
frames); this module applies them bone by bone to a trial, as the marker
set's ``paper_solver`` section prescribes (see ``marker_sets/kojima_paper.yaml``):

- a joint centre given by a marker **pair** is held in the frame of the
  pair's midpoint, x toward the pair's first marker and y along the bone's
  rough axis (the two ends' markers), at the subject's offset measured in
  the static trial (relative-position preservation: the bare midpoint would
  throw the MRI's joint centre away);
- a joint centre given by one **marker** is held the same way, the frame's x
  taken from the bone's twist pair;
- a **parent** joint centre is where the already solved parent puts it;
- the bone's direction and twist come from
  :func:`bonecap.motion.paper.solve_bone`, mapped into the skeleton's bone
  frame through the static pose.

Bones the paper's rules do not name (pelvis, trunk, head, scapulae...) follow
the least-squares solver: the paper drove only the limbs this way.
"""

from __future__ import annotations

import numpy as np

from bonecap.errors import DataError, InputError
from bonecap.model import Motion
from bonecap.motion.paper import joint_centre_from_markers, joint_centre_offset, marker_frame, solve_bone

__all__ = ["solve_paper"]


def solve_paper(subject, names: list[str], measured: np.ndarray, *, max_gap_frames: int = 10,
                forearm=None, lab_up: str = "z", rate_hz: float = 100.0) -> Motion:
    """Every bone's pose by the paper's rules where the marker set gives them.

    Parameters
    ----------
    subject : bonecap.subject.Subject
        Needs ``static`` (the static trial's markers and bone poses) and a
        marker set with a ``paper_solver`` section.
    names : list of str
        Subject marker names, parallel to axis 1 of ``measured``.
    measured : ndarray (F, M, 3)
        Lab frame of the trial, mm.
    forearm : optional
        The forearm model passed on to the least-squares base solve; radius
        and ulna marked ``forearm_model: true`` keep the model's poses.

    Returns
    -------
    Motion
        ``bone_to_lab`` in the skeleton's bone frames.

    Raises
    ------
    DataError
        No static trial in the subject, or no paper rules in its marker set.
    """
    from bonecap.markers import load_marker_set
    from bonecap.motion.lsq import solve_lsq

    if not subject.static:
        raise DataError("the paper solver needs the static trial the subject was bound in "
                        "(build the subject with --static)")
    try:
        mset = load_marker_set(subject.marker_set) if subject.marker_set else None
    except InputError:          # not a shipped set: an OpenSim model's own MarkerSet
        mset = None
    config = mset.paper_solver if mset is not None else {}
    if not config:
        raise DataError(f"marker set {subject.marker_set!r} has no paper_solver rules (they come with the "
                        "kojima_paper set): use --solver lsq")
    sk = subject.skeleton
    _, bones, local = subject.marker_arrays(names)
    base = solve_lsq(sk, bones, local, measured, max_gap_frames=max_gap_frames, forearm=forearm,
                     marker_labels=names, rate_hz=rate_hz, rhythm=subject.follows_rhythm())
    T = base.transforms.copy()
    index = {b: i for i, b in enumerate(base.bones)}
    col = {n: i for i, n in enumerate(names)}
    s_markers = subject.static["markers_lab"]
    s_pose = subject.static["bone_to_lab"]

    def marker(n: str, static: bool) -> np.ndarray | None:
        if static:
            return np.asarray(s_markers[n], float) if n in s_markers else None
        return measured[:, col[n]] if n in col else None

    def jc(bone: str, joint: str, static: bool) -> np.ndarray | None:
        b = sk.bones[bone]
        if joint not in b.joint_centres:
            return None
        if static:
            P = s_pose.get(bone)
            return None if P is None else P[:3, :3] @ b.joint_centres[joint] + P[:3, 3]
        Tb = T[:, index[bone]]
        return Tb[:, :3, :3] @ b.joint_centres[joint] + Tb[:, :3, 3]

    def raw_end(spec: dict, bone: str, static: bool) -> np.ndarray | None:
        if "pair" in spec:
            a, b = (marker(n, static) for n in spec["pair"])
            return None if a is None or b is None else 0.5 * (a + b)
        if "marker" in spec:
            return marker(spec["marker"], static)
        parent = sk.bones[bone].parent
        return None if parent is None else jc(parent, spec["parent"], static)

    def centre(spec: dict, bone: str, axis: np.ndarray, axis_s: np.ndarray, tw: tuple) -> np.ndarray | None:
        if "parent" in spec:
            return raw_end(spec, bone, False)
        joint = spec.get("joint")
        c_s = jc(bone, joint, True)
        if "pair" in spec:
            a, b = (marker(n, False) for n in spec["pair"])
            a_s, b_s = (marker(n, True) for n in spec["pair"])
            if a is None or a_s is None or b is None or b_s is None:
                return None
            frame = marker_frame(0.5 * (a + b), a, axis)
            frame_s = marker_frame(0.5 * (a_s + b_s), a_s, axis_s)[0]
        else:
            m, m_s = marker(spec["marker"], False), marker(spec["marker"], True)
            if m is None or m_s is None or tw[0] is None:
                return None
            frame = marker_frame(m, m + tw[1] - tw[0], axis)
            frame_s = marker_frame(m_s, m_s + tw[3] - tw[2], axis_s)[0]
        if c_s is None:  # no joint of that name: the frame origin itself
            return frame[:, :3, 3]
        return joint_centre_from_markers(frame, joint_centre_offset(frame_s, c_s))

    solved = []
    for bone in sk.names:
        rule = config.get(bone)
        if rule is None or bone not in s_pose:
            continue
        if rule.get("forearm_model") and forearm is not None:
            continue  # the pronation model already placed it in the base solve
        tw_names = rule.get("twist", [])
        tw = tuple(marker(n, st) for st in (False, True) for n in tw_names) if len(tw_names) == 2 else (None,) * 4
        p_raw, d_raw = raw_end(rule["proximal"], bone, False), raw_end(rule["distal"], bone, False)
        p_raw_s, d_raw_s = raw_end(rule["proximal"], bone, True), raw_end(rule["distal"], bone, True)
        if any(x is None for x in (p_raw, d_raw, p_raw_s, d_raw_s)) or tw[0] is None or tw[2] is None:
            continue
        axis, axis_s = d_raw - p_raw, np.atleast_2d(d_raw_s - p_raw_s)
        prox = centre(rule["proximal"], bone, axis, axis_s, tw)
        dist = centre(rule["distal"], bone, axis, axis_s, tw)
        if prox is None or dist is None:
            continue
        prox_s = jc(bone, rule["proximal"].get("joint") or rule["proximal"].get("parent"), True)
        dist_s = jc(bone, rule["distal"].get("joint"), True)
        if prox_s is None:
            prox_s = p_raw_s
        if dist_s is None:
            dist_s = d_raw_s
        res = solve_bone(prox, dist, tw[0], tw[1], (prox_s, dist_s, tw[2], tw[3]), s_pose[bone], lab_up=lab_up)
        ok = np.isfinite(res["transforms"]).all(axis=(1, 2))
        T[ok, index[bone]] = res["transforms"][ok]
        solved.append(bone)
    valid = np.isfinite(T).all(axis=(2, 3)) & base.valid
    # residuals against the paper poses
    idx = np.array([index[b] for b in bones])
    Tm = T[:, idx]
    pred = np.einsum("fmij,mj->fmi", Tm[..., :3, :3], local) + Tm[..., :3, 3]
    resid = np.linalg.norm(pred - measured, axis=-1)
    return Motion(base.bones, base.times, T, valid, base.first_frame, list(names), resid, flags=dict(base.flags))
