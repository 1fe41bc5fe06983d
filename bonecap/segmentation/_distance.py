"""In-plane Euclidean distances of a stack of slices, shared by the slice rules and the meshing."""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def inplane_edt(mask: np.ndarray, sampling) -> np.ndarray:
    """Distance (mm) of every voxel of ``mask[:, :, k]`` to the nearest ``False`` voxel of its own slice.

    The same numbers as one 3-D ``scipy.ndimage.distance_transform_edt`` with a
    huge spacing along ``k`` (the old way of keeping the transform in each
    slice), 2.5-4x faster: the 3-D transform carries a feature-index array
    through a third pass. A slice without a ``False`` voxel has no finite
    distance: ``inf`` there (the 3-D call gave about the huge spacing, scipy's
    2-D call distances to a point off the array).

    Parameters
    ----------
    mask : ndarray of bool (I, J, K)
        ``K`` slices; ``True`` is the region whose depth is measured.
    sampling : sequence of 2 float
        Pixel size along ``i`` and ``j`` (mm).

    Returns
    -------
    ndarray of float64 (I, J, K)
        0 outside the region.
    """
    mask = np.asarray(mask, bool)
    if mask.ndim != 3:
        raise ValueError(f"mask must be 3-D [i, j, k], got shape {mask.shape}")
    samp = (float(sampling[0]), float(sampling[1]))
    out = np.empty(mask.shape, float)
    for k in range(mask.shape[2]):
        s = mask[:, :, k]
        if s.all():
            out[:, :, k] = np.inf
        else:
            out[:, :, k] = ndimage.distance_transform_edt(s, sampling=samp)
    return out
