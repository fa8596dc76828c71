"""Decoding the ROS messages a bag reader meets (:mod:`tracker.io.bags`): camera info and RealSense
info strings to intrinsics, ``sensor_msgs/Image`` and ``compressedDepth`` to depth, colour images, and
the RealSense extrinsics' quaternion. Each problem is a RecordingError naming ``where``.
"""
from __future__ import annotations

import io
import struct

import numpy as np
from PIL import Image as PILImage

from ..errors import RecordingError
from .base import MAX_FRAME_SIDE, check_frame_size
from .images import COMPRESSED_DEPTH_HEADER, decode_png_units, decode_rvl, inverse_depth_to_metres

_DEPTH_ENCODINGS = {"16uc1": "units", "mono16": "units", "32fc1": "metres"}
_COLOR_CHANNELS = {"rgb8": (3, False), "bgr8": (3, True), "rgba8": (4, False), "bgra8": (4, True), "mono8": (1, False)}


def _wrap(path, what: str, exc: Exception) -> RecordingError:
    msg = str(exc).splitlines()[0] if str(exc) else ""
    return RecordingError(path, f"{what} ({type(exc).__name__}{': ' + msg if msg else ''})")


def _kv(text: str) -> dict:
    """``key=value;key=value`` (RealSense ROS2 info strings) as a dict."""
    out = {}
    for part in str(text).split(";"):
        if "=" in part:
            k, v = part.split("=", 1)
            out[k.strip()] = v.strip()
    return out


def _number(value, where, what: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise RecordingError(where, f"{what} is not a number: {str(value)[:40]!r}") from None
    if not np.isfinite(v):
        raise RecordingError(where, f"{what} is not finite: {value!r}")
    return v


def intrinsics_of(msg, where) -> tuple[int, int, np.ndarray]:
    """``(width, height, K)`` of a ``sensor_msgs/CameraInfo`` or a RealSense ``width=…;fx=…;ppx=…``
    string."""
    if hasattr(msg, "K") or hasattr(msg, "k"):
        K = np.asarray(getattr(msg, "K", None) if hasattr(msg, "K") else msg.k, float)
        if K.shape != (9,):
            raise RecordingError(where, f"camera_info K has {K.size} values, expected 9")
        w, h = int(msg.width), int(msg.height)
        K = K.reshape(3, 3)
    else:
        kv = _kv(getattr(msg, "data", ""))
        lack = [k for k in ("width", "height", "fx", "fy", "ppx", "ppy") if k not in kv]
        if lack:
            raise RecordingError(where, f"camera info lacks {', '.join(lack)}")
        w, h = int(_number(kv["width"], where, "width")), int(_number(kv["height"], where, "height"))
        f = {k: _number(kv[k], where, k) for k in ("fx", "fy", "ppx", "ppy")}
        K = np.array([[f["fx"], 0, f["ppx"]], [0, f["fy"], f["ppy"]], [0, 0, 1.0]])
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise RecordingError(where, f"camera_info has no usable intrinsics (fx {K[0, 0]:g}, fy {K[1, 1]:g})")
    if w < 1 or h < 1:
        raise RecordingError(where, f"camera_info gives an image of {w}×{h} pixels")
    check_frame_size(w, h, where)
    return w, h, K


def _image_array(msg, where, channels: int, itemsize: int) -> np.ndarray:
    """The pixel rows of a ``sensor_msgs/Image`` as ``(h, w·channels·itemsize)`` bytes, checked."""
    w, h, step = int(msg.width), int(msg.height), int(msg.step)
    check_frame_size(w, h, where)
    row = w * channels * itemsize
    data = np.asarray(msg.data, np.uint8)
    if step < row:
        raise RecordingError(where, f"image step {step} is shorter than a row of {w} pixels ({row} bytes)")
    if data.size < step * h:
        raise RecordingError(where, f"image holds {data.size} bytes, {w}×{h} with step {step} needs {step * h}")
    return data[: step * h].reshape(h, step)[:, :row]


def depth_from_image(msg, where):
    """``(kind, depth)`` of a ``sensor_msgs/Image`` depth message: ``units`` uint16 or ``metres`` float32."""
    enc = str(msg.encoding).lower()
    kind = _DEPTH_ENCODINGS.get(enc)
    if kind is None:
        raise RecordingError(where, f"depth image encoding {msg.encoding!r} is not read "
                                    "(16UC1/mono16 millimetres or 32FC1 metres)")
    size = 2 if kind == "units" else 4
    rows = _image_array(msg, where, 1, size)
    order = ">" if msg.is_bigendian else "<"
    a = np.ascontiguousarray(rows).view(f"{order}{'u2' if kind == 'units' else 'f4'}")
    return kind, a.astype(np.uint16 if kind == "units" else np.float32)


def depth_from_compressed(msg, where):
    """``(kind, depth)`` of a ``compressedDepth`` ``sensor_msgs/CompressedImage``."""
    fmt = str(msg.format)
    enc = fmt.split(";")[0].strip().lower()
    kind = _DEPTH_ENCODINGS.get(enc)
    if "compresseddepth" not in fmt.lower().replace(" ", "") or kind is None:
        raise RecordingError(where, f"compressed image format {fmt!r} is not a 16UC1/32FC1 compressedDepth image")
    data = bytes(np.asarray(msg.data, np.uint8))
    if len(data) < COMPRESSED_DEPTH_HEADER:
        raise RecordingError(where, f"compressedDepth message of {len(data)} bytes has no 12-byte header")
    codec, quant_a, quant_b = struct.unpack("<iff", data[:COMPRESSED_DEPTH_HEADER])
    body = data[COMPRESSED_DEPTH_HEADER:]
    if codec == 1 or "rvl" in fmt.lower():
        if len(body) < 8:
            raise RecordingError(where, "RVL depth image without its size")
        w, h = struct.unpack("<II", body[:8])
        check_frame_size(w, h, where)
        units = decode_rvl(body[8:], w, h, where)
    elif codec == 0:
        units = decode_png_units(body, where, MAX_FRAME_SIDE)
    else:
        raise RecordingError(where, f"compressedDepth header names codec {codec} (0 = PNG, 1 = RVL)")
    if kind == "units":
        return kind, units
    if not (np.isfinite(quant_a) and np.isfinite(quant_b)):
        raise RecordingError(where, "compressedDepth 32FC1 header has no finite quantisation parameters")
    return kind, inverse_depth_to_metres(units, quant_a, quant_b)


def color_from_message(msg, where) -> np.ndarray:
    """RGB ``(H, W, 3)`` uint8 of a colour ``Image`` (rgb8, bgr8, rgba8, bgra8, mono8) or a JPEG/PNG
    ``CompressedImage``; the size is checked before the pixels are decoded."""
    if hasattr(msg, "encoding"):
        enc = str(msg.encoding).lower()
        if enc not in _COLOR_CHANNELS:
            raise RecordingError(where, f"colour image encoding {msg.encoding!r} is not read "
                                        f"({', '.join(_COLOR_CHANNELS)})")
        ch, bgr = _COLOR_CHANNELS[enc]
        a = _image_array(msg, where, ch, 1).reshape(int(msg.height), int(msg.width), ch)
        if ch == 1:
            return np.repeat(a, 3, axis=2)
        a = a[..., :3]
        return np.ascontiguousarray(a[..., ::-1] if bgr else a)
    try:
        im = PILImage.open(io.BytesIO(bytes(np.asarray(msg.data, np.uint8))))
        check_frame_size(im.width, im.height, where)
        return np.asarray(im.convert("RGB"))
    except RecordingError:
        raise
    except Exception as exc:  # Pillow raises many types for damaged images
        raise _wrap(where, "unreadable compressed colour image", exc) from None


def _quat_matrix(q) -> np.ndarray:
    x, y, z, w = (float(q.x), float(q.y), float(q.z), float(q.w))
    n = np.sqrt(x * x + y * y + z * z + w * w)
    if not np.isfinite(n) or n < 1e-9:
        return np.eye(3)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


# ----------------------------------------------------------------------------- the recording
