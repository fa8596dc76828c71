"""Pinhole depth-camera models and presets.

Pixel (u, v) has its centre at integer coordinates; a camera-frame point (x right, y down, z forward)
projects to u = fx·x/z + cx, v = fy·y/z + cy.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .errors import TrackerError


@dataclass(frozen=True)
class Camera:
    """Intrinsics and how depth is stored: ``depth_encoding`` 'uint16' (value × ``depth_scale`` =
    metres, 0 = no data) or 'nyu_rgb' (an RGB PNG with depth = G·256 + B in units of ``depth_scale``)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float = 0.001
    depth_encoding: str = "uint16"
    name: str = "custom"

    def __post_init__(self):
        if self.width < 1 or self.height < 1 or not (self.fx > 0 and self.fy > 0):
            raise TrackerError(f"camera {self.name}", "width, height, fx and fy must be positive")
        if self.depth_encoding not in ("uint16", "nyu_rgb"):
            raise TrackerError(f"camera {self.name}", f"unknown depth encoding {self.depth_encoding!r}")
        if not self.depth_scale > 0:
            raise TrackerError(f"camera {self.name}", "depth_scale must be positive")

    def project(self, points):
        """Pixel coordinates ``(..., 2)`` of camera-frame points ``(..., 3)``."""
        p = np.asarray(points, float)
        return np.stack([self.fx * p[..., 0] / p[..., 2] + self.cx, self.fy * p[..., 1] / p[..., 2] + self.cy], -1)

    def backproject(self, depth):
        """Camera-frame points ``(H, W, 3)`` of a depth image in metres (NaN where no depth)."""
        from .observe import backproject_image

        return backproject_image(depth, self)

    def to_dict(self) -> dict:
        return asdict(self)

    def with_size(self, width, height) -> "Camera":
        """The same camera at another resolution (intrinsics scaled)."""
        sx, sy = width / self.width, height / self.height
        return Camera(width, height, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5,
                      self.depth_scale, self.depth_encoding, self.name)


PRESETS = {
    # Kinect v1 depth camera, N. Burrus' calibration (widely used; OpenNI delivers depth in mm)
    "kinect1": Camera(640, 480, 582.624, 582.691, 313.045, 238.444, 0.001, "uint16", "kinect1"),
    # Kinect v2 (Xbox One) depth camera, typical factory intrinsics as reported by libfreenect2
    "kinect2": Camera(512, 424, 365.456, 365.456, 254.878, 205.395, 0.001, "uint16", "kinect2"),
    # RealSense SR305/SR300 at 640×480, depth unit 0.125 mm; intrinsics stated with the SR305 frames of
    # LadaOndris/hand-recognition (focal 476.007, principal point 313.683, 242.755)
    "sr305": Camera(640, 480, 476.007, 476.007, 313.683, 242.755, 0.000125, "uint16", "sr305"),
    "sr300": Camera(640, 480, 476.007, 476.007, 313.683, 242.755, 0.000125, "uint16", "sr300"),
    # NYU hand dataset convention: depth (mm) = G·256 + B of an RGB PNG
    "nyu": Camera(640, 480, 588.03, 587.07, 320.0, 240.0, 0.001, "nyu_rgb", "nyu"),
}


def preset(name: str) -> Camera:
    """A camera preset by name (kinect1, kinect2, sr305, sr300, nyu)."""
    try:
        return PRESETS[str(name).lower()]
    except KeyError:
        raise TrackerError(f"camera {name}", f"unknown preset (known: {', '.join(PRESETS)})") from None
