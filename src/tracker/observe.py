"""From a depth frame to what the tracker fits: the segmented hand's 3-D points (every ``stride``-th
pixel in x and y), their surface normals, and the silhouette. Pixel (u, v) has its centre at integer
coordinates: x = (u − cx)/fx · z, y = (v − cy)/fy · z (camera frame: x right, y down, z forward)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def backproject_image(depth, camera):
    """Camera-frame points ``(H, W, 3)`` of a depth image in metres (NaN where no depth); any object with
    ``fx fy cx cy`` serves as the camera. float32 depth gives float32 points, anything else float64."""
    d = np.asarray(depth)
    dt = np.float32 if d.dtype == np.float32 else np.float64
    d = d.astype(dt, copy=False)
    H, W = d.shape
    out = np.empty((H, W, 3), dt)
    out[..., 0] = d * ((np.arange(W, dtype=dt) - camera.cx) / camera.fx)[None, :]
    out[..., 1] = d * ((np.arange(H, dtype=dt) - camera.cy) / camera.fy)[:, None]
    out[..., 2] = d
    return out


def image_normals(X, max_jump=0.01):
    """Unit normals ``(H, W, 3)`` from central differences of back-projected points, oriented
    towards the camera; NaN where a neighbour is missing or a depth jump exceeds ``max_jump`` m."""
    dx = np.full_like(X, np.nan)
    dy = np.full_like(X, np.nan)
    dx[:, 1:-1] = X[:, 2:] - X[:, :-2]
    dy[1:-1] = X[2:] - X[:-2]
    with np.errstate(invalid="ignore"):
        bad = (np.abs(dx[..., 2]) > max_jump) | (np.abs(dy[..., 2]) > max_jump)
    n = np.cross(dx, dy)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-300
    n *= -np.sign(np.einsum("...i,...i->...", n, X))[..., None]
    n[bad] = np.nan
    return n


def smooth_depth(depth, radius=1, max_diff=0.01):
    """Edge-preserving smoothing: each pixel becomes the mean of the valid pixels in its
    (2r+1)² window whose depth is within ``max_diff`` m of its own (a cheap bilateral filter that
    averages sensor noise without blurring the hand into the background)."""
    d = np.asarray(depth, float)
    H, W = d.shape
    pad = np.pad(d, radius, constant_values=np.nan)
    acc = np.zeros_like(d)
    cnt = np.zeros_like(d)
    with np.errstate(invalid="ignore"):
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                nb = pad[radius + dy:radius + dy + H, radius + dx:radius + dx + W]
                ok = np.isfinite(nb) & (np.abs(nb - d) <= max_diff)
                acc += np.where(ok, nb, 0.0)
                cnt += ok
    out = np.where(cnt > 0, acc / np.maximum(cnt, 1), np.nan)
    out[~np.isfinite(d)] = np.nan
    return out


@dataclass
class Observation:
    points: np.ndarray        # (N, 3) metres
    normals: np.ndarray       # (N, 3), NaN where unknown
    mask: np.ndarray          # (H, W) hand silhouette
    depth: np.ndarray         # (H, W) metres
    density: float            # share of silhouette pixels kept (≈ 1/stride²)
    stride: int = 1


def observe(depth, camera, *, stride=3, segmenter=None, color=None, target_points=None, smooth=0):
    """Segment the hand and sample its points (every ``stride``-th pixel in x and y).

    With ``target_points`` the stride adapts to the hand's size in the image: the largest stride
    (at most ``stride``) that still keeps about that many points, so a distant hand is sampled densely
    enough and a near one is not oversampled. ``smooth`` > 0 applies :func:`smooth_depth` with that
    radius first (for noisy sensors)."""
    from .segment import Segmenter

    d = np.asarray(depth, np.float64)
    if smooth:
        d = smooth_depth(d, int(smooth))
    seg = segmenter or Segmenter()
    X = backproject_image(d, camera)
    mask = seg(d, color, X)
    N = image_normals(X)
    if target_points:
        stride = int(np.clip(np.floor(np.sqrt(mask.sum() / float(target_points))), 1, stride))
    sub = np.zeros_like(mask)
    sub[::stride, ::stride] = True
    keep = mask & sub & np.isfinite(X).all(-1)
    n_mask = max(int(mask.sum()), 1)
    return Observation(X[keep], N[keep], mask, np.where(mask, d, np.nan), float(keep.sum()) / n_mask, stride)
