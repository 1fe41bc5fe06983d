"""The ``bonecap`` command line: argparse wiring only.

Each sub-command parses its arguments and calls one library function; the
logic lives in the stage modules so everything is usable from Python.

Exit codes: 0 success, 1 bad input (a :class:`~bonecap.errors.BonecapError`,
reported on one line as ``bonecap: error: PATH: what is wrong``), 2 bad usage
(argparse's own convention).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Callable, Sequence

from bonecap import __version__
from bonecap.errors import BonecapError

Handler = Callable[[argparse.Namespace], int]


def _cmd_inspect(args: argparse.Namespace) -> int:
    from bonecap.inspect import format_summary, inspect_path

    # Every path is summarised before anything is written, so one bad input
    # leaves no output at all.
    summaries = [inspect_path(p, subject=args.subject) for p in args.paths]
    if args.out_dir:
        from bonecap.inspect import write_summaries

        for written in write_summaries(summaries, args.out_dir):
            print(f"wrote {written}", file=sys.stderr)
    if args.json:
        out = summaries[0] if len(summaries) == 1 else summaries
        print(json.dumps(out, indent=2, default=str))
    else:
        print("\n\n".join(format_summary(s) for s in summaries))
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from bonecap.demo import format_report, run_demo

    report = run_demo(args.out_dir, args.generic, n_frames=args.frames, seed=args.seed,
                      phantom=not args.no_phantom, preset=args.preset)
    print(format_report(report))
    return 0


def _cmd_phantom(args: argparse.Namespace) -> int:
    from bonecap.phantom import PRESETS, make_phantom

    summary = make_phantom(args.out_dir, seed=args.seed, stature_mm=args.stature * 1000.0 if args.stature else None,
                           generic=args.generic, preset=args.preset, marker_capsules=args.marker_capsules)
    print(f"phantom seed {summary['seed']} ({summary['preset']}): {summary['bones']} bones, "
          f"stature {summary['stature_mm']:.0f} mm")
    print(f"  MRI: {len(summary['stations'])} stations and forearm stacks "
          f"{', '.join(summary['forearm_stacks'])} deg in {args.out_dir}/mri")
    print(f"  trials: {', '.join(summary['trials'])} in {args.out_dir}/trials")
    print(f"  truth: {args.out_dir}/truth (formats in truth/README.md)")
    print(f"  took {summary['wall_s']:.1f} s: "
          + ", ".join(f"{k} {v:.1f}" for k, v in summary["timings_s"].items())
          + (" (trials made beside the MRI)" if PRESETS[summary["preset"]]["trials_beside"] else ""))
    return 0


def _cmd_build_subject(args: argparse.Namespace) -> int:
    from bonecap.build_subject import run_build_subject

    report = run_build_subject(args.mri, args.out_dir, generic=args.generic, marker_set=args.marker_set,
                               static=args.static, forearm_poses=args.forearm_poses, seeds=args.seeds,
                               labels=args.labels, subject_name=args.subject, static_frames=args.static_frames,
                               functional=args.functional)
    print(report["summary"])
    return 0


def _cmd_animate(args: argparse.Namespace) -> int:
    from bonecap.animate import animate, format_report

    if args.max_gap_frames < 0:
        raise BonecapError(f"--max-gap-frames must be >= 0, got {args.max_gap_frames}")
    if args.lowpass is not None and args.lowpass <= 0:
        raise BonecapError(f"--lowpass must be a positive cut-off in Hz, got {args.lowpass}")
    report = animate(args.subject_dir, args.trials, args.out_dir, solver=args.solver,
                     forearm=not args.no_forearm_model, max_gap_frames=args.max_gap_frames,
                     lowpass_hz=args.lowpass, subject_name=args.subject)
    print(format_report(report))
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from bonecap import evaluate

    if args.what == "motion":
        result = evaluate.evaluate_motion(args.path, args.truth)
        text = evaluate.format_motion_table(result)
    else:
        result = evaluate.evaluate_subject(args.path, args.truth)
        text = evaluate.format_subject_table(result)
    print(json.dumps(result, indent=2, default=float) if args.json else text)
    return 0


def _add_generic(p: argparse.ArgumentParser) -> None:
    p.add_argument("--generic", default="default", metavar="default|MODEL.osim",
                   help="template skeleton: bonecap's embedded one (default) or an OpenSim model")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bonecap",
        description="From a person's MRI to their own skeleton, driven by optical motion capture.",
    )
    parser.add_argument("--version", action="version", version=f"bonecap {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser(
        "inspect",
        help="summarise a C3D trial, a DICOM folder, a NIfTI/NRRD volume, a glTF or a mesh",
        description="Summarise input files: C3D (frames, rate, units as stored, markers, gaps, "
        "analogs), DICOM folders (each series: shape, spacing, orientation, echo), NIfTI/NRRD "
        "volumes, glTF (nodes, animation length) and meshes.",
    )
    p.add_argument("paths", nargs="+", metavar="PATH", help="file or DICOM folder")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.add_argument("--subject", metavar="NAME", help="C3D: the subject prefix to keep")
    p.add_argument("-o", dest="out_dir", metavar="OUT_DIR",
                   help="also write each summary as OUT_DIR/<name>.summary.json")
    p.set_defaults(handler=_cmd_inspect)

    p = sub.add_parser(
        "demo",
        help="run every stage that exists, end to end, on the embedded default",
        description="Build the template skeleton, write its meshes and pictures, place its markers, "
        "move it by a synthetic motion written as a C3D trial, recover the motion from that trial, "
        "export it as an animated glTF, make a phantom subject with its truth, build the personal "
        "skeleton from its MRI, animate its trials and score both against the truth.",
    )
    p.add_argument("-o", dest="out_dir", required=True, metavar="OUT_DIR", help="output folder")
    _add_generic(p)
    p.add_argument("--frames", type=int, default=200, help="length of the synthetic trial (default 200)")
    p.add_argument("--seed", type=int, default=0, help="seed of the marker noise and the phantom")
    p.add_argument("--preset", choices=("default", "tiny"), default="default",
                   help="the phantom subject: the whole body (default: 8 MRI stations, a few minutes) or "
                   "the reduced one the tests use (tiny: 2 coarse stations, too few for the personal "
                   "skeleton's warp)")
    p.add_argument("--no-phantom", action="store_true", help="skip the phantom subject")
    p.set_defaults(handler=_cmd_demo)

    p = sub.add_parser(
        "phantom",
        help="make a synthetic subject with ground truth: MRI stations, forearm stacks, C3D trials",
        description="Make a synthetic subject (a varied skeleton and body) with whole-body MRI stations, "
        "forearm stacks with oil capsules, motion-capture trials and the ground truth of all of them.",
    )
    p.add_argument("-o", dest="out_dir", required=True, metavar="OUT_DIR", help="output folder")
    p.add_argument("--seed", type=int, default=0, help="seed (everything is deterministic for it)")
    p.add_argument("--stature", type=float, metavar="M", help="stature in metres (default: drawn around 1.70)")
    _add_generic(p)
    p.add_argument("--preset", choices=["tiny", "default"], default="default",
                   help="tiny: a few coarse stations and short trials (for tests); default: the full subject")
    p.add_argument("--marker-capsules", action="store_true",
                   help="image an 8 mm oil capsule under every trial marker in the stations and under the "
                        "forearm's markers in the forearm stacks (the paper's protocol)")
    p.set_defaults(handler=_cmd_phantom)

    p = sub.add_parser(
        "build-subject",
        help="MRI stations (or a static trial alone) -> personal skeleton with bound markers",
        description="Build a subject folder: register the MRI stations, segment skin and bones slice by "
        "slice, mesh them, warp the template onto them (affine + Gaussian RBF), place and bind the markers "
        "(posed to a static trial when given), fit the forearm model from three forearm stacks. Without "
        "MRI, scale the template to a static trial.",
    )
    p.add_argument("mri", nargs="*", metavar="MRI_PATH",
                   help="DICOM folders (one per station, or one holding several series), NIfTI or NRRD")
    p.add_argument("-o", dest="out_dir", required=True, metavar="SUBJECT_DIR", help="output subject folder")
    _add_generic(p)
    p.add_argument("--marker-set", metavar="NAME|FILE.yaml",
                   help="marker set (default: Kojima's set for MRI subjects, the template's otherwise)")
    p.add_argument("--static", metavar="STATIC.c3d", help="static trial: pose the skeleton and bind the markers")
    p.add_argument("--functional", metavar="TRIAL.c3d", nargs="+",
                   help="movement trials with knee flexion (walking): each femur's twist about its long axis "
                   "from the knee's flexion axis (the static's thigh and knee markers fix it poorly); needs --static")
    p.add_argument("--static-frames", metavar="START:STOP",
                   help="frames of --static to average (0-based, STOP excluded; default all), e.g. the quiet "
                   "stance at the start of a movement trial when there is no static trial")
    p.add_argument("--forearm-poses", nargs=3, metavar="DIR", help="three forearm stacks (about 0/90/180 deg)")
    p.add_argument("--seeds", metavar="SEEDS.yaml", help="bone seeds in world mm (override the template's)")
    p.add_argument("--labels", metavar="LABELMAP", help="your own bone label map (skips contour extraction)")
    p.add_argument("--subject", metavar="NAME", help="C3D: the subject prefix to keep")
    p.set_defaults(handler=_cmd_build_subject)

    p = sub.add_parser(
        "animate",
        help="C3D trials -> each bone's pose per frame -> animated glTF, poses, angles, residuals",
        description="Solve every bone's pose in every frame of one or more C3D trials for a subject "
        "folder, and write an animated glTF, the poses (NPZ), joint angles (CSV), a residual plot and a "
        "copy of the trial with the joint centres and angles.",
    )
    p.add_argument("subject_dir", metavar="SUBJECT_DIR", help="a folder written by build-subject")
    p.add_argument("trials", nargs="+", metavar="TRIAL.c3d")
    p.add_argument("-o", dest="out_dir", required=True, metavar="OUT_DIR", help="output folder")
    p.add_argument("--solver", choices=["lsq", "paper"], default="lsq",
                   help="lsq: joint-coupled least squares (default); paper: Kojima et al.'s axis rules")
    p.add_argument("--no-forearm-model", action="store_true",
                   help="solve radius and ulna from their markers, not the pronation model")
    p.add_argument("--max-gap-frames", type=int, default=10, metavar="N",
                   help="interpolate a bone over gaps up to N frames, flag it invalid beyond (default 10)")
    p.add_argument("--lowpass", type=float, metavar="HZ",
                   help="zero-lag Butterworth low-pass of the markers before solving (cut-off in Hz)")
    p.add_argument("--subject", metavar="NAME", help="C3D: the subject prefix to keep")
    p.set_defaults(handler=_cmd_animate)

    p = sub.add_parser(
        "evaluate",
        help="score a subject folder or animated trials against ground truth",
        description="Compare bonecap's results with ground truth (a phantom's truth folder): "
        "'subject' scores a subject folder, 'motion' an animate output folder.",
    )
    p.add_argument("what", choices=["subject", "motion"])
    p.add_argument("path", metavar="DIR", help="SUBJECT_DIR or the animate OUT_DIR")
    p.add_argument("--truth", required=True, metavar="DIR", help="ground truth folder (a phantom's truth/)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(handler=_cmd_evaluate)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``bonecap`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    handler: Handler = args.handler
    try:
        return handler(args)
    except BonecapError as exc:
        print(f"bonecap: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("bonecap: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # stdout closed early (`bonecap inspect ... | head`): not an error of ours.
        sys.stderr.close()
        return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
