"""The native C3D readers (ezc3d, then the ``c3d`` package), run isolated in a worker process.

Fuzzing the corpus showed ezc3d segfaulting on about 1 % of mutated files and spinning or
allocating gigabytes on others; the checks of :mod:`synergy.c3d_sections` cannot prove a file safe
for a C++ reader. A crash, a hang or a memory blow-up costs the worker, never the caller, and
becomes a :class:`~synergy.errors.C3DError` naming the file.
"""
from __future__ import annotations

import io
import json
import os
import re
import select
import signal
import subprocess
import sys
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from synergy.errors import C3DError

from synergy.c3d_sections import _Layout

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


#: What a backend failure says when the backend gave no reason of its own that we can name: the
#: file is malformed, and :func:`synergy.c3d.read_c3d` prefers any more specific reason.
C3D_PARAMETERS_FAILED = "corrupt parameter section (its entries cannot be followed)"
C3D_FRAMES_FAILED = "corrupt data section (its frames cannot be decoded)"
EZC3D_FAILED = "malformed (its sections cannot be followed to the end)"
#: A limit of the c3d package, not a fault of the file (read_c3d drops it when ezc3d says more).
C3D_TRIAL_FIELDS = ("TRIAL:ACTUAL_START_FIELD or ACTUAL_END_FIELD is not a plain pair of words, "
                    "which the c3d reader needs")


def vague(reason: str) -> int:
    """0 if a backend's reason says what is wrong with the file, else how little it says: the c3d
    package's parse failed (1), ezc3d's (2), a reader crashed or hung (3).

    Examples
    --------
    >>> vague("truncated: 3 frames announced"), vague(C3D_PARAMETERS_FAILED), vague(EZC3D_FAILED)
    (0, 1, 2)
    """
    if reason in (C3D_PARAMETERS_FAILED, C3D_FRAMES_FAILED):
        return 1
    if reason == EZC3D_FAILED:
        return 2
    return 3 if reason.endswith("(the file is malformed)") else 0


# py-c3d's consistency checks (Reader._check_metadata), as "inconsistent <what>! <a> header != <b> ...".
_C3D_CHECKS = (
    (r"inconsistent point count! (\S+) header != (\S+) POINT:USED",
     "the header says {0:.6g} points but POINT:USED says {1:.6g}"),
    (r"inconsistent scale factor! (\S+) header != (\S+) POINT:SCALE",
     "the header's scale factor {0:.6g} differs from POINT:SCALE {1:.6g}"),
    (r"inconsistent frame rate! (\S+) header != (\S+) POINT:RATE",
     "the header's frame rate {0:.6g} Hz differs from POINT:RATE {1:.6g} Hz"),
    (r"inconsistent analog rate! (\S+) header != (\S+) analog-fps / (\S+) point-fps",
     "the header's {0:.6g} analog samples per frame differ from ANALOG:RATE {1:.6g} / POINT:RATE {2:.6g}"),
    (r"inconsistent analog count! (\S+) header != (\S+) analog used \* (\S+) per-frame",
     "the header's {0:.6g} analog values per frame differ from ANALOG:USED {1:.6g} x {2:.6g} samples per frame"),
)


def _c3d_inconsistency(text: str) -> str:
    """py-c3d's failed consistency check in our words.

    Examples
    --------
    >>> _c3d_inconsistency("inconsistent point count! 14 header != 1806 POINT:USED")
    'the header says 14 points but POINT:USED says 1806'
    >>> _c3d_inconsistency("something else")
    'the header and the parameters disagree'
    """
    for pattern, words in _C3D_CHECKS:
        m = re.match(pattern, text)
        if m:
            try:
                return words.format(*(float(g) for g in m.groups()))
            except ValueError:
                break
    return "the header and the parameters disagree"


# ezc3d's C++ reasons that name a fault of the file, in our words; anything else is EZC3D_FAILED.
_EZC3D_REASONS = (
    (r"(\w+) parameter is not (?:a|an) (INT|FLOAT|BYTE|string)",
     lambda m: f"parameter {m[1]} is not stored as {_TYPES[m[2]]}"),
    (r"CHAR type cannot be converted to (INT|FLOAT)",
     lambda m: f"a parameter read as {_TYPES[m[1]]} is stored as text"),
    (r"(\w+) is not present in (\w+)", lambda m: f"parameter {m[2]}:{m[1]} is missing"),
    (r"RATIO or RATE must be present in (\w+)", lambda m: f"parameter {m[1]}:RATIO or {m[1]}:RATE is missing"),
    (r"Group::parameterIdx could not find (\S+)", lambda m: f"parameter {m[1]} is missing"),
    (r"Parameters::groupIdx could not find (\S+)", lambda m: f"group {m[1]} is missing"),
    (r"Could not read the processor type", lambda m: "unknown processor type in the parameter section"),
    (r"File must be a valid c3d file", lambda m: "not a C3D file"),
    (r"Data type (?:is not set|not implemented yet|not recognized)", lambda m: "a parameter has an unknown data type"),
    (r"bad_alloc", lambda m: "out of memory"),  # std::bad_alloc under the worker's memory limit
)
_TYPES = {"INT": "integers", "FLOAT": "floats", "BYTE": "bytes", "string": "text"}


def _ezc3d_reason(text: str) -> str:
    """ezc3d's exception text in our words.

    Examples
    --------
    >>> _ezc3d_reason("OFFSET parameter is not an INT")
    'parameter OFFSET is not stored as integers'
    >>> _ezc3d_reason("std::bad_alloc")
    'out of memory'
    >>> _ezc3d_reason("The format is not standard. If you want to ignore this error, set "
    ...               "ignoreBadFormatting to true: iostream error") == EZC3D_FAILED
    True
    """
    for pattern, words in _EZC3D_REASONS:
        m = re.search(pattern, text)
        if m:
            return words(m)
    return EZC3D_FAILED


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
        try:
            reader = c3d.Reader(fh)
        except AssertionError as exc:
            raise C3DError(path, _c3d_inconsistency(str(exc))) from None
        except KeyError as exc:
            dup = re.fullmatch(r"Parameter already exists with key (.*)", str(exc.args[0]) if exc.args else "")
            raise C3DError(path, f"corrupt parameter section: parameter {dup[1]} appears twice in its group" if dup
                           else C3D_PARAMETERS_FAILED) from None
        except (MemoryError, C3DError):
            raise
        except Exception:  # noqa: BLE001 - struct, Overflow, Value, Index errors of a section it misreads
            raise C3DError(path, C3D_PARAMETERS_FAILED) from None
        if reader.get("POINT:LABELS") is None and reader.get("POINT:USED") is None:
            raise C3DError(path, "no POINT group in the parameter section")
        try:  # read_frames starts from these; the package takes only 1-D TRIAL fields (ART's are [1, 2])
            reader.first_frame, reader.last_frame
        except (TypeError, ValueError, IndexError, AssertionError):
            raise C3DError(path, C3D_TRIAL_FIELDS) from None
        try:
            frames = [pts[:, :4].copy() for _, pts, _ in reader.read_frames(copy=False)]
        except MemoryError:
            raise
        except Exception:  # noqa: BLE001
            raise C3DError(path, C3D_FRAMES_FAILED) from None
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

        try:
            c = ezc3d.c3d(str(path))
        except MemoryError:
            raise
        except Exception as exc:  # noqa: BLE001 - C++ exceptions arrive as RuntimeError, OSError, ValueError, ...
            raise C3DError(path, _ezc3d_reason(str(exc))) from None
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
        except Exception:  # noqa: BLE001 - any backend failure is reported, not fatal
            doc = {"ok": False, "error": EZC3D_FAILED if req["backend"] == "ezc3d" else C3D_PARAMETERS_FAILED}
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
            [sys.executable, "-c", "from synergy.c3d_native import _worker_main; _worker_main()"],
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
