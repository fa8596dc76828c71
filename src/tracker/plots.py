"""PNG plots of tracking: the fitted model over the depth image, error per frame."""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path):
    from handmodel.fileio import atomic_write_bytes

    plt = _plt()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(Path(path), buf.getvalue())


def overlay_png(path, depth, camera, hand, theta, status=""):
    """The depth image with the fitted skeleton projected on it."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
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
    plt = _plt()
    fig, ax = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
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
