"""Closed triangle meshes of the renderer's clutter (:class:`tracker.sim.clutter.Clutter`): the forearm, its
sleeve and the upper arm as tapered elliptic tubes, the torso and the box as superellipsoids, the cylinder; faces
oriented outward, as the renderer's back-face culling needs."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from handmodel import libm

if TYPE_CHECKING:
    from .clutter import Clutter


def closed_mesh(rings):
    """Triangles over ``rings`` (R, A, 3) of A points each, closed by a fan at each end around the
    ring's centroid; faces oriented outward (positive signed volume)."""
    R, A = rings.shape[:2]
    V = np.concatenate([rings.reshape(-1, 3), rings[0].mean(0, keepdims=True), rings[-1].mean(0, keepdims=True)])
    k = np.arange(A)
    k1 = (k + 1) % A
    F = []
    for i in range(R - 1):
        a, b = i * A, (i + 1) * A
        F += [np.stack([a + k, a + k1, b + k], 1), np.stack([a + k1, b + k1, b + k], 1)]
    top, bot, last = R * A, R * A + 1, (R - 1) * A
    F.append(np.stack([np.full(A, top), k1, k], 1))
    F.append(np.stack([np.full(A, bot), last + k, last + k1], 1))
    F = np.concatenate(F).astype(np.int64)
    tri = V[F] - V.mean(0)
    vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum()
    if vol < 0:  # make the normals point outward (back-face culling relies on it)
        F = F[:, ::-1].copy()
    return np.ascontiguousarray(V), np.ascontiguousarray(F)


def tube(y0, y1, half0, half1, n_around=24, n_rings=8):
    """Closed elliptic tube along y from ``y0`` to ``y1``, half-axes (x, z) tapering from ``half0`` to ``half1``."""
    s = np.linspace(0.0, 1.0, n_rings)
    y = y0 + s * (y1 - y0)
    hw = half0[0] + s * (half1[0] - half0[0])
    ht = half0[1] + s * (half1[1] - half0[1])
    phi = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    rings = np.stack([hw[:, None] * np.cos(phi), np.broadcast_to(y[:, None], (n_rings, n_around)),
                      ht[:, None] * np.sin(phi)], -1)
    return closed_mesh(rings)


def forearm_mesh(c: Clutter):
    """Closed forearm tube in the wrist frame (vertices, outward faces)."""
    return tube(0.004, -c.forearm_length_m, c.forearm_wrist_m, c.forearm_far_m)


def sleeve_mesh(c: Clutter):
    """The sleeve over the forearm from ``sleeve_start_m`` to 1 cm past its far end (wrist frame)."""
    s0 = c.sleeve_start_m / c.forearm_length_m
    half0 = [c.sleeve_scale * (w + s0 * (f - w)) + c.sleeve_ease_m for w, f in zip(c.forearm_wrist_m, c.forearm_far_m)]
    half1 = [c.sleeve_scale * f + c.sleeve_ease_m for f in c.forearm_far_m]
    return tube(-c.sleeve_start_m, -c.forearm_length_m - 0.01, half0, half1, n_rings=6)


def arm_frame(direction):
    """Rotation (3, 3) whose y column is the unit ``direction`` and whose x column lies in the camera's image
    plane (perpendicular to the optical axis z, or camera x when ``direction`` is along z): a tube built along y
    and rotated by it shows its width, not its thickness, to the camera. A proper rotation (determinant +1),
    so the tube's outward faces stay outward.

    >>> R = arm_frame((0.0, -0.6, 0.8))
    >>> np.round(R[:, 1], 3).tolist(), round(float(R[2, 0]), 12), round(float(np.linalg.det(R)), 12)
    ([0.0, -0.6, 0.8], 0.0, 1.0)
    """
    y = np.asarray(direction, float)
    y = y / np.linalg.norm(y)
    x = np.cross(y, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-9:  # straight along the optical axis: any width direction is as good
        x = np.array([1.0, 0.0, 0.0])
    x = x / np.linalg.norm(x)
    return np.stack([x, y, np.cross(x, y)], 1)


def upper_arm_mesh(c: Clutter):
    """The upper arm about the elbow, in camera axes (vertices, outward faces): a tube from
    ``upper_arm_elbow_m`` half-axes at the elbow to ``upper_arm_shoulder_m`` at ``upper_arm_length_m``
    along ``upper_arm_dir``. It starts at the elbow itself, its first ring around the forearm's end: started
    behind the elbow (an olecranon) it would stick out toward the camera past the forearm's front wherever the
    arm runs away from the camera, nearer than any real elbow is. With ``c.sleeve`` it is the sleeve's cloth,
    widened as the sleeve is (``sleeve_scale`` × + ``sleeve_ease_m``)."""
    h0, h1 = c.upper_arm_elbow_m, c.upper_arm_shoulder_m
    if c.sleeve:
        h0, h1 = ([c.sleeve_scale * v + c.sleeve_ease_m for v in h] for h in (h0, h1))
    V, F = tube(0.0, c.upper_arm_length_m, h0, h1, n_around=24, n_rings=8)
    return np.ascontiguousarray(V @ arm_frame(c.upper_arm_dir).T), F


def superellipsoid(half, e, n_lat=28, n_lon=56):
    """Closed superellipsoid about the origin (half-extents ``half`` along x, y, z, exponent ``e``:
    1 an ellipsoid, towards 0 a box); y is the polar axis."""
    def spow(x, p):
        return np.sign(x) * libm.power(np.abs(x), p)  # the same bits on every processor
    eta = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 2)[1:-1]
    om = np.linspace(-np.pi, np.pi, n_lon, endpoint=False)
    ce, se = spow(np.cos(eta), e)[:, None], spow(np.sin(eta), e)[:, None]
    rings = np.stack([half[0] * ce * spow(np.cos(om), e)[None], np.broadcast_to(half[1] * se, (n_lat, n_lon)),
                      half[2] * ce * spow(np.sin(om), e)[None]], -1)
    return closed_mesh(rings)


def object_mesh(c: Clutter):
    """The second object about its centre: a rounded box or an upright cylinder."""
    if c.object == "cylinder":
        r, h = c.object_size_m[0], c.object_size_m[1]
        return tube(h, -h, (r, r), (r, r), n_around=32, n_rings=4)
    return superellipsoid(c.object_size_m, 0.12, n_lat=16, n_lon=32)
