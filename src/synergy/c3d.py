"""Read and write C3D marker trajectories.

:func:`read_c3d` reads every file that either ezc3d or the ``c3d`` package can read
and returns a :class:`MarkerData` in metres, with NaN for gaps. Every failure becomes
:class:`~synergy.errors.C3DError` naming the file and the reason.

Why the extra work around the two backends (all measured on ``../shared/data``):

- ezc3d (tried first, it is fast) cannot read big-endian MIPS files, and it stalls for
  seconds or forever on some malformed or truncated parameter sections, so the sections are
  checked here first and such files go straight to the ``c3d`` package.
- ezc3d swaps the residual and camera-mask bytes of each point: its residual is only used as
  a validity flag and the real residual is rebuilt from the (7-bit) camera mask it reports.
- ``c3d`` keeps stale coordinates for invalid points, crashes on ART's 2-D TRIAL parameters
  and rejects files whose header and parameters disagree.
- Both backends silently return the frames present in a truncated data section; a trial is
  called truncated when fewer frames are stored than both header and POINT:FRAMES announce
  and a partial frame is left at the end (Optotrak's sample ends cleanly after 29 of 1149).
- Kyowa Dengyo's sample has POINT:USED = 12 while header and data hold 11 points; ezc3d
  then reads misaligned garbage, so POINT:USED is corrected (in memory) for the c3d package.
"""
from __future__ import annotations

import errno
import io
import json
import os
import select
import signal
import struct
import subprocess
import sys
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from synergy.errors import C3DError

__all__ = ["MarkerData", "read_c3d", "write_c3d", "strip_prefix", "UNIT_SCALE"]

#: Metres per length unit accepted in POINT:UNITS.
UNIT_SCALE = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}

# POINT parameters that list channels holding model outputs rather than positions.
_NON_MARKER_GROUPS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "REACTIONS", "SCALARS")
_BACKENDS = ("auto", "ezc3d", "c3d")


# --------------------------------------------------------------------------------------
# The result
# --------------------------------------------------------------------------------------
@dataclass(eq=False)
class MarkerData:
    """Marker trajectories of one C3D trial, in metres.

    Attributes
    ----------
    labels : list of str
        Marker names with any subject prefix (``"Name:"``) removed.
    original_labels : list of str
        Marker names as stored in the file.
    points : ndarray, shape (F, M, 3)
        Positions in metres; NaN where the point is missing or invalid.
    residuals : ndarray, shape (F, M)
        Reconstruction residuals in metres; NaN where the point is invalid.
    rate : float
        Frame rate in Hz.
    first_frame : int
        Number of the first stored frame, as the file header gives it (1-based).
    events : list of (str, float, str)
        ``(label, time_s, context)`` from the EVENT parameters, sorted by time.
    units : str
        Length unit the file stored (``"mm"``, ``"cm"`` or ``"m"``).
    path : Path or None
        Source file.
    descriptions : list of str or None
        POINT:DESCRIPTIONS per marker, None if the file has none.
    backend : str
        Reader that decoded the file (``"ezc3d"``, ``"c3d"``, or ``""`` if built in memory).
    """

    labels: list[str]
    original_labels: list[str]
    points: np.ndarray
    residuals: np.ndarray
    rate: float
    first_frame: int = 1
    events: list[tuple[str, float, str]] = field(default_factory=list)
    units: str = "mm"
    path: Path | None = None
    descriptions: list[str] | None = None
    backend: str = ""

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64)
        self.residuals = np.asarray(self.residuals, dtype=np.float64)
        f, m = self.points.shape[:2] if self.points.ndim == 3 else (-1, -1)
        if self.points.ndim != 3 or self.points.shape[2] != 3:
            raise C3DError(self.path, f"points must have shape (F, M, 3), got {self.points.shape}")
        if self.residuals.shape != (f, m):
            raise C3DError(self.path, f"residuals must have shape {(f, m)}, got {self.residuals.shape}")
        if len(self.labels) != m or len(self.original_labels) != m:
            raise C3DError(self.path, f"{m} markers but {len(self.labels)} labels")
        if self.descriptions is not None and len(self.descriptions) != m:
            raise C3DError(self.path, f"{m} markers but {len(self.descriptions)} descriptions")

    @property
    def n_frames(self) -> int:
        """Number of frames F."""
        return self.points.shape[0]

    @property
    def n_markers(self) -> int:
        """Number of markers M."""
        return self.points.shape[1]

    @property
    def times(self) -> np.ndarray:
        """Frame times in seconds on the trial clock (frame 1 at 0 s, as EVENT times are)."""
        start = max(self.first_frame, 1) - 1
        return (start + np.arange(self.n_frames)) / self.rate

    @property
    def gap_fraction(self) -> np.ndarray:
        """Fraction of frames in which each marker is missing, shape (M,)."""
        if self.n_frames == 0:
            return np.zeros(self.n_markers)
        return np.isnan(self.points[..., 0]).mean(axis=0)

    def index(self, label: str) -> int:
        """Column of a marker, found by its stripped or its original label."""
        for names in (self.labels, self.original_labels):
            if label in names:
                return names.index(label)
        raise C3DError(self.path, f"no marker {label!r} in the trial")

    def select(self, labels: str | Iterable[str]) -> "MarkerData":
        """A copy holding only ``labels``, in that order.

        Examples
        --------
        >>> d = MarkerData(["a", "b"], ["S:a", "S:b"], np.zeros((2, 2, 3)), np.zeros((2, 2)), 100.0)
        >>> d.select(["b"]).original_labels
        ['S:b']
        """
        wanted = [labels] if isinstance(labels, str) else list(labels)
        missing = [lab for lab in wanted if lab not in self.labels and lab not in self.original_labels]
        if missing:
            raise C3DError(self.path, f"markers not in the trial: {', '.join(map(repr, missing))}")
        idx = [self.index(lab) for lab in wanted]
        return MarkerData(
            labels=[self.labels[i] for i in idx],
            original_labels=[self.original_labels[i] for i in idx],
            points=self.points[:, idx].copy(),
            residuals=self.residuals[:, idx].copy(),
            rate=self.rate,
            first_frame=self.first_frame,
            events=list(self.events),
            units=self.units,
            path=self.path,
            descriptions=None if self.descriptions is None else [self.descriptions[i] for i in idx],
            backend=self.backend,
        )


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


# --------------------------------------------------------------------------------------
# Backends: each returns a _Raw in the file's own length unit
# --------------------------------------------------------------------------------------
@dataclass
class _Raw:
    params: Any                 # callable (group, name) -> value or None
    xyz: np.ndarray             # (F, M, 3), NaN where invalid
    residual: np.ndarray        # (F, M), NaN where invalid
    frame_bytes: int            # bytes of one stored frame (points and analogs)


def _text(s: str) -> str:
    # ezc3d hands undecodable bytes over as surrogates; read them as Latin-1 like c3d does.
    b = s.encode("utf-8", "surrogateescape")
    try:
        return b.decode("utf-8").strip()
    except UnicodeDecodeError:
        return b.decode("latin-1").strip()


def _ezc3d_param(groups: dict, group: str, name: str):
    try:
        value = groups[group][name]["value"]
    except KeyError:
        return None
    return [_text(str(v)) for v in value] if isinstance(value, list) else np.asarray(value)


def _read_ezc3d(path: Path, c) -> _Raw:
    groups = c["parameters"]
    data = c["data"]
    pts = data["points"]                               # (4, M, F)
    flag = data["meta_points"]["residuals"][0]         # (M, F): only its sign is meaningful
    masks = data["meta_points"]["camera_masks"]        # (7, M, F): really the residual's low bits
    invalid = (flag < 0) | np.isnan(pts[:3]).any(axis=0)
    scale = _ezc3d_param(groups, "POINT", "SCALE")
    scale = float(scale.ravel()[0]) if scale is not None and scale.size else -1.0
    analogs = data["analogs"]                          # (1, channels, F * subframes)
    n_frames = pts.shape[2]
    word = 4 if scale < 0 else 2
    analog_words = analogs.shape[1] * analogs.shape[2] // n_frames if n_frames else 0
    frame_bytes = word * (4 * pts.shape[1] + analog_words)
    scale = abs(scale)
    code = np.zeros(masks.shape[1:], dtype=np.uint8)
    for bit, plane in enumerate(masks):                # 7 bit planes, not frames
        code |= plane.view(np.uint8) << bit
    residual = code * scale
    residual[invalid] = np.nan
    xyz = pts[:3].transpose(2, 1, 0).copy()            # (F, M, 3)
    xyz[invalid.T] = np.nan
    return _Raw(lambda g, n: _ezc3d_param(groups, g, n), xyz, residual.T, frame_bytes)


def _c3d_param(reader, group: str, name: str):
    p = reader.get(f"{group}:{name}")
    if p is None:
        return None
    dims = list(p.dimensions)
    if p.bytes_per_element == -1:
        if not dims or 0 in dims:
            return []
        if len(dims) == 1:
            return [p.string_value.strip()]
        return [str(s).strip() for s in np.asarray(p.string_array).ravel()]
    if 0 in dims:
        return np.zeros(0)
    if p.bytes_per_element == 4:
        flat = np.atleast_1d(p.float_value if not dims else p.float_array).astype(np.float64)
    else:
        flat = np.atleast_1d(p.int16_value if not dims and p.bytes_per_element == 2
                             else p.int8_value if not dims else p.int_array).astype(np.int64)
    # Fortran-ordered like ezc3d's values.
    return flat.ravel().reshape(dims[::-1]).T if len(dims) > 1 else flat.ravel()


def _read_c3d_package(path: Path, repair: tuple[int, bytes] | None = None):
    import c3d

    if repair:
        data = bytearray(path.read_bytes())
        data[repair[0]:repair[0] + len(repair[1])] = repair[1]
        source = io.BytesIO(bytes(data))
    else:
        source = open(path, "rb")
    with source as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # EOF and "no analog data" notices; truncation is judged later
        reader = c3d.Reader(fh)
        if reader.get("POINT:LABELS") is None and reader.get("POINT:USED") is None:
            raise ValueError("no POINT group in the parameter section")
        frames = [pts[:, :4].copy() for _, pts, _ in reader.read_frames(copy=False)]
    m = int(reader.point_used)
    word = 4 if reader.point_scale < 0 else 2
    frame_bytes = word * (4 * m + int(reader.analog_used) * int(reader.analog_per_frame))
    arr = np.stack(frames).astype(np.float64) if frames else np.zeros((0, m, 4))
    invalid = arr[..., 3] < 0
    xyz = arr[..., :3]
    xyz[invalid] = np.nan
    residual = arr[..., 3]
    residual[invalid] = np.nan
    return _Raw(lambda g, n: _c3d_param(reader, g, n), xyz, residual, frame_bytes), reader


# --------------------------------------------------------------------------------------
# Isolation: the native readers run in a worker process
# --------------------------------------------------------------------------------------
# Fuzzing the corpus showed ezc3d segfaulting on about 1 % of mutated files and spinning or
# allocating gigabytes on others; the checks above cannot prove a file safe for a C++ reader.
# So both backends run in one long-lived worker process (started on first use, about 0.15 s)
# with an address-space limit and a deadline: a crash or a hang costs that worker, never the
# caller, and becomes a C3DError naming the file. The worker is reused across files, so the
# normal path pays only a pipe round trip.

#: Seconds a worker may spend on one file before it is killed: a base plus one second per
#: 8 MiB (ezc3d reads ~50 MB/s here, so a sound file is far below the deadline).
READ_TIMEOUT_S = 3.0
#: Address space a worker may add while reading one file: a base plus a multiple of the file
#: size (a sound file decodes to about 3x its size in float64).
READ_MEMORY_BASE = 768 << 20
READ_MEMORY_PER_BYTE = 16

_GROUPS_EXPORTED = ("POINT", "EVENT")
_STARTUP_TIMEOUT_S = 60.0


def _read_deadline(size: int) -> float:
    return READ_TIMEOUT_S + size / (8 << 20)


def _export_params(get, names_of) -> dict:
    """``{"GROUP:NAME": value}`` of the groups _assemble reads, as JSON-able values."""
    out = {}
    for group in _GROUPS_EXPORTED:
        for name in names_of(group):
            v = get(group, name)
            if v is None:
                continue
            key = f"{group}:{str(name).upper()}"
            if isinstance(v, list):
                out[key] = {"s": [str(x) for x in v]}
            else:
                a = np.asarray(v)
                kind = "f8" if a.dtype.kind == "f" else "i8"
                out[key] = {"a": a.astype(kind).ravel().tolist(), "shape": list(a.shape), "dtype": kind}
    return out


def _import_params(doc: dict):
    values = {}
    for key, v in doc.items():
        if "s" in v:
            values[key] = list(v["s"])
        else:
            values[key] = np.array(v["a"], dtype=v["dtype"]).reshape(v["shape"])
    return lambda g, n: values.get(f"{g.upper()}:{n.upper()}")


def _worker_read(path: Path, backend: str, repair) -> tuple[dict, list[np.ndarray]]:
    """Decode one file in the worker: the JSON-able part and the arrays."""
    if backend == "ezc3d":
        import ezc3d

        c = ezc3d.c3d(str(path))
        raw = _read_ezc3d(path, c)
        groups = c["parameters"]

        def names_of(g):
            return [k for k, v in groups.get(g, {}).items() if isinstance(v, dict) and "value" in v]
    else:
        raw, reader = _read_c3d_package(path, repair)

        def names_of(g):
            grp = reader.get(g)
            return [] if grp is None else list(grp.param_keys())
    doc = {"params": _export_params(raw.params, names_of), "frame_bytes": int(raw.frame_bytes),
           "shapes": [list(raw.xyz.shape), list(raw.residual.shape)]}
    return doc, [np.ascontiguousarray(raw.xyz, np.float64), np.ascontiguousarray(raw.residual, np.float64)]


def _worker_main() -> None:
    """Serve read requests on stdin (one JSON line each), answer on stdout (length-prefixed
    JSON, then the raw float64 arrays). Ends on EOF, i.e. when the caller goes away."""
    import resource  # POSIX only, and only the worker needs it

    import c3d  # noqa: F401 - imported once here, not per request
    import ezc3d  # noqa: F401

    out = sys.stdout.buffer
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    base = _vm_size()
    out.write(b"R")  # ready: start-up (imports) is not charged to the first file's deadline
    out.flush()
    for line in sys.stdin.buffer:
        req = json.loads(line)
        # SIGALRM's default action ends the process even inside C++ code: a worker left
        # behind by a killed caller cannot spin for ever.
        signal.alarm(int(req["timeout"]) + 2)
        limit = base + int(req["memory"])
        if hard == resource.RLIM_INFINITY or limit < hard:
            resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
        arrays: list[np.ndarray] = []
        try:
            repair = req["repair"] and (req["repair"][0], bytes.fromhex(req["repair"][1]))
            doc, arrays = _worker_read(Path(req["path"]), req["backend"], repair)
            doc["ok"] = True
        except C3DError as exc:
            doc = {"ok": False, "error": exc.reason}
        except MemoryError:
            doc = {"ok": False, "error": "out of memory"}
        except Exception as exc:  # noqa: BLE001 - any backend failure is reported, not fatal
            doc = {"ok": False, "error": str(exc).split("\n")[0][:200] or type(exc).__name__}
        body = json.dumps(doc).encode()
        # The answer is built before the limit is lifted: sending it must not need more memory.
        out.write(len(body).to_bytes(8, "little") + body)
        for a in arrays:
            if a.size:  # memoryview refuses to cast an empty view
                out.write(memoryview(a.reshape(-1)).cast("B"))
        out.flush()
        signal.alarm(0)
        if hard == resource.RLIM_INFINITY or limit < hard:
            resource.setrlimit(resource.RLIMIT_AS, (hard, hard))


def _vm_size() -> int:
    """Address space of this process in bytes (Linux; 0 where /proc is missing)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):
        return 0


class _Worker:
    """The caller's handle on one worker process (restarted after a crash or a hang)."""

    def __init__(self) -> None:
        env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1",
                   PYTHONDONTWRITEBYTECODE="1")
        self.owner = os.getpid()
        self.proc = subprocess.Popen(
            [sys.executable, "-c", "from synergy.c3d import _worker_main; _worker_main()"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env,
            close_fds=True)
        try:  # a loaded machine may take seconds to import numpy and the readers
            ready = self._read_exact(1, time.monotonic() + _STARTUP_TIMEOUT_S)
        except (TimeoutError, EOFError, OSError):
            ready = b""
        if ready != b"R":
            self.kill()
            raise C3DError(None, "the C3D reader process did not start")

    def alive(self) -> bool:
        return self.owner == os.getpid() and self.proc.poll() is None

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        for fh in (self.proc.stdin, self.proc.stdout):
            try:
                fh.close()
            except OSError:
                pass

    def _read_exact(self, n: int, deadline: float) -> bytes:
        fd = self.proc.stdout.fileno()
        chunks, got = [], 0
        while got < n:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise TimeoutError
            b = os.read(fd, min(n - got, 1 << 20))
            if not b:
                raise EOFError
            chunks.append(b)
            got += len(b)
        return b"".join(chunks)

    def request(self, req: dict, timeout: float):
        deadline = time.monotonic() + timeout
        self.proc.stdin.write(json.dumps(req).encode() + b"\n")
        self.proc.stdin.flush()
        head = self._read_exact(8, deadline)
        doc = json.loads(self._read_exact(int.from_bytes(head, "little"), deadline))
        arrays = []
        for shape in doc.get("shapes", []) if doc.get("ok") else []:
            count = int(np.prod(shape, dtype=np.int64))
            arrays.append(np.frombuffer(self._read_exact(8 * count, deadline), np.float64).reshape(shape).copy())
        return doc, arrays


_worker: _Worker | None = None


def _worker_handle() -> _Worker:
    global _worker
    if _worker is None or not _worker.alive():
        if _worker is not None and _worker.owner == os.getpid():
            _worker.kill()
        _worker = _Worker()  # a forked child never touches its parent's worker
    return _worker


def _stop_worker() -> None:
    global _worker
    if _worker is not None and _worker.owner == os.getpid():
        _worker.kill()
    _worker = None


def _signal_name(code: int) -> str:
    try:
        return signal.Signals(-code).name
    except ValueError:
        return f"signal {-code}"


def _read_isolated(path: Path, backend: str, layout: "_Layout") -> _Raw:
    """One backend's :class:`_Raw` for ``path``, decoded in the worker process."""
    req = {"path": str(path.resolve()), "backend": backend,
           "repair": layout.repair and [layout.repair[0], layout.repair[1].hex()],
           "timeout": _read_deadline(layout.size),
           "memory": READ_MEMORY_BASE + READ_MEMORY_PER_BYTE * layout.size}
    with _worker_lock:
        w = _worker_handle()
        try:
            doc, arrays = w.request(req, req["timeout"])
        except TimeoutError:
            w.kill()
            raise C3DError(path, f"the {backend} reader took over {req['timeout']:.0f} s and was stopped "
                                 f"(the file is malformed)") from None
        except (EOFError, BrokenPipeError, ValueError, OSError):
            w.kill()
            code = w.proc.returncode
            how = f"crashed ({_signal_name(code)})" if code and code < 0 else f"failed (exit {code})"
            raise C3DError(path, f"the {backend} reader {how} on this file (the file is malformed)") from None
    if not doc["ok"]:
        raise C3DError(path, doc["error"])
    return _Raw(_import_params(doc["params"]), arrays[0], arrays[1], doc["frame_bytes"])


_worker_lock = threading.Lock()


# --------------------------------------------------------------------------------------
# From raw backend output to MarkerData
# --------------------------------------------------------------------------------------
def _strings(params, group: str, name: str) -> list[str] | None:
    """A CHAR parameter and its continuations (NAME2, NAME3, ...), None if absent."""
    first = params(group, name)
    if first is None:
        return None
    out, k = [str(s).strip() for s in first], 2
    while (more := params(group, f"{name}{k}")) is not None:
        out.extend(str(s).strip() for s in more)
        k += 1
    return out


def _number(params, group: str, name: str) -> float | None:
    v = params(group, name)
    if v is None or isinstance(v, list) or np.size(v) == 0:
        return None
    return float(np.ravel(v)[0])


def strip_prefix(label: str) -> str:
    """Drop a subject prefix: ``"Human4:LIFT"`` -> ``"LIFT"``.

    Examples
    --------
    >>> strip_prefix("Daphnee:INDEX"), strip_prefix("INDEX")
    ('INDEX', 'INDEX')
    """
    head, sep, tail = label.partition(":")
    return tail.strip() if sep and tail.strip() else label


def _units(path: Path, params) -> str:
    raw = {u.strip().lower() for u in (_strings(params, "POINT", "UNITS") or []) if u.strip()}
    if not raw:
        return "mm"  # the C3D default when POINT:UNITS is missing or blank
    if len(raw) > 1:
        raise C3DError(path, f"mixed POINT:UNITS {sorted(raw)}")
    unit = raw.pop()
    if unit not in UNIT_SCALE:
        raise C3DError(path, f"unsupported POINT:UNITS {unit!r} (expected mm, cm or m)")
    return unit


def _f32(value: float) -> float:
    # The file holds a float32; its shortest decimal is the value meant (65.05334, not 65.0533447...).
    return float(str(np.float32(value)))


def _events(params) -> list[tuple[str, float, str]]:
    times = params("EVENT", "TIMES")
    if times is None or isinstance(times, list) or np.size(times) == 0:
        return []
    times = np.asarray(times, dtype=np.float64)
    if times.ndim == 2 and times.shape[0] == 2:   # (minutes, seconds) per event
        secs = times[0] * 60.0 + np.array([_f32(t) for t in times[1]])
    else:
        secs = np.array([_f32(t) for t in times.ravel()])
    used = _number(params, "EVENT", "USED")
    n = len(secs) if used is None else min(int(used), len(secs))
    labels = _strings(params, "EVENT", "LABELS") or []
    contexts = _strings(params, "EVENT", "CONTEXTS") or []
    ev = [(labels[i] if i < len(labels) else "", float(secs[i]), contexts[i] if i < len(contexts) else "")
          for i in range(n)]
    return sorted(ev, key=lambda e: e[1])


def _assemble(path: Path, raw: _Raw, layout: _Layout, backend: str) -> MarkerData:
    params = raw.params
    n_frames, n_points = raw.xyz.shape[:2]
    if n_points == 0:
        extra = f" (the header claims {layout.n_points})" if layout.n_points else ""
        raise C3DError(path, f"no point channels{extra}")
    if n_frames == 0:
        raise C3DError(path, "no frames stored")

    # Truncated: fewer frames than every count the file announces, and a partial frame at
    # the end. A file ending exactly after its last whole frame is taken at its word
    # (Optotrak's sample announces 1149 frames and cleanly stores 29).
    claims = []
    if layout.last_frame >= layout.first_frame:
        claims.append(layout.last_frame - layout.first_frame + 1)
    if layout.frames_param:  # as stored: ezc3d rewrites POINT:FRAMES to what it read
        claims.append(int(layout.frames_param))
    leftover = layout.size - layout.data_start - n_frames * raw.frame_bytes
    if claims and n_frames < min(claims) and leftover != 0:
        raise C3DError(path, f"truncated: {min(claims)} frames announced, {n_frames} whole frames "
                             f"stored and {leftover} bytes of a partial frame")

    original = _strings(params, "POINT", "LABELS") or []
    original = original[:n_points] + [f"POINT{i + 1}" for i in range(len(original), n_points)]
    descriptions = _strings(params, "POINT", "DESCRIPTIONS")
    if descriptions is not None:
        descriptions = descriptions[:n_points] + [""] * max(0, n_points - len(descriptions))

    # Model outputs (angles, forces, ...) are stored as points but are not markers.
    groups = set(_NON_MARKER_GROUPS)
    groups.update(g.strip().upper() for g in (_strings(params, "POINT", "TYPE_GROUPS") or [])
                  if g.strip().upper() not in {"MARKERS", "MARKER", "LABELS"})
    non_markers = set()
    for g in groups:
        non_markers.update(s for s in (_strings(params, "POINT", g) or []) if s)
    keep = [i for i, lab in enumerate(original)
            if lab not in non_markers and strip_prefix(lab) not in non_markers]
    if not keep:
        raise C3DError(path, f"no marker channels: all {n_points} points are model outputs")

    unit = _units(path, params)
    rate = _number(params, "POINT", "RATE")
    if rate is None or not np.isfinite(rate) or rate <= 0:
        raise C3DError(path, f"no valid POINT:RATE ({rate})")

    original = [original[i] for i in keep]
    stripped = [strip_prefix(lab) for lab in original]
    # Two subjects may share marker names; those keep their prefixes.
    counts: dict[str, int] = {}
    for lab in stripped:
        counts[lab] = counts.get(lab, 0) + 1
    labels = [s if counts[s] == 1 or s == o else o for s, o in zip(stripped, original)]

    factor = UNIT_SCALE[unit]
    all_kept = len(keep) == n_points
    xyz = raw.xyz if all_kept else raw.xyz[:, keep]
    res = raw.residual if all_kept else raw.residual[:, keep]
    return MarkerData(
        labels=labels,
        original_labels=original,
        points=np.multiply(xyz, factor, out=xyz) if all_kept else xyz * factor,
        residuals=np.multiply(res, factor, out=res) if all_kept else res * factor,
        rate=_f32(rate),
        first_frame=int(layout.first_frame),
        events=_events(params),
        units=unit,
        path=path,
        descriptions=None if descriptions is None else [descriptions[i] for i in keep],
        backend=backend,
    )


def read_c3d(path: str | os.PathLike, *, backend: str = "auto") -> MarkerData:
    """Read the marker trajectories of a C3D file.

    Parameters
    ----------
    path : str or PathLike
        The C3D file.
    backend : {"auto", "ezc3d", "c3d"}
        ``"auto"`` tries ezc3d, then the ``c3d`` package; the others force one reader.

    Returns
    -------
    MarkerData
        Points in metres with NaN gaps; model outputs (POINT:ANGLES, FORCES, ...) left out.

    Raises
    ------
    C3DError
        The file is missing, empty, truncated, corrupt, has no markers or frames, or has
        units other than mm, cm or m.
    """
    path = Path(path)
    if backend not in _BACKENDS:
        raise ValueError(f"backend must be one of {_BACKENDS}, not {backend!r}")
    if not path.is_file():
        raise C3DError(path, "no such file" if not path.exists() else "not a regular file")
    layout = _layout(path)

    order = ["ezc3d", "c3d"] if backend == "auto" else [backend]
    reasons = []
    for name in order:
        if name == "ezc3d" and layout.processor == 86:
            reasons.append("ezc3d: big-endian (MIPS) files are not supported")
            continue
        if name == "ezc3d" and layout.ezc3d_problem:
            reasons.append(f"ezc3d: skipped, {layout.ezc3d_problem}")
            continue
        try:
            return _assemble(path, _read_isolated(path, name, layout), layout, name)
        except C3DError as exc:
            reasons.append(f"{name}: {exc.reason}")
        except MemoryError:
            reasons.append(f"{name}: out of memory")
        except Exception as exc:  # noqa: BLE001 - any backend failure becomes a C3DError
            msg = str(exc).split("\n")[0][:200] or type(exc).__name__
            reasons.append(f"{name}: {msg}")
    distinct = {r.split(": ", 1)[1] for r in reasons}
    if len(distinct) == 1:
        raise C3DError(path, distinct.pop())
    raise C3DError(path, "unreadable; " + "; ".join(reasons))


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------
def write_c3d(
    path: str | os.PathLike,
    points: np.ndarray,
    labels: Sequence[str],
    rate: float,
    *,
    units: str = "mm",
    prefix: str = "",
    first_frame: int = 1,
    descriptions: Sequence[str] | None = None,
    events: Iterable[tuple[str, float, str]] = (),
    overwrite: bool = False,
) -> Path:
    """Write marker trajectories to a float C3D file with ezc3d.

    The file is written to a temporary name in the same folder and then moved into place,
    so a reader never sees half a file.

    Parameters
    ----------
    path : str or PathLike
        Destination.
    points : array_like, shape (F, M, 3)
        Positions in metres; a NaN (or infinite) coordinate marks the point invalid
        (stored with residual -1).
    labels : sequence of str
        M unique marker names (ASCII, no surrounding spaces).
    rate : float
        Frame rate in Hz (stored as float32).
    units : {"mm", "cm", "m"}
        Length unit of the file.
    prefix : str
        Subject prefix written before each label (``"Sim"`` gives ``"Sim:label"``).
    first_frame : int
        Number of the first frame (1-based).
    descriptions : sequence of str, optional
        POINT:DESCRIPTIONS, one per marker.
    events : iterable of (label, time_s, context)
        Written to the EVENT group.
    overwrite : bool
        Replace an existing file; otherwise ``FileExistsError``.

    Returns
    -------
    Path
        The written file.
    """
    import ezc3d

    path = Path(path)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise C3DError(path, f"points must have shape (F, M, 3), got {pts.shape}")
    n_frames, n_markers = pts.shape[:2]
    if n_frames == 0 or n_markers == 0:
        raise C3DError(path, f"nothing to write: {n_frames} frames x {n_markers} markers")
    labels = [str(lab) for lab in labels]
    if len(labels) != n_markers:
        raise C3DError(path, f"{n_markers} markers but {len(labels)} labels")
    bad = [lab for lab in labels if not lab or lab != lab.strip() or not lab.isascii()]
    if bad:
        raise C3DError(path, f"labels must be non-empty ASCII without surrounding spaces: {bad[:3]}")
    if len(set(labels)) != n_markers:
        raise C3DError(path, "labels are not unique")
    if units not in UNIT_SCALE:
        raise C3DError(path, f"unsupported units {units!r} (expected mm, cm or m)")
    if not np.isfinite(rate) or rate <= 0:
        raise C3DError(path, f"rate must be positive, got {rate}")
    if not 1 <= int(first_frame) <= 65535:
        raise C3DError(path, f"first_frame must be in 1..65535, got {first_frame}")
    if descriptions is not None and len(descriptions) != n_markers:
        raise C3DError(path, f"{n_markers} markers but {len(descriptions)} descriptions")
    prefix = prefix.strip()
    if prefix and not prefix.endswith(":"):
        prefix += ":"
    if not overwrite and path.exists():
        raise FileExistsError(f"{path}: exists and is never overwritten")

    invalid = ~np.isfinite(pts).all(axis=2)                # (F, M)
    data = np.empty((4, n_markers, n_frames))
    data[:3] = (pts / UNIT_SCALE[units]).transpose(2, 1, 0)
    data[3] = 1.0
    data[:3, invalid.T] = 0.0
    residuals = np.where(invalid.T, -1.0, 0.0)[None]

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = np.array([float(rate)])
    c["parameters"]["POINT"]["LABELS"]["value"] = [prefix + lab for lab in labels]
    c.add_parameter("POINT", "UNITS", [units])
    if descriptions is not None:
        c.add_parameter("POINT", "DESCRIPTIONS", [str(d) for d in descriptions])
    c["header"]["points"]["first_frame"] = int(first_frame) - 1   # ezc3d counts from 0
    for label, time_s, context in events:
        c.add_event([0, float(time_s)], context=str(context), label=str(label))
    c["data"]["points"] = data
    c["data"]["meta_points"]["residuals"] = residuals

    from handmodel.fileio import atomic_path

    def reads_back(tmp: Path) -> None:
        # ezc3d reports no failed write (a full disk left a 16 KB file that segfaults readers):
        # the file is published only if it reads back whole.
        try:
            got = read_c3d(tmp)
        except C3DError as exc:
            raise OSError(errno.EIO, f"the written C3D file does not read back ({exc.reason})", str(path)) from None
        if (got.n_frames, got.n_markers) != (n_frames, n_markers):
            raise OSError(errno.EIO, f"the written C3D file reads back as {got.n_frames} frames × {got.n_markers} "
                                     f"markers, not {n_frames} × {n_markers}", str(path))

    with atomic_path(path, overwrite=overwrite, suffix=".tmp.c3d", verify=reads_back) as tmp:
        try:
            c.write(str(tmp))
        except Exception as exc:  # noqa: BLE001
            raise C3DError(path, f"ezc3d could not write the file: {exc}") from None
    return path


TASK_EVENT = "task:"


def task_from_events(data) -> str | None:
    """The task label a file carries as an event named ``task:<label>`` (written by our simulator
    and usable in any C3D editor), or None."""
    for label, _, _ in getattr(data, "events", []) or []:
        if str(label).lower().startswith(TASK_EVENT):
            return str(label)[len(TASK_EVENT):].strip() or None
    return None
