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


def contact_sheet(path, depths_mm, panel_titles, title, *, near_mm=None, far_mm=None, overwrite=False,
                  masks=None):
    """Depth frames in a grid, colour-mapped (viridis) in mm; pixels without depth are light grey.

    Parameters
    ----------
    path : PNG to write (refused if it exists, unless ``overwrite``)
    depths_mm : list of (H, W) depth images in mm, NaN = no depth
    panel_titles, title : one title per frame, and the figure's
    near_mm, far_mm : colour-scale ends (default: :func:`depth_scale_mm`)
    masks : optional list of (H, W) bool segmentation masks, outlined in white on their panels

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
    for k, (ax, label, d) in enumerate(zip(axes.ravel(), panel_titles, depths_mm)):
        im = ax.imshow(np.ma.masked_invalid(d), cmap=cmap, vmin=lo, vmax=hi, interpolation="nearest")
        if masks is not None and np.any(masks[k]):
            ax.contour(np.asarray(masks[k], float), [0.5], colors="w", linewidths=0.8)
        ax.set_title(label, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in axes.ravel()[n:]:
        ax.set_axis_off()
    fig.suptitle(title, fontsize=9)
    fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.8, label="depth (mm)")
    _save(fig, path, dpi=90, overwrite=overwrite)
    return lo, hi


def project(points, camera):
    """Pixel coordinates ``(u, v)`` of camera-frame points ``(..., 3)`` (pixel centres at integers)."""
    p = np.asarray(points, float)
    return camera.fx * p[..., 0] / p[..., 2] + camera.cx, camera.fy * p[..., 1] / p[..., 2] + camera.cy


def model_silhouette(hand, theta, camera, shape, spacing=0.003):
    """Boolean ``(H, W)`` image of the pixels the posed hand model covers (its surface samples,
    projected, each filling the pixels within its footprint)."""
    from handmodel.geometry import surface_samples

    H, W = shape
    sil = np.zeros((H, W), bool)
    pts = surface_samples(hand, theta, spacing=spacing)[0]
    pts = pts[pts[:, 2] > 1e-3]
    if not len(pts):
        return sil
    u, v = project(pts, camera)
    # a sample covers about spacing·f/z pixels: fill that square around it
    half = np.maximum(np.ceil(0.5 * spacing * camera.fx / pts[:, 2]).astype(int), 1)
    for du in range(-int(half.max()), int(half.max()) + 1):
        for dv in range(-int(half.max()), int(half.max()) + 1):
            ok = (np.abs(du) <= half) & (np.abs(dv) <= half)
            uu = np.rint(u[ok]).astype(int) + du
            vv = np.rint(v[ok]).astype(int) + dv
            inside = (uu >= 0) & (uu < W) & (vv >= 0) & (vv < H)
            sil[vv[inside], uu[inside]] = True
    return sil


def overlay_png(path, depth, camera, hand, theta, status="", mask=None, labelled=None):
    """The whole depth frame (grey where there is no depth) with the segmentation mask's outline
    (white), the fitted hand's silhouette (translucent red) and skeleton (thumb in orange, its
    tip ringed), so a wrong segmentation or a fit on the wrong object is seen at a glance.

    Parameters
    ----------
    path : PNG to write
    depth : (H, W) depth in metres, NaN = no data
    camera : anything with ``fx fy cx cy``
    hand, theta : the hand model and its fitted parameters (NaN: no fit drawn)
    status : text for the title (e.g. tracked / lost)
    mask : (H, W) bool segmentation mask, or None
    labelled : (N, 2) pixels labelled by hand (e.g. fingertips), drawn as cyan crosses, or None
    """
    d = np.asarray(depth, float)
    H, W = d.shape
    fig = _figure(figsize=(W / 100, (H + 60) / 100))
    ax = fig.add_axes((0.0, 0.0, 1.0, H / (H + 60)))
    cmap = colormaps["viridis"].with_extremes(bad="0.85")
    finite = d[np.isfinite(d)]
    lo, hi = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
    ax.imshow(np.ma.masked_invalid(d), cmap=cmap, vmin=lo, vmax=max(hi, lo + 1e-3), interpolation="nearest")
    if mask is not None and np.any(mask):
        ax.contour(np.asarray(mask, float), [0.5], colors="w", linewidths=1.2)
    theta = np.asarray(theta, float)
    fitted = theta.size and np.all(np.isfinite(theta))
    if fitted:
        sil = model_silhouette(hand, theta, camera, (H, W))
        rgba = np.zeros((H, W, 4))
        rgba[sil] = (1.0, 0.15, 0.15, 0.35)
        ax.imshow(rgba, interpolation="nearest")
        kp = hand.keypoints(theta)
        u, v = project(kp, camera)
        names = hand.keypoint_names
        for i, p in enumerate(hand.parents):
            if p >= 0:
                thumb = names[i].startswith("thumb")
                ax.plot(u[[p, i]], v[[p, i]], "-", color="orange" if thumb else "k", lw=2.5 if thumb else 1.8)
        ax.plot(u, v, "o", color="r", ms=3)
        if "thumb_tip" in names:
            t = names.index("thumb_tip")
            ax.plot(u[t], v[t], "o", mfc="none", mec="orange", ms=10, mew=2)
    if labelled is not None and len(labelled):
        lu, lv = np.asarray(labelled, float).reshape(-1, 2).T
        ax.plot(lu, lv, "+", color="c", ms=12, mew=2.5)
    ax.set_xlim(-0.5, W - 0.5)
    ax.set_ylim(H - 0.5, -0.5)
    ax.set_axis_off()
    legend = "white: segmentation mask · red: fitted hand · orange: thumb" if fitted else \
        "white: segmentation mask · no fit"
    if labelled is not None and len(labelled):
        legend += " · cyan: labelled"
    fig.text(0.01, 1 - 30 / (H + 60), f"{Path(path).stem}  {status}", fontsize=10, va="center")
    fig.text(0.01, 1 - 50 / (H + 60), legend, fontsize=8, va="center")
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
