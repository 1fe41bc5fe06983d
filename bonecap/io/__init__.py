"""File formats <-> bonecap's model objects.

One module per format family; each one's docstring explains how the format maps
onto the data classes of :mod:`bonecap.model`:

- :mod:`bonecap.io.c3d`     -- C3D motion-capture trials <-> :class:`~bonecap.model.Trial`
- :mod:`bonecap.io.imaging` -- DICOM series, NIfTI, NRRD <-> :class:`~bonecap.model.Volume`
- :mod:`bonecap.io.mesh`    -- PLY/STL/OBJ/VTP <-> :class:`~bonecap.model.Mesh`
- :mod:`bonecap.io.gltf`    -- animated bone meshes -> binary glTF (``.glb``)
- :func:`load_yaml`         -- our YAML files (``subject.yaml``, marker sets, tables) -> plain Python objects

Every writer writes to a temporary file beside its target and renames it at
the end (:func:`bonecap.io.atomic.atomic_path`), so a failure never leaves a
half-written output behind.
"""


def load_yaml(text):
    """Parse YAML (a string or an open text file) with pyyaml's safe loader, in C when available.

    libyaml's ``CSafeLoader`` builds the same objects as ``yaml.safe_load`` (plain
    Python types, no arbitrary tags) about five times faster: a whole-body
    subject's 170 kB ``subject.yaml`` 665 -> 129 ms, the Plug-in Gait marker set
    65 -> 8 ms. pyyaml built without libyaml falls back to the pure-Python loader.

    Raises
    ------
    yaml.YAMLError
        The text is not valid YAML.
    """
    import yaml

    return yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
