"""Depth and colour images as recordings store them: PNG headers checked before decoding, depth
units ↔ metres for each camera's encoding (``uint16`` units, NYU's ``G·256+B``), colour frames.

>>> import numpy as np
>>> from tracker.io.cameras import preset
>>> cam = preset("sr305")                      # 0.125 mm per unit
>>> float(units_to_metres(np.array([8000], np.uint16), cam)[0])
1.0
"""
from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np

from .._image_kernels import RVL_OK, RVL_OVERRUN, RVL_SHORT, RVL_VALUE, rvl_decode
from ..errors import RecordingError
from .cameras import MAX_UNITS, Camera

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_TYPES = {0: "greyscale", 2: "RGB", 3: "palette", 4: "greyscale+alpha", 6: "RGBA"}


def png_header(data: bytes, where) -> tuple[int, int, int, str]:
    """``(width, height, bit_depth, colour_type_name)`` from a PNG's IHDR chunk."""
    if len(data) < 26 or data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR":
        raise RecordingError(where, "unreadable PNG (no PNG signature / IHDR header)")
    w, h = struct.unpack(">II", data[16:24])
    return w, h, data[24], _PNG_TYPES.get(data[25], f"colour type {data[25]}")


def read_bytes(path: Path) -> bytes:
    """A frame file's bytes; a missing or unreadable file is a RecordingError naming it."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise RecordingError(path, "missing frame file") from None
    except OSError as exc:
        raise RecordingError(path, f"cannot read: {exc.strerror or exc}") from None


#: Pillow's modes that imageio's Pillow plugin returns as Pillow decodes them (no palette applied, no
#: mode changed): 8- and 16-bit greyscale, RGB, RGBA — every depth and colour frame a recording holds
_PLAIN_MODES = ("L", "I;16", "RGB", "RGBA")


def _decode_png(data: bytes, where) -> np.ndarray:
    """The pixels of a PNG file: imageio's ``imread(data, extension=".png", plugin="pillow")``, the same
    array to the bit, or its error as a RecordingError.

    A one-image PNG in one of :data:`_PLAIN_MODES` is decoded by Pillow here, as imageio's plugin
    decodes it (``Image.open``, the pixels as they are); imageio's import and plugin search, ~0.03 s
    of a one-still ``tracker track``, are left out. Anything else — a palette, an animated PNG, a file
    Pillow refuses — goes through imageio, so its result or its error is imageio's."""
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data), formats=["PNG"]) as im:
            # imageio reads every frame of an animated PNG (acTL: custom_mimetype image/apng)
            if im.mode in _PLAIN_MODES and getattr(im, "custom_mimetype", None) is None:
                return np.array(im)
    except Exception:  # said below, in imageio's words
        pass
    import imageio.v3 as iio

    try:
        return np.asarray(iio.imread(data, extension=".png", plugin="pillow"))
    except Exception as exc:  # Pillow raises many types for damaged files
        raise RecordingError(where, f"unreadable PNG ({type(exc).__name__}: {exc})") from None


def png_bytes(a) -> bytes:
    """The PNG file of an image array."""
    import imageio.v3 as iio  # here: reading frames does not need imageio (_decode_png)

    return iio.imwrite("<bytes>", a, extension=".png", plugin="pillow")


def _expect(header, camera: Camera, kind: str, where):
    """Check a PNG header against the camera size and what ``kind`` (depth or color) needs."""
    w, h, bits, ctype = header
    if kind == "color":
        what, need_bits, need_types = "colour frames need", 8, ("RGB", "RGBA")
    elif camera.depth_encoding == "nyu_rgb":
        what, need_bits, need_types = "depth encoding nyu_rgb needs", 8, ("RGB", "RGBA")
    else:
        what, need_bits, need_types = f"depth encoding {camera.depth_encoding} needs", 16, ("greyscale",)
    need = f"{'an' if need_bits == 8 else 'a'} {need_bits}-bit {need_types[0]} PNG"
    if bits != need_bits:
        raise RecordingError(where, f"wrong bit depth: {bits}-bit {ctype} PNG, {what} {need}")
    if ctype not in need_types:
        raise RecordingError(where, f"wrong PNG type: {bits}-bit {ctype} PNG, {what} {need}")
    if (w, h) != (camera.width, camera.height):
        raise RecordingError(where, f"image is {w}×{h}, the camera says {camera.width}×{camera.height}")


def read_depth_units(path, camera: Camera) -> np.ndarray:
    """Stored depth units ``(H, W)`` uint16 of one depth PNG, checked against the camera."""
    path = Path(path)
    data = read_bytes(path)
    _expect(png_header(data, path), camera, "depth", path)
    a = _decode_png(data, path)
    if camera.depth_encoding == "nyu_rgb":
        return (a[..., 1].astype(np.uint16) << 8) | a[..., 2].astype(np.uint16)
    if a.dtype != np.uint16 or a.ndim != 2:  # e.g. a reader that widened the data
        raise RecordingError(path, f"decoded as {a.dtype} {a.shape}, expected uint16 (H, W)")
    return a


def read_color(path, camera: Camera) -> np.ndarray:
    """Colour frame ``(H, W, 3)`` uint8 of one PNG, checked against the camera."""
    path = Path(path)
    data = read_bytes(path)
    _expect(png_header(data, path), camera, "color", path)
    return np.ascontiguousarray(_decode_png(data, path)[..., :3])


def units_to_metres(units, camera: Camera) -> np.ndarray:
    """Depth units → metres, float32 with NaN where the unit is 0."""
    u = np.asarray(units)
    d = (u * camera.depth_scale_m).astype(np.float32)
    d[u == 0] = np.nan
    return d


def metres_to_units(depth_m, camera: Camera, where="depth") -> np.ndarray:
    """Metres → depth units (uint16, rounded to the nearest unit; NaN, ±inf and 0 → 0 = no data).

    Negative depths, depths beyond the encoding's range and positive depths under half a unit are
    errors (they cannot be stored faithfully).
    """
    d = np.asarray(depth_m, float)
    if d.shape != (camera.height, camera.width):
        size = "×".join(map(str, d.shape[::-1])) or "a scalar"
        raise RecordingError(where, f"depth frame is {size}, the camera says {camera.width}×{camera.height}")
    finite = np.isfinite(d)
    units = np.zeros(d.shape, float)
    units[finite] = np.rint(d[finite] / camera.depth_scale_m)
    bad = finite & (d < 0)
    if bad.any():
        raise RecordingError(where, f"negative depth ({d[bad].min():.4g} m)")
    bad = units > MAX_UNITS
    if bad.any():
        raise RecordingError(where, f"depth {d[bad].max():.4g} m beyond the encoding's range "
                                    f"{camera.max_depth_m:.4g} m (scale {camera.depth_scale_m:g} m)")
    bad = finite & (d > 0) & (units == 0)
    if bad.any():
        raise RecordingError(where, f"depth {d[bad].min():.3g} m is under half a depth unit "
                                    f"({camera.depth_scale_m:g} m)")
    return units.astype(np.uint16)


def encode_units(units, camera: Camera) -> np.ndarray:
    """The image a PNG of the camera's depth encoding stores for these units."""
    u = np.asarray(units, np.uint16)
    if camera.depth_encoding == "nyu_rgb":
        rgb = np.zeros(u.shape + (3,), np.uint8)
        rgb[..., 1] = u >> 8
        rgb[..., 2] = u & 255
        return rgb
    return u


def decode_depth(img, camera: Camera, where="depth") -> np.ndarray:
    """A decoded depth image (as stored) → metres (float32, NaN = no data), checking type and size."""
    a = np.asarray(img)
    if a.shape[:2] != (camera.height, camera.width):
        raise RecordingError(where, f"image is {a.shape[1] if a.ndim > 1 else '?'}×{a.shape[0]}, "
                                    f"the camera says {camera.width}×{camera.height}")
    if camera.depth_encoding == "nyu_rgb":
        if a.ndim != 3 or a.shape[2] < 3 or a.dtype != np.uint8:
            raise RecordingError(where, f"depth encoding nyu_rgb needs an 8-bit RGB image, got {a.dtype} {a.shape}")
        units = (a[..., 1].astype(np.uint16) << 8) | a[..., 2].astype(np.uint16)
    else:
        if a.ndim != 2 or a.dtype != np.uint16:
            raise RecordingError(where, f"wrong bit depth: {a.dtype} {a.shape}, depth encoding uint16 needs "
                                        "16-bit greyscale")
        units = a
    return units_to_metres(units, camera)


def encode_depth(depth_m, camera: Camera, where="depth") -> np.ndarray:
    """Metres → the image stored in a depth PNG (see :func:`metres_to_units`)."""
    return encode_units(metres_to_units(depth_m, camera, where), camera)


# ----------------------------------------------------------------------------- recording files
#: Where a ROS ``compressedDepth`` message's 12-byte ConfigHeader says PNG (0) or RVL (1) follows.
COMPRESSED_DEPTH_HEADER = 12
_RVL_REASONS = {RVL_SHORT: "the RVL stream ends before the image is complete",
                RVL_OVERRUN: "an RVL run is longer than the image",
                RVL_VALUE: "an RVL value has more than 32 bits"}


def decode_rvl(data: bytes, width: int, height: int, where) -> np.ndarray:
    """Depth units ``(height, width)`` uint16 from an RVL stream (Wilson's run-length / variable-length
    code, as ``compressed_depth_image_transport`` writes it: little-endian 32-bit words).

    A stream that ends early, or whose runs overflow the image, is a RecordingError naming ``where``.
    """
    n = int(width) * int(height)
    pad = (-len(data)) % 4
    words = np.frombuffer(bytes(data) + b"\0" * pad, "<u4").astype(np.uint32)
    out, status = rvl_decode(words, n)
    if status != RVL_OK:
        raise RecordingError(where, f"damaged RVL depth image ({_RVL_REASONS[status]})")
    return out.reshape(height, width)


def decode_png_units(data: bytes, where, max_side: int) -> np.ndarray:
    """A 16-bit greyscale PNG (as ``compressedDepth`` stores depth) → ``(H, W)`` uint16; a side over
    ``max_side`` is refused from the header, before anything is decoded."""
    w, h, bits, ctype = png_header(data, where)
    if w > max_side or h > max_side:
        raise RecordingError(where, f"frames of {w}×{h} pixels are larger than the supported {max_side}×{max_side}")
    if bits != 16 or ctype != "greyscale":
        raise RecordingError(where, f"compressed depth is a {bits}-bit {ctype} PNG, expected 16-bit greyscale")
    a = _decode_png(data, where)
    if a.dtype != np.uint16 or a.shape != (h, w):
        raise RecordingError(where, f"decoded as {a.dtype} {a.shape}, expected uint16 ({h}, {w})")
    return a


def inverse_depth_to_metres(q, quant_a: float, quant_b: float) -> np.ndarray:
    """ROS ``compressedDepth`` 32FC1 images store quantised inverse depth ``q = A / d + B``; this is
    ``d = A / (q - B)`` in metres (float32), NaN where ``q`` is 0 (no data)."""
    q = np.asarray(q)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = (np.float32(quant_a) / (q.astype(np.float32) - np.float32(quant_b))).astype(np.float32)
    d[(q == 0) | ~np.isfinite(d) | (d <= 0)] = np.nan
    return d


def register_color(depth_m, camera: Camera, color, color_K, rotation=None, translation=None) -> np.ndarray:
    """A colour image resampled onto the depth image's pixel grid (``(H, W, 3)`` uint8).

    Each depth pixel is lifted to 3-D, moved into the colour camera (``p_c = R p_d + t``, metres) and
    projected with the colour intrinsics ``color_K`` (3×3); the nearest colour pixel is taken. Pixels
    without depth, or landing outside the colour image, are black. Lens distortion is not modelled
    (RealSense colour streams are rectified: their distortion coefficients are zero).
    """
    d = np.asarray(depth_m, np.float64)
    c = np.asarray(color)
    K = np.asarray(color_K, float).reshape(3, 3)
    R = np.eye(3) if rotation is None else np.asarray(rotation, float).reshape(3, 3)
    t = np.zeros(3) if translation is None else np.asarray(translation, float).reshape(3)
    out = np.zeros(d.shape + (3,), np.uint8)
    v, u = np.nonzero(np.isfinite(d) & (d > 0))
    if not u.size:
        return out
    z = d[v, u]
    p = np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], -1) @ R.T + t
    ok = p[:, 2] > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        uc = np.rint(K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2])
        vc = np.rint(K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2])
    ok &= (uc >= 0) & (uc < c.shape[1]) & (vc >= 0) & (vc < c.shape[0])
    out[v[ok], u[ok]] = c[vc[ok].astype(int), uc[ok].astype(int), :3]
    return out
