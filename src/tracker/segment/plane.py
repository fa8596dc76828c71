"""The frame's support plane (a table, a floor, a wall): :func:`support_plane`, RANSAC on sampled pixels."""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .._segment_kernels import (
    plane_pixels,
    plane_ransac,
    plane_refit,
    plane_samples,
)
from . import constants as K


@dataclass(frozen=True)
class SupportPlane:
    """A plane ``normal · x = offset`` (camera frame, metres; ``normal`` unit) that covers ``area`` m²
    of the frame, and the ``band`` (m) around it whose pixels :meth:`pixels` gives."""

    normal: tuple
    offset: float
    band: float
    area: float

    def pixels(self, depth, focal, cy, cx) -> np.ndarray:
        """Boolean ``(H, W)``: the pixels of ``depth`` (metres, NaN = none; principal point ``cy, cx``
        in its pixels) within ``band`` of the plane."""
        nx, ny, nz = self.normal
        return plane_pixels(np.ascontiguousarray(depth, dtype=np.float64), float(nx), float(ny), float(nz),
                            float(self.offset), float(focal), float(cy), float(cx), float(self.band))


@lru_cache(maxsize=16)
def _tries(seed, n, tries):
    """The RANSAC triplets ``(tries, 3)`` (indices below ``n``) drawn with ``seed``: the same for the same
    sample count, so kept (read-only) rather than drawn again every frame (a generator's set-up and draw:
    ~0.1 ms a depth-only frame)."""
    out = np.random.default_rng(seed).integers(0, n, size=(tries, 3))
    out.flags.writeable = False
    return out


def support_plane(depth, focal, *, z_min=0.2, z_max=1.5, min_area=None, min_tilt_deg=None, seed=0):
    """The largest plane of the depth frame (metres, NaN = none) seen at least ``min_tilt_deg`` off
    face-on (a table or floor; not a wall or torso facing the camera), as a :class:`SupportPlane`, or
    None when none covers ``min_area`` m² (fronto-parallel pixel areas, so a tilted table counts low).

    RANSAC on about :attr:`SegmentConstants.plane_samples` pixels of a grid over the frame (principal point at the
    image centre, as the segmenter's back-projection): :attr:`SegmentConstants.plane_tries` planes through three
    samples (drawn with ``seed``: the same frame gives the same plane), each weighed by the area of
    the samples within :attr:`SegmentConstants.plane_tol_m`; the best one is refitted to its samples by least squares
    (twice), and its band is 3 robust standard deviations of their distances, within
    :attr:`SegmentConstants.plane_band_m`. A hand is never the plane: 0.01–0.03 m².

    >>> v, u = np.mgrid[0:240, 0:320]
    >>> table = 0.6 / (0.6 * (v - 119.5) / 300.0 + 0.8) + 0 * u   # the plane (0, 0.6, 0.8) · x = 0.6
    >>> table[100:140, 150:180] = 0.45                               # something standing in front of it
    >>> p = support_plane(table, 300.0)
    >>> (np.round(p.normal, 3) + 0.0).tolist(), round(p.offset, 3), p.band
    ([0.0, 0.6, 0.8], 0.6, 0.008)
    >>> on = p.pixels(table, 300.0, 119.5, 159.5)
    >>> int(on.sum()), bool(on[120, 160])
    (75600, False)
    """
    min_area = K.TUNING.plane_min_area_m2 if min_area is None else min_area
    min_tilt_deg = K.TUNING.plane_min_tilt_deg if min_tilt_deg is None else min_tilt_deg
    d = np.ascontiguousarray(depth, dtype=np.float64)
    H, W = d.shape
    step = max(int(round(np.sqrt(H * W / K.TUNING.plane_samples))), 1)
    # compiled: the segmenter runs it on every frame without colour
    P, w = plane_samples(d, step, float(focal), (H - 1) / 2, (W - 1) / 2, float(z_min), float(z_max))
    if len(P) < 3 or w.sum() < min_area:
        return None
    if isinstance(seed, (int, np.integer)):
        tries = _tries(int(seed), len(P), K.TUNING.plane_tries)
    else:
        tries = np.random.default_rng(seed).integers(0, len(P), size=(K.TUNING.plane_tries, 3))
    max_cos = float(np.cos(np.radians(min_tilt_deg)))
    n, dn, got = plane_ransac(P, w, tries, K.TUNING.plane_tol_m, K.TUNING.plane_preempt, K.TUNING.plane_keep, max_cos)
    if got < min_area:
        return None
    for _ in range(2):
        n, dn, area, mad, c = plane_refit(P, w, n, dn, K.TUNING.plane_tol_m)
    # seen obliquely from the camera (the triplets were; the refitted plane must be too)
    if area < min_area or abs(float(n @ c)) > max_cos * float(np.linalg.norm(c)):
        return None
    sd = 1.4826 * mad
    band = float(np.clip(3.0 * sd, *K.TUNING.plane_band_m))
    if dn < 0:  # the camera on the normal's negative side: what stands in front has normal · x < offset
        n, dn = -n, -dn
    return SupportPlane(tuple(float(x) + 0.0 for x in n), float(dn), band, float(area))
