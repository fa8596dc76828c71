"""Pipeline stage ``segment``: the hand's pixels in a depth (and colour) frame — working volume,
skin colour, nearest blob.

No wristband is needed: with colour, skin pixels (HSV range of the original detector) inside the
working volume; without colour, the connected blob of pixels within ``band`` of the nearest valid
depth (the hand is usually the closest object to the camera in hand-tracking set-ups).
"""
from __future__ import annotations

from dataclasses import dataclass

import matplotlib.colors as mcolors
import numpy as np
from scipy import ndimage

# HSV skin range of htrack's Detector (OpenCV scale: H 0–179, S and V 0–255)
SKIN_HSV = ((0, 56, 113), (179, 174, 255))


@dataclass
class Segmenter:
    """Settings: depth range (m), optional box in the camera frame (m), nearest-blob band (m),
    minimum blob size (pixels), whether to use colour when present."""

    z_min: float = 0.2
    z_max: float = 1.5
    box_min: tuple | None = None
    box_max: tuple | None = None
    band: float = 0.15
    min_pixels: int = 30
    use_color: bool = True

    def __call__(self, depth, color=None, points=None):
        """Boolean hand mask ``(H, W)`` for a depth image in metres (NaN = no data)."""
        d = np.asarray(depth, float)
        valid = np.isfinite(d) & (d > self.z_min) & (d < self.z_max)
        if (self.box_min is not None or self.box_max is not None) and points is not None:
            valid &= in_box(points, self.box_min, self.box_max)
        if not valid.any():
            return valid
        if color is not None and self.use_color:
            skin = skin_mask(color) & valid
            if skin.sum() >= self.min_pixels:
                return largest_component(skin)
        return nearest_blob(np.where(valid, d, np.nan), self.band, self.min_pixels)


def in_box(points, box_min=None, box_max=None) -> np.ndarray:
    """Boolean ``(...)``: points ``(..., 3)`` inside the axis-aligned box (bounds inclusive; None, a None
    entry or ±inf = open; NaN points are outside)."""
    p = np.asarray(points, float)
    lo = np.array([-np.inf if v is None else v for v in np.broadcast_to(np.asarray(box_min, object), 3)], float)
    hi = np.array([np.inf if v is None else v for v in np.broadcast_to(np.asarray(box_max, object), 3)], float)
    with np.errstate(invalid="ignore"):
        return np.all((p >= lo) & (p <= hi), axis=-1)


def skin_mask(color):
    """Pixels inside the skin HSV range (colour ``(H, W, 3)`` uint8 RGB)."""
    hsv = mcolors.rgb_to_hsv(np.asarray(color, float) / 255.0)
    h, s, v = hsv[..., 0] * 179.0, hsv[..., 1] * 255.0, hsv[..., 2] * 255.0
    (h0, s0, v0), (h1, s1, v1) = SKIN_HSV
    return (h >= h0) & (h <= h1) & (s >= s0) & (s <= s1) & (v >= v0) & (v <= v1)


def largest_component(mask):
    lab, n = ndimage.label(mask)
    if n <= 1:
        return mask
    sizes = ndimage.sum(mask, lab, index=np.arange(1, n + 1))
    return lab == (1 + int(np.argmax(sizes)))


def nearest_blob(depth, band=0.15, min_pixels=30, jump=0.02, margin_px=25):
    """The nearest sizeable surface, cut to ``band`` metres behind its nearest part.

    Pixels are grouped into surfaces by depth continuity (neighbours closer than ``jump``); among
    surfaces of at least ``min_pixels`` (and 5 % of the largest) the one whose 2nd-percentile depth is
    smallest wins (the hand held towards the camera). Then everything within ``band`` of that depth
    that is connected to the biggest part of it, or lies within ``margin_px`` of that part (fingers cut
    off by sensor shadows), is kept — the hand, not the arm or body behind it."""
    d = np.asarray(depth, float)
    finite = np.isfinite(d)
    if not finite.any():
        return finite
    with np.errstate(invalid="ignore"):
        cut = np.zeros_like(finite)
        cut[:, :-1] |= np.abs(d[:, 1:] - d[:, :-1]) > jump
        cut[:-1, :] |= np.abs(d[1:, :] - d[:-1, :]) > jump
    lab, n = ndimage.label(finite & ~cut)
    if n == 0:
        return np.zeros_like(finite)
    ids = np.arange(1, n + 1)
    sizes = ndimage.sum(np.ones_like(d), lab, index=ids)
    big = ids[sizes >= max(min_pixels, 0.05 * sizes.max())]
    if big.size == 0:
        return np.zeros_like(finite)
    fronts = [np.percentile(d[lab == k], 2) for k in big]
    front = min(fronts)
    near = finite & (d <= front + band)
    lab2, n2 = ndimage.label(near)
    if n2 == 0:
        return np.zeros_like(finite)
    sizes2 = ndimage.sum(np.ones_like(d), lab2, index=np.arange(1, n2 + 1))
    main = lab2 == (1 + int(np.argmax(sizes2)))
    zone = ndimage.binary_dilation(main, iterations=margin_px)
    keep = np.unique(lab2[zone & near])
    keep = keep[keep > 0]
    return np.isin(lab2, keep)
