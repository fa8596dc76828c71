"""Matplotlib drawings of the hand: skeleton views and a shaded mesh.

Figures are built on matplotlib's object API with an Agg canvas, so nothing here touches pyplot's
global state or the user's backend.
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from .fileio import atomic_write_bytes

FINGER_COLOURS = {"thumb": "#d62728", "index": "#1f77b4", "middle": "#2ca02c", "ring": "#9467bd", "pinky": "#ff7f0e"}


def _figure(**kw) -> Figure:
    fig = Figure(**kw)
    FigureCanvasAgg(fig)
    return fig


def draw_skeleton(ax, hand, theta, view=(0, 1), colour=None, alpha=1.0, label=None):
    """Bones as lines in the plane of the two given axes (0=x, 1=y, 2=z), millimetres."""
    kp = hand.keypoints(theta) * 1000.0
    first = True
    for i, p in enumerate(hand.parents):
        if p < 0:
            continue
        name = hand.node_names[i]
        c = colour or next((v for k, v in FINGER_COLOURS.items() if name.startswith(k)), "k")
        ax.plot(kp[[p, i], view[0]], kp[[p, i], view[1]], "-", color=c, lw=2, alpha=alpha,
                label=label if first else None)
        first = False
    ax.plot(kp[:, view[0]], kp[:, view[1]], "o", color=colour or "k", ms=2.5, alpha=alpha)
    ax.set_aspect("equal")


def draw_mesh(ax, hand, theta, mesh=None, light=(0.3, -0.4, -1.0), colour=(0.93, 0.76, 0.64)):
    """A shaded, LBS-posed mesh on a 3-D axis (orthographic, millimetres)."""
    mesh = mesh or hand.mesh()
    V = mesh.pose(theta) * 1000.0
    tri = V[mesh.faces]
    n = mesh.face_normals(V)
    L = np.asarray(light, float).copy()
    L /= np.linalg.norm(L)
    shade = 0.35 + 0.65 * np.clip(n @ L, 0, 1)
    col = np.clip(np.outer(shade, colour), 0, 1)
    pc = Poly3DCollection(tri, facecolors=col, edgecolors="none", linewidths=0)
    ax.add_collection3d(pc)
    lo, hi = V.min(0), V.max(0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))
    ax.set_axis_off()


def skeleton_figure(hand, thetas, titles, path, estimates=None):
    """One column per posture: front (x–y) and side (z–y) views; estimates drawn dashed in grey."""
    k = len(thetas)
    fig = _figure(figsize=(2.6 * k, 5.2))
    axes = fig.subplots(2, k, squeeze=False)
    for j, (th, title) in enumerate(zip(thetas, titles)):
        for r, view in enumerate([(0, 1), (2, 1)]):
            ax = axes[r, j]
            draw_skeleton(ax, hand, th, view)
            if estimates is not None:
                draw_skeleton(ax, hand, estimates[j], view, colour="0.4", alpha=0.7)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(title, fontsize=9)
        axes[0, 0].set_ylabel("front (x–y)")
        axes[1, 0].set_ylabel("side (z–y)")
    fig.tight_layout()
    _save(fig, path)


def mesh_figure(hand, thetas, titles, path, elev=-55, azim=-95):
    k = len(thetas)
    fig = _figure(figsize=(3.0 * k, 3.4))
    mesh = hand.mesh()
    for j, (th, title) in enumerate(zip(thetas, titles)):
        ax = fig.add_subplot(1, k, j + 1, projection="3d", proj_type="ortho")
        draw_mesh(ax, hand, th, mesh)
        ax.view_init(elev=elev, azim=azim)
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    _save(fig, path)


def _save(fig, path):
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    atomic_write_bytes(Path(path), buf.getvalue())
