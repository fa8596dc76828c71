"""Pinhole depth-camera models and presets.

Camera frame: x right, y down, z forward along the optical axis, metres. Pixel ``(u, v)`` is
(column, row) with its centre at integer coordinates, so a point projects to
``u = fx·x/z + cx``, ``v = fy·y/z + cy`` (OpenCV convention). Lens distortion is not modelled.

Examples
--------
>>> cam = preset("sr305")
>>> cam.width, cam.height, cam.depth_scale_m
(640, 480, 0.000125)
>>> cam.project([0.0, 0.0, 0.7]).tolist() == [cam.cx, cam.cy]
True
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..errors import TrackerError

#: How a depth PNG stores integer depth units (``metres = units · depth_scale_m``, 0 = no data):
#: ``uint16`` a 16-bit greyscale PNG (OpenNI, Kinect, RealSense); ``nyu_rgb`` an 8-bit RGB PNG with
#: ``units = G·256 + B`` (NYU hand dataset).
DEPTH_ENCODINGS = ("uint16", "nyu_rgb")

#: Largest depth unit either encoding can hold.
MAX_UNITS = 65535


@dataclass(frozen=True)
class Camera:
    """Intrinsics, image size and depth encoding of a depth camera.

    Parameters
    ----------
    width, height : int
        Image size in pixels.
    fx, fy, cx, cy : float
        Focal lengths and principal point in pixels (pixel centres at integer coordinates).
    depth_scale_m : float
        Metres per stored depth unit (0.001 for millimetres, 0.000125 for RealSense SR300/SR305).
    depth_encoding : str
        One of :data:`DEPTH_ENCODINGS`.
    name : str
        A label (the preset name, or ``custom``).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale_m: float = 0.001
    depth_encoding: str = "uint16"
    name: str = "custom"

    def __post_init__(self):
        where = f"camera {self.name}"
        for key in ("width", "height"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise TrackerError(where, f"{key} must be a positive integer, got {v!r}")
            object.__setattr__(self, key, int(v))
        for key in ("fx", "fy", "cx", "cy", "depth_scale_m"):
            v = getattr(self, key)
            try:
                f = float(v)
            except (TypeError, ValueError):
                raise TrackerError(where, f"{key} must be a number, got {v!r}") from None
            if not np.isfinite(f):
                raise TrackerError(where, f"{key} must be finite, got {v!r}")
            object.__setattr__(self, key, f)
        if not (self.fx > 0 and self.fy > 0):
            raise TrackerError(where, "fx and fy must be positive")
        if not self.depth_scale_m > 0:
            raise TrackerError(where, "depth scale must be positive")
        if self.depth_encoding not in DEPTH_ENCODINGS:
            raise TrackerError(where, f"unknown depth encoding {self.depth_encoding!r} "
                                      f"(known: {', '.join(DEPTH_ENCODINGS)})")

    @property
    def depth_scale(self) -> float:
        """Alias of :attr:`depth_scale_m`."""
        return self.depth_scale_m

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape ``(height, width)`` in numpy order."""
        return (self.height, self.width)

    @property
    def K(self) -> np.ndarray:
        """The 3×3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def max_depth_m(self) -> float:
        """Largest depth the encoding can store."""
        return MAX_UNITS * self.depth_scale_m

    def project(self, points) -> np.ndarray:
        """Pixel coordinates ``(..., 2)`` = (u, v) of camera-frame points ``(..., 3)``; NaN where z ≤ 0."""
        p = np.asarray(points, float)
        if p.shape[-1:] != (3,):
            raise ValueError(f"points must have shape (..., 3), got {p.shape}")
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(z > 0, 1.0 / z, np.nan)
        return np.stack([self.fx * p[..., 0] * inv + self.cx, self.fy * p[..., 1] * inv + self.cy], -1)

    def unproject(self, uv, z) -> np.ndarray:
        """Camera-frame points ``(..., 3)`` at pixel coordinates ``uv (..., 2)`` and depths ``z (...)``."""
        uv = np.asarray(uv, float)
        z = np.asarray(z, float)
        x = (uv[..., 0] - self.cx) / self.fx * z
        y = (uv[..., 1] - self.cy) / self.fy * z
        return np.stack(np.broadcast_arrays(x, y, z), -1)

    def to_dict(self) -> dict:
        return asdict(self)

    def with_size(self, width, height) -> "Camera":
        """The same camera at another resolution (intrinsics scaled, pixel centres kept)."""
        sx, sy = width / self.width, height / self.height
        return Camera(width, height, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5,
                      self.depth_scale_m, self.depth_encoding, self.name)


# Nominal values; every device differs by a few per cent. Calibrate and pass explicit intrinsics
# (tracker import --fx … or Camera(...)) when it matters.
PRESETS = {
    # Kinect v1 (PrimeSense, OpenNI depth in mm): the depth-camera intrinsics published with the
    # NYU Depth V2 toolbox (camera_params.m: fx 582.624, fy 582.691, cx 313.045, cy 238.444).
    # The OpenNI/ROS default camera_info is fx = fy = 575.8157, (314.5, 235.5): 1.2 % shorter.
    "kinect1": Camera(640, 480, 582.624, 582.691, 313.045, 238.444, 0.001, "uint16", "kinect1"),
    # Kinect v2 (Xbox One) 512×424 depth (mm): the factory IR intrinsics libfreenect2 reports and
    # many projects reproduce, fx = fy = 365.456, cx = 254.878, cy = 205.395.
    "kinect2": Camera(512, 424, 365.456, 365.456, 254.878, 205.395, 0.001, "uint16", "kinect2"),
    # Intel RealSense SR305 (SR300 module) at 640×480, depth unit 0.125 mm (the SR300 default):
    # the values stated in readme.txt of the LadaOndris/hand-recognition SR305 frames
    # (focal 476.007, principal point (313.683, 242.755); ../shared/data/SOURCES.md §8).
    "sr305": Camera(640, 480, 476.007, 476.007, 313.683, 242.755, 0.000125, "uint16", "sr305"),
    "sr300": Camera(640, 480, 476.007, 476.007, 313.683, 242.755, 0.000125, "uint16", "sr300"),
    # NYU hand pose dataset (Tompson et al. 2014; Kinect v1): depth (mm) = G·256 + B of an RGB PNG.
    # Intrinsics from the dataset's convert_uvd_to_xyz (xzFactor 1.08836710, yzFactor 0.817612648 →
    # fx = 640/1.0883671 = 588.03, fy = 480/0.817612648 = 587.07, centre (320, 240)); that helper
    # has y pointing up, here y points down as for every camera.
    "nyu": Camera(640, 480, 588.03, 587.07, 320.0, 240.0, 0.001, "nyu_rgb", "nyu"),
}

_ALIASES = {"kinect": "kinect1", "kinect_v1": "kinect1", "kinectv1": "kinect1", "kinect_v2": "kinect2",
            "kinectv2": "kinect2", "realsense_sr305": "sr305", "realsense_sr300": "sr300", "nyu_hand": "nyu"}


def preset(name: str) -> Camera:
    """A camera preset by name: kinect1, kinect2, sr305, sr300, nyu (case, ``-`` and ``_`` ignored).

    Raises
    ------
    TrackerError
        For an unknown name; the message lists the valid names.
    """
    key = str(name).strip().lower().replace("-", "_")
    key = _ALIASES.get(key, key)
    try:
        return PRESETS[key]
    except KeyError:
        raise TrackerError(f"camera {name}", f"unknown preset (valid: {', '.join(PRESETS)})") from None


def as_camera(camera) -> Camera:
    """A :class:`Camera` from a preset name, a Camera, or any object with pinhole intrinsics
    (``width height fx fy`` and ``cx cy``, or pyrealsense2's ``ppx ppy``; ``depth_scale_m``,
    ``depth_encoding`` and ``name`` if it has them).

    >>> as_camera("kinect1").name, as_camera(as_camera("sr305")).depth_scale_m
    ('kinect1', 0.000125)
    >>> from types import SimpleNamespace  # what pyrealsense2's video_stream_profile.get_intrinsics() has
    >>> rs = SimpleNamespace(width=640, height=480, fx=475.9, fy=475.9, ppx=315.2, ppy=245.3)
    >>> as_camera(rs).cx, as_camera(rs).name
    (315.2, 'custom')
    """
    if isinstance(camera, Camera):
        return camera
    if isinstance(camera, str):
        return preset(camera)
    try:
        # pyrealsense2 names the principal point ppx, ppy
        cx = camera.cx if hasattr(camera, "cx") else camera.ppx
        cy = camera.cy if hasattr(camera, "cy") else camera.ppy
        return Camera(camera.width, camera.height, camera.fx, camera.fy, cx, cy,
                      getattr(camera, "depth_scale_m", getattr(camera, "depth_scale", 0.001)),
                      getattr(camera, "depth_encoding", "uint16"), getattr(camera, "name", "custom"))
    except AttributeError as exc:
        raise TrackerError("camera", f"needs pinhole intrinsics ({exc})") from None
