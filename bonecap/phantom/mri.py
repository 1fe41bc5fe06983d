"""MRI of the phantom: whole-body stations and forearm stacks rendered from meshes, with truth.

The image is *rendered from the surfaces*, never painted from a label grid:
for every slice, each layer mesh is cut by several planes across the slice
thickness, the sections are scan-converted with exact coverage along rows
and supersampled along columns (:mod:`bonecap.phantom.render`), and each
voxel gets the partial-volume mix of its tissues' intensities. A smooth
multiplicative bias field, a per-voxel tissue texture and Rician noise follow.
Tissue intensities, texture and noise are measured on the real knee MRI in
``../shared/data/mri/knee_mese_t2_echo1_dicom`` (GE 3 T multi-echo spin echo,
first echo) and stored in ``tissue_intensities.yaml`` beside this module, so
the phantom runs without the shared data and has a real scanner's contrast.

Public API
----------
Tissue intensities
    - :data:`KNEE_ROIS` -- the ROI boxes measured on the knee (documented there).
    - :func:`measure_knee_tissues` ``(knee_dir, rois=KNEE_ROIS) -> dict``
    - :func:`tissue_table` ``(measured) -> dict`` -- the phantom's tissue table
      derived from the measurements (adds air and the assumed oil).
    - :func:`write_tissue_intensities` ``(knee_dir, path=TISSUE_YAML) -> Path``
    - :func:`load_tissue_intensities` ``(path=TISSUE_YAML) -> dict``
Rendering
    - :func:`render_volume` ``(layers, affine, shape, *, slice_thickness_mm,
      inplane_supersample, through_plane_samples, intensities, rng, bias, noise,
      texture, scale, motion) -> ndarray float32``
    - re-exported from :mod:`bonecap.phantom.render`: :func:`tissue_fractions`,
      :func:`mesh_coverage`, :func:`voxelise_labels` (the oracle).
Whole-body stations
    - :class:`StationPlan`, :func:`plan_stations` ``(body, n_stations=8, ...)``
    - :class:`StationTruth`, :class:`StationsResult`,
      :func:`render_stations` ``(layers, plans, out_dir, rng, *, label_meshes,
      merged_voxel_mm=2.0, on_station=None, keep_labels=True, ...) -> StationsResult``
    - :func:`merged_grid` ``(meshes, voxel_mm=2.0, margin_mm=10.0) -> (affine, shape)``
Forearm stacks and capsules
    - :class:`CapsulePlacement`, :func:`place_capsules` ``(skin_mesh, n, rng, ...)``,
      :func:`capsule_meshes`, :func:`icosphere`, :func:`capsule_centres_on`, :data:`CAPSULE_DIAMETER_MM`
    - :class:`ForearmPose`, :func:`plan_forearm_stack`,
      :class:`ForearmTruth`, :func:`render_forearm_stacks` ``(poses, out_dir, rng, ...)``

Frames and conventions
----------------------
- Meshes are closed surfaces in the **LPS world, mm** (``+x`` left, ``+y``
  posterior, ``+z`` superior), the frame of the truth ("true world").
- ``affine`` is always ``voxel_to_lps`` (:class:`bonecap.model.Volume`);
  stations are axial: ``i`` along ``+x``, ``j`` along ``+y``, ``k`` along
  ``+z`` (the slice normal is the affine's third column). ``data[i, j, k]``.
- **Patient motion per station.** ``StationPlan.true_to_nominal`` (4x4,
  rigid, ``p_nominal = true_to_nominal @ p_true``) maps a point of the true
  body to where it lay while that station was acquired, in the scanner
  coordinates that the DICOM header (the *nominal* geometry,
  ``StationPlan.affine``) describes. The renderer images the meshes moved by
  it, the header carries the nominal affine, so the world position of
  station voxel ``ijk`` in the true frame is ``inv(true_to_nominal) @ affine
  @ ijk``. It is a rotation about the station's FOV centre ``c`` (angle <= 1
  deg) followed by a translation of that centre (<= 3 mm); points far from
  ``c`` move by up to ``3 mm + 1 deg x distance``. build-subject has to
  recover these transforms (up to a common rigid motion of the whole body).
- Stations are numbered from 1 at the head (``station_1``) to the feet;
  ``SeriesNumber`` is the station number, all stations share one
  ``StudyInstanceUID`` and one ``FrameOfReferenceUID`` (one exam).
- Each station has its own ``intensity_scale`` (receiver gain: multiplies
  signal and noise) and its own bias field.
- Forearm stacks are axial *to the forearm axis* (elbow -> wrist = ``+k``),
  imaged without patient motion (``true_to_nominal`` = identity).

Imaging model (per voxel)
-------------------------
``value = scale * | b(x) * sum_t f_t * m_t * (1 + c_t * g(x)) + sigma * (n1 + i n2) |``
with ``f_t`` the painter's-order partial-volume fractions of tissue ``t``
(``air`` fills the rest), ``m_t`` the tissue mean and ``c_t`` its texture
coefficient of variation from the YAML, ``g`` a unit-variance Gaussian random
field smoothed to ``texture_corr_mm`` in-plane and independent between
slices (shared by all tissues; the factor ``(1 + c g)`` is in fact the
log-normal ``exp(s g - s^2/2)`` with ``s^2 = log(1 + c^2)``: positive, mean 1,
coefficient of variation ``c``), ``b`` a
random quadratic polynomial over the FOV with ``max |b - 1| = bias``, and
``n1, n2`` independent standard normals (the magnitude of complex Gaussian
noise is Rician). Values are rounded to integers and written as 16-bit
unsigned DICOM (no rescale), like a scanner's magnitude images.

References
----------
- Gudbjartsson H, Patz S. The Rician distribution of noisy MRI data. *Magn
  Reson Med* 34(6):910-914, 1995 (magnitude noise; background mean =
  ``sigma sqrt(pi/2)``).
- Immerkaer J. Fast noise variance estimation. *Comput Vis Image Underst*
  64(2):300-302, 1996 (the in-tissue noise cross-check).
- Sled JG, Zijdenbos AP, Evans AC. A nonparametric method for automatic
  correction of intensity nonuniformity in MRI data. *IEEE Trans Med Imaging*
  17(1):87-97, 1998 (smooth multiplicative bias model).
- Collins DL, Zijdenbos AP, Kollokian V, et al. Design and construction of a
  realistic digital brain phantom. *IEEE Trans Med Imaging* 17(3):463-468,
  1998 (BrainWeb: partial-volume phantom, bias and Rician noise applied to
  rendered tissue fractions).
"""

from __future__ import annotations

import functools
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy import ndimage

from bonecap.model import Mesh, Volume
from bonecap.phantom.render import iter_tissue_slabs, mesh_coverage, tissue_fractions, voxelise_labels

__all__ = [
    "TISSUE_YAML",
    "KNEE_ROIS",
    "measure_knee_tissues",
    "tissue_table",
    "write_tissue_intensities",
    "load_tissue_intensities",
    "render_volume",
    "tissue_fractions",
    "mesh_coverage",
    "voxelise_labels",
    "StationPlan",
    "StationTruth",
    "StationsResult",
    "plan_stations",
    "render_stations",
    "merged_grid",
    "write_merged_labels",
    "CapsulePlacement",
    "place_capsules",
    "capsule_meshes",
    "icosphere",
    "CAPSULE_DIAMETER_MM",
    "capsule_centres_on",
    "ForearmPose",
    "ForearmTruth",
    "plan_forearm_stack",
    "render_forearm_stacks",
]

#: The MRI-visible oil capsules' diameter (mm): the paper's 8 mm.
CAPSULE_DIAMETER_MM = 8.0

#: The measured tissue table shipped with the package.
TISSUE_YAML = Path(__file__).with_name("tissue_intensities.yaml")

#: Knee ROIs, half-open voxel boxes ``[i0, i1) x [j0, j1) x [k0, k1)`` of
#: ``read_dicom_series(knee_dir)[0].data`` (``i`` = DICOM column, running
#: anterior -> posterior in this sagittal series; ``j`` = row, superior ->
#: inferior; ``k`` = slice, 4 mm apart). All boxes use slices 10-14, the
#: central slices through the femoral and tibial shafts, and lie in the rows
#: j <= 200 where the coil's sensitivity is flat (below j ~ 200 the signal
#: falls off by ~30 %). Chosen by looking at the slices (0.625 mm pixels).
KNEE_ROIS: dict[str, dict[str, Any]] = {
    "marrow_femur": {
        "box": [104, 128, 30, 80, 10, 15],
        "statistic": "mean",
        "what": "yellow marrow of the distal femoral shaft/metaphysis, above the physeal scar, "
                "clear of the cortex by >= 5 px",
    },
    "marrow_tibia": {
        "box": [112, 148, 176, 196, 10, 15],
        "statistic": "mean",
        "what": "yellow marrow of the proximal tibial metaphysis, below the physeal scar",
    },
    "cortex": {
        "box": [128, 146, 8, 56, 10, 15],
        "statistic": "darkest2_along_i",
        "what": "posterior cortex of the femoral shaft: a 3-5 px dark band that moves from i ~ 131 "
                "(k = 10) to i ~ 141 (k = 14); per (j, k) the mean of the 2 darkest pixels of the "
                "profile along i, so only the band's core is measured (partial volume at its edges "
                "excluded; biased slightly low by the selection)",
    },
    "muscle": {
        "box": [198, 212, 150, 200, 10, 15],
        "statistic": "mean",
        "what": "gastrocnemius, posterior calf, between the posterior fascia and the deep septa",
    },
    "fat": {
        "box": [200, 212, 74, 94, 10, 15],
        "statistic": "mean",
        "what": "posterior subcutaneous / popliteal fat above the gastrocnemius heads, between septa",
    },
    "background": {
        "box": [236, 254, 10, 110, 10, 15],
        "statistic": "rician_background",
        "what": "air behind the posterior skin (skin at i ~ 217-225 in these rows); Rician "
                "background: sigma = mean / sqrt(pi / 2)",
    },
}

#: Assumed oil-capsule intensity relative to fat (not measured: the knee holds
#: no capsule). Vitamin-E / fish-oil capsules are fat-like with a longer T2
#: than adipose tissue, hence brighter on a T2-weighted echo.
OIL_OVER_FAT = 1.3

#: Assumed in-plane correlation length of tissue texture (mm): the knee ROIs'
#: lag-1 autocorrelation at 0.625 mm pixels is 0.65-0.9, i.e. a Gaussian
#: correlation of roughly 1 mm.
TEXTURE_CORR_MM = 1.0

_BUILTIN_TISSUES = ("air", "fat", "muscle", "cortex", "marrow", "oil")


# --------------------------------------------------------------------------- #
# tissue intensities from the knee
# --------------------------------------------------------------------------- #
def _detrended_std(roi: np.ndarray) -> float:
    """Std of the ROI after removing a plane ``a + b i + c j`` per slice (coil shading)."""
    I, J, K = roi.shape
    ii, jj = np.meshgrid(np.arange(I, dtype=float), np.arange(J, dtype=float), indexing="ij")
    A = np.c_[np.ones(I * J), ii.ravel(), jj.ravel()]
    res = []
    for k in range(K):
        y = roi[:, :, k].ravel().astype(float)
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        res.append(y - A @ coef)
    return float(np.concatenate(res).std())


def _immerkaer_sigma(image: np.ndarray, box: Sequence[int]) -> float:
    """Immerkaer (1996) noise sigma inside a box, per slice, pooled."""
    i0, i1, j0, j1, k0, k1 = box
    kern = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], float)
    vals = []
    for k in range(k0, k1):
        r = ndimage.convolve(image[:, :, k].astype(float), kern)[i0 + 1:i1 - 1, j0 + 1:j1 - 1]
        vals.append(np.abs(r).ravel())
    v = np.concatenate(vals)
    return float(math.sqrt(math.pi / 2) * v.mean() / 6.0)


def measure_knee_tissues(knee_dir: str | os.PathLike, rois: Mapping[str, Mapping[str, Any]] | None = None
                         ) -> dict[str, Any]:
    """Measure tissue statistics in fixed ROIs of the real knee MRI.

    Parameters
    ----------
    knee_dir : path-like
        The knee DICOM folder (``../shared/data/mri/knee_mese_t2_echo1_dicom``).
    rois : mapping, optional
        ``name -> {"box": [i0, i1, j0, j1, k0, k1], "statistic": ...}``;
        default :data:`KNEE_ROIS`. Statistics: ``"mean"`` (all voxels),
        ``"darkest2_along_i"`` (per ``(j, k)`` profile the mean of its two
        lowest values), ``"rician_background"`` (air).

    Returns
    -------
    dict
        Per ROI name: ``mean``, ``std``, ``n`` and, for ``"mean"`` ROIs,
        ``detrended_std`` (after a per-slice plane fit, i.e. without coil
        shading); for the background also ``sigma`` = ``mean / sqrt(pi/2)``.
        Plus ``noise_sigma_immerkaer_muscle`` (cross-check of the noise level
        inside tissue, Immerkaer 1996, on the muscle ROI when present).

    Raises
    ------
    ValueError
        A box outside the image or empty, or an unknown statistic.
    bonecap.errors.InputError
        ``knee_dir`` holds no readable series.

    References
    ----------
    Gudbjartsson & Patz 1995 (Rician background); Immerkaer 1996.
    """
    from bonecap.io.imaging import read_dicom_series

    rois = KNEE_ROIS if rois is None else rois
    vols = read_dicom_series(knee_dir)
    image = vols[0].data.astype(float)
    out: dict[str, Any] = {}
    for name, spec in rois.items():
        box = [int(v) for v in spec["box"]]
        if len(box) != 6:
            raise ValueError(f"ROI {name!r}: box must be [i0, i1, j0, j1, k0, k1], got {spec['box']}")
        i0, i1, j0, j1, k0, k1 = box
        if not (0 <= i0 < i1 <= image.shape[0] and 0 <= j0 < j1 <= image.shape[1]
                and 0 <= k0 < k1 <= image.shape[2]):
            raise ValueError(f"ROI {name!r}: box {box} is empty or outside the image {image.shape}")
        roi = image[i0:i1, j0:j1, k0:k1]
        stat = spec.get("statistic", "mean")
        if stat == "mean":
            out[name] = {"mean": float(roi.mean()), "std": float(roi.std()),
                         "detrended_std": _detrended_std(roi), "n": int(roi.size)}
        elif stat == "darkest2_along_i":
            core = np.sort(roi, axis=0)[:2].mean(axis=0)
            out[name] = {"mean": float(core.mean()), "std": float(core.std()), "n": int(core.size)}
        elif stat == "rician_background":
            m = float(roi.mean())
            out[name] = {"mean": m, "std": float(roi.std()), "n": int(roi.size),
                         "sigma": m / math.sqrt(math.pi / 2)}
        else:
            raise ValueError(f"ROI {name!r}: unknown statistic {stat!r}")
    if "muscle" in rois:
        out["noise_sigma_immerkaer_muscle"] = _immerkaer_sigma(image, rois["muscle"]["box"])
    return out


def tissue_table(measured: Mapping[str, Any]) -> dict[str, Any]:
    """The phantom's tissue table from knee measurements.

    Parameters
    ----------
    measured : mapping
        Output of :func:`measure_knee_tissues` (needs ``marrow_femur``,
        ``marrow_tibia``, ``cortex``, ``muscle``, ``fat``, ``background``).

    Returns
    -------
    dict
        ``{"noise_sigma": float, "tissues": {name: {"mean", "texture_cv"}}}``
        for air, fat, muscle, cortex, marrow, oil. ``noise_sigma`` is the
        Rician background sigma. ``texture_cv`` is the part of an ROI's
        (detrended) spread that noise does not explain, relative to its mean:
        ``sqrt(max(std^2 - sigma^2, 0)) / mean``. Marrow is the mean of the
        femoral and tibial ROIs; air is 0 (its measured mean is the noise
        floor, reproduced by the Rician noise); oil is ``OIL_OVER_FAT`` x fat,
        without texture (an assumption: a homogeneous liquid).

    Raises
    ------
    KeyError
        A needed ROI is missing.
    """
    sigma = float(measured["background"]["sigma"])

    def cv(std: float, mean: float) -> float:
        return math.sqrt(max(std * std - sigma * sigma, 0.0)) / mean if mean > 0 else 0.0

    mf, mt = measured["marrow_femur"], measured["marrow_tibia"]
    marrow_mean = 0.5 * (mf["mean"] + mt["mean"])
    marrow_cv = 0.5 * (cv(mf["detrended_std"], mf["mean"]) + cv(mt["detrended_std"], mt["mean"]))
    fat, mus, cor = measured["fat"], measured["muscle"], measured["cortex"]
    tissues = {
        "air": {"mean": 0.0, "texture_cv": 0.0},
        "fat": {"mean": fat["mean"], "texture_cv": cv(fat["detrended_std"], fat["mean"])},
        "muscle": {"mean": mus["mean"], "texture_cv": cv(mus["detrended_std"], mus["mean"])},
        "cortex": {"mean": cor["mean"], "texture_cv": cv(cor["std"], cor["mean"])},
        "marrow": {"mean": marrow_mean, "texture_cv": marrow_cv},
        "oil": {"mean": OIL_OVER_FAT * fat["mean"], "texture_cv": 0.0},
    }
    tissues = {k: {kk: round(float(vv), 4) for kk, vv in v.items()} for k, v in tissues.items()}
    return {"noise_sigma": round(sigma, 4), "tissues": tissues}


def _rounded(obj):
    if isinstance(obj, float):
        return round(obj, 4)
    if isinstance(obj, dict):
        return {k: _rounded(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_rounded(v) for v in obj]
    return obj


def write_tissue_intensities(knee_dir: str | os.PathLike, path: str | os.PathLike = TISSUE_YAML) -> Path:
    """Measure the knee and write the tissue table with its ROI definitions as YAML.

    Parameters
    ----------
    knee_dir : path-like
        The knee DICOM folder.
    path : path-like
        Output YAML (default: the package's ``tissue_intensities.yaml``).

    Returns
    -------
    pathlib.Path
    """
    import yaml

    from bonecap.io.atomic import atomic_path

    measured = measure_knee_tissues(knee_dir)
    table = tissue_table(measured)
    doc = {
        "source": {
            "series": "../shared/data/mri/knee_mese_t2_echo1_dicom",
            "description": "GE 3 T knee, sagittal multi-echo spin echo (T2 map), echo 1 (TE 6.3 ms, TR 2450 ms), "
                           "256x256 at 0.625 mm, 3 mm slices 4 mm apart, HD TR knee coil; "
                           "gattia/pymskt data (MIT)",
            "reader": "bonecap.io.imaging.read_dicom_series(folder)[0].data[i, j, k] (float, scanner units)",
            "box_convention": "half-open voxel boxes [i0, i1) x [j0, j1) x [k0, k1); i = column "
                              "(anterior -> posterior), j = row (superior -> inferior), k = slice",
        },
        "rois": {k: dict(v) for k, v in KNEE_ROIS.items()},
        "measured": _rounded(measured),
        "assumptions": {
            "oil_over_fat": OIL_OVER_FAT,
            "oil": "capsule oil is not in the knee; assumed OIL_OVER_FAT x fat (longer T2 than adipose "
                   "tissue), no texture",
            "texture_corr_mm": TEXTURE_CORR_MM,
            "noise": "noise_sigma is the Rician background sigma; the background here is partly "
                     "suppressed by the vendor (many exact zeros), so the in-tissue Immerkaer estimate "
                     "(measured.noise_sigma_immerkaer_muscle) is larger; the rest of each ROI's spread is "
                     "modelled as texture (texture_cv)",
            "scale": "only relative contrast matters: each station multiplies everything by its own "
                     "intensity scale",
        },
        "noise_sigma": table["noise_sigma"],
        "tissues": table["tissues"],
    }
    header = ("# Tissue intensities of the MRI phantom, measured on a real knee MRI.\n"
              "# Generated by bonecap.phantom.mri.write_tissue_intensities(knee_dir); do not edit by hand:\n"
              "# tests/test_phantom_mri.py re-measures the ROIs below and checks these numbers (1 %).\n")
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(header + yaml.safe_dump(doc, sort_keys=False, width=100, default_flow_style=None))
    return path


def load_tissue_intensities(path: str | os.PathLike | None = None) -> dict[str, Any]:
    """Read the tissue table (default: the package's ``tissue_intensities.yaml``).

    Parameters
    ----------
    path : path-like, optional

    Returns
    -------
    dict
        The whole YAML document; the renderer uses ``tissues`` (``{name:
        {"mean", "texture_cv"}}``) and ``noise_sigma``.

    Raises
    ------
    ValueError
        The file lacks ``tissues`` or ``noise_sigma``.
    """
    from bonecap.io import load_yaml

    path = TISSUE_YAML if path is None else Path(path)
    doc = load_yaml(Path(path).read_text())
    if not isinstance(doc, dict) or "tissues" not in doc or "noise_sigma" not in doc:
        raise ValueError(f"{path}: not a tissue table (needs 'tissues' and 'noise_sigma')")
    return doc


_TABLE_CACHE: dict[str, Any] = {}


def _default_table() -> dict[str, Any]:
    if "doc" not in _TABLE_CACHE:
        _TABLE_CACHE["doc"] = load_tissue_intensities()
    return _TABLE_CACHE["doc"]


# --------------------------------------------------------------------------- #
# rendering
# --------------------------------------------------------------------------- #
def _as_rng(rng) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None:
        # Reproducible by default: a phantom must come out the same twice.
        return np.random.default_rng(0)
    if isinstance(rng, (int, np.integer)):
        return np.random.default_rng(int(rng))
    raise ValueError(f"rng must be a numpy Generator, an int seed or None, got {type(rng).__name__}")


def _resolve_tissues(tissue_names: Sequence[str], intensities, texture, noise):
    """Means, texture CVs and noise sigma for the tissues used."""
    table = _default_table()
    means = {k: float(v["mean"]) for k, v in table["tissues"].items()}
    cvs = {k: float(v.get("texture_cv", 0.0)) for k, v in table["tissues"].items()}
    if intensities is not None:
        for k, v in dict(intensities).items():
            v = float(v)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"intensity of {k!r} must be finite and >= 0, got {v}")
            means[k] = v
            cvs.setdefault(k, 0.0)
    if texture is False or texture == 0:
        cvs = {k: 0.0 for k in cvs}
    elif isinstance(texture, Mapping):
        for k, v in texture.items():
            if not (np.isfinite(float(v)) and float(v) >= 0):
                raise ValueError(f"texture of {k!r} must be >= 0, got {v}")
            cvs[k] = float(v)
    elif not (texture is None or texture is True):
        raise ValueError("texture must be None/True (measured), False (none) or a {tissue: cv} mapping")
    unknown = [t for t in tissue_names if t not in means]
    if unknown:
        raise ValueError(f"unknown tissue(s) {unknown}; known: {sorted(means)} (or pass intensities=)")
    if noise is None or noise is True:
        sigma = float(table["noise_sigma"])
    elif noise is False:
        sigma = 0.0
    else:
        sigma = float(noise)
        if not (np.isfinite(sigma) and sigma >= 0):
            raise ValueError(f"noise must be a sigma >= 0, got {noise}")
    return means, cvs, sigma


def _bias_coefficients(rng: np.random.Generator, amplitude: float) -> np.ndarray | None:
    """Random quadratic in normalised (u, v, w) in [-1, 1]^3, scaled to max |q| = amplitude."""
    if amplitude == 0:
        return None
    c = rng.standard_normal(9)
    # Normalised on a 17^3 sampling of the FOV (corners included): the true
    # maximum of the quadratic can exceed it by well under 1 % of ``amplitude``.
    g = np.linspace(-1, 1, 17)
    u, v, w = np.meshgrid(g, g, g, indexing="ij")
    q = _bias_poly(c, u, v, w)
    return c * (amplitude / np.abs(q).max())


def _bias_poly(c, u, v, w):
    return (c[0] * u + c[1] * v + c[2] * w + c[3] * u * u + c[4] * v * v + c[5] * w * w
            + c[6] * u * v + c[7] * u * w + c[8] * v * w)


def _bias_slab(c, u: np.ndarray, v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``1 + q`` on the slab grid ``(i, j, k)``, built from 2-D terms (q = A(u, v) + w B(u, v) + c5 w^2)."""
    U, V = u[:, None], v[None, :]
    A2 = c[0] * U + c[1] * V + c[3] * U * U + c[4] * V * V + c[6] * U * V
    B2 = c[2] + c[7] * U + c[8] * V
    return 1.0 + A2[:, :, None] + B2[:, :, None] * w[None, None, :] + (c[5] * w * w)[None, None, :]


def _norm_coords(n: int) -> np.ndarray:
    return np.zeros(1) if n == 1 else np.linspace(-1.0, 1.0, n)


def render_volume(layers: Sequence[tuple[Mesh, str]], affine: np.ndarray, shape, *,
                  slice_thickness_mm: float | None = None, inplane_supersample: int = 4,
                  through_plane_samples: int = 4, intensities: Mapping[str, float] | None = None,
                  rng: np.random.Generator | int | None = None, bias: float = 0.15,
                  noise: float | bool | None = None, texture: Mapping[str, float] | bool | None = None,
                  scale: float = 1.0, motion: np.ndarray | None = None,
                  texture_corr_mm: float = TEXTURE_CORR_MM) -> np.ndarray:
    """Render an MR magnitude image of layered closed meshes with sub-voxel partial volume.

    Parameters
    ----------
    layers : sequence of (Mesh, str)
        Closed surfaces in LPS mm and tissue names, painted in order (later
        over earlier), e.g. ``[(skin, "fat"), (fascia, "muscle"), (bone,
        "cortex"), (bone_inner, "marrow"), (capsule, "oil")]``. Outside every
        layer is ``air``.
    affine : ndarray (4, 4)
        ``voxel_to_lps`` of the output grid (any orientation; the slice
        normal is column 2).
    shape : (I, J, K)
    slice_thickness_mm : float, optional
        Slice profile thickness (default: the pitch, the norm of column 2).
    inplane_supersample : int
        Scan lines per pixel (columns are integrated exactly).
    through_plane_samples : int
        Section planes per slice across its thickness.
    intensities : mapping, optional
        ``{tissue: mean}`` overriding the YAML table (before ``scale``).
    rng : numpy Generator or int, optional
        Source of the bias, texture and noise (``None``: seed 0).
    bias : float
        Maximum relative deviation of the smooth multiplicative bias field
        over the FOV (``0`` for none).
    noise : float, bool or None
        Rician noise sigma; ``None``/``True`` the knee's, ``False`` or ``0`` none.
    texture : mapping, bool or None
        Tissue texture CVs; ``None``/``True`` the knee's, ``False`` none, or
        ``{tissue: cv}`` overrides.
    scale : float
        Intensity scale (receiver gain), multiplies signal and noise.
    motion : ndarray (4, 4), optional
        Rigid motion of the subject during the acquisition: the meshes are
        imaged at ``motion @ p`` while ``affine`` stays nominal.
    texture_corr_mm : float
        Gaussian correlation length of the texture, in-plane.

    Returns
    -------
    ndarray (I, J, K), float32
        Non-negative magnitude values, in Fortran memory order (each slice
        ``[:, :, k]`` contiguous).

    Raises
    ------
    ValueError
        Bad grid or sampling, unknown tissue, negative intensity, bias outside
        [0, 1), non-positive scale.

    Notes
    -----
    Work is done slab by slab (a few slices at a time): memory stays at the
    output plus a few tens of MB whatever the grid. Each mesh is skipped for
    slabs its k-range misses, and on each plane only the triangles crossing
    it are cut (see :mod:`bonecap.phantom.render`).
    """
    from bonecap.phantom.render import _check_grid

    affine, shape = _check_grid(affine, shape)
    if not 0 <= float(bias) < 1:
        raise ValueError(f"bias must be in [0, 1), got {bias}")
    if not float(scale) > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    if not float(texture_corr_mm) > 0:
        raise ValueError(f"texture_corr_mm must be positive, got {texture_corr_mm}")
    layers = list(layers)
    tissues = list(dict.fromkeys(name for _, name in layers))
    means, cvs, sigma = _resolve_tissues(tissues + ["air"], intensities, texture, noise)
    rng = _as_rng(rng)
    I, J, K = shape
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    coef = _bias_coefficients(rng, float(bias))
    u, v, w = _norm_coords(I), _norm_coords(J), _norm_coords(K)
    tex_sigma_px = (float(texture_corr_mm) / spacing[0], float(texture_corr_mm) / spacing[1])
    use_texture = any(cvs.get(t, 0.0) > 0 for t in tissues)
    # Slabs come as (k, j, i)-ordered buffers seen as (i, j, k): every array
    # here uses that memory order (Fortran order for (i, j, k)) so that
    # element-wise work streams through memory, and so does the output.
    out = np.empty(shape, np.float32, order="F")

    def draw(nk):  # standard normals on the slab, in the slabs' memory order
        return rng.standard_normal((nk, J, I)).transpose(2, 1, 0)

    for k0, k1, frac in iter_tissue_slabs(layers, affine, shape, slice_thickness_mm=slice_thickness_mm,
                                          inplane_supersample=inplane_supersample,
                                          through_plane_samples=through_plane_samples, motion=motion):
        nk = k1 - k0
        if use_texture:
            g = ndimage.gaussian_filter(draw(nk), sigma=(tex_sigma_px[0], tex_sigma_px[1], 0.0), mode="wrap")
            # Normalise to unit variance (the filter's variance reduction).
            g /= max(float(g.std()), 1e-12)
        covered = np.zeros((nk, J, I)).transpose(2, 1, 0)
        signal = np.zeros((nk, J, I)).transpose(2, 1, 0)
        for name, f in frac.items():
            covered += f
            m = means[name]
            if m == 0:
                continue
            c = cvs.get(name, 0.0)
            if use_texture and c > 0:
                # Log-normal texture: positive, mean exactly 1 and CV exactly c
                # (a Gaussian factor 1 + c g would need clipping at the cortex's
                # CV of ~0.9, which biases the mean up by ~5 %).
                s2 = math.log1p(c * c)
                signal += f * (m * np.exp(math.sqrt(s2) * g - s2 / 2))
            else:
                signal += f * m
        if means["air"]:
            signal += np.clip(1.0 - covered, 0.0, 1.0) * means["air"]
        if coef is not None:
            signal *= _bias_slab(coef, u, v, w[k0:k1])
        if sigma > 0:
            re = signal + sigma * draw(nk)
            im = sigma * draw(nk)
            signal = np.hypot(re, im)
        out[:, :, k0:k1] = signal * float(scale)
    return out


# --------------------------------------------------------------------------- #
# stations
# --------------------------------------------------------------------------- #
@dataclass
class StationPlan:
    """One acquisition: nominal grid, true patient motion and intensity scale.

    Attributes
    ----------
    index : int
        Station number, 1 at the head (also the DICOM ``SeriesNumber``).
    name : str
        Output folder name (``"station_3"``, ``"forearm_99.5"``).
    affine : ndarray (4, 4)
        Nominal ``voxel_to_lps`` written to the DICOM header.
    shape : (I, J, K)
    slice_thickness_mm : float
    true_to_nominal : ndarray (4, 4)
        Rigid: ``p_nominal = true_to_nominal @ p_true`` (see the module
        docstring); identity when the subject did not move.
    intensity_scale : float
    shift_mm : float
        Displacement of the FOV centre by ``true_to_nominal`` (mm).
    rotation_deg : float
        Rotation angle of ``true_to_nominal`` (degrees).
    description : str
        DICOM series description.
    """

    index: int
    name: str
    affine: np.ndarray
    shape: tuple[int, int, int]
    slice_thickness_mm: float
    true_to_nominal: np.ndarray = field(default_factory=lambda: np.eye(4))
    intensity_scale: float = 1.0
    shift_mm: float = 0.0
    rotation_deg: float = 0.0
    description: str = ""

    @property
    def spacing(self) -> np.ndarray:
        """Pixel, pixel and slice pitch (mm)."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    @property
    def centre(self) -> np.ndarray:
        """World position (nominal LPS) of the grid's centre."""
        c = (np.asarray(self.shape, float) - 1) / 2
        return self.affine[:3, :3] @ c + self.affine[:3, 3]

    def slice_range_mm(self) -> tuple[float, float]:
        """Extent along the slice normal covered by the slice profiles (nominal, mm from origin)."""
        pitch = self.spacing[2]
        n = self.affine[:3, 2] / pitch
        z0 = float(self.affine[:3, 3] @ n)
        return z0 - self.slice_thickness_mm / 2, z0 + (self.shape[2] - 1) * pitch + self.slice_thickness_mm / 2

    @property
    def nominal_to_true(self) -> np.ndarray:
        """Inverse of ``true_to_nominal``: where a station voxel's nominal position lies on the true body."""
        return np.linalg.inv(self.true_to_nominal)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (for the truth files)."""
        return {"index": self.index, "name": self.name, "affine_voxel_to_lps": self.affine.tolist(),
                "shape": list(self.shape), "slice_thickness_mm": self.slice_thickness_mm,
                "true_to_nominal": self.true_to_nominal.tolist(),
                "intensity_scale": self.intensity_scale, "shift_mm": self.shift_mm,
                "rotation_deg": self.rotation_deg, "description": self.description}


def _rotation_matrix(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    axis = np.asarray(axis, float)
    axis = axis / np.linalg.norm(axis)
    Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * Kx + (1 - math.cos(angle_rad)) * Kx @ Kx


def _random_motion(rng: np.random.Generator, centre: np.ndarray, max_shift_mm: float, max_rotation_deg: float
                   ) -> tuple[np.ndarray, float, float]:
    """Random rigid motion about ``centre``: angle U(0, max), shift |t| U(0, max), random directions."""
    axis = rng.standard_normal(3)
    angle = rng.uniform(0.0, max_rotation_deg)
    R = _rotation_matrix(axis, math.radians(angle))
    d = rng.standard_normal(3)
    t = d / np.linalg.norm(d) * rng.uniform(0.0, max_shift_mm)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre + t - R @ centre
    return T, float(np.linalg.norm(t)), float(angle)


def _body_points(body) -> tuple[np.ndarray | None, np.ndarray]:
    """(vertices or None, bounds (2, 3)) from bounds, a Mesh, a mesh list or points."""
    if isinstance(body, Mesh):
        pts = body.vertices
    elif isinstance(body, (list, tuple)) and body and all(isinstance(m, Mesh) for m in body):
        pts = np.concatenate([m.vertices for m in body])
    else:
        arr = np.asarray(body, dtype=float)
        if arr.shape == (2, 3):
            if not np.all(arr[1] > arr[0]):
                raise ValueError(f"body bounds must be [min, max] with max > min, got {arr.tolist()}")
            return None, arr
        if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) < 2:
            raise ValueError("body must be bounds (2, 3), points (N, 3), a Mesh or a list of Meshes")
        pts = arr
    if not np.all(np.isfinite(pts)):
        raise ValueError("body points must be finite")
    return pts, np.stack([pts.min(axis=0), pts.max(axis=0)])


def plan_stations(body, n_stations: int = 8, pixel_mm: float = 1.8, pitch_mm: float = 5.0,
                  thickness_mm: float = 5.0, overlap_mm: float | None = None, *,
                  overlap_fraction: float = 0.2, margin_mm: float = 20.0, max_shift_mm: float = 3.0,
                  max_rotation_deg: float = 1.0, scale_range: tuple[float, float] = (0.75, 1.3),
                  rng: np.random.Generator | int | None = None) -> list[StationPlan]:
    """Plan axial whole-body stations head to feet, each with its own small patient motion.

    Parameters
    ----------
    body : bounds (2, 3), points (N, 3), Mesh or list of Mesh
        The body in the true LPS world (mm). With points or meshes each
        station's in-plane FOV fits the body *within that station's z
        range*; with bounds every station uses the global x-y extent.
    n_stations : int
        Number of stations (the paper: 8).
    pixel_mm : float
        In-plane pixel size (square pixels).
    pitch_mm : float
        Slice pitch (centre to centre).
    thickness_mm : float
        Slice thickness (may differ from the pitch).
    overlap_mm : float, optional
        Overlap of consecutive stations along z; default ``overlap_fraction``
        of the station length.
    overlap_fraction : float
        Used when ``overlap_mm`` is None (0.2: 20 %).
    margin_mm : float
        Air margin around the body, in-plane and beyond head and feet (10 mm
        of it along z).
    max_shift_mm, max_rotation_deg : float
        Bounds of each station's random patient motion (``true_to_nominal``).
    scale_range : (float, float)
        Each station's intensity scale is uniform in this range.
    rng : numpy Generator or int, optional

    Returns
    -------
    list of StationPlan
        ``station_1`` (head) ... ``station_n`` (feet); axial grids with ``i``
        along +x, ``j`` along +y, ``k`` along +z (right-handed), even
        in-plane matrix sizes.

    Raises
    ------
    ValueError
        Non-positive sizes, fewer than 1 station, an overlap that leaves no
        progress between stations, a bad scale range.
    """
    rng = _as_rng(rng)
    n = int(n_stations)
    if n < 1 or n != n_stations:
        raise ValueError(f"n_stations must be a positive integer, got {n_stations}")
    for nm, val in (("pixel_mm", pixel_mm), ("pitch_mm", pitch_mm), ("thickness_mm", thickness_mm)):
        if not float(val) > 0:
            raise ValueError(f"{nm} must be positive, got {val}")
    if margin_mm < 0 or max_shift_mm < 0 or max_rotation_deg < 0:
        raise ValueError("margin_mm, max_shift_mm and max_rotation_deg must be >= 0")
    lo_s, hi_s = scale_range
    if not 0 < lo_s <= hi_s:
        raise ValueError(f"scale_range must be 0 < low <= high, got {scale_range}")
    pts, bounds = _body_points(body)
    z_margin = min(margin_mm, 10.0)
    z_top = bounds[1, 2] + z_margin
    z_bot = bounds[0, 2] - z_margin
    H = z_top - z_bot
    if overlap_mm is None:
        if not 0 <= overlap_fraction < 1:
            raise ValueError(f"overlap_fraction must be in [0, 1), got {overlap_fraction}")
        L = H / (n - overlap_fraction * (n - 1))
        overlap = overlap_fraction * L
    else:
        overlap = float(overlap_mm)
        if overlap < 0:
            raise ValueError(f"overlap_mm must be >= 0, got {overlap_mm}")
        L = (H + (n - 1) * overlap) / n
        if L <= overlap:
            raise ValueError(f"overlap_mm={overlap_mm} is not smaller than the station length {L:.1f} mm")
    K = int(math.ceil((L - thickness_mm) / pitch_mm)) + 1 if L > thickness_mm else 1
    length = (K - 1) * pitch_mm + thickness_mm        # covered by the slice profiles
    plans = []
    for s in range(n):
        zc = z_top - L / 2 - s * (L - overlap)
        z0, z1 = zc - length / 2, zc + length / 2
        if pts is not None:
            # A little beyond the station so that a rotated body still fits.
            sel = (pts[:, 2] >= z0 - 20) & (pts[:, 2] <= z1 + 20)
            sub = pts[sel] if sel.any() else pts
            xy_lo, xy_hi = sub[:, :2].min(axis=0), sub[:, :2].max(axis=0)
        else:
            xy_lo, xy_hi = bounds[0, :2], bounds[1, :2]
        # Motion slack: the shift plus what a rotation moves the station's ends.
        slack = max_shift_mm + math.radians(max_rotation_deg) * (length / 2 + float(np.max(xy_hi - xy_lo)) / 2)
        width = xy_hi - xy_lo + 2 * (margin_mm + slack)
        IJ = [int(math.ceil(wd / pixel_mm)) for wd in width]
        IJ = [m + (m % 2) for m in IJ]                 # even matrix, as scanners use
        cxy = (xy_lo + xy_hi) / 2
        affine = np.diag([pixel_mm, pixel_mm, pitch_mm, 1.0])
        affine[:3, 3] = [cxy[0] - (IJ[0] - 1) / 2 * pixel_mm, cxy[1] - (IJ[1] - 1) / 2 * pixel_mm,
                         zc - (K - 1) / 2 * pitch_mm]
        centre = np.array([cxy[0], cxy[1], zc])
        T, shift, angle = _random_motion(rng, centre, max_shift_mm, max_rotation_deg)
        scale = float(rng.uniform(lo_s, hi_s))
        plans.append(StationPlan(index=s + 1, name=f"station_{s + 1}", affine=affine,
                                 shape=(IJ[0], IJ[1], K), slice_thickness_mm=float(thickness_mm),
                                 true_to_nominal=T, intensity_scale=scale, shift_mm=shift,
                                 rotation_deg=angle, description=f"station {s + 1}"))
    return plans


@dataclass
class StationTruth:
    """What one station's truth holds.

    Attributes
    ----------
    plan : StationPlan
        Nominal geometry, ``true_to_nominal`` and intensity scale.
    folder : Path
        The DICOM series written.
    labels : Volume or None
        Oracle bone labels on the acquisition grid (nominal affine), i.e. the
        truth meshes *moved by* ``true_to_nominal`` and voxelised with the
        renderer's sampling; aligned voxel for voxel with the image.
    """

    plan: StationPlan
    folder: Path
    labels: Volume | None = None


@dataclass
class StationsResult:
    """Output of :func:`render_stations`.

    Attributes
    ----------
    stations : list of StationTruth
    merged_labels : Volume or None
        Bone labels of the true (unmoved) meshes on a common grid in the true
        world frame (:func:`merged_grid`).
    study_uid, frame_of_reference_uid : str
    timings_s : dict
        ``render``, ``labels``, ``write``, ``merged`` totals.
    """

    stations: list[StationTruth]
    merged_labels: Volume | None
    study_uid: str
    frame_of_reference_uid: str
    timings_s: dict[str, float] = field(default_factory=dict)


def merged_grid(meshes: Sequence[Mesh], voxel_mm: float = 2.0, margin_mm: float = 10.0
                ) -> tuple[np.ndarray, tuple[int, int, int]]:
    """An axis-aligned isotropic LPS grid covering meshes with a margin.

    Parameters
    ----------
    meshes : sequence of Mesh
        LPS mm.
    voxel_mm : float
    margin_mm : float

    Returns
    -------
    affine : ndarray (4, 4)
        ``voxel_to_lps``: diagonal ``voxel_mm``, origin on a multiple of
        ``voxel_mm`` (so grids of different subjects line up).
    shape : (I, J, K)

    Raises
    ------
    ValueError
        No meshes, or non-positive ``voxel_mm``.
    """
    if not float(voxel_mm) > 0:
        raise ValueError(f"voxel_mm must be positive, got {voxel_mm}")
    meshes = [m for m in meshes if len(m.vertices)]
    if not meshes:
        raise ValueError("merged_grid needs at least one non-empty mesh")
    lo = np.min([m.vertices.min(axis=0) for m in meshes], axis=0) - margin_mm
    hi = np.max([m.vertices.max(axis=0) for m in meshes], axis=0) + margin_mm
    lo = np.floor(lo / voxel_mm) * voxel_mm
    shape = tuple(int(v) for v in np.ceil((hi - lo) / voxel_mm).astype(int) + 1)
    affine = np.diag([voxel_mm, voxel_mm, voxel_mm, 1.0])
    affine[:3, 3] = lo
    return affine, shape  # type: ignore[return-value]


def write_merged_labels(label_meshes: Sequence[tuple[Mesh, int]], path: str | os.PathLike, *,
                        voxel_mm: float = 2.0, inplane_supersample: int = 4, through_plane_samples: int = 4,
                        slab_slices: int = 48) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Voxelise the unmoved truth bones on the merged grid and write them as NIfTI, slab by slab.

    The same labels as ``render_stations(..., merged_voxel_mm=voxel_mm).merged_labels``
    (:func:`merged_grid`, :func:`voxelise_labels`), computed ``slab_slices`` axial slices at
    a time and streamed into the file: the whole-body grid (~70 M voxels, 140 MB of uint16 at
    2 mm) is never held.

    Parameters
    ----------
    label_meshes : sequence of (Mesh, int)
        Bone outer surfaces (LPS, true world) and their label ids.
    path : path-like
        ``.nii.gz`` (or ``.nii``); written atomically.
    voxel_mm : float
        Merged grid spacing (:func:`merged_grid`).
    inplane_supersample, through_plane_samples : int
        As :func:`voxelise_labels`.
    slab_slices : int
        Axial slices voxelised at a time (memory ~ one slab of uint16 plus its sampling).

    Returns
    -------
    affine, shape
        The merged grid.
    """
    from bonecap.io.imaging import _write_nifti_slabs

    label_meshes = _check_label_meshes(label_meshes)
    affine, shape = merged_grid([m for m, _ in label_meshes], voxel_mm)

    def slabs():
        for k0 in range(0, shape[2], slab_slices):
            k1 = min(k0 + slab_slices, shape[2])
            sub = affine.copy()
            sub[:3, 3] = affine[:3, :3] @ np.array([0.0, 0.0, k0]) + affine[:3, 3]
            yield voxelise_labels(label_meshes, sub, (shape[0], shape[1], k1 - k0),
                                  inplane_supersample=inplane_supersample,
                                  through_plane_samples=through_plane_samples)

    _write_nifti_slabs(affine, shape, np.uint16, slabs(), path)
    return affine, shape


def _to_uint16(img: np.ndarray) -> np.ndarray:
    """Round and clip to uint16, in ``img``'s own buffer (it is discarded after): a 5-million-voxel
    forearm stack had taken two more float32 copies (~40 MB) on the phantom's peak."""
    np.rint(img, out=img)
    np.clip(img, 0, 65535, out=img)
    return img.astype(np.uint16)


def _check_label_meshes(label_meshes):
    if label_meshes is None:
        return None
    items = list(label_meshes)
    for item in items:
        if not (isinstance(item, (tuple, list)) and len(item) == 2 and isinstance(item[0], Mesh)):
            raise ValueError("label_meshes must be (Mesh, id) pairs")
    return items


def render_stations(layers: Sequence[tuple[Mesh, str]], plans: Sequence[StationPlan],
                    out_dir: str | os.PathLike, rng: np.random.Generator | int | None = None, *,
                    label_meshes: Sequence[tuple[Mesh, int]] | None = None, merged_voxel_mm: float | None = 2.0,
                    inplane_supersample: int = 4, through_plane_samples: int = 4,
                    intensities: Mapping[str, float] | None = None, noise: float | bool | None = None,
                    texture: Mapping[str, float] | bool | None = None, bias: float = 0.15,
                    study_uid: str | None = None, frame_of_reference_uid: str | None = None,
                    patient: Mapping[str, str] | None = None, show_progress: bool = True,
                    on_station: Callable[[StationTruth], None] | None = None,
                    keep_labels: bool = True) -> StationsResult:
    """Render and write every station as a DICOM series, with its oracle labels.

    Parameters
    ----------
    layers : sequence of (Mesh, str)
        Render layers in the true LPS world (see :func:`render_volume`).
    plans : sequence of StationPlan
        From :func:`plan_stations`.
    out_dir : path-like
        Each station goes to ``out_dir / plan.name`` (``station_1/``...),
        replaced as a whole if present.
    rng : numpy Generator or int, optional
        Bias, texture and noise of every station, drawn in station order.
    label_meshes : sequence of (Mesh, int), optional
        Bone outer surfaces (LPS, true world) and label ids for the oracle
        and the merged label volume.
    merged_voxel_mm : float or None
        Voxel size of the merged label grid (:func:`merged_grid`); ``None``
        skips it.
    inplane_supersample, through_plane_samples : int
        Sampling of the renderer and of the oracle (the same).
    intensities, noise, texture, bias
        As :func:`render_volume`.
    study_uid, frame_of_reference_uid : str, optional
        Shared by all stations (new ones when not given).
    patient : mapping, optional
        ``patient_name`` and ``patient_id`` for the headers.
    show_progress : bool
        A progress bar on stderr (hidden when stderr is not a terminal).
    on_station : callable, optional
        Called with each :class:`StationTruth` as soon as its station is
        written (e.g. to save its oracle labels right away).
    keep_labels : bool
        Keep each station's label volume in the result; with ``False`` it is
        dropped after ``on_station`` (memory stays at one station's labels).

    Returns
    -------
    StationsResult

    Raises
    ------
    ValueError
        Bad layers, label meshes or plans.

    Notes
    -----
    Each station is rendered, quantised to uint16 and written before the next
    one starts, so only one station image is in memory at a time; the label
    volumes (uint16) are kept and returned unless ``keep_labels=False``.
    """
    import time

    from pydicom.uid import generate_uid

    from bonecap.io.imaging import write_dicom_series
    from bonecap.progress import progress

    rng = _as_rng(rng)
    plans = list(plans)
    if not plans or not all(isinstance(p, StationPlan) for p in plans):
        raise ValueError("plans must be a non-empty sequence of StationPlan")
    label_meshes = _check_label_meshes(label_meshes)
    out_dir = Path(out_dir)
    study_uid = study_uid or generate_uid()
    frame_of_reference_uid = frame_of_reference_uid or generate_uid()
    patient = dict(patient or {})
    times = {"render": 0.0, "labels": 0.0, "write": 0.0, "merged": 0.0}
    layers = list(layers)
    stations = []
    iterator = progress(plans, desc="MRI stations", unit="station") if show_progress else plans
    for plan in iterator:
        t0 = time.perf_counter()
        img = render_volume(layers, plan.affine, plan.shape, slice_thickness_mm=plan.slice_thickness_mm,
                            inplane_supersample=inplane_supersample,
                            through_plane_samples=through_plane_samples, intensities=intensities, rng=rng,
                            bias=bias, noise=noise, texture=texture, scale=plan.intensity_scale,
                            motion=plan.true_to_nominal)
        t1 = time.perf_counter()
        meta = {"modality": "MR", "slice_thickness": plan.slice_thickness_mm,
                "patient_name": patient.get("patient_name", "PHANTOM^BONECAP"),
                "patient_id": patient.get("patient_id", "")}
        folder = out_dir / plan.name
        img16 = _to_uint16(img)
        del img                               # the float image is not needed while the series is written
        write_dicom_series(Volume(img16, plan.affine, meta), folder,
                           series_description=plan.description or plan.name, rescale=False,
                           series_number=plan.index, study_uid=study_uid,
                           frame_of_reference_uid=frame_of_reference_uid)
        del img16
        t2 = time.perf_counter()
        labels = None
        if label_meshes:
            lab = voxelise_labels(label_meshes, plan.affine, plan.shape,
                                  slice_thickness_mm=plan.slice_thickness_mm,
                                  inplane_supersample=inplane_supersample,
                                  through_plane_samples=through_plane_samples, motion=plan.true_to_nominal)
            labels = Volume(lab, plan.affine.copy(), {"kind": "oracle_labels", "station": plan.name,
                                                      "frame": "nominal (station acquisition grid)"})
        t3 = time.perf_counter()
        times["render"] += t1 - t0
        times["write"] += t2 - t1
        times["labels"] += t3 - t2
        truth = StationTruth(plan=plan, folder=folder, labels=labels)
        if on_station is not None:
            on_station(truth)
        if not keep_labels:
            truth.labels = None
        stations.append(truth)
    merged = None
    if label_meshes and merged_voxel_mm:
        t0 = time.perf_counter()
        aff, shp = merged_grid([m for m, _ in label_meshes], merged_voxel_mm)
        lab = voxelise_labels(label_meshes, aff, shp, inplane_supersample=inplane_supersample,
                              through_plane_samples=through_plane_samples)
        merged = Volume(lab, aff, {"kind": "merged_labels", "frame": "true LPS world"})
        times["merged"] = time.perf_counter() - t0
    return StationsResult(stations=stations, merged_labels=merged, study_uid=study_uid,
                          frame_of_reference_uid=frame_of_reference_uid, timings_s=times)


# --------------------------------------------------------------------------- #
# capsules and forearm stacks
# --------------------------------------------------------------------------- #
@dataclass
class CapsulePlacement:
    """Where oil capsules sit on a skin mesh.

    Attributes
    ----------
    face_ids : ndarray (n,) of int
        Skin triangle under each capsule.
    barycentric : ndarray (n, 3)
        Contact point in that triangle; with a posed skin of the same topology
        the capsule follows the skin (:func:`capsule_centres_on`).
    centres : ndarray (n, 3)
        Capsule centres on the skin the placement was made on: contact point
        + radius x the triangle's outward unit normal (LPS mm).
    radius_mm : float
    """

    face_ids: np.ndarray
    barycentric: np.ndarray
    centres: np.ndarray
    radius_mm: float

    @property
    def meshes(self) -> list[Mesh]:
        """Icosphere meshes of the capsules at ``centres`` (:func:`capsule_meshes`)."""
        return capsule_meshes(self.centres, self.radius_mm)


def _face_normals(mesh: Mesh, face_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    tri = mesh.vertices[mesh.faces[face_ids]]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(nrm, axis=1)
    return nrm / np.maximum(area2, 1e-300)[:, None], area2


def capsule_centres_on(skin: Mesh, placement: CapsulePlacement) -> np.ndarray:
    """Capsule centres on a (posed) skin with the placement's topology.

    Parameters
    ----------
    skin : Mesh
        A skin mesh whose faces index the same vertices as the one the
        placement was drawn on (e.g. the same skin posed by skinning).
    placement : CapsulePlacement

    Returns
    -------
    ndarray (n, 3)
        Contact point (same barycentric coordinates) + radius x outward unit
        face normal, LPS mm.

    Raises
    ------
    ValueError
        The skin has fewer faces than the placement refers to.
    """
    if len(skin.faces) <= int(np.max(placement.face_ids, initial=-1)):
        raise ValueError("skin does not have the faces the capsule placement refers to")
    tri = skin.vertices[skin.faces[placement.face_ids]]
    p = np.einsum("nk,nkd->nd", placement.barycentric, tri)
    nrm, _ = _face_normals(skin, placement.face_ids)
    return p + placement.radius_mm * nrm


def _plane_distance_mm(plan: StationPlan, points: np.ndarray) -> np.ndarray:
    """Distance along the slice normal from each point to the nearest slice-centre plane."""
    k = (points @ np.linalg.inv(plan.affine)[:3, :3].T + np.linalg.inv(plan.affine)[:3, 3])[:, 2]
    return np.abs(k - np.rint(k)) * plan.spacing[2]


def _sphere_in_field(plan: StationPlan, centre: np.ndarray, radius_mm: float) -> bool:
    """Whether a sphere lies wholly inside a stack's field of view (voxel centres, slice reach included)."""
    inv = np.linalg.inv(plan.affine)
    k = inv[:3, :3] @ np.asarray(centre, float) + inv[:3, 3]
    reach = float(radius_mm) / np.asarray(plan.spacing, float)
    return bool(np.all(k - reach >= -0.5) and np.all(k + reach <= np.asarray(plan.shape) - 0.5))


def place_capsules(skin_mesh: Mesh, n: int, rng: np.random.Generator | int | None = None, *,
                   diameter_mm: float = CAPSULE_DIAMETER_MM, plans: Sequence[StationPlan] | None = None,
                   skins: Sequence[Mesh] | None = None, min_plane_distance_mm: float = 0.5,
                   min_separation_mm: float | None = None, region: np.ndarray | None = None,
                   region_radius_mm: float = 80.0, max_tries: int = 200,
                   avoid: np.ndarray | None = None) -> CapsulePlacement:
    """Place capsules on a skin, centres at random depths *between* slice planes.

    Parameters
    ----------
    skin_mesh : Mesh
        Closed skin surface (outward normals), LPS mm.
    n : int
        Number of capsules.
    rng : numpy Generator or int, optional
    diameter_mm : float
        Capsule (sphere) diameter; the centre is one radius off the skin
        along the contact triangle's outward normal.
    plans : sequence of StationPlan, optional
        Stacks the capsules will be imaged in. A centre closer than
        ``min_plane_distance_mm`` to any slice-centre plane of any of them is
        rejected, so every centre lies at a random depth between planes.
    skins : sequence of Mesh, optional
        The skin in each plan's pose (same topology as ``skin_mesh``);
        default ``skin_mesh`` for every plan.
    min_plane_distance_mm : float
    min_separation_mm : float, optional
        Minimum centre distance between capsules (default ``diameter + 6``,
        so their images do not touch).
    region : ndarray (2, 3), optional
        Segment ``[proximal, distal]`` (e.g. elbow, wrist centre); capsules
        go only on skin whose projection on it falls in its central 70 % and
        that lies within ``region_radius_mm`` of it (so a whole-body skin
        gives forearm skin only, not the trunk beside it).
    region_radius_mm : float
    max_tries : int
        Rounds of candidate draws before giving up.
    avoid : sequence of ndarray (m_k, 3), optional
        Centres of capsules placed otherwise (e.g. at marker spots), one array
        per plan and skin (``skin_mesh``'s pose without plans): the new ones
        keep ``min_separation_mm`` from them in every pose.

    Returns
    -------
    CapsulePlacement
        Centres on ``skin_mesh``; in another pose use :func:`capsule_centres_on`.

    Raises
    ------
    ValueError
        Bad arguments, or no room for ``n`` capsules under the constraints.
    """
    rng = _as_rng(rng)
    n = int(n)
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    if not float(diameter_mm) > 0:
        raise ValueError(f"diameter_mm must be positive, got {diameter_mm}")
    if len(skin_mesh.faces) == 0:
        raise ValueError("skin_mesh has no faces")
    r = float(diameter_mm) / 2
    sep = float(diameter_mm) + 6.0 if min_separation_mm is None else float(min_separation_mm)
    plans = list(plans or [])
    skins = list(skins) if skins is not None else [skin_mesh] * len(plans)
    if len(skins) != len(plans):
        raise ValueError("skins must be parallel to plans")
    for s in skins:
        if s.faces.shape != skin_mesh.faces.shape:
            raise ValueError("every posed skin must have the topology of skin_mesh")
    for p in plans:
        if min_plane_distance_mm * 2 >= p.spacing[2]:
            raise ValueError(f"min_plane_distance_mm={min_plane_distance_mm} leaves no room between "
                             f"slices {p.spacing[2]:.2f} mm apart in {p.name}")
    _, area2 = _face_normals(skin_mesh, np.arange(len(skin_mesh.faces)))
    weights = area2.copy()
    if region is not None:
        region = np.asarray(region, float)
        if region.shape != (2, 3):
            raise ValueError(f"region must be (2, 3) [proximal, distal], got {region.shape}")
        ax = region[1] - region[0]
        Lr = float(np.linalg.norm(ax))
        if Lr == 0:
            raise ValueError("region end points coincide")
        cen = skin_mesh.vertices[skin_mesh.faces].mean(axis=1)
        s = (cen - region[0]) @ ax / Lr**2
        radial = np.linalg.norm(cen - region[0] - s[:, None] * ax, axis=1)
        weights = weights * ((s >= 0.15) & (s <= 0.85) & (radial <= region_radius_mm))
    if weights.sum() <= 0:
        raise ValueError("no skin area where capsules may go")
    prob = weights / weights.sum()
    chosen_f: list[int] = []
    chosen_b: list[np.ndarray] = []
    chosen_c: list[np.ndarray] = []
    avoid = [np.asarray(a, float).reshape(-1, 3) for a in (avoid or [])]
    if avoid and len(avoid) != max(len(plans), 1):
        raise ValueError(f"avoid needs one array per pose ({max(len(plans), 1)}), got {len(avoid)}")
    tries = 0
    while len(chosen_f) < n:
        tries += 1
        if tries > max_tries:
            raise ValueError(f"could place only {len(chosen_f)} of {n} capsules under the constraints")
        m = 64
        f = rng.choice(len(prob), size=m, p=prob)
        a, b = rng.random(m), rng.random(m)
        flip = a + b > 1
        a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
        bary = np.stack([1 - a - b, a, b], axis=1)
        cand = CapsulePlacement(f, bary, np.zeros((m, 3)), r)
        ok = np.ones(m, bool)
        posed = [capsule_centres_on(sk, cand) for sk in skins] or [capsule_centres_on(skin_mesh, cand)]
        for p, c_k in zip(plans, posed):
            ok &= _plane_distance_mm(p, c_k) >= min_plane_distance_mm
        for a, c_k in zip(avoid, posed):
            if len(a):
                ok &= np.min(np.linalg.norm(c_k[:, None] - a[None], axis=2), axis=1) >= sep
        centres = capsule_centres_on(skin_mesh, cand)
        for idx in np.nonzero(ok)[0]:
            c = centres[idx]
            if chosen_c and np.min(np.linalg.norm(np.asarray(chosen_c) - c, axis=1)) < sep:
                continue
            chosen_f.append(int(f[idx]))
            chosen_b.append(bary[idx])
            chosen_c.append(c)
            if len(chosen_f) == n:
                break
    return CapsulePlacement(np.asarray(chosen_f, np.int64), np.asarray(chosen_b).reshape(-1, 3),
                            np.asarray(chosen_c).reshape(-1, 3), r)


def capsule_meshes(centres: np.ndarray, radius_mm: float, subdivisions: int = 3) -> list[Mesh]:
    """Icosphere meshes of the capsules (LPS mm).

    Parameters
    ----------
    centres : ndarray (n, 3)
    radius_mm : float
    subdivisions : int
        Icosphere level (3: 1280 triangles, volume within 0.4 % of the sphere).

    Returns
    -------
    list of Mesh
    """
    if not float(radius_mm) > 0:
        raise ValueError(f"radius_mm must be positive, got {radius_mm}")
    V, F = icosphere(float(radius_mm), int(subdivisions))
    return [Mesh(V + c, F.copy(), "lps") for c in np.asarray(centres, float).reshape(-1, 3)]


@functools.lru_cache(maxsize=8)
def icosphere(radius_mm: float, subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """``trimesh.creation.icosphere`` as read-only ``(vertices, faces)`` arrays, made once per size.

    Where trimesh is not imported yet, a short forked child makes it
    (:func:`bonecap.parallel.fork_or_here`): trimesh and its dependencies hold
    ~21 MiB to the end of a process that imports them. :func:`~bonecap.phantom.make_phantom`
    asks for its capsules' sphere first, while its process is small (its body
    decimation and trials run in children too), so that no trimesh sits under
    the MRI rendering's peaks.
    """
    def run():
        import trimesh

        m = trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=float(radius_mm))
        return np.asarray(m.vertices, dtype=float), np.asarray(m.faces, dtype=np.int64)

    if "trimesh" in sys.modules:
        V, F = run()
    else:
        from bonecap.parallel import fork_or_here

        V, F = fork_or_here(run)()
    V.flags.writeable = F.flags.writeable = False      # shared by every call (the cache)
    return V, F


@dataclass
class ForearmPose:
    """One forearm pose to image.

    Attributes
    ----------
    layers : list of (Mesh, str)
        Posed render layers (LPS mm), without capsules.
    axis : ndarray (2, 3)
        Proximal (elbow) and distal (wrist) points of the forearm axis; the
        stack's slices are perpendicular to it and ``+k`` runs towards the
        wrist.
    skin : Mesh, optional
        The posed skin the capsules stick to (default: the first layer's
        mesh); all poses must share its topology.
    label_meshes : list of (Mesh, int), optional
        Posed bone surfaces and ids for the oracle labels of the stack.
    """

    layers: list[tuple[Mesh, str]]
    axis: np.ndarray
    skin: Mesh | None = None
    label_meshes: list[tuple[Mesh, int]] | None = None

    def __post_init__(self):
        self.axis = np.asarray(self.axis, dtype=float)
        if self.axis.shape != (2, 3) or np.linalg.norm(self.axis[1] - self.axis[0]) == 0:
            raise ValueError(f"ForearmPose.axis must be two distinct points (2, 3), got {self.axis.shape}")
        if self.skin is None:
            if not self.layers:
                raise ValueError("ForearmPose needs layers")
            self.skin = self.layers[0][0]


#: How far a forearm stack's slices reach past the elbow and the wrist (mm), by default.
FOREARM_EXTEND_MM = 10.0


def plan_forearm_stack(skin: Mesh, axis: np.ndarray, *, name: str = "forearm", index: int = 100,
                       pixel_mm: float = 0.7, pitch_mm: float = 2.5, thickness_mm: float = 2.5,
                       margin_mm: float = 12.0, extend_mm: float = FOREARM_EXTEND_MM, max_radius_mm: float = 80.0,
                       intensity_scale: float = 1.0, cover: np.ndarray | None = None,
                       cover_radius_mm: float = CAPSULE_DIAMETER_MM / 2) -> StationPlan:
    """A stack of slices perpendicular to the forearm axis covering the forearm.

    Parameters
    ----------
    skin : Mesh
        Posed skin (LPS mm); only vertices within ``max_radius_mm`` of the axis
        and along it set the in-plane FOV.
    axis : ndarray (2, 3)
        Elbow and wrist points (LPS mm).
    name : str
        Folder / plan name.
    index : int
        DICOM series number.
    pixel_mm, pitch_mm, thickness_mm : float
        In-plane pixel (square), slice pitch and thickness.
    margin_mm : float
        In-plane margin beyond the skin (covers the capsules: keep > 8).
    extend_mm : float
        Slices extend this far beyond the elbow and wrist points.
    max_radius_mm : float
    intensity_scale : float
    cover : ndarray (m, 3), optional
        Centres of spheres (radius ``cover_radius_mm``) the stack must hold
        whole, slices' reach included: the capsules at the wrist and elbow
        markers' spots, as the paper's stacks held them (the styloid markers lie
        at the wrist's level, a few millimetres from the end ``extend_mm`` gives).
    cover_radius_mm : float

    Returns
    -------
    StationPlan
        ``affine`` columns: ``e1 * pixel``, ``e2 * pixel``, ``n * pitch``
        with ``n`` the unit axis (elbow -> wrist), ``e1`` the LPS axis most
        perpendicular to ``n`` made orthogonal to it, ``e2 = n x e1``
        (right-handed); no motion.

    Raises
    ------
    ValueError
        Bad sizes or no skin near the axis.
    """
    axis = np.asarray(axis, float)
    if axis.shape != (2, 3):
        raise ValueError(f"axis must be (2, 3), got {axis.shape}")
    for nm, val in (("pixel_mm", pixel_mm), ("pitch_mm", pitch_mm), ("thickness_mm", thickness_mm)):
        if not float(val) > 0:
            raise ValueError(f"{nm} must be positive, got {val}")
    d = axis[1] - axis[0]
    L = float(np.linalg.norm(d))
    if L == 0:
        raise ValueError("axis end points coincide")
    nvec = d / L
    ref = np.eye(3)[int(np.argmin(np.abs(nvec)))]
    e1 = ref - (ref @ nvec) * nvec
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(nvec, e1)
    rel = skin.vertices - axis[0]
    s = rel @ nvec
    radial = rel - s[:, None] * nvec
    sel = (s >= -extend_mm) & (s <= L + extend_mm) & (np.linalg.norm(radial, axis=1) <= max_radius_mm)
    if not sel.any():
        raise ValueError("no skin vertex near the forearm axis")
    a, b = radial[sel] @ e1, radial[sel] @ e2
    lo = np.array([a.min(), b.min()]) - margin_mm
    hi = np.array([a.max(), b.max()]) + margin_mm
    s0, s1 = -extend_mm, L + extend_mm
    if cover is not None and len(cover):
        c_rel = np.asarray(cover, float).reshape(-1, 3) - axis[0]
        c_s = c_rel @ nvec
        reach = float(cover_radius_mm) + pitch_mm           # whole, and a slice beyond
        s0, s1 = min(s0, float(c_s.min()) - reach), max(s1, float(c_s.max()) + reach)
        c_ab = np.stack([c_rel @ e1, c_rel @ e2], axis=1)
        lo = np.minimum(lo, c_ab.min(axis=0) - reach)
        hi = np.maximum(hi, c_ab.max(axis=0) + reach)
    IJ = [int(math.ceil((h - l) / pixel_mm)) for l, h in zip(lo, hi)]
    IJ = [m + (m % 2) for m in IJ]
    K = int(math.ceil((s1 - s0) / pitch_mm)) + 1
    c_ab = (lo + hi) / 2
    centre_s = (s0 + s1) / 2
    origin = (axis[0] + centre_s * nvec + c_ab[0] * e1 + c_ab[1] * e2
              - (IJ[0] - 1) / 2 * pixel_mm * e1 - (IJ[1] - 1) / 2 * pixel_mm * e2 - (K - 1) / 2 * pitch_mm * nvec)
    affine = np.eye(4)
    affine[:3, 0] = e1 * pixel_mm
    affine[:3, 1] = e2 * pixel_mm
    affine[:3, 2] = nvec * pitch_mm
    affine[:3, 3] = origin
    return StationPlan(index=int(index), name=name, affine=affine, shape=(IJ[0], IJ[1], K),
                       slice_thickness_mm=float(thickness_mm), intensity_scale=float(intensity_scale),
                       description=name.replace("_", " "))


@dataclass
class ForearmTruth:
    """Truth of one forearm stack.

    Attributes
    ----------
    plan : StationPlan
    folder : Path
    capsule_centres : ndarray (n, 3)
        Capsule centres in this pose, LPS mm (true world = nominal here).
    labels : Volume or None
        Oracle bone labels on the stack's grid.
    marker_capsules : dict of str -> ndarray (3,)
        The capsules at marker spots in this pose (LPS mm), by marker name;
        they are also the last rows of ``capsule_centres``.
    """

    plan: StationPlan
    folder: Path
    capsule_centres: np.ndarray
    labels: Volume | None = None
    marker_capsules: dict[str, np.ndarray] = field(default_factory=dict)


def render_forearm_stacks(poses: Mapping[str, ForearmPose | Sequence[tuple[Mesh, str]]],
                          out_dir: str | os.PathLike, rng: np.random.Generator | int | None = None, *,
                          axis: np.ndarray | None = None, n_capsules: int = 8, capsule_diameter_mm: float = CAPSULE_DIAMETER_MM,
                          pixel_mm: float = 0.7, pitch_mm: float = 2.5, thickness_mm: float = 2.5,
                          min_plane_distance_mm: float = 0.5, scale_range: tuple[float, float] = (0.75, 1.3),
                          inplane_supersample: int = 4, through_plane_samples: int = 4,
                          intensities: Mapping[str, float] | None = None, noise: float | bool | None = None,
                          texture: Mapping[str, float] | bool | None = None, bias: float = 0.15,
                          study_uid: str | None = None, frame_of_reference_uid: str | None = None,
                          patient: Mapping[str, str] | None = None, first_series_number: int = 101,
                          marker_capsules: Mapping[str, Mapping[str, np.ndarray]] | None = None
                          ) -> tuple[dict[str, ForearmTruth], CapsulePlacement]:
    """Render forearm stacks (one per pose) with oil capsules on the skin, and write them as DICOM.

    Parameters
    ----------
    poses : mapping name -> ForearmPose or list of (Mesh, str)
        E.g. ``{"0": ..., "99.5": ..., "172.1": ...}`` (the paper's measured
        twists, degrees). A plain layer list needs ``axis``. All poses' skins
        must share a topology (the capsules stick to the same skin triangles).
    out_dir : path-like
        Each stack goes to ``out_dir / f"forearm_{name}"``.
    rng : numpy Generator or int, optional
        Capsule placement, intensity scales, then bias/texture/noise per pose.
    axis : ndarray (2, 3), optional
        Elbow and wrist points for plain layer lists.
    n_capsules : int
    capsule_diameter_mm : float
    pixel_mm, pitch_mm, thickness_mm : float
        Forearm-coil stack geometry (defaults 0.7 mm pixels, 2.5 mm slices).
    min_plane_distance_mm : float
        Every capsule centre is at least this far from every slice-centre
        plane of every stack.
    scale_range : (float, float)
        Intensity scale range per stack.
    inplane_supersample, through_plane_samples, intensities, noise, texture, bias
        As :func:`render_volume`.
    study_uid, frame_of_reference_uid : str, optional
        Shared by the forearm stacks (new ones when not given).
    patient : mapping, optional
    first_series_number : int
        Series numbers are consecutive from this.
    marker_capsules : mapping marker name -> (mapping pose name -> ndarray (3,)), optional
        Capsules at marker spots, as the paper's protocol marked them (LPS mm,
        the centre in each pose that shows it: the caller carries them with
        their bones). Unlike the random ones they sit where their marker is, on
        a slice plane or not, and each stack is planned to hold them whole
        (:func:`plan_forearm_stack`'s ``cover``). The random capsules keep
        their separation from them in every pose.

    Returns
    -------
    truths : dict name -> ForearmTruth
    placement : CapsulePlacement
        Capsule contact triangles and barycentric coordinates (and centres in
        the first pose).

    Raises
    ------
    ValueError
        No poses, mismatched skin topologies, no room for the capsules.
    """
    from pydicom.uid import generate_uid

    from bonecap.io.imaging import write_dicom_series

    rng = _as_rng(rng)
    if not poses:
        raise ValueError("poses must not be empty")
    fp: dict[str, ForearmPose] = {}
    for name, pose in poses.items():
        if isinstance(pose, ForearmPose):
            fp[str(name)] = pose
        else:
            if axis is None:
                raise ValueError(f"pose {name!r} is a plain layer list: give axis=")
            fp[str(name)] = ForearmPose(layers=list(pose), axis=np.asarray(axis, float))
    names = list(fp)
    first = fp[names[0]]
    marked: dict[str, dict[str, np.ndarray]] = {}
    for mname, per_pose in (marker_capsules or {}).items():
        if not set(per_pose) <= set(names):
            raise ValueError(f"marker capsule {mname!r} has centres for poses {sorted(set(per_pose) - set(names))} "
                             f"that are not among {names}")
        marked[mname] = {nm: np.asarray(p, float).reshape(3) for nm, p in per_pose.items()}
    at_pose = {nm: np.array([c[nm] for c in marked.values() if nm in c]).reshape(-1, 3) for nm in names}
    lo_s, hi_s = scale_range
    plans = {}
    for n_, (name, pose) in enumerate(fp.items()):
        plans[name] = plan_forearm_stack(pose.skin, pose.axis, name=f"forearm_{name}",
                                         index=first_series_number + n_, pixel_mm=pixel_mm, pitch_mm=pitch_mm,
                                         thickness_mm=thickness_mm, margin_mm=max(12.0, capsule_diameter_mm + 4),
                                         intensity_scale=float(rng.uniform(lo_s, hi_s)),
                                         cover=at_pose[name], cover_radius_mm=capsule_diameter_mm / 2)
    # (a plan holds its marker capsules whole unless they lie beyond max_radius_mm of the axis)
    marked = {m: {nm: p for nm, p in c.items() if _sphere_in_field(plans[nm], p, capsule_diameter_mm / 2)}
              for m, c in marked.items()}
    marked = {m: c for m, c in marked.items() if c}
    placement = place_capsules(first.skin, n_capsules, rng, diameter_mm=capsule_diameter_mm,
                               plans=[plans[nm] for nm in names], skins=[fp[nm].skin for nm in names],
                               min_plane_distance_mm=min_plane_distance_mm, region=first.axis,
                               avoid=[np.array([c[nm] for c in marked.values() if nm in c]).reshape(-1, 3)
                                      for nm in names])
    study_uid = study_uid or generate_uid()
    frame_of_reference_uid = frame_of_reference_uid or generate_uid()
    patient = dict(patient or {})
    out_dir = Path(out_dir)
    truths = {}
    for name in names:
        pose, plan = fp[name], plans[name]
        at_markers = {m: c[name] for m, c in marked.items() if name in c}
        centres = np.vstack([capsule_centres_on(pose.skin, placement),
                             np.array(list(at_markers.values())).reshape(-1, 3)])
        layers = list(pose.layers) + [(m, "oil") for m in capsule_meshes(centres, placement.radius_mm)]
        img = render_volume(layers, plan.affine, plan.shape, slice_thickness_mm=plan.slice_thickness_mm,
                            inplane_supersample=inplane_supersample,
                            through_plane_samples=through_plane_samples, intensities=intensities, rng=rng,
                            bias=bias, noise=noise, texture=texture, scale=plan.intensity_scale)
        meta = {"modality": "MR", "slice_thickness": plan.slice_thickness_mm,
                "patient_name": patient.get("patient_name", "PHANTOM^BONECAP"),
                "patient_id": patient.get("patient_id", "")}
        folder = out_dir / plan.name
        img16 = _to_uint16(img)
        del img                               # the float image is not needed while the series is written
        write_dicom_series(Volume(img16, plan.affine, meta), folder, series_description=plan.description,
                           rescale=False, series_number=plan.index, study_uid=study_uid,
                           frame_of_reference_uid=frame_of_reference_uid)
        del img16
        labels = None
        if pose.label_meshes:
            lab = voxelise_labels(_check_label_meshes(pose.label_meshes), plan.affine, plan.shape,
                                  slice_thickness_mm=plan.slice_thickness_mm,
                                  inplane_supersample=inplane_supersample,
                                  through_plane_samples=through_plane_samples)
            labels = Volume(lab, plan.affine.copy(), {"kind": "oracle_labels", "station": plan.name})
        truths[name] = ForearmTruth(plan=plan, folder=folder, capsule_centres=centres, labels=labels,
                                    marker_capsules=at_markers)
    return truths, placement
