"""Input checks shared by the slice rules (one 2-D slice, its masks, a seed)."""

from __future__ import annotations

import numpy as np


def check_image(image, name: str = "image") -> np.ndarray:
    """One non-empty 2-D slice ``image[i, j]``, else ``ValueError``."""
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"{name} must be one 2-D slice image[i, j], got shape {image.shape}")
    if image.size == 0:
        raise ValueError(f"{name} is empty")
    return image


def check_mask(mask, shape, name: str, *, allow_none: bool = False) -> np.ndarray:
    """A boolean mask of the image's shape; ``None`` means everywhere when ``allow_none``."""
    if mask is None and allow_none:
        return np.ones(shape, bool)
    mask = np.asarray(mask)
    if mask.shape != tuple(shape):
        raise ValueError(f"{name} must have the image's shape {tuple(shape)}, got {mask.shape}")
    return mask.astype(bool, copy=False)


def check_seed(seed_ij) -> np.ndarray:
    """Two finite pixel coordinates ``(i, j)``."""
    seed = np.asarray(seed_ij, dtype=float)
    if seed.shape != (2,) or not np.isfinite(seed).all():
        raise ValueError(f"seed_ij must be two finite pixel coordinates (i, j), got {seed_ij!r}")
    return seed


def check_body_mask(volume, body_mask) -> np.ndarray:
    """The body of an axial stack: ``body_mask`` checked against ``volume.data``'s shape, or
    :func:`bonecap.segmentation.skin.segment_body` of the volume when it is None."""
    if body_mask is None:
        from bonecap.segmentation.skin import segment_body

        return segment_body(volume)
    body_mask = np.asarray(body_mask, bool)
    if body_mask.shape != np.shape(volume.data):
        raise ValueError(f"body_mask must have the volume's shape {np.shape(volume.data)}, got {body_mask.shape}")
    return body_mask
