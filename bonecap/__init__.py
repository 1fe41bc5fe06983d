"""bonecap: from a person's MRI to their own skeleton, driven by optical motion capture.

The package is laid out by stage of the data flow::

    io/          file formats -> model objects (C3D, DICOM/NIfTI/NRRD, meshes, glTF)
    model.py     the plain data classes that pass between stages
    errors.py    the exception hierarchy (one ``BonecapError`` root)
    cli.py       argparse wiring only

Later stages (segmentation, meshing, skeleton warp, markers, motion solving,
export, markerless) each get their own module beside these.
"""

from bonecap.errors import BonecapError
from bonecap.model import Bone, Mesh, Motion, Skeleton, Trial, Volume

__all__ = ["BonecapError", "Bone", "Mesh", "Motion", "Skeleton", "Trial", "Volume"]
__version__ = "0.1.0"
