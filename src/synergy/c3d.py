"""Read C3D marker trajectories (the writer: :mod:`synergy.c3d_write`).

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

The work is in three modules: :mod:`synergy.c3d_sections` (our bounded parse of the header and
parameter section), :mod:`synergy.c3d_native` (the two native readers, isolated in a worker
process) and this one (the public reader and the assembly of :class:`MarkerData`); the writer is
:mod:`synergy.c3d_write`.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np

from synergy.errors import C3DError

__all__ = ["MarkerData", "read_c3d", "strip_prefix", "UNIT_SCALE"]

#: Metres per length unit accepted in POINT:UNITS.
from synergy.c3d_native import C3D_PARAMETERS_FAILED, C3D_TRIAL_FIELDS, _read_isolated, _Raw, vague
from synergy.c3d_sections import _Layout, _layout

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
    n = len(secs) if used is None or not np.isfinite(used) else min(int(used), len(secs))
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

    # Truncated: fewer frames than every count the file announces, and a partial frame at
    # the end. A file ending exactly after its last whole frame is taken at its word
    # (Optotrak's sample announces 1149 frames and cleanly stores 29).
    claims = []
    if layout.last_frame >= layout.first_frame:
        claims.append(layout.last_frame - layout.first_frame + 1)
    if layout.frames_param and np.isfinite(layout.frames_param):  # as stored: ezc3d rewrites POINT:FRAMES
        claims.append(int(layout.frames_param))
    leftover = layout.size - layout.data_start - n_frames * raw.frame_bytes
    if claims and n_frames < min(claims) and leftover != 0:
        raise C3DError(path, f"truncated: {min(claims)} frames announced, {n_frames} whole frames "
                             f"stored and {leftover} bytes of a partial frame")
    if n_frames == 0:
        raise C3DError(path, "no frames stored")

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
            reasons.append(_BIG_ENDIAN)
            continue
        if name == "ezc3d" and layout.ezc3d_problem:
            reasons.append(layout.ezc3d_problem)
            continue
        try:
            return _assemble(path, _read_isolated(path, name, layout), layout, name)
        except C3DError as exc:
            reasons.append(exc.reason)
        except MemoryError:
            reasons.append("out of memory")
        except Exception:  # noqa: BLE001 - any failure becomes a C3DError, in our words
            reasons.append(C3D_PARAMETERS_FAILED)
    raise C3DError(path, _verdict(reasons, layout))


_BIG_ENDIAN = "big-endian (MIPS) files are not supported by the ezc3d reader"


def _verdict(reasons: list[str], layout: _Layout) -> str:
    """The one reason given for a file no backend read: what is wrong with the file, in our words.

    First a truncation (the sizes say so), then what the backends found; only when they said no
    more than "malformed", a header field the c3d package cannot take, what our own parse found
    wrong with the parameter section (when the c3d package could not parse it either), the c3d
    package's limit on TRIAL fields, the vaguest reason last. ezc3d's limit on MIPS files is never
    the reason while another exists.

    Examples
    --------
    >>> lay = _Layout(1024, 1024, 86, 1, 10, 3, None, None)
    >>> _verdict([_BIG_ENDIAN, "truncated: 10 frames announced"], lay)
    'truncated: 10 frames announced'
    >>> _verdict(["no point channels", "no POINT group in the parameter section"], lay)
    'unreadable: no point channels; no POINT group in the parameter section'
    >>> _verdict([_BIG_ENDIAN, C3D_PARAMETERS_FAILED], lay) == C3D_PARAMETERS_FAILED
    True
    """
    limits = {_BIG_ENDIAN, C3D_TRIAL_FIELDS, layout.repair_note}  # POINT:USED is repaired for the c3d package
    facts = list(dict.fromkeys(r for r in reasons if r not in limits and not vague(r)))
    for r in facts:
        if r.startswith("truncated"):
            return r
    if facts:
        return facts[0] if len(facts) == 1 else "unreadable: " + "; ".join(facts)
    if layout.header_fault:
        return layout.header_fault
    if C3D_PARAMETERS_FAILED in reasons and (layout.chain or layout.overlap):
        return f"corrupt parameter section: {layout.chain or layout.overlap}"
    return min(reasons, key=lambda r: (r == _BIG_ENDIAN, r != C3D_TRIAL_FIELDS, vague(r)))


TASK_EVENT = "task:"


def task_from_events(data) -> str | None:
    """The task label a file carries as an event named ``task:<label>`` (written by our simulator
    and usable in any C3D editor), or None."""
    for label, _, _ in getattr(data, "events", []) or []:
        if str(label).lower().startswith(TASK_EVENT):
            return str(label)[len(TASK_EVENT):].strip() or None
    return None
