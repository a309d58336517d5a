"""Where a generic bundle adjustment's observations fall on its grid, and the image regions left
without any (:func:`blurcalib.calib.bundle.bundle_adjust`'s warnings)."""

from __future__ import annotations

import numpy as np

from blurcalib.camera.generic import CentralGeneric
from blurcalib.io.text import count

__all__ = ["cell_coverage", "coverage_warnings"]


def cell_coverage(model: CentralGeneric, px: np.ndarray) -> np.ndarray:
    """Observation count per grid cell of the calibrated area, ``(GH - 3, GW - 3)``."""
    g = model.to_grid(px)
    cw, ch = model.grid_width - 3, model.grid_height - 3
    cx = np.clip(np.floor(g[:, 0]).astype(int) - 1, 0, cw - 1)
    cy = np.clip(np.floor(g[:, 1]).astype(int) - 1, 0, ch - 1)
    return np.bincount(cy * cw + cx, minlength=cw * ch).reshape(ch, cw)


def _off_axis_deg(model: CentralGeneric, px: np.ndarray) -> str:
    """`` , A-B degrees off the axis`` of the model's rays at pixels ``(N, 2)`` (the angle of each
    ray from the camera's z axis), or "" where it has none."""
    rays = model.pixel_to_ray(px)
    rays = rays[np.all(np.isfinite(rays), axis=1)]
    if not len(rays):
        return ""
    angle = np.degrees(np.arctan2(np.hypot(rays[:, 0], rays[:, 1]), rays[:, 2]))
    return f", {angle.min():.0f}-{angle.max():.0f} degrees off the axis"


def coverage_warnings(model: CentralGeneric, coverage: np.ndarray) -> list[str]:
    """One line per image region (3 x 3 split) holding grid cells without observations: where, in
    pixels and in degrees off the optical axis (a wide lens's corners are hard to fill)."""
    ch, cw = coverage.shape
    x0, y0, x1, y1 = model.area_opencv
    cell_w = (x1 - x0) / cw
    cell_h = (y1 - y0) / ch
    names_y = ("top", "middle", "bottom")
    names_x = ("left", "centre", "right")
    out: list[str] = []
    rows, cols = np.nonzero(coverage == 0)
    if len(rows) == 0:
        return out
    ry = np.minimum(rows * 3 // ch, 2)
    rx = np.minimum(cols * 3 // cw, 2)
    for by in range(3):
        for bx in range(3):
            sel = (ry == by) & (rx == bx)
            if not sel.any():
                continue
            name = "centre" if (by, bx) == (1, 1) else f"{names_y[by]}-{names_x[bx]}"
            xa = x0 + cols[sel].min() * cell_w
            xb = x0 + (cols[sel].max() + 1) * cell_w
            ya = y0 + rows[sel].min() * cell_h
            yb = y0 + (rows[sel].max() + 1) * cell_h
            centres = np.column_stack([x0 + (cols[sel] + 0.5) * cell_w, y0 + (rows[sel] + 0.5) * cell_h])
            out.append(f"{count(int(sel.sum()), 'grid cell')} without observations in the {name} of the "
                       f"image (x {max(xa, 0):.0f}-{xb:.0f} px, y {max(ya, 0):.0f}-{yb:.0f} px"
                       f"{_off_axis_deg(model, centres)}): the model there follows the initial camera "
                       "(smoothness prior)")
    return out
