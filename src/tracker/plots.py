"""PNG plots of recordings and tracking: a contact sheet of depth frames, the fitted model over the
depth image, error per frame.

Figures are drawn with matplotlib's object API on an Agg canvas (no pyplot), so nothing depends on
or changes a global backend, and each PNG is written atomically.
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from handmodel.fileio import atomic_write_bytes


def _figure(**kwargs) -> Figure:
    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path, dpi=100, overwrite=True):
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    atomic_write_bytes(Path(path), buf.getvalue(), overwrite=overwrite)


def depth_scale_mm(depths_mm, near_mm=None, far_mm=None) -> tuple[float, float]:
    """Colour-scale ends for depth images in mm: the 1st and 99th percentile of all valid pixels
    unless given; the far end is kept above the near one.

    >>> depth_scale_mm([np.array([[500.0, np.nan], [700.0, 900.0]])], far_mm=800.0)
    (504.0, 800.0)
    """
    finite = np.concatenate([np.ravel(d)[np.isfinite(np.ravel(d))] for d in depths_mm])
    lo, hi = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
    lo = float(lo if near_mm is None else near_mm)
    hi = float(hi if far_mm is None else far_mm)
    if not hi > lo:
        hi = lo + 1.0
    return lo, hi


def contact_sheet(path, depths_mm, panel_titles, title, *, near_mm=None, far_mm=None, overwrite=False):
    """Depth frames in a grid, colour-mapped (viridis) in mm; pixels without depth are light grey.

    Parameters
    ----------
    path : PNG to write (refused if it exists, unless ``overwrite``)
    depths_mm : list of (H, W) depth images in mm, NaN = no depth
    panel_titles, title : one title per frame, and the figure's
    near_mm, far_mm : colour-scale ends (default: :func:`depth_scale_mm`)

    Returns
    -------
    (lo, hi) : the colour scale used, mm
    """
    lo, hi = depth_scale_mm(depths_mm, near_mm, far_mm)
    n = len(depths_mm)
    cols = int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / cols))
    height, width = np.shape(depths_mm[0])
    aspect = height / width
    fig = _figure(figsize=(2.6 * cols + 0.8, 2.6 * aspect * rows + 0.9), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False)
    cmap = colormaps["viridis"].with_extremes(bad="0.85")  # grey is not in viridis: no data stands out
    im = None
    for ax, label, d in zip(axes.ravel(), panel_titles, depths_mm):
        im = ax.imshow(np.ma.masked_invalid(d), cmap=cmap, vmin=lo, vmax=hi, interpolation="nearest")
        ax.set_title(label, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in axes.ravel()[n:]:
        ax.set_axis_off()
    fig.suptitle(title, fontsize=9)
    fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.8, label="depth (mm)")
    _save(fig, path, dpi=90, overwrite=overwrite)
    return lo, hi


def overlay_png(path, depth, camera, hand, theta, status=""):
    """The depth image with the fitted skeleton projected on it."""
    fig = _figure(figsize=(6.4, 4.8))
    ax = fig.subplots()
    d = np.asarray(depth, float)
    ax.imshow(np.where(np.isfinite(d), d, np.nan), cmap="viridis")
    if np.all(np.isfinite(theta)):
        kp = hand.keypoints(theta)
        u = camera.fx * kp[:, 0] / kp[:, 2] + camera.cx
        v = camera.fy * kp[:, 1] / kp[:, 2] + camera.cy
        for i, p in enumerate(hand.parents):
            if p >= 0:
                ax.plot(u[[p, i]], v[[p, i]], "-", color="w", lw=2)
        ax.plot(u, v, "o", color="r", ms=3)
        pad = 40
        ax.set_xlim(max(u.min() - pad, 0), min(u.max() + pad, d.shape[1]))
        ax.set_ylim(min(v.max() + pad, d.shape[0]), max(v.min() - pad, 0))
    ax.set_title(f"{Path(path).stem} {status}")
    ax.set_axis_off()
    _save(fig, path)


def error_plot(path, posture_deg, keypoint_mm, status=None, title=""):
    """Posture and keypoint error per frame; frames not tracked are marked in red."""
    fig = _figure(figsize=(8, 5))
    ax = fig.subplots(2, 1, sharex=True)
    f = np.arange(len(posture_deg))
    ax[0].plot(f, posture_deg, lw=1)
    ax[0].set_ylabel("posture error (°)")
    ax[1].plot(f, keypoint_mm, lw=1, color="C1")
    ax[1].set_ylabel("keypoint error (mm)")
    ax[1].set_xlabel("frame")
    if status is not None:
        lost = np.flatnonzero(np.asarray(status) != "tracked")
        for a in ax:
            for i in lost:
                a.axvline(i, color="r", alpha=0.2, lw=1)
    ax[0].set_title(title)
    fig.tight_layout()
    _save(fig, path)
