"""PNG plots of recordings and tracking: a contact sheet of depth frames, the fitted model over the
depth image, error per frame.

Figures are drawn with matplotlib's object API on an Agg canvas (no pyplot), so nothing depends on
or changes a global backend, and each PNG is written atomically.
"""
from __future__ import annotations

import io
import textwrap
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.colors import ListedColormap
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


#: Colours of the overlay's marks, chosen to stand out on its grey depth image and from each other.
OVERLAY_COLOURS = {"mask": (0.1, 0.9, 0.1), "fit": (0.9, 0.1, 0.1), "bone": (0.05, 0.05, 0.05),
                   "thumb": (1.0, 0.55, 0.0), "wrist": (0.0, 0.35, 1.0), "labelled": (0.0, 0.9, 0.9)}


def depth_greys():
    """The colour map of depth under drawn marks: light grey near, dark grey far, white = no depth.

    Grey, not a colour map: the hand is the nearest surface, and a colour map's near end (viridis'
    dark purple, turbo's blue) hid the marks drawn over it; each colour then means one mark."""
    return ListedColormap(colormaps["gray_r"](np.linspace(0.2, 0.75, 256))).with_extremes(bad="1.0")


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


def contact_sheet_figure(depths_mm, panel_titles, title, *, near_mm=None, far_mm=None, masks=None,
                         skeletons=None, hand=None):
    """The figure of :func:`contact_sheet` (not saved), and its colour scale: ``(figure, (lo, hi))``."""
    lo, hi = depth_scale_mm(depths_mm, near_mm, far_mm)
    n = len(depths_mm)
    cols = int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / cols))
    height, width = np.shape(depths_mm[0])
    aspect = height / width
    fig_w = 2.6 * cols + 0.8
    # a sheet of one or two frames is narrower than its title: wrap it (~0.55 em per character at 9 pt)
    lines = textwrap.wrap(title, max(20, int(fig_w * 72 / (0.55 * 9)))) or [""]
    fig = _figure(figsize=(fig_w, 2.6 * aspect * rows + 0.9 + 0.16 * (len(lines) - 1)), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False)
    # grey is not in viridis: no data stands out; under fitted skeletons the overlay's greys and colours
    cmap = colormaps["viridis"].with_extremes(bad="0.85") if skeletons is None else depth_greys()
    outline = "w" if skeletons is None else OVERLAY_COLOURS["mask"]
    im = None
    for k, (ax, label, d) in enumerate(zip(axes.ravel(), panel_titles, depths_mm)):
        im = ax.imshow(np.ma.masked_invalid(d), cmap=cmap, vmin=lo, vmax=hi, interpolation="nearest")
        if masks is not None and np.any(masks[k]):
            ax.contour(np.asarray(masks[k], float), [0.5], colors=[outline], linewidths=0.8)
        if skeletons is not None and skeletons[k] is not None:
            draw_skeleton(ax, *np.asarray(skeletons[k], float).T, hand.parents, hand.keypoint_names, size=0.45)
            ax.set_xlim(-0.5, width - 0.5)
            ax.set_ylim(height - 0.5, -0.5)
        ax.set_title(label, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in axes.ravel()[n:]:
        ax.set_axis_off()
    fig.suptitle("\n".join(lines), fontsize=9)
    fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.8, label="depth (mm)")
    return fig, (lo, hi)


def contact_sheet(path, depths_mm, panel_titles, title, *, near_mm=None, far_mm=None, overwrite=False,
                  masks=None, skeletons=None, hand=None):
    """Depth frames in a grid, colour-mapped (viridis) in mm; pixels without depth are light grey.

    Parameters
    ----------
    path : PNG to write (refused if it exists, unless ``overwrite``)
    depths_mm : list of (H, W) depth images in mm, NaN = no depth
    panel_titles, title : one title per frame, and the figure's (wrapped to the sheet's width)
    near_mm, far_mm : colour-scale ends (default: :func:`depth_scale_mm`)
    masks : optional list of (H, W) bool segmentation masks, outlined in white on their panels (in
        green over the overlay's greys when skeletons are drawn)
    skeletons, hand : optional list of (K, 2) keypoint pixels (None: no fit on that panel) drawn as
        :func:`draw_skeleton` does, with the bones of ``hand`` (anything with ``parents`` and
        ``keypoint_names``)

    Returns
    -------
    (lo, hi) : the colour scale used, mm
    """
    fig, (lo, hi) = contact_sheet_figure(depths_mm, panel_titles, title, near_mm=near_mm, far_mm=far_mm,
                                         masks=masks, skeletons=skeletons, hand=hand)
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



def draw_skeleton(ax, u, v, parents, names, size: float = 1.0) -> None:
    """The fitted hand's skeleton at pixels ``(u, v)`` (one per keypoint): bones black, the thumb's
    orange with its tip ringed, keypoints red, the wrist a blue square — the wrist is what tells a hand
    fitted upside down (fingers along the arm) from a right one. ``size`` scales lines and markers."""
    c = OVERLAY_COLOURS
    u, v = np.asarray(u, float), np.asarray(v, float)
    for i, p in enumerate(parents):
        if p >= 0:
            thumb = names[i].startswith("thumb")
            ax.plot(u[[p, i]], v[[p, i]], "-", color=c["thumb"] if thumb else c["bone"],
                    lw=(2.5 if thumb else 1.8) * size)
    ax.plot(u, v, "o", color=c["fit"], ms=3 * size)
    if "thumb_tip" in names:
        t = names.index("thumb_tip")
        ax.plot(u[t], v[t], "o", mfc="none", mec=c["thumb"], ms=10 * size, mew=2 * size)
    w = names.index("wrist") if "wrist" in names else 0
    ax.plot(u[w], v[w], "s", color=c["wrist"], mec="w", ms=9 * size, mew=size)


def overlay_legend(fitted: bool, mask_empty: bool, labelled: bool, depth_mm=None) -> str:
    """The overlay's key line: what each colour marks, and what is missing (no fit, nothing segmented).

    >>> overlay_legend(True, False, False, (488.0, 899.0))
    'depth 488–899 mm, light = near · green: segmentation mask · red: fitted hand · blue square: wrist · orange: thumb'
    >>> overlay_legend(False, True, False)
    'green: segmentation mask (empty: no hand segmented) · no fit'
    """
    parts = [] if depth_mm is None else [f"depth {depth_mm[0]:.0f}–{depth_mm[1]:.0f} mm, light = near"]
    parts.append("green: segmentation mask" + (" (empty: no hand segmented)" if mask_empty else ""))
    parts += ["red: fitted hand", "blue square: wrist", "orange: thumb"] if fitted else ["no fit"]
    if labelled:
        parts.append("cyan: labelled")
    return " · ".join(parts)


def overlay_png(path, depth, camera, hand, theta, status="", mask=None, labelled=None):
    """The whole depth frame in grey (light = near, white where there is no depth) with the
    segmentation mask's outline (green), the fitted hand's silhouette (red, outlined) and skeleton
    (black, the thumb orange, its tip ringed) and the wrist (a blue square), so a wrong segmentation,
    a fit on the wrong object or a hand fitted upside down is seen at a glance.

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
    c = OVERLAY_COLOURS
    d = np.asarray(depth, float)
    H, W = d.shape
    fig = _figure(figsize=(W / 100, (H + 60) / 100))
    ax = fig.add_axes((0.0, 0.0, 1.0, H / (H + 60)))
    finite = d[np.isfinite(d)]
    lo, hi = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
    hi = max(hi, lo + 1e-3)
    ax.imshow(np.ma.masked_invalid(d), cmap=depth_greys(), vmin=lo, vmax=hi, interpolation="nearest")
    theta = np.asarray(theta, float)
    fitted = bool(theta.size and np.all(np.isfinite(theta)))
    if fitted:
        sil = model_silhouette(hand, theta, camera, (H, W))
        rgba = np.zeros((H, W, 4))
        rgba[sil] = (*c["fit"], 0.3)
        ax.imshow(rgba, interpolation="nearest")
        if sil.any():
            ax.contour(sil.astype(float), [0.5], colors=[c["fit"]], linewidths=1.0)
    mask_empty = mask is None or not np.any(mask)
    if not mask_empty:
        # drawn over the fitted silhouette: where the two disagree both edges stay visible
        ax.contour(np.asarray(mask, float), [0.5], colors=[c["mask"]], linewidths=1.5)
    if fitted:
        u, v = project(hand.keypoints(theta), camera)
        draw_skeleton(ax, u, v, hand.parents, hand.keypoint_names)
    if labelled is not None and len(labelled):
        lu, lv = np.asarray(labelled, float).reshape(-1, 2).T
        ax.plot(lu, lv, "+", color=c["labelled"], ms=12, mew=2.5)
    ax.set_xlim(-0.5, W - 0.5)
    ax.set_ylim(H - 0.5, -0.5)
    ax.set_axis_off()
    legend = overlay_legend(fitted, mask_empty, labelled is not None and len(labelled) > 0,
                            (lo * 1000, hi * 1000) if finite.size else None)
    fig.text(0.01, 1 - 30 / (H + 60), f"{Path(path).stem}  {status}", fontsize=10, va="center")
    # the key stays on one line across the frame: a longer one (the labelled marks) gets a smaller font
    size = 7 if W < 700 else 8
    fig.text(0.01, 1 - 50 / (H + 60), legend, fontsize=min(size, size * W / 640 * 118 / max(len(legend), 1)),
             va="center")
    _save(fig, path)


def error_plot(path, posture_deg, keypoint_mm, status=None, title="", frames=None):
    """Posture and keypoint error per frame (``frames``: their numbers, default 0, 1, …); frames the
    tracker lost are shaded red, frames it started from a new search (``reinit``: the first frame, or
    the safety net's replacement) orange, each named in the legend; the means in the title."""
    from matplotlib.patches import Patch
    from matplotlib.ticker import MaxNLocator

    fig = _figure(figsize=(8, 5))
    ax = fig.subplots(2, 1, sharex=True)
    f = np.arange(len(posture_deg)) if frames is None else np.asarray(frames)
    ax[0].plot(f, posture_deg, lw=1)
    ax[0].set_ylabel("posture error (°)")
    ax[1].plot(f, keypoint_mm, lw=1, color="C1")
    ax[1].set_ylabel("keypoint error (mm)")
    ax[1].set_xlabel("frame")
    ax[1].xaxis.set_major_locator(MaxNLocator(integer=True))  # frames are whole numbers
    marks = []
    if status is not None:
        st = np.asarray(status)
        for kind, colour in (("lost", "r"), ("reinit", "orange")):
            at = f[st == kind]
            for a in ax:
                for i in at:
                    a.axvspan(i - 0.5, i + 0.5, color=colour, alpha=0.25, lw=0)
            if at.size:
                marks.append(Patch(color=colour, alpha=0.4, label=f"{kind} ({at.size} frame{'s' * (at.size != 1)})"))
    if marks:
        ax[0].legend(handles=marks, fontsize=8, loc="best")
    mean = f"posture {np.nanmean(posture_deg):.1f}° mean, keypoints {np.nanmean(keypoint_mm):.1f} mm mean"
    ax[0].set_title(f"{title}: {mean}" if title else mean, fontsize=10)
    fig.tight_layout()
    _save(fig, path)
