"""The phantom subject is a person, not the template: varied skeleton, a body around it.

Every test here measures something that could fail: shapes that differ beyond
any affine map, closed meshes, bones inside the fascia inside the skin,
plausible soft-tissue depths, and arms and legs that a per-slice skin
segmentation sees as separate components.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from bonecap.errors import InputError
from bonecap.model import Mesh
from bonecap.phantom.subject import (
    BODY_PARAM_RANGES,
    PhantomSubject,
    affine_fit_residual,
    build_subject_skeleton,
    draw_subject_params,
    make_subject,
)

RAJAGOPAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "bones" / "opensim" / "models" / \
    "Rajagopal2016.osim"
TEMPLATES = ["default", "rajagopal"]
#: The two seeds compared per template (the first one is the subject measured below).
SEEDS = {"default": (2, 4), "rajagopal": (0, 1)}
#: The generic subject is measured at the default preset; the OpenSim one at ``tiny`` (6 mm grid), which
#: keeps this module's run time down: the generic skeleton itself takes ~20-40 s to build.
PRESET = {"default": "default", "rajagopal": "tiny"}
_SUBJECTS: dict[str, PhantomSubject] = {}


def _generic(kind: str) -> str:
    if kind == "default":
        pytest.importorskip("bonecap.skeleton.generic")
        return "default"
    if not RAJAGOPAL.is_file():
        pytest.skip(f"Rajagopal2016 model not found at {RAJAGOPAL}")
    return str(RAJAGOPAL)


def _subject(kind: str) -> PhantomSubject:
    """The first seed of a template, built once per session."""
    if kind not in _SUBJECTS:
        _SUBJECTS[kind] = make_subject(SEEDS[kind][0], generic=_generic(kind), preset=PRESET[kind])
    return _SUBJECTS[kind]


@pytest.fixture(params=TEMPLATES)
def subject(request) -> PhantomSubject:
    return _subject(request.param)


# --------------------------------------------------------------------------- #
# measuring helpers
# --------------------------------------------------------------------------- #
def _inside(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """Which points are inside a closed mesh (VTK's enclosed-points test)."""
    import pyvista as pv

    faces = np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).ravel()
    surface = pv.PolyData(mesh.vertices, faces)
    sel = pv.PolyData(np.asarray(points, dtype=float)).select_interior_points(surface, check_surface=False)
    return np.asarray(sel["selected_points"], dtype=bool)


def _section_components(mesh: Mesh, y: float) -> int:
    """Separate regions of the axial cut Y = y: closed loops not nested in another loop."""
    seg = trimesh.intersections.mesh_plane(mesh.to_trimesh(), [0, 1, 0], [0, y, 0])
    if len(seg) == 0:
        return 0
    S = seg[:, :, [0, 2]]
    _, inv = np.unique(np.round(S.reshape(-1, 2), 3), axis=0, return_inverse=True)
    inv = inv.ravel().reshape(-1, 2)
    n = int(inv.max()) + 1
    n_loops, lab = connected_components(coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])), shape=(n, n)),
                                        directed=False)
    seg_lab = lab[inv[:, 0]]
    outer = 0
    for c in range(n_loops):
        p = S[seg_lab == c][0, 0] + 1e-3
        nested = False
        for c2 in range(n_loops):
            if c2 == c:
                continue
            a, b = S[seg_lab == c2][:, 0], S[seg_lab == c2][:, 1]
            cross = (a[:, 1] > p[1]) != (b[:, 1] > p[1])
            x = a[cross, 0] + (p[1] - a[cross, 1]) * (b[cross, 0] - a[cross, 0]) / (b[cross, 1] - a[cross, 1])
            if np.sum(x > p[0]) % 2 == 1:
                nested = True
                break
        outer += not nested
    return outer


def _skin_distance(subject: PhantomSubject, points: np.ndarray) -> np.ndarray:
    """Distance to the skin surface, from a dense point sampling of it (vertices, edge midpoints and
    face centroids: < 0.3 mm over-estimate at the depths tested, much faster than exact queries)."""
    v, f = subject.skin.vertices, subject.skin.faces
    tri = v[f]
    dense = np.concatenate([v, tri.mean(1), 0.5 * (tri[:, 0] + tri[:, 1]), 0.5 * (tri[:, 1] + tri[:, 2]),
                            0.5 * (tri[:, 2] + tri[:, 0])])
    d, _ = cKDTree(dense).query(np.atleast_2d(points))
    return d


def _bone(subject: PhantomSubject, name: str) -> np.ndarray:
    return subject.skeleton.world_mesh(name).vertices


def _skull_name(subject: PhantomSubject) -> str:
    return "skull" if "skull" in subject.skeleton.bones else "torso"


# --------------------------------------------------------------------------- #
# parameters
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("kind", TEMPLATES)
def test_params_are_deterministic_and_within_their_ranges(kind):
    generic = _generic(kind)
    p0 = draw_subject_params(0, generic=generic)
    assert p0 == draw_subject_params(0, generic=generic)
    p1 = draw_subject_params(1, generic=generic)
    assert p0["skeleton"] != p1["skeleton"] and p0["body"] != p1["body"]
    for p in (p0, p1):
        lo, hi = p["ranges"]["stature_mm"]
        assert lo <= p["stature_mm"] <= hi
        for group in ("skeleton", "body"):
            for name, (lo, hi) in p["ranges"][group].items():
                assert lo - 1e-9 <= p[group][name] <= hi + 1e-9, (group, name, p[group][name], (lo, hi))
        lengths = {k: v for k, v in p["skeleton"].items() if "scale" in k or k.startswith("length.")}
        lengths = {k: v for k, v in lengths.items() if "cortical" not in k and "width" not in k}
        assert lengths and all(0.91 <= v <= 1.09 for v in lengths.values()), lengths
    # the body parameters cover the stated ranges' names
    assert set(BODY_PARAM_RANGES) <= set(p0["body"])
    assert draw_subject_params(0, 1800.0, generic)["stature_mm"] == 1800.0


def test_unknown_preset_and_template_are_refused():
    with pytest.raises(InputError):
        make_subject(0, preset="huge")
    with pytest.raises(InputError):
        build_subject_skeleton(draw_subject_params(0, generic="model.txt"), "model.txt")


def test_same_seed_same_subject():
    a = _subject("rajagopal")
    b = make_subject(SEEDS["rajagopal"][0], generic=_generic("rajagopal"), preset=PRESET["rajagopal"])
    assert a.params == b.params
    np.testing.assert_array_equal(a.skin.vertices, b.skin.vertices)
    np.testing.assert_array_equal(a.muscle.faces, b.muscle.faces)
    for name in a.skeleton.bones:
        np.testing.assert_array_equal(a.skeleton.bones[name].bone_to_world, b.skeleton.bones[name].bone_to_world)


# --------------------------------------------------------------------------- #
# a person, not the template
# --------------------------------------------------------------------------- #
def test_affine_fit_residual_is_zero_for_an_affine_image_only():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(800, 3)) * [30.0, 200.0, 25.0]
    M = np.array([[1.1, 0.05, 0.0], [0.02, 0.93, 0.1], [0.0, -0.04, 1.05]])
    Q = P @ M.T + [5.0, -20.0, 3.0]
    assert affine_fit_residual(P, Q) < 1e-6
    assert affine_fit_residual(P, Q[rng.permutation(len(Q))][:700]) < 2.0       # no correspondence: ICP
    bent = Q.copy()
    bent[:, 0] += 2e-4 * (Q[:, 1] - Q[:, 1].mean()) ** 2                       # a bow: not affine
    assert affine_fit_residual(P, bent) > 1.0
    # meshes: two triangulations of one (stretched) sphere match through the surfaces, not the vertices
    ico, uv = trimesh.creation.icosphere(4, radius=30.0), trimesh.creation.uv_sphere(30.0, count=[40, 40])
    a = Mesh(ico.vertices * [1.0, 4.0, 1.0], ico.faces)
    b = Mesh(uv.vertices * [1.1, 4.4, 0.9] + 5.0, uv.faces)
    assert affine_fit_residual(a, b) < 0.3
    # same vertex count, different numbering (a remeshed bone): no vertex-by-vertex correspondence
    perm = np.random.default_rng(1).permutation(len(ico.vertices))
    inv = np.argsort(perm)
    shuffled = Mesh(a.vertices[perm] * 1.05, inv[a.faces])
    assert affine_fit_residual(a, shuffled) < 0.05


@pytest.mark.parametrize("kind", TEMPLATES)
def test_two_seeds_differ_beyond_any_affine_map(kind, record_property):
    generic = _generic(kind)
    first = _subject(kind)
    sk0 = copy.deepcopy(first.skeleton)                   # back to its anatomical pose (no MRI abduction)
    for name, T in first.metadata["anatomical_bone_to_world"].items():
        sk0.bones[name].bone_to_world = np.asarray(T)
    seed1 = SEEDS[kind][1]
    sk = [sk0, build_subject_skeleton(draw_subject_params(seed1, generic=generic), generic)]
    pelvis = "hip_r" if "hip_r" in sk[0].bones else "pelvis"

    def joint(s, a, b):
        c = [k for k in s.bones[b].joint_centres if k in s.bones[a].joint_centres][0]
        return s.bones[b].landmark_in_world(c)

    # segment lengths differ, independently (the thigh/shank ratio changes)
    thigh = [np.linalg.norm(joint(s, pelvis, "femur_r") - joint(s, "femur_r", "tibia_r")) for s in sk]
    arm = [np.linalg.norm(s.bones["humerus_r"].bone_to_world[:3, 3] - joint(s, "humerus_r", "ulna_r")) for s in sk]
    assert abs(thigh[0] / thigh[1] - 1) > 0.01 or abs(arm[0] / arm[1] - 1) > 0.01
    femur = affine_fit_residual(sk[0].world_mesh("femur_r"), sk[1].world_mesh("femur_r"))
    chain = affine_fit_residual([sk[0].world_mesh(n) for n in (pelvis, "femur_r", "tibia_r")],
                                [sk[1].world_mesh(n) for n in (pelvis, "femur_r", "tibia_r")])
    record_property("femur_affine_residual_mm", femur)
    record_property("leg_chain_affine_residual_mm", chain)
    print(f"{kind}: affine-fit residual seed {SEEDS[kind][0]} -> {seed1}: femur {femur:.2f} mm, "
          f"{pelvis}+femur+tibia {chain:.2f} mm")
    assert chain > 1.0
    assert femur > 0.3


def test_bones_still_meet_their_parents_after_the_individual_shapes(subject):
    """Each bone's own shape field keeps its joints in place, and the bone is re-placed on the joint it
    shares with its parent -- also where the names differ by a side (a hip bone's ``sacroiliac`` is
    the sacrum's ``sacroiliac_r``): placed by its origin instead, seed 2's hip bones came off the
    sacrum by up to 15 mm and met each other nowhere near the pubic symphysis."""
    sk = subject.skeleton
    checked = 0
    for name, bone in sk.bones.items():
        if bone.parent is None:
            continue
        par = sk.bones[bone.parent]
        side = name[-2:] if name.endswith(("_r", "_l")) else ""
        for k in bone.joint_centres:
            kp = k if k in par.joint_centres else (k + side if side and k + side in par.joint_centres else None)
            if kp is None:
                continue
            gap = np.linalg.norm(bone.landmark_in_world(k) - par.landmark_in_world(kp))
            assert gap < 0.5, (name, k, bone.parent, kp, gap)
            checked += 1
    assert checked >= (20 if "hip_r" in sk.bones else 10)
    if "hip_r" in sk.bones:
        gap = np.linalg.norm(sk.bones["hip_r"].landmark_in_world("pubic_symphysis")
                             - sk.bones["hip_l"].landmark_in_world("pubic_symphysis"))
        assert gap < 0.5


# --------------------------------------------------------------------------- #
# the body
# --------------------------------------------------------------------------- #
def test_skin_and_fascia_are_closed_and_outward(subject):
    volumes = []
    budget = 200_000 if subject.params["preset"] == "default" else 20_000
    for mesh in (subject.skin, subject.muscle):
        tm = mesh.to_trimesh()
        assert tm.is_watertight and tm.is_winding_consistent
        assert tm.volume > 0
        assert len(mesh.faces) <= budget
        volumes.append(tm.volume)
    # a 1.6-1.8 m adult: 45-110 L; fat is 5-35 % of it
    assert 45e6 < volumes[0] < 110e6
    assert 0.65 < volumes[1] / volumes[0] < 0.97
    assert 0.95 < subject.metadata["height_mm"] / subject.params["stature_mm"] < 1.05


def test_bones_inside_fascia_inside_skin(subject):
    rng = np.random.default_rng(1)
    bones = subject.bone_world_vertices()
    sample = bones[rng.choice(len(bones), min(len(bones), 15000), replace=False)]
    inside = _inside(subject.muscle, sample)
    assert inside.all(), f"{(~inside).sum()} bone vertices outside the fascia, e.g. {sample[~inside][:3]}"
    fascia = subject.muscle.vertices[rng.choice(len(subject.muscle.vertices), 5000, replace=False)]
    assert _inside(subject.skin, fascia).all()


def test_soft_tissue_depths_are_plausible(subject):
    for side in "rl":
        femur = _bone(subject, f"femur_{side}")
        y0, y1 = femur[:, 1].min(), femur[:, 1].max()
        mid = femur[np.abs(femur[:, 1] - 0.5 * (y0 + y1)) < 15]
        depth = _skin_distance(subject, mid).min()
        assert 20 <= depth <= 80, f"femur_{side} mid-shaft {depth:.1f} mm under the skin"
        tibia = _bone(subject, f"tibia_{side}")
        y0, y1 = tibia[:, 1].min(), tibia[:, 1].max()
        shaft = tibia[(tibia[:, 1] > y0 + 0.35 * (y1 - y0)) & (tibia[:, 1] < y0 + 0.65 * (y1 - y0))]
        crest = shaft[np.argmax(shaft[:, 0])]                         # the anterior border
        assert _skin_distance(subject, crest)[0] <= 15
    skull = _bone(subject, _skull_name(subject))
    vertex = skull[np.argmax(skull[:, 1])]
    assert 3 <= _skin_distance(subject, vertex)[0] <= 12


def test_arms_and_legs_are_separate_in_axial_slices(subject):
    levels = subject.metadata["levels_mm"]
    assert _section_components(subject.skin, levels["mid_humerus"]) >= 3      # trunk + two arms
    assert _section_components(subject.skin, levels["mid_thigh"]) >= 2        # two thighs
    assert subject.params["pose"]["arm_gap_mm_r"] >= 0.8 * subject.params["body"]["arm_gap_mm"]
    assert subject.params["pose"]["leg_gap_mm"] >= 0.8 * subject.params["body"]["leg_gap_mm"]


def test_layers_are_ordered_for_the_renderer(subject):
    layers = subject.layers()
    assert [t for _, t in layers[:2]] == ["fat", "muscle"]
    tissues = [t for _, t in layers[2:]]
    assert set(tissues) <= {"cortex", "marrow"} and tissues[0] == "cortex"
    n_bones = sum(b.mesh is not None for b in subject.skeleton.bones.values())
    assert tissues.count("cortex") == n_bones
    assert tissues.count("marrow") == sum(b.inner_mesh is not None for b in subject.skeleton.bones.values())
    assert all(m.frame == subject.skeleton.world == "model" for m, _ in layers)
    # mapped to another frame: the same layers transformed, sharing the subject's faces arrays
    T = np.array([[1.0, 0, 0, 5], [0, 0, -1, 7], [0, 1, 0, -3], [0, 0, 0, 1]])
    mapped = subject.layers(T, "lps")
    assert [t for _, t in mapped] == [t for _, t in layers]
    for (m, _), (w, _) in zip(mapped, layers):
        assert m.frame == "lps"
        assert np.allclose(m.vertices, w.vertices @ T[:3, :3].T + T[:3, 3], atol=1e-9)
        assert np.array_equal(m.faces, w.faces)
    assert mapped[0][0].faces is subject.skin.faces
    first = next(n for n, b in subject.skeleton.bones.items() if b.mesh is not None)
    assert mapped[2][0].faces is subject.skeleton.bones[first].mesh.faces


def test_an_opensim_model_s_bones_get_marrow_under_their_cortex():
    """An OpenSim model's bones are outer surfaces only; the phantom makes each an endosteal surface at the
    embedded description's cortical thickness (``with_marrow``), else they render as solid cortex, which no
    bone rule segments. Every body with geometry gets one; a long bone's marrow fills a plausible part of it,
    lies under its surface (mid-shaft by about the shaft's cortex), and renders as the ``marrow`` layer."""
    import dataclasses

    import trimesh

    from bonecap.model import Skeleton
    from bonecap.phantom.subject import OSIM_CORTEX, with_marrow
    from bonecap.skeleton.generic import _cortical_summary, load_generic_description
    from bonecap.skeleton.opensim import read_osim

    subj = _subject("rajagopal")
    sk = subj.skeleton
    with_mesh = [n for n, b in sk.bones.items() if b.mesh is not None]
    assert sorted(sk.metadata["marrow"]) == sorted(with_mesh)
    assert all(sk.bones[n].inner_mesh is not None for n in with_mesh)
    assert [t for _, t in subj.layers()].count("marrow") == len(with_mesh)
    desc = load_generic_description()
    for name in ("femur_r", "tibia_l", "humerus_r"):
        b = sk.bones[name]
        outer = trimesh.Trimesh(b.mesh.vertices, b.mesh.faces, process=False)
        inner = trimesh.Trimesh(b.inner_mesh.vertices, b.inner_mesh.faces, process=False)
        assert inner.is_watertight and 0.2 < inner.volume / abs(outer.volume) < 0.9, name
        # the inner surface's depth under the outer one, mid-shaft: about the diaphysis's cortex
        u = np.linalg.svd(b.mesh.vertices - b.mesh.vertices.mean(0), full_matrices=False)[2][0]
        pts = trimesh.sample.sample_surface(inner, 4000, seed=0)[0]     # (decimated: few vertices mid-shaft)
        s = (pts - b.mesh.vertices.mean(0)) @ u
        mid = np.abs(s) < 0.15 * np.ptp(b.mesh.vertices @ u)
        depth = trimesh.proximity.closest_point(outer, pts[mid])[1]      # (an OpenSim mesh need not be closed)
        cortex = _cortical_summary(desc, OSIM_CORTEX.get(name[:-2], name[:-2]))["diaphysis"]
        assert 0.5 * cortex < np.median(depth) < 2.0 * cortex, (name, np.median(depth), cortex)
    # bones that have an inner surface keep it; the input is not changed
    kneecap = dataclasses.replace(read_osim(RAJAGOPAL).bones["patella_r"], parent=None)
    raw = Skeleton({"patella_r": kneecap}, world="opensim_ground")
    once = with_marrow(raw)
    assert once.metadata["marrow"] == ["patella_r"] and raw.bones["patella_r"].inner_mesh is None
    again = with_marrow(sk)
    assert again.metadata["marrow"] == [] and all(again.bones[n].inner_mesh is sk.bones[n].inner_mesh for n in with_mesh)
    with pytest.raises(ValueError, match="voxel_mm"):
        with_marrow(raw, voxel_mm=0.0)


def test_slab_marching_cubes_equals_the_whole_grid(monkeypatch):
    """The body grid is meshed in slabs (memory): the result must be the whole grid's surface,
    closed, with the shared layers' vertices merged; checked on two analytic spheres (a float16
    field, as the body's) against scikit-image on the whole grid and against the true volume."""
    from skimage.measure import marching_cubes

    import bonecap.phantom.subject as subject_mod

    monkeypatch.setattr(subject_mod, "_MC_SLAB_VOXELS", 40 * 40 * 5)   # slabs of 5 layers: many seams
    ax = np.arange(40, dtype=np.float32)
    X, Y, Z = np.meshgrid(ax, ax, ax, indexing="ij")
    field = np.minimum(np.sqrt((X - 19.3) ** 2 + (Y - 12.6) ** 2 + (Z - 20.1) ** 2) - 8.0,
                       np.sqrt((X - 20.2) ** 2 + (Y - 28.4) ** 2 + (Z - 19.7) ** 2) - 6.5).astype(np.float16)
    v, f = subject_mod._marching_cubes_slabs(field, 1.0)
    tm = trimesh.Trimesh(v, f, process=False)
    assert tm.is_watertight and tm.is_winding_consistent
    ref_v, ref_f, _, _ = marching_cubes(field.astype(np.float32), 0.0, allow_degenerate=False)
    assert len(v) == len(np.unique(ref_v, axis=0)) and len(f) == len(ref_f)
    assert np.abs(np.sort(v, axis=0) - np.sort(ref_v, axis=0)).max() < 2e-3        # the same surface
    true_volume = 4.0 / 3.0 * np.pi * (8.0 ** 3 + 6.5 ** 3)
    assert abs(abs(tm.volume) / true_volume - 1.0) < 0.02


def test_body_smoothing_and_decimation_helpers_match_the_libraries(tmp_path, monkeypatch):
    """``_taubin`` is trimesh's equal-weight Taubin filter; ``_decimate`` in a child process returns
    what fast_simplification and trimesh's processing return in this one (the body meshes must not
    depend on where it ran); with BONECAP_WORKERS=1 or ``lean=False`` it runs here."""
    import os

    import fast_simplification

    from bonecap.phantom import subject as subj

    tm = trimesh.creation.icosphere(subdivisions=5, radius=50.0)
    tm.vertices += np.random.default_rng(0).normal(scale=1.0, size=tm.vertices.shape)
    ref = tm.copy()
    trimesh.smoothing.filter_taubin(ref, lamb=0.5, nu=0.53, iterations=6)
    V = subj._taubin(np.asarray(tm.vertices), np.asarray(tm.faces), 0.5, 0.53, 6)
    assert np.abs(V - tm.vertices).max() > 0.1                 # it did smooth
    assert np.allclose(V, ref.vertices, atol=1e-9)

    v32 = np.asarray(tm.vertices, np.float32)
    f = np.asarray(tm.faces)
    a = trimesh.Trimesh(*fast_simplification.simplify(v32, f, target_reduction=0.7), process=True)
    a = (np.asarray(a.vertices), np.asarray(a.faces))
    pids = tmp_path / "pids"
    library = fast_simplification.simplify

    def recorded(*args, **kwargs):                               # which process decimated
        with open(pids, "a") as fh:
            fh.write(f"{os.getpid()}\n")
        return library(*args, **kwargs)

    monkeypatch.setattr(fast_simplification, "simplify", recorded)
    monkeypatch.setattr(subj, "_SIMPLIFY_IN_CHILD_FACES", 1000)  # force the child process
    monkeypatch.delenv("BONECAP_WORKERS", raising=False)
    b = subj._decimate(v32, f, 0.7)
    assert len(b[1]) < 0.4 * len(f)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    d = subj._decimate(v32, f, 0.7, lean=False)                  # (the tiny preset: here, same result)
    assert np.array_equal(a[0], d[0]) and np.array_equal(a[1], d[1])
    monkeypatch.setenv("BONECAP_WORKERS", "1")
    c = subj._decimate(v32, f, 0.7)
    assert np.array_equal(a[0], c[0]) and np.array_equal(a[1], c[1])
    child, here_not_lean, here = (int(x) for x in pids.read_text().split())
    assert child != os.getpid() and here_not_lean == here == os.getpid()


def test_a_fin_folded_by_the_decimation_is_dropped_and_the_mesh_closes():
    """Quadric decimation sometimes folds a sliver into two coincident faces wound opposite ways (the
    default phantom of seed 3: its fascia on every target tried, so ``bonecap phantom --seed 3`` failed).
    ``_drop_fins`` removes exactly such pairs -- here one added on a closed sphere, whose edges then join
    three and four faces -- and the sphere is closed again; a closed mesh loses nothing."""
    from bonecap.phantom import subject as subj

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=20.0)
    V, F = np.asarray(sphere.vertices), np.asarray(sphere.faces, dtype=np.int64)
    a, b, _ = F[0]
    c = F[40][0] if F[40][0] not in (a, b) else F[40][1]
    finned = np.vstack([F, [[a, b, c], [c, b, a]]])
    assert not subj._closed_and_oriented(finned, len(V))
    V2, F2 = subj._drop_fins(V, finned)
    assert np.array_equal(F2, F) and subj._closed_and_oriented(F2, len(V2))
    assert np.array_equal(subj._drop_fins(V, F)[1], F)
    # the same triangle twice with the same winding is not a fin (a duplicated face): kept
    assert len(subj._drop_fins(V, np.vstack([F, F[:1]]))[1]) == len(F) + 1


def test_mesh_checks_match_trimesh_and_extract_orients_outward():
    """``_closed_and_oriented`` is trimesh's ``is_watertight and is_winding_consistent`` and
    ``_signed_volume`` its ``volume`` (both replace trimesh in ``_finish_surface`` for memory); checked on
    a closed sphere, one with a flipped face, one with a face removed and two spheres touching at
    an edge shared by four faces (what ``_repair_pinches`` separates)."""
    from bonecap.phantom import subject as subj

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    flipped = sphere.copy()
    flipped.faces[5] = flipped.faces[5][::-1]
    holed = trimesh.Trimesh(sphere.vertices, sphere.faces[1:], process=False)
    a = trimesh.creation.box(extents=(10, 10, 10))
    b = trimesh.creation.box(extents=(10, 10, 10))
    b.apply_translation((10, 10, 0))                   # the boxes share one edge
    pinched = trimesh.util.concatenate([a, b])
    pinched.merge_vertices()
    for tm in (sphere, flipped, holed, pinched):
        ours = subj._closed_and_oriented(np.asarray(tm.faces), len(tm.vertices))
        assert ours == bool(tm.is_watertight and tm.is_winding_consistent)
    assert subj._closed_and_oriented(np.asarray(sphere.faces), len(sphere.vertices))
    assert not subj._closed_and_oriented(np.asarray(pinched.faces), len(pinched.vertices))
    fixed = subj._repair_pinches(np.asarray(pinched.vertices), np.asarray(pinched.faces))
    assert fixed is not None and subj._closed_and_oriented(fixed[1], len(fixed[0]))
    V, F = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    assert np.isclose(subj._signed_volume(V, F, chunk=100), sphere.volume, rtol=1e-12)
    assert np.isclose(subj._signed_volume(V, F[:, ::-1]), -sphere.volume, rtol=1e-12)

    # an inward-wound level set, extracted and finished, comes out closed, outward and decimated to budget
    ax = np.arange(48, dtype=np.float32)
    X, Y, Z = np.meshgrid(ax, ax, ax, indexing="ij")
    field = (np.sqrt((X - 23.5) ** 2 + (Y - 24.2) ** 2 + (Z - 23.1) ** 2) - 15.0).astype(np.float16)
    mesh = subj._finish_surface(*subj._dense_surface(field, np.zeros(3), 2.0, 4, 1500), 1500, "test")
    assert len(mesh.faces) <= 1500
    assert subj._closed_and_oriented(mesh.faces, len(mesh.vertices))
    vol = subj._signed_volume(mesh.vertices, mesh.faces)
    assert vol > 0 and abs(vol / (4 / 3 * np.pi * 30.0 ** 3) - 1) < 0.05


def test_a_surface_decimated_in_two_halves_stays_closed_and_on_the_surface(monkeypatch):
    """The body surfaces' first decimation runs on two halves with their cut kept (the library's memory
    grows with the faces it is given): joined again, the halves are one closed, consistently wound
    surface with about ``keep`` of the faces, still on the dense one; ``_finish_surface`` then brings
    the whole to its budget, closed."""
    from bonecap.phantom import subject as subj

    tm = trimesh.creation.icosphere(subdivisions=6, radius=80.0)
    tm.vertices *= [1.0, 2.5, 0.8]                                # elongated: the cut goes across its length
    v, f = np.asarray(tm.vertices, np.float32), np.asarray(tm.faces, np.int32)
    hv, hf = subj._presimplify_halves(v, f, 0.6)
    assert abs(len(hf) / len(f) - 0.6) < 0.02
    assert subj._closed_and_oriented(hf, len(hv)) and subj._signed_volume(hv.astype(float), hf) > 0
    half = trimesh.Trimesh(hv, hf, process=False)
    # no gap along the cut: the volume is the dense surface's (a seam left open or doubled would not be)
    assert abs(half.volume / tm.volume - 1.0) < 0.002
    _, dist, _ = trimesh.Trimesh(v, f, process=False).nearest.on_surface(hv[::7])
    assert dist.max() < 0.3

    monkeypatch.setattr(subj, "_HALVES_ABOVE_FACES", 10_000)
    mesh = subj._finish_surface(v, f, 20_000, "test")
    assert len(mesh.faces) <= 20_000 and subj._closed_and_oriented(mesh.faces, len(mesh.vertices))
    _, dist, _ = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).nearest.on_surface(v[::11].astype(float))
    assert dist.mean() < 0.1 and dist.max() < 1.0
