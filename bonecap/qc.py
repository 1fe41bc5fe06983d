"""Quality-control pictures of build-subject, written next to the subject.

- ``qc/contours_<station>.png``: a mosaic of slices of each station with the
  skin (cyan) and every bone label's contour (one colour per bone) drawn over
  the image — the first thing to look at when a bone comes out wrong — and
  the personal skeleton's outline on the same slices (yellow dashes), where
  the warp put each bone against what the slice rules found.
- ``qc/personal_skeleton_front.png`` / ``_side.png``: the personal skeleton.
- ``qc/warp_residuals.png``: per bone, the warp's residual at its feature
  points and the extracted-vs-personal fit.
- ``qc/spine_levels.png``: the MRI along the spinal column, its dark discs,
  and where the vertebrae's joints were put on them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from bonecap.io.atomic import atomic_path
from bonecap.model import Bone, Skeleton
from bonecap.parallel import fork_start

__all__ = ["contour_mosaic", "write_build_qc"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def contour_mosaic(path: Path, image: np.ndarray, labels: np.ndarray, body: np.ndarray | None = None, *,
                   n_slices: int = 12, title: str = "", pixel_aspect: float = 1.0,
                   outline: np.ndarray | None = None) -> Path:
    """Write a mosaic of ``n_slices`` evenly spaced axial slices with label contours.

    Parameters
    ----------
    image : ndarray [i, j, k]
    labels : ndarray [i, j, k] of int
    body : ndarray [i, j, k] of bool, optional
    outline : ndarray [i, j, k] of int, optional
        A second label map drawn as one yellow dashed outline of all its bones
        (the personal skeleton over the slice rules' contours).
    """
    plt = _plt()
    K = image.shape[2]
    ks = np.unique(np.linspace(0, K - 1, min(n_slices, K)).round().astype(int))
    # a panel shows image[:, :, k].T: i across, j (times the pixel aspect) down. Whole-body stations
    # are ~3x wider than tall: fewer, wider panels keep them readable, and the figure's height follows
    # the panels' (a height from the wrong axis left them a thin strip in a tall empty page)
    wide = image.shape[0] / max(image.shape[1] * pixel_aspect, 1e-9)
    cols = 2 if wide > 2.0 else 4
    rows = int(np.ceil(len(ks) / cols))
    panel_w = 3.2 * float(np.clip(wide, 1.0, 2.5))
    fig, axes = plt.subplots(rows, cols, figsize=(cols * panel_w, rows * (panel_w / wide + 0.3)))
    axes = np.atleast_1d(axes).ravel()
    cmap = plt.get_cmap("tab20")
    vmax = float(np.percentile(image, 99.5)) or 1.0
    for ax, k in zip(axes, ks):
        # rows = j (posterior down), columns = i: the radiological view
        ax.imshow(image[:, :, k].T, cmap="gray", vmin=0, vmax=vmax, interpolation="nearest",
                  aspect=pixel_aspect)
        if body is not None and body[:, :, k].any():
            ax.contour(body[:, :, k].T.astype(float), levels=[0.5], colors="cyan", linewidths=0.5)
        for lab in np.unique(labels[:, :, k]):
            if lab == 0:
                continue
            # tab20's saturated colours first, so that neighbouring ids (femur 1, tibia 2) differ at a glance
            c = (2 * (int(lab) - 1)) % 20 + ((int(lab) - 1) // 10) % 2
            ax.contour((labels[:, :, k] == lab).T.astype(float), levels=[0.5], colors=[cmap(c)], linewidths=0.7)
        if outline is not None and outline[:, :, k].any():
            ax.contour((outline[:, :, k] > 0).T.astype(float), levels=[0.5], colors="yellow", linewidths=0.5,
                       linestyles="dashed")
        ax.set_title(f"slice {k}", fontsize=7)
        ax.axis("off")
    for ax in axes[len(ks):]:
        ax.axis("off")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    return path


def _in_model_frame(skeleton: Skeleton) -> Skeleton:
    """An LPS skeleton turned into the template frame (Y up) for the standard views."""
    if skeleton.world != "lps":
        return skeleton
    from bonecap.build_mri import MODEL_TO_LPS

    L2M = np.linalg.inv(MODEL_TO_LPS)
    bones = {n: Bone(n, b.parent, b.mesh, L2M @ b.bone_to_world) for n, b in skeleton.bones.items()}
    return Skeleton(bones, world="model")


def write_build_qc(qc_dir: Path, subject, data: dict[str, Any], report: dict[str, Any]) -> list[Path]:
    """Write every QC picture of a build-subject run (see the module docstring)."""
    from bonecap.skeleton.generic import render_skeleton_views

    qc_dir = Path(qc_dir)
    qc_dir.mkdir(parents=True, exist_ok=True)
    mosaics = []
    for n, (v, (lab, _aff)) in enumerate(zip(data["vols"], data["pieces"])):
        name = v.metadata.get("series_description") or v.metadata.get("name") or f"station_{n + 1}"
        safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in str(name))
        sp = v.spacing
        body = data.get("bodies", [None] * len(data["vols"]))[n] if data.get("bodies") else None
        personal = data["personal"][n] if data.get("personal") else None
        what = "bone contours (colours), personal skeleton (yellow dashes)" if personal is not None \
            else "bone contours (colours)"
        mosaics.append(((qc_dir / f"contours_{n + 1:02d}_{safe}.png", v.data, lab, body),
                        {"title": f"{name}: {what} and skin (cyan)", "pixel_aspect": float(sp[0] / sp[1]),
                         "outline": personal}))
    # the stations' mosaics (matplotlib, ~1 s each) in worker processes while the skeleton's views are
    # rendered here (VTK's off-screen window stays in this process)
    drawing = fork_start(lambda m: contour_mosaic(*m[0], **m[1]), mosaics)
    try:
        views = render_skeleton_views(_in_model_frame(subject.skeleton), qc_dir, prefix="personal_skeleton")
    except BaseException:
        drawing.close()
        raise
    out = drawing.result() + views
    warp = report.get("warp") or {}
    per_bone = warp.get("bones", warp) if isinstance(warp, dict) else {}
    rows = [(b, r) for b, r in per_bone.items() if isinstance(r, dict) and r.get("residual_mean_mm") is not None]
    if rows:
        plt = _plt()
        fig, ax = plt.subplots(figsize=(8, max(3, 0.18 * len(rows))))
        names = [b for b, _ in rows]
        ax.barh(names, [r["residual_mean_mm"] for _, r in rows], label="mean")
        ax.barh(names, [r.get("residual_max_mm") or np.nan for _, r in rows], alpha=0.3, label="max")
        ax.set_xlabel("warp residual at the feature points (mm)")
        ax.tick_params(axis="y", labelsize=6)
        ax.legend()
        fig.tight_layout()
        p = qc_dir / "warp_residuals.png"
        with atomic_path(p) as tmp:
            fig.savefig(tmp, dpi=100, format="png")
        plt.close(fig)
        out.append(p)
    if data.get("spine"):
        out.append(spine_levels_plot(qc_dir / "spine_levels.png", data["spine"]))
    return out


def spine_levels_plot(path: Path, prof: dict[str, Any]) -> Path:
    """The profile along the spinal column with its dark dips, where the warp's spread put the discs and
    where they were matched (:func:`bonecap.segmentation.spine.spine_levels`'s ``profile_out``)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(12, 3.2))
    s, v = np.asarray(prof["s"]), np.asarray(prof["values"])
    ax.plot(s, v, color="0.3", lw=1, label="MRI along the column")
    lo, hi = np.nanmin(v), np.nanmax(v)
    for i, x in enumerate(prof["dips"]):
        ax.axvline(x, color="tab:blue", lw=0.6, ls=":", label="dark dips" if i == 0 else None)
    e, d = np.asarray(prof["expected"]), np.asarray(prof["matched"])
    ax.plot(e, np.full(len(e), lo), "v", color="tab:red", ms=5, label="discs as spread (template proportions)")
    ok = np.isfinite(d)
    ax.plot(e[ok] + d[ok], np.full(ok.sum(), hi), "^", color="tab:green", ms=5, label="discs matched")
    ax.set_xlabel("arc length along the column from the lumbosacral joint (mm)")
    ax.set_ylabel("intensity")
    rep = prof.get("report") or {}
    verdict = "the vertebrae moved onto the matched discs" if rep.get("used") else \
        f"not used: {rep.get('reason', 'refused')} (the template's proportions kept)"
    ax.set_title(f"spine levels: {rep.get('matched', 0)} of {rep.get('discs', len(e))} discs matched; {verdict}",
                 fontsize=9, pad=28)
    ax.legend(fontsize=7, ncol=4, loc="upper center", bbox_to_anchor=(0.5, 1.22))
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return path
