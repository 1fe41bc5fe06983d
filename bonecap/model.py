"""The plain data classes that pass between bonecap's stages.

Conventions shared by every class here:

- **Lengths in millimetres, times in seconds.** Readers convert on the way in
  (C3D ``POINT:UNITS``, DICOM spacing, metres of OpenSim and glTF); writers
  convert on the way out.
- **World frame of images: LPS** (DICOM patient coordinates: +x to the
  patient's Left, +y Posterior, +z Superior). NIfTI (RAS) is converted on read
  with ``diag(-1, -1, 1, 1)``.
- **Lab frame of trials**: the frame the C3D file stores (usually Z up).
- **Poses are 4x4 homogeneous transforms named ``a_to_b``**: they map
  coordinates in frame *a* to frame *b* (``p_b = T @ p_a``). Bone frames follow
  the ISB recommendations (Wu et al. 2002, 2005); see :mod:`bonecap.skeleton`.
- Missing samples are ``NaN``, never zero.

Each class checks its shapes in ``__post_init__`` and raises ``ValueError``
with the offending shape, so a stage that builds a malformed object fails where
the mistake is made, not three stages later.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Volume", "Trial", "Mesh", "Bone", "Skeleton", "Motion"]


def _check_transform(name: str, T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"{name} must end in 4x4, got shape {T.shape}")
    return T


@dataclass
class Volume:
    """A 3-D image on a regular grid.

    Attributes
    ----------
    data : ndarray, shape (I, J, K)
        Voxel values, indexed ``data[i, j, k]``. For a DICOM series ``i`` runs
        along a row (columns), ``j`` down the columns (rows) and ``k`` along the
        slice normal; for NIfTI/NRRD the file's own axis order is kept.
        Rescale slope/intercept are already applied (MR in scanner units, CT in HU).
    affine : ndarray, shape (4, 4)
        ``voxel_to_lps``: maps ``(i, j, k, 1)`` to LPS world millimetres.
    metadata : dict
        Free-form description: ``modality``, ``series_uid``,
        ``series_description``, ``echo_number``, ``echo_time``,
        ``acquisition_number``, ``source_files`` (list of str), ``format``.
    """

    data: np.ndarray
    affine: np.ndarray
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        self.data = np.asarray(self.data)
        if self.data.ndim != 3:
            raise ValueError(f"Volume.data must be 3-D (I, J, K), got shape {self.data.shape}")
        self.affine = _check_transform("Volume.affine", self.affine)
        if self.affine.shape != (4, 4):
            raise ValueError(f"Volume.affine must be 4x4, got {self.affine.shape}")

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.data.shape)  # type: ignore[return-value]

    @property
    def spacing(self) -> np.ndarray:
        """Voxel size along i, j, k in mm (the column norms of the affine)."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    @property
    def direction(self) -> np.ndarray:
        """Unit direction cosines of the i, j, k axes in LPS, as columns (3x3)."""
        return self.affine[:3, :3] / self.spacing

    def index_to_world(self, ijk: np.ndarray) -> np.ndarray:
        """Map voxel indices ``(..., 3)`` to LPS millimetres ``(..., 3)``."""
        ijk = np.asarray(ijk, dtype=float)
        return ijk @ self.affine[:3, :3].T + self.affine[:3, 3]

    def world_to_index(self, xyz: np.ndarray) -> np.ndarray:
        """Map LPS millimetres ``(..., 3)`` to (fractional) voxel indices."""
        inv = np.linalg.inv(self.affine)
        xyz = np.asarray(xyz, dtype=float)
        return xyz @ inv[:3, :3].T + inv[:3, 3]


@dataclass
class Trial:
    """A motion-capture trial: marker trajectories in the lab frame.

    Attributes
    ----------
    labels : list of str
        Marker names with the subject prefix removed (``"Derrick:LSHO"`` ->
        ``"LSHO"``).
    points : ndarray, shape (F, M, 3)
        Marker positions in **mm** in the lab frame of the file; ``NaN`` where
        the marker was not seen (a gap).
    rate : float
        Point frame rate in Hz.
    first_frame : int
        The file's first frame number (C3D ``header.first_frame``), so frame
        ``f`` of ``points`` is frame ``first_frame + f`` of the recording.
    prefixes : list of str
        The prefix stripped from each label (``""`` when there was none),
        parallel to ``labels``.
    residuals : ndarray, shape (F, M), optional
        Per-sample reconstruction residual as stored (mm), ``NaN`` in gaps.
    other_points : dict of str -> ndarray (F, 3)
        Points that are *not* markers (Vicon's ``POINT:ANGLES``, ``FORCES``,
        ``MOMENTS``, ``POWERS``, ``SCALARS``, ``REACTIONS``,
        ``MODELED_MARKERS``), kept **as stored**: joint angles stay in degrees
        and are never scaled as positions.
    other_point_groups : dict of str -> str
        For each entry of ``other_points``, the parameter that listed it
        (``"ANGLES"``, ``"FORCES"``...).
    analog_labels : list of str
    analogs : ndarray, shape (A, S)
        Analog channels (scaled by the file's gains and offsets), ``S`` samples.
    analog_rate : float
        Analog sample rate in Hz (0 when there are no analogs).
    events : list of dict
        ``{"label", "context", "time"}`` with time in seconds from the
        recording's start, when the file holds events.
    subject_parameters : dict of str -> float
        The subject's measurements a lab stores with the trial (C3D
        ``PROCESSING``: Plug-in Gait's ``LKNEEWIDTH``, ``RANKLEWIDTH``,
        ``LELBOWWIDTH``, ``MARKERDIAMETER``..., mm), upper-case names.
    units : str
        ``POINT:UNITS`` as stored in the file (positions here are always mm).
    metadata : dict
        ``source`` path, ``reader`` ("ezc3d" or "c3d"), manufacturer, etc.
    """

    labels: list[str]
    points: np.ndarray
    rate: float
    first_frame: int = 1
    prefixes: list[str] = field(default_factory=list)
    residuals: np.ndarray | None = None
    other_points: dict[str, np.ndarray] = field(default_factory=dict)
    other_point_groups: dict[str, str] = field(default_factory=dict)
    analog_labels: list[str] = field(default_factory=list)
    analogs: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    analog_rate: float = 0.0
    events: list[dict[str, Any]] = field(default_factory=list)
    subject_parameters: dict[str, float] = field(default_factory=dict)
    units: str = "mm"
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        self.labels = [str(s) for s in self.labels]
        self.points = np.asarray(self.points, dtype=float)
        if self.points.ndim != 3 or self.points.shape[2] != 3:
            raise ValueError(f"Trial.points must have shape (frames, markers, 3), got {self.points.shape}")
        if self.points.shape[1] != len(self.labels):
            raise ValueError(
                f"Trial has {len(self.labels)} labels but points for {self.points.shape[1]} markers")
        if not self.prefixes:
            self.prefixes = [""] * len(self.labels)
        if len(self.prefixes) != len(self.labels):
            raise ValueError("Trial.prefixes must be parallel to Trial.labels")
        if self.residuals is not None:
            self.residuals = np.asarray(self.residuals, dtype=float)
            if self.residuals.shape != self.points.shape[:2]:
                raise ValueError(
                    f"Trial.residuals must have shape {self.points.shape[:2]}, got {self.residuals.shape}")
        if not self.rate > 0:
            raise ValueError(f"Trial.rate must be positive, got {self.rate}")
        self.analogs = np.asarray(self.analogs, dtype=float)

    @property
    def n_frames(self) -> int:
        return self.points.shape[0]

    @property
    def times(self) -> np.ndarray:
        """Sample times in seconds, starting at 0."""
        return np.arange(self.n_frames) / self.rate

    def marker(self, label: str) -> np.ndarray:
        """The ``(F, 3)`` trajectory of one marker, by its label without prefix."""
        try:
            return self.points[:, self.labels.index(label)]
        except ValueError:
            raise KeyError(f"no marker {label!r} in trial (has {', '.join(self.labels)})") from None

    def gap_counts(self) -> dict[str, int]:
        """Number of missing frames per marker."""
        missing = np.isnan(self.points).any(axis=2).sum(axis=0)
        return dict(zip(self.labels, (int(n) for n in missing)))


@dataclass
class Mesh:
    """A triangle mesh.

    Attributes
    ----------
    vertices : ndarray, shape (N, 3)
        Vertex positions in **mm**, in the frame named by ``frame``.
    faces : ndarray, shape (M, 3) of int
        Vertex indices, counter-clockwise seen from outside (outward normals).
    frame : str
        Name of the frame the vertices are expressed in (``"lps"``, ``"lab"``,
        or a bone name for a mesh in its bone's own frame).
    """

    vertices: np.ndarray
    faces: np.ndarray
    frame: str = ""

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, dtype=float)
        self.faces = np.asarray(self.faces, dtype=np.int64)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise ValueError(f"Mesh.vertices must have shape (N, 3), got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"Mesh.faces must have shape (M, 3), got {self.faces.shape}")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= len(self.vertices)):
            raise ValueError("Mesh.faces index vertices that do not exist")

    def transformed(self, T: np.ndarray, frame: str = "") -> "Mesh":
        """A copy with vertices mapped by the 4x4 transform ``T`` (current frame -> ``frame``)."""
        T = _check_transform("T", T)
        return Mesh(self.vertices @ T[:3, :3].T + T[:3, 3], self.faces.copy(), frame)

    def to_trimesh(self):
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)


@dataclass
class Bone:
    """One rigid bone of a skeleton.

    Attributes
    ----------
    name : str
        Our bone name (``"femur_r"``...) or, for an imported OpenSim model, the
        OpenSim body name.
    parent : str or None
        Name of the parent bone; ``None`` for the root (pelvis).
    mesh : Mesh or None
        Surface in the bone's **own frame** (mm).
    bone_to_world : ndarray, shape (4, 4)
        Pose of the bone frame in the skeleton's world frame at the reference pose.
    joint_centres : dict of str -> ndarray (3,)
        Joint centres in the bone's own frame (mm), e.g. ``{"hip": ..., "knee": ...}``.
    joint_axes : dict of str -> ndarray (3,)
        Unit joint axes in the bone's own frame (e.g. the knee flexion axis,
        the radio-ulnar axis), keyed like ``joint_centres``.
    landmarks : dict of str -> ndarray (3,)
        Named anatomical landmarks in the bone's own frame (mm).
    inner_mesh : Mesh or None
        Endosteal surface (the marrow boundary) in the bone's own frame: the
        space between ``mesh`` and ``inner_mesh`` is cortex. ``None`` for bones
        modelled as solid.
    metadata : dict
        Free-form: ISB frame description, cortical thickness, OpenSim body name.
    """

    name: str
    parent: str | None = None
    mesh: Mesh | None = None
    bone_to_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    joint_centres: dict[str, np.ndarray] = field(default_factory=dict)
    joint_axes: dict[str, np.ndarray] = field(default_factory=dict)
    landmarks: dict[str, np.ndarray] = field(default_factory=dict)
    inner_mesh: Mesh | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        self.bone_to_world = _check_transform(f"Bone {self.name!r} bone_to_world", self.bone_to_world)
        self.joint_centres = {k: np.asarray(v, dtype=float).reshape(3) for k, v in self.joint_centres.items()}
        self.landmarks = {k: np.asarray(v, dtype=float).reshape(3) for k, v in self.landmarks.items()}
        axes = {k: np.asarray(v, dtype=float).reshape(3) for k, v in self.joint_axes.items()}
        self.joint_axes = {k: v / np.linalg.norm(v) for k, v in axes.items()}

    def landmark_in_world(self, name: str) -> np.ndarray:
        """A landmark (or joint centre) of this bone in the skeleton's world frame."""
        p = self.landmarks[name] if name in self.landmarks else self.joint_centres[name]
        return self.bone_to_world[:3, :3] @ p + self.bone_to_world[:3, 3]


@dataclass
class Skeleton:
    """A set of bones at a reference pose.

    Attributes
    ----------
    bones : dict of str -> Bone
        In parent-before-child order.
    world : str
        Name of the world frame of ``bone_to_world`` (``"lps"`` for an MRI
        subject, ``"model"`` for a template).
    metadata : dict
        Provenance (template, source file, parameters).
    """

    bones: dict[str, Bone] = field(default_factory=dict)
    world: str = "model"
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        for name, bone in self.bones.items():
            if bone.parent is not None and bone.parent not in self.bones:
                raise ValueError(f"bone {name!r} names a parent {bone.parent!r} that is not in the skeleton")

    @property
    def names(self) -> list[str]:
        return list(self.bones)

    def world_mesh(self, name: str) -> Mesh:
        """The bone's mesh placed in the world frame at the reference pose."""
        bone = self.bones[name]
        if bone.mesh is None:
            raise ValueError(f"bone {name!r} has no mesh")
        return bone.mesh.transformed(bone.bone_to_world, self.world)


@dataclass
class Motion:
    """Per-frame poses of a skeleton's bones in the lab.

    Attributes
    ----------
    bones : list of str
        Bone names, parallel to axis 1 of ``transforms``.
    times : ndarray, shape (F,)
        Seconds from the first frame (starts at 0).
    transforms : ndarray, shape (F, B, 4, 4)
        ``bone_to_lab`` transforms in mm; ``NaN`` where a bone is not solved.
    valid : ndarray of bool, shape (F, B)
        ``False`` where the pose is missing or was flagged (too few markers,
        gap longer than allowed).
    first_frame : int
        Frame number of the first frame in the source trial.
    marker_labels : list of str
    residuals : ndarray, shape (F, M)
        Distance in mm between each measured marker and where the solved
        skeleton puts it; ``NaN`` where the marker is missing.
    flags : dict of str -> ndarray of bool, shape (F, B)
        Named per-frame warnings that leave the pose valid, e.g.
        ``"forearm_clamped"``: the forearm model's twist was outside its fitted
        range and held at the range's end.
    """

    bones: list[str]
    times: np.ndarray
    transforms: np.ndarray
    valid: np.ndarray | None = None
    first_frame: int = 1
    marker_labels: list[str] = field(default_factory=list)
    residuals: np.ndarray | None = None
    flags: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        self.bones = [str(b) for b in self.bones]
        self.times = np.asarray(self.times, dtype=float).reshape(-1)
        self.transforms = _check_transform("Motion.transforms", self.transforms)
        F, B = len(self.times), len(self.bones)
        if self.transforms.shape != (F, B, 4, 4):
            raise ValueError(f"Motion.transforms must have shape ({F}, {B}, 4, 4), got {self.transforms.shape}")
        if F > 1 and not np.all(np.diff(self.times) > 0):
            raise ValueError("Motion.times must increase strictly")
        if self.valid is None:
            self.valid = np.isfinite(self.transforms).all(axis=(2, 3))
        self.valid = np.asarray(self.valid, dtype=bool)
        if self.valid.shape != (F, B):
            raise ValueError(f"Motion.valid must have shape ({F}, {B}), got {self.valid.shape}")
        if self.residuals is not None:
            self.residuals = np.asarray(self.residuals, dtype=float)
            if self.residuals.shape != (F, len(self.marker_labels)):
                raise ValueError(
                    f"Motion.residuals must have shape ({F}, {len(self.marker_labels)}), got {self.residuals.shape}")

    @property
    def n_frames(self) -> int:
        return len(self.times)
