"""The C3D header and parameter section, read with our own bounded parser before any native reader
sees the file (:mod:`synergy.c3d` uses it).

Every offset, count and dimension product is checked against the file and the section sizes in
Python integers (no overflow); files whose sections could send a native reader into a stall or a
crash (e.g. ANALOG:RATE × ANALOG:USED beyond the data section) are recognised here.
"""
from __future__ import annotations

import re
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
    # Said only when no reader reads the file (no check acts on them):
    chain: str | None = None                  # what _walk_parameters found wrong with the parameter chain
    overlap: str | None = None                # an entry longer than its offset to the next
    header_fault: str | None = None           # a header field the c3d package cannot take
    repair: tuple[int, bytes] | None = None   # (byte offset, new bytes) for POINT:USED
    repair_note: str | None = None            # why ezc3d is skipped when the repair is the only problem


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


def _entry(label: str, pos: int, group: bool) -> str:
    """How a message names a parameter-section entry: by its name when that reads as one (letters,
    digits, ``_``), else by its place (a chain gone astray reads names out of text)."""
    if re.fullmatch(r"[A-Za-z0-9_]{1,64}", label):
        return f"{'group' if group else 'parameter'} {label}"
    return f"the {'group' if group else 'parameter'} entry at byte {pos}"


def _walk_parameters(buf: bytes, start: int, processor: int) -> tuple[str | None, dict, str | None]:
    """Check the parameter chain the way ezc3d will follow it; also fetch POINT scalars.

    Returns why ezc3d would stall on this section (None if it looks sound), the POINT
    parameters USED, FRAMES and SCALE as stored, each as ``(value, byte offset, size)``
    (ezc3d replaces FRAMES by the number of frames it managed to read), and the first entry whose
    offset to the next entry is shorter than the entry itself (the ``c3d`` package then reads past
    it; only said when no reader reads the file). ezc3d loops until an
    entry says "last", reads description lengths as signed bytes (128 or more makes it
    allocate gigabytes) and does not stop at the end of the file.
    """
    fmt = ">h" if processor == 86 else "<h"
    pos, n = start + 4, len(buf)
    groups: dict[int, bytes] = {}
    found: dict[tuple[int, str], tuple[float | None, int, int]] = {}
    overlap: list[str] = []

    def done(problem: str | None) -> tuple[str | None, dict, str | None]:
        ids: dict[bytes, int] = {}
        for gid, name in groups.items():
            ids.setdefault(name, gid)
        out = {k: v for (g, k), v in found.items() if g == ids.get(b"POINT")}
        out.update({f"ANALOG_{k}": v for (g, k), v in found.items() if g == ids.get(b"ANALOG")})
        return problem, out, (overlap[0] if overlap else None)

    for _ in range(100_000):
        if pos + 2 > n:
            return done(f"the parameter chain leaves the parameter section at byte {pos}")
        nch, gid = _int8(buf[pos]), _int8(buf[pos + 1])
        if nch == 0:
            return done(None)
        if gid == 0:
            return done(f"the parameter entry at byte {pos} has group id 0")
        q = pos + 2 + abs(nch)
        if q + 2 > n:
            return done(f"the parameter chain leaves the parameter section at byte {pos}")
        name = buf[pos + 2:q]
        if not all(32 <= c < 127 for c in name):
            return done(f"garbled parameter name at byte {pos}")
        label = name.decode()
        what = _entry(label, pos, gid < 0)
        (offset,) = struct.unpack_from(fmt, buf, q)
        desc_at = q + 2
        if gid > 0:
            if desc_at + 2 > n:
                return done(f"{what} runs past the parameter section")
            bpe, ndim = _int8(buf[desc_at]), buf[desc_at + 1]
            if bpe not in (-1, 1, 2, 4):
                return done(f"{what} has element size {bpe} (expected -1, 1, 2 or 4)")
            data_at = desc_at + 2 + ndim
            if data_at > n:
                return done(f"{what} runs past the parameter section")
            # Python integers: up to 255 dimensions of up to 255 each must not wrap around.
            count = 1
            for d in buf[desc_at + 2:data_at]:
                count *= d
            desc_at = data_at + abs(bpe) * count
            if desc_at > n:
                return done(f"{what} holds {count} elements, more than the parameter section has room for")
            key = label.upper()
            if key in ("USED", "FRAMES", "SCALE", "RATE") and count and bpe > 0:
                found[(gid, key)] = (_decode_number(buf[data_at:desc_at], bpe, processor), data_at, bpe)
        else:
            groups[-gid] = name.upper()
        if desc_at >= n:
            return done(f"{what} runs past the parameter section")
        if buf[desc_at] > 127:
            return done(f"{what} has a description of {buf[desc_at]} bytes (over 127)")
        if offset == 0:
            return done(None)
        if offset < 0:
            return done(f"{what} points backwards to the next entry ({offset})")
        if q + offset < desc_at + 1 + buf[desc_at] and not overlap:
            overlap.append(f"{what} is {desc_at + 1 + buf[desc_at] - q} bytes long but its offset to the next "
                           f"entry is {offset}")
        pos = q + offset
    return done("the parameter chain has no end")


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


# Signatures of common files given a .c3d name by mistake: (leading bytes, what the file is).
_SIGNATURES = (
    (b"\x89PNG\r\n\x1a\n", "a PNG image"), (b"\xff\xd8\xff", "a JPEG image"), (b"GIF8", "a GIF image"),
    (b"%PDF", "a PDF document"), (b"PK\x03\x04", "a zip archive"), (b"PK\x05\x06", "a zip archive"),
    (b"\x1f\x8b", "a gzip archive"), (b"\x93NUMPY", "a .npy array"), (b"\x7fELF", "an executable"),
    (b"\x89HDF", "an HDF5 file"),
)
# The processor types a C3D parameter section may name (Intel, DEC, MIPS).
_PROCESSORS = {84: "Intel", 85: "DEC", 86: "MIPS"}


def _foreign(head: bytes) -> str | None:
    """Why the first bytes of a file (up to its 512-byte header) are not a C3D header, or None
    if they may be one. The header's first byte points to the parameter section (block 2 or
    later: block 1 is the header), its second is the key 0x50.

    Examples
    --------
    >>> _foreign(b"\\x02\\x50"), _foreign(b"\\x02")
    (None, None)
    >>> _foreign(b"this is not a c3d file at all\\n")
    'it is text'
    >>> _foreign(b"\\x89PNG\\r\\n\\x1a\\n")
    'it is a PNG image'
    >>> _foreign(b"\\x00" * 100)
    'header key byte is 0x00, expected 0x50'
    """
    for magic, kind in _SIGNATURES:
        if head.startswith(magic):
            return f"it is {kind}"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as exc:  # a character cut at the end of the 512 bytes read is still text
        text = head[:exc.start].decode("utf-8") if exc.reason == "unexpected end of data" else ""
    if text and all(c.isprintable() or c in "\t\n\r\f\v" for c in text):
        return "it is text"
    if len(head) >= 2 and head[1] != 0x50:
        return f"header key byte is {head[1]:#04x}, expected 0x50"
    if head[0] < 2:
        return f"its first byte, the parameter section's block number, is {head[0]}; expected 2 or more"
    return None


def _plural(n: int, unit: str) -> str:
    return f"{n} {unit}" if n == 1 else f"{n} {unit}s"


def _layout(path: Path) -> _Layout:
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(512)
            if size == 0 or not head:
                raise C3DError(path, "empty file (0 bytes)")
            foreign = _foreign(head)
            if foreign:
                raise C3DError(path, f"not a C3D file ({foreign})")
            if len(head) < 512:
                raise C3DError(path, f"truncated: {_plural(len(head), 'byte')}, shorter than the 512-byte header")
            start = (head[0] - 1) * 512
            fh.seek(start)
            params = fh.read(4)
            if len(params) < 4:
                raise C3DError(path, f"truncated: the parameter section starts at byte {start} "
                                     f"but the file has {size} bytes")
            n_blocks, processor = params[2], params[3]
            if processor not in _PROCESSORS:  # neither ezc3d nor the c3d package reads a file without one
                raise C3DError(path, f"not a C3D file, or a corrupt one (processor type {processor} at byte "
                                     f"{start + 4}, expected 84 Intel, 85 DEC or 86 MIPS)")
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
    chain, point, overlap = _walk_parameters(buf, start, processor)
    problem = chain or _analog_problem(point, size - data_start)
    frames = point.get("FRAMES", (None,))[0]
    announced = max(words[4] - words[3] + 1, int(frames) if frames and np.isfinite(frames) else 0)
    if size <= data_start and announced > 0:
        raise C3DError(path, f"truncated: {_plural(announced, 'frame')} announced but the file ends where its "
                             f"data section starts (byte {data_start})")
    layout = _Layout(size=size, data_start=data_start, processor=processor, first_frame=words[3],
                     last_frame=words[4], n_points=words[1], ezc3d_problem=problem,
                     frames_param=frames, chain=chain, overlap=overlap)
    (events,) = struct.unpack_from(">H" if big else "<H", head, 300)
    if events > 18:  # the c3d package indexes its 18 event slots with it
        layout.header_fault = f"the header says {events} events, more than its 18 event slots"
    layout.repair = _point_count_repair(layout, point, analog_words=words[2])
    if layout.repair and not layout.ezc3d_problem:
        layout.ezc3d_problem = layout.repair_note = (f"POINT:USED says {int(point['USED'][0])} points but the "
                                                     f"header and the data section hold {layout.n_points}")
    return layout
