"""QC pictures: the contour mosaic's layout follows the slices' shape; the personal skeleton's outline."""

from __future__ import annotations

import numpy as np
import pytest

from bonecap.qc import contour_mosaic


@pytest.mark.parametrize("shape, max_ratio", [((594, 182, 20), 1.3), ((256, 256, 24), 1.0)])
def test_mosaic_panels_fill_the_page(tmp_path, shape, max_ratio):
    """A whole-body station is ~3x wider than tall: the page must not be a tall sheet with a thin strip
    of panels (its height once came from the wrong image axis); a square knee slice gives a 4 x 3 grid."""
    from PIL import Image

    img = np.random.default_rng(0).random(shape).astype(np.float32)
    lab = np.zeros(shape, np.int32)
    lab[shape[0] // 3: shape[0] // 2, shape[1] // 3: shape[1] // 2, :] = 1
    p = contour_mosaic(tmp_path / "m.png", img, lab, None, title="t")
    w, h = Image.open(p).size
    assert h / w <= max_ratio
    # the panels take most of the page: the labelled square's contour colour covers some pixels
    px = np.asarray(Image.open(p).convert("RGB"), float)
    blue = (px[..., 2] > 150) & (px[..., 0] < 80)
    assert blue.sum() > 200


def test_mosaic_draws_the_personal_outline_in_yellow(tmp_path):
    """``outline`` (the personal skeleton's label map) is drawn as yellow dashes over the rules' contours;
    without it the page has next to no yellow, even with an olive (tab20) contour on it."""
    from PIL import Image

    shape = (120, 120, 6)
    img = np.random.default_rng(1).random(shape).astype(np.float32)
    lab = np.zeros(shape, np.int32)
    lab[30:60, 30:60, :] = 1
    lab[5:25, 80:110, :] = 9                             # olive: must not count as the outline
    outline = np.zeros(shape, np.int16)
    outline[50:100, 50:100, :] = 7

    def yellow(p):
        px = np.asarray(Image.open(p).convert("RGB"), float)
        # pure yellow, not tab20's olive (188, 189, 34: label 9's contour)
        return int(((px[..., 0] > 215) & (px[..., 1] > 215) & (px[..., 2] < px[..., 0] - 80)).sum())

    # (olive's anti-aliased edge on a bright pixel passes for yellow here and there: a few)
    without = yellow(contour_mosaic(tmp_path / "a.png", img, lab, None))
    with_outline = yellow(contour_mosaic(tmp_path / "b.png", img, lab, None, outline=outline))
    assert without < 30 and with_outline > without + 200
