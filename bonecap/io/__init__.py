"""File formats <-> bonecap's model objects.

One module per format family; each one's docstring explains how the format maps
onto the data classes of :mod:`bonecap.model`:

- :mod:`bonecap.io.c3d`     -- C3D motion-capture trials <-> :class:`~bonecap.model.Trial`
- :mod:`bonecap.io.imaging` -- DICOM series, NIfTI, NRRD <-> :class:`~bonecap.model.Volume`
- :mod:`bonecap.io.mesh`    -- PLY/STL/OBJ/VTP <-> :class:`~bonecap.model.Mesh`
- :mod:`bonecap.io.gltf`    -- animated bone meshes -> binary glTF (``.glb``)

Every writer writes to a temporary file beside its target and renames it at
the end (:func:`bonecap.io.atomic.atomic_path`), so a failure never leaves a
half-written output behind.
"""
