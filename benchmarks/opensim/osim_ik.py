"""OpenSim 4.6 side of ``benchmarks/bench_opensim_peer.py``: scale, inverse kinematics, body poses.

Runs in a separate interpreter that has the ``opensim`` wheel (benchmark only,
never a bonecap dependency), e.g.::

    python3.11 -m venv /tmp/osvenv && /tmp/osvenv/bin/pip install opensim numpy
    /tmp/osvenv/bin/python benchmarks/opensim/osim_ik.py JOB.json

``JOB.json`` (written by the benchmark) holds ``generic`` (the .osim),
``workdir``, ``static_trc``, ``trials`` ({name: trc path}), ``markers`` (the
physical markers: weight 1 each; virtual ones are not in the .trc files and so
not used), ``scale`` (bool), ``mass_kg``, ``accuracy``, ``measurements``
({name: {"pairs": [[m1, m2], ...], "bodies": [...]}}).

The .trc files are in OpenSim's Y-up ground, metres. Steps:

1. ScaleTool (if ``scale``): measurement-based scaling of the generic model
   (marker-pair distances in the static trial over the same in the model),
   then the MarkerPlacer (IK on the static, weights 1, markers moved to the
   static) -> ``scaled.osim``.
2. Per trial: ``InverseKinematicsSolver`` (the engine of InverseKinematicsTool),
   accuracy ``accuracy``, constraint weight infinite, marker weights 1;
   ``assemble`` on the first frame, ``track`` on the others. Only the
   ``track`` loop is timed (CPU ``process_time`` and wall): steady state,
   without model loading, initSystem or the first assembly.
3. The solved coordinates are set frame by frame and every body's
   ``getTransformInGround`` is read, converted to the Z-up lab of the C3D
   (ground (X, Y, Z) -> lab (X, -Z, Y)) and to mm, and written as
   ``<workdir>/<trial>_poses.npz`` with the keys ``bonecap evaluate`` reads.
4. ``<workdir>/osim_result.json``: timings, marker RMS errors, scale factors.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import opensim as osim

C = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # ground (Y-up) -> lab (Z-up)


def trc_times(path: str) -> np.ndarray:
    t = osim.TimeSeriesTableVec3(path)
    return np.array(t.getIndependentColumn())


def scale_model(job: dict, out: Path) -> dict:
    generic = job["generic"]
    times = trc_times(job["static_trc"])
    tr = osim.ArrayDouble()
    tr.append(float(times[0]))
    tr.append(float(times[-1]))
    st = osim.ScaleTool()
    st.setName("subject")
    st.setSubjectMass(job["mass_kg"])
    st.getGenericModelMaker().setModelFileName(generic)
    ms = st.getModelScaler()
    ms.setApply(True)
    order = osim.ArrayStr()
    order.append("measurements")
    ms.setScalingOrder(order)
    ms.setMarkerFileName(job["static_trc"])
    ms.setTimeRange(tr)
    ms.setPreserveMassDist(True)
    mset = ms.getMeasurementSet()
    for name, spec in job["measurements"].items():
        m = osim.Measurement()
        m.setName(name)
        m.setApply(True)
        for a, b in spec["pairs"]:
            m.getMarkerPairSet().cloneAndAppend(osim.MarkerPair(a, b))
        for body in spec["bodies"]:
            bs = osim.BodyScale()
            bs.setName(body)
            axes = osim.ArrayStr()
            for ax in ("X", "Y", "Z"):
                axes.append(ax)
            bs.setAxisNames(axes)
            m.getBodyScaleSet().cloneAndAppend(bs)
        mset.cloneAndAppend(m)
    scaled_only = str(out / "scaled_only.osim")
    ms.setOutputModelFileName(scaled_only)
    ms.setOutputScaleFileName(str(out / "scale_factors.xml"))
    mp = st.getMarkerPlacer()
    mp.setApply(True)
    mp.setStaticPoseFileName(job["static_trc"])
    mp.setTimeRange(tr)
    mp.setMaxMarkerMovement(-1.0)
    tasks = mp.getIKTaskSet()
    for mk in job["markers"]:
        t = osim.IKMarkerTask()
        t.setName(mk)
        t.setApply(True)
        t.setWeight(1.0)
        tasks.cloneAndAppend(t)
    scaled = str(out / "scaled.osim")
    mp.setOutputModelFileName(scaled)
    mp.setOutputMotionFileName(str(out / "static_placed.mot"))
    st.printToXML(str(out / "scale_setup.xml"))
    ok = st.run()
    if not ok or not Path(scaled).is_file():
        raise RuntimeError("ScaleTool failed")
    factors = (out / "scale_factors.xml").read_text() if (out / "scale_factors.xml").is_file() else ""
    return {"scaled_model": scaled, "scale_setup": str(out / "scale_setup.xml"), "scale_factors_xml": factors}


def run_ik(model_path: str, trc: str, markers: list[str], accuracy: float) -> dict:
    model = osim.Model(model_path)
    state = model.initSystem()
    weights = osim.SetMarkerWeights()
    for mk in markers:
        weights.cloneAndAppend(osim.MarkerWeight(mk, 1.0))
    mref = osim.MarkersReference(trc, weights)
    cref = osim.SimTKArrayCoordinateReference()
    solver = osim.InverseKinematicsSolver(model, mref, cref, float("inf"))
    solver.setAccuracy(accuracy)
    times = np.array(mref.getTimes()) if hasattr(mref, "getTimes") else trc_times(trc)
    nq = state.getNQ()
    Q = np.full((len(times), nq), np.nan)
    state.setTime(float(times[0]))
    solver.assemble(state)
    Q[0] = [state.getQ().get(i) for i in range(nq)]
    cpu0, wall0 = time.process_time(), time.perf_counter()
    for k in range(1, len(times)):
        state.setTime(float(times[k]))
        solver.track(state)
        q = state.getQ()
        Q[k] = [q.get(i) for i in range(nq)]
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    bodies = model.getBodySet()
    names = [bodies.get(i).getName() for i in range(bodies.getSize())]
    T = np.zeros((len(times), len(names), 4, 4))
    qv = state.getQ()
    for k in range(len(times)):
        for i in range(nq):
            qv.set(i, float(Q[k, i]))
        state.setQ(qv)
        model.realizePosition(state)
        for j, n in enumerate(names):
            X = bodies.get(j).getTransformInGround(state)
            R = np.array([[X.R().get(a, b) for b in range(3)] for a in range(3)])
            p = np.array([X.p().get(a) for a in range(3)])
            T[k, j, :3, :3] = C @ R
            T[k, j, :3, 3] = 1000.0 * (C @ p)
            T[k, j, 3, 3] = 1.0
    return {"times": times, "bones": names, "transforms": T, "Q": Q, "cpu_s": cpu, "wall_s": wall,
            "tracked_frames": len(times) - 1}


def main(job_path: str) -> None:
    job = json.loads(Path(job_path).read_text())
    out = Path(job["workdir"])
    out.mkdir(parents=True, exist_ok=True)
    result: dict = {"opensim_version": osim.__version__, "scaled": bool(job["scale"]), "trials": {}}
    t0 = time.perf_counter()
    if job["scale"]:
        result.update(scale_model(job, out))
        model_path = result["scaled_model"]
    else:
        model_path = job["generic"]
    result["scale_seconds"] = time.perf_counter() - t0
    for name, trc in job["trials"].items():
        r = run_ik(model_path, trc, job["markers"], job["accuracy"])
        valid = np.isfinite(r["transforms"]).all(axis=(2, 3))
        np.savez(out / f"{name}_poses.npz", bones=np.array(r["bones"]), times=r["times"] - r["times"][0],
                 first_frame=np.int64(job.get("first_frames", {}).get(name, 1)), transforms=r["transforms"],
                 valid=valid, Q=r["Q"])
        result["trials"][name] = {"frames": int(len(r["times"])), "tracked_frames": r["tracked_frames"],
                                  "track_cpu_s": r["cpu_s"], "track_wall_s": r["wall_s"],
                                  "fps_cpu": r["tracked_frames"] / r["cpu_s"] if r["cpu_s"] > 0 else None,
                                  "fps_wall": r["tracked_frames"] / r["wall_s"] if r["wall_s"] > 0 else None}
        print(f"opensim IK {name}: {len(r['times'])} frames, {result['trials'][name]['fps_cpu']:.1f} frames/s CPU",
              flush=True)
    (out / "osim_result.json").write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main(sys.argv[1])
