"""The one rule every object box obeys, in calibration and prediction alike: the guarantee needs
them from one population, and a sliver of a box magnifies its crop into outlier scores. Boxes are
``[x, y, width, height]`` of finite numbers in image pixels, origin at the top-left corner.
"""

from __future__ import annotations

from collections.abc import Sequence

#: the smallest box side accepted, in image pixels
MIN_BOX_SIDE_PX = 1.0
#: how far a box may reach past the image border (rounding of labelling tools)
BOX_TOLERANCE_PX = 1.0


def box_problem(bbox: Sequence[float], width: int, height: int) -> str | None:
    """Why this box cannot be used on a ``width`` x ``height`` image, or None."""
    x, y, w, h = (float(v) for v in bbox)
    if w < MIN_BOX_SIDE_PX or h < MIN_BOX_SIDE_PX:
        return f"box width and height must be at least {MIN_BOX_SIDE_PX:g} pixel, got w={w:g}, h={h:g}"
    tol = BOX_TOLERANCE_PX
    if x < -tol or y < -tol or x + w > width + tol or y + h > height + tol:
        return (
            f"box [{x:g}, {y:g}, {w:g}, {h:g}] (x, y, w, h) extends outside the {width}x{height} image; "
            f"boxes must lie inside the image (up to {tol:g} px): clip the box to the image"
        )
    return None
