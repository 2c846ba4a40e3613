"""The live view's colour scale, shared by the web page (core/runtime/view_page.py) and Blender's live link
(addon/live.py): force in N from 0 to `vmax` (default twice the largest taxel threshold), dark blue ->
red at the threshold -> yellow; grey: no fresh reading (an excluded taxel, a silent board). numpy only."""
from __future__ import annotations

import numpy as np

# colour scale stops: fraction of vmax -> sRGB (0-255); the threshold sits at 0.5 with the default vmax
STOPS = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
COLOURS = np.array([[30, 50, 110], [60, 80, 200], [220, 40, 30], [255, 140, 0], [255, 240, 90]], float)
NO_DATA = np.array([150, 150, 150], np.uint8)


def default_vmax(thresholds) -> float:
    """Top of the scale: twice the largest taxel threshold (1 N without thresholds)."""
    th = np.asarray(thresholds, float)
    return 2.0 * (float(np.max(th)) if th.size else 1.0)


def colours(force: np.ndarray, vmax: float) -> np.ndarray:
    """(N, 3) uint8 sRGB colours of forces (N) on the scale; NaN grey."""
    f = np.asarray(force, float)
    x = np.clip(np.nan_to_num(f, nan=0.0) / vmax, 0.0, 1.0)
    rgb = np.stack([np.interp(x, STOPS, COLOURS[:, c]) for c in range(3)], 1).astype(np.uint8)
    rgb[~np.isfinite(f)] = NO_DATA
    return rgb
