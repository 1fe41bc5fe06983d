"""Markers placed on the personal skin (build-subject with MRI): along the landmark's ray, else the nearest skin."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import trimesh

from bonecap.build_mri import _onto_skin
from bonecap.model import Mesh


def _setup():
    box = trimesh.creation.box(extents=(200.0, 200.0, 200.0))        # the skin: z = +-100, normals out
    skin = Mesh(np.asarray(box.vertices), np.asarray(box.faces), "lps")
    bone = SimpleNamespace(landmarks={"top": np.array([0.0, 0.0, 90.0]), "out": np.array([0.0, 0.0, 300.0]),
                                      "above": np.array([0.0, 0.0, 115.0])},
                           joint_centres={}, bone_to_world=np.eye(4))
    sk = SimpleNamespace(bones={"b": bone})
    mset = SimpleNamespace(markers={n: SimpleNamespace(bone="b", landmark=lm)
                                    for n, lm in (("A", "top"), ("NOTCH", "top"), ("FAR", "out"),
                                                  ("BESIDE", "above"))})
    return skin, sk, mset


def test_a_marker_rests_on_the_skin_above_its_landmark_or_at_the_nearest_skin():
    skin, sk, mset = _setup()
    placed = {"A": np.array([0.0, 0.0, 95.0]),        # pushed out of the bone: the ray meets the skin 10 mm out
              "NOTCH": np.array([0.0, 0.0, 85.0]),    # a notch's normal points into the body: the ray crosses it
              "FAR": np.array([0.0, 0.0, 310.0]),     # no skin near (a hand outside the scan)
              "BESIDE": np.array([0.0, 0.0, 125.0])}  # outside the skin, 25 mm from it: not moved onto it
    out = _onto_skin(placed, skin, sk, mset, marker_radius_mm=7.0)
    np.testing.assert_allclose(out["A"], [0.0, 0.0, 107.0], atol=1e-6)
    # the notch's marker went through the body (190 mm): it rests on the nearest skin instead of staying inside
    np.testing.assert_allclose(out["NOTCH"], [0.0, 0.0, 107.0], atol=1e-6)
    np.testing.assert_allclose(out["FAR"], placed["FAR"])
    np.testing.assert_allclose(out["BESIDE"], placed["BESIDE"])
    # without the snap the notch's marker stays where it was guessed, inside the body
    kept = _onto_skin(placed, skin, sk, mset, marker_radius_mm=7.0, snap_mm=0.0)
    np.testing.assert_allclose(kept["NOTCH"], placed["NOTCH"])
