"""The C3D header and parameter section, read with our own bounded parser before any native reader
sees the file (:mod:`synergy.c3d` uses it).

Every offset, count and dimension product is checked against the file and the section sizes in
Python integers (no overflow); files whose sections could send a native reader into a stall or a
crash (e.g. ANALOG:RATE × ANALOG:USED beyond the data section) are recognised here.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from synergy.errors import C3DError

# --------------------------------------------------------------------------------------
# File layout checks (cheap, done before any backend sees the file)
# --------------------------------------------------------------------------------------
@dataclass
class _Layout:
    """What the header and the raw parameter section say, read without any backend."""

    size: int
    data_start: int
    processor: int
    first_frame: int
    last_frame: int
    n_points: int
    ezc3d_problem: str | None
    frames_param: float | None
    repair: tuple[int, bytes] | None = None   # (byte offset, new bytes) for POINT:USED


def _int8(b: int) -> int:
    return b - 256 if b > 127 else b


def _decode_number(raw: bytes, bpe: int, processor: int) -> float | None:
    """First element of a numeric parameter in the file's own encoding."""
    if bpe == 2 and len(raw) >= 2:
        return float(struct.unpack((">" if processor == 86 else "<") + "H", raw[:2])[0])
    if bpe == 4 and len(raw) >= 4:
        if processor == 85:  # DEC F-float: swap the 16-bit words, then a factor 4 in the exponent
            return float(struct.unpack("<f", raw[2:4] + raw[0:2])[0]) / 4.0
        return float(struct.unpack((">" if processor == 86 else "<") + "f", raw[:4])[0])
    return None


def _walk_parameters(buf: bytes, start: int, processor: int) -> tuple[str | None, dict]:
    """Check the parameter chain the way ezc3d will follow it; also fetch POINT scalars.

    Returns why ezc3d would stall on this section (None if it looks sound) and the POINT
    parameters USED, FRAMES and SCALE as stored, each as ``(value, byte offset, size)``
    (ezc3d replaces FRAMES by the number of frames it managed to read). ezc3d loops until an
    entry says "last", reads description lengths as signed bytes (128 or more makes it
    allocate gigabytes) and does not stop at the end of the file.
    """
    fmt = ">h" if processor == 86 else "<h"
    pos, n = start + 4, len(buf)
    groups: dict[int, bytes] = {}
    found: dict[tuple[int, str], tuple[float | None, int, int]] = {}

    def done(problem: str | None) -> tuple[str | None, dict]:
        ids: dict[bytes, int] = {}
        for gid, name in groups.items():
            ids.setdefault(name, gid)
        out = {k: v for (g, k), v in found.items() if g == ids.get(b"POINT")}
        out.update({f"ANALOG_{k}": v for (g, k), v in found.items() if g == ids.get(b"ANALOG")})
        return problem, out

    for _ in range(100_000):
        if pos + 2 > n:
            return done(f"parameter chain leaves the parameter section at byte {pos}")
        nch, gid = _int8(buf[pos]), _int8(buf[pos + 1])
        if nch == 0:
            return done(None)
        if gid == 0:
            return done(f"parameter entry at byte {pos} has group id 0")
        q = pos + 2 + abs(nch)
        if q + 2 > n:
            return done(f"parameter chain leaves the parameter section at byte {pos}")
        name = buf[pos + 2:q]
        if not all(32 <= c < 127 for c in name):
            return done(f"unreadable parameter name at byte {pos}")
        label = name.decode()
        (offset,) = struct.unpack_from(fmt, buf, q)
        desc_at = q + 2
        if gid > 0:
            if desc_at + 2 > n:
                return done(f"parameter {label} leaves the parameter section")
            bpe, ndim = _int8(buf[desc_at]), buf[desc_at + 1]
            if bpe not in (-1, 1, 2, 4):
                return done(f"parameter {label} has element size {bpe}")
            data_at = desc_at + 2 + ndim
            if data_at > n:
                return done(f"parameter {label} leaves the parameter section")
            # Python integers: up to 255 dimensions of up to 255 each must not wrap around.
            count = 1
            for d in buf[desc_at + 2:data_at]:
                count *= d
            desc_at = data_at + abs(bpe) * count
            if desc_at > n:
                return done(f"parameter {label} holds {count} elements, more than the parameter section has room for")
            key = label.upper()
            if key in ("USED", "FRAMES", "SCALE", "RATE") and count and bpe > 0:
                found[(gid, key)] = (_decode_number(buf[data_at:desc_at], bpe, processor), data_at, bpe)
        else:
            groups[-gid] = name.upper()
        if desc_at >= n:
            return done(f"parameter {label} leaves the parameter section")
        if buf[desc_at] > 127:
            return done(f"{label} has a description of {buf[desc_at]} bytes (over 127)")
        if offset == 0:
            return done(None)
        if offset < 0:
            return done(f"parameter {label} points backwards ({offset})")
        pos = q + offset
    return done("parameter section has no end")


def _analog_problem(params: dict, room: int) -> str | None:
    """Why ezc3d would allocate without bound for the analog channels, or None.

    ezc3d sizes every frame's analog block from ANALOG:RATE / POINT:RATE x ANALOG:USED before
    reading a byte: a mutated rate of 1e9 made it spin and allocate gigabytes (fuzzing).
    """
    rate = params.get("ANALOG_RATE", (None,))[0]
    used = params.get("ANALOG_USED", (None,))[0]
    point_rate = params.get("RATE", (None,))[0]
    if rate is None or not used:
        return None
    if not np.isfinite(rate) or rate < 0:
        return f"ANALOG:RATE is {rate}"
    if point_rate is None or not np.isfinite(point_rate) or point_rate <= 0:
        return None
    per_frame = used * rate / point_rate
    if per_frame * 2 > max(room, 0):   # 2 bytes: the smallest analog sample
        return (f"ANALOG:RATE {rate:g} Hz and ANALOG:USED {used:g} give {per_frame:.0f} analog samples per "
                f"frame, more than the {room}-byte data section holds")
    return None


def _point_count_repair(layout: "_Layout", point: dict, analog_words: int) -> tuple[int, bytes] | None:
    """Patch for POINT:USED when it contradicts the header and only the header fits the data.

    Kyowa Dengyo's sample says 12 points in POINT:USED, 11 in the header, and stores 11 x 152
    frames: ezc3d reads 12 misaligned points per frame (garbage), c3d refuses the file.
    """
    used = point.get("USED")
    if used is None or used[0] is None or used[2] != 2 or not layout.n_points:
        return None
    n_used = int(used[0])
    if n_used == layout.n_points:
        return None
    counts = [layout.last_frame - layout.first_frame + 1, layout.frames_param or 0]
    counts = [c for c in counts if c > 0]
    scale = point.get("SCALE", (None,))[0]
    if not counts or scale is None:
        return None
    word = 4 if scale < 0 else 2
    room = layout.size - layout.data_start

    def fits(m: int) -> bool:
        return min(counts) * word * (4 * m + analog_words) <= room

    if fits(layout.n_points) and not fits(n_used):
        return used[1], struct.pack(">H" if layout.processor == 86 else "<H", layout.n_points)
    return None


def _layout(path: Path) -> _Layout:
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(512)
            if size == 0:
                raise C3DError(path, "empty file (0 bytes)")
            if len(head) < 512:
                raise C3DError(path, f"truncated: {size} bytes, shorter than the 512-byte header")
            if head[1] != 0x50:
                raise C3DError(path, f"not a C3D file (header key byte is {head[1]:#04x}, expected 0x50)")
            if head[0] == 0:
                raise C3DError(path, "header points to parameter block 0")
            start = (head[0] - 1) * 512
            fh.seek(start)
            params = fh.read(4)
            if len(params) < 4:
                raise C3DError(path, f"truncated: the parameter section starts at byte {start} "
                                     f"but the file has {size} bytes")
            # An unknown processor byte is read as Intel, as the c3d package does.
            n_blocks, processor = params[2], params[3]
            big = processor == 86
            words = struct.unpack((">" if big else "<") + "10H", head[:20])
            data_start = max(words[8] - 1, 0) * 512
            needed = max(start + n_blocks * 512, data_start)
            if size < needed:
                raise C3DError(path, f"truncated: the header announces {needed} bytes of header and "
                                     f"parameters but the file has {size}")
            fh.seek(0)
            # The parameter chain may run past its declared blocks; 64 KiB more is plenty.
            buf = fh.read(start + max(n_blocks, 1) * 512 + 65536)
    except OSError as exc:
        raise C3DError(path, f"cannot open: {exc.strerror or exc}") from None
    problem, point = _walk_parameters(buf, start, processor)
    problem = problem or _analog_problem(point, size - data_start)
    frames = point.get("FRAMES", (None,))[0]
    layout = _Layout(size=size, data_start=data_start, processor=processor, first_frame=words[3],
                     last_frame=words[4], n_points=words[1], ezc3d_problem=problem,
                     frames_param=frames)
    layout.repair = _point_count_repair(layout, point, analog_words=words[2])
    if layout.repair and not layout.ezc3d_problem:
        layout.ezc3d_problem = (f"POINT:USED says {int(point['USED'][0])} points but the header and "
                                f"the data section hold {layout.n_points}")
    return layout
