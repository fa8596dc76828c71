"""What the command modules share (:mod:`tracker.cli`, :mod:`tracker.track_cli`,
:mod:`tracker.sim.cli`): the progress bar, the check that no output replaces an input, the check that
a result file belongs to the recording given, and the
segmenter the ``--depth-range`` / ``--box`` / ``--forearm`` / ``--plane`` options describe. The
command modules import this one and never each other's helpers.
"""
from __future__ import annotations

from pathlib import Path


def progress_bar(label: str):
    """A progress bar on stderr labelled ``label`` (off when stderr is not a terminal)."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    console = Console(stderr=True)
    # off when stderr is not a terminal: a transient bar would still leave an empty line in logs
    return Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                    console=console, transient=True, disable=not console.is_terminal)


def check_not_inputs(inputs, outputs):
    """Refuse an output that is one of the command's inputs or lies inside an input folder (a
    recording): ``--overwrite`` replaces earlier outputs, never what the command reads.

    Parameters
    ----------
    inputs : paths the command reads (None entries are skipped)
    outputs : ``(option, path)`` pairs of what it writes (None paths are skipped)

    Raises
    ------
    TrackerError
        Naming the output, the option and the input.
    """
    import os

    from .errors import TrackerError

    # resolved, so a symbolic link or ``rec/../rec`` does not slip past; samefile catches a hard link
    ins = [(p, Path(p).resolve()) for p in inputs if p is not None]
    for option, out in outputs:
        if out is None:
            continue
        o = Path(out).resolve()
        for given, i in ins:
            if o == i or (o.exists() and i.exists() and os.path.samefile(o, i)):
                raise TrackerError(out, f"{option} is an input of this command ({given}); an output never "
                                        "replaces an input: write it elsewhere")
            if i.is_dir() and i in o.parents:
                raise TrackerError(out, f"{option} lies inside the input {given}; an output never goes into "
                                        "an input: write it elsewhere")


def check_same_recording(path, meta, recording, rec):
    """Refuse an output of tracker track (``path``, its header ``meta``) whose ``# recording:`` or
    ``# handedness:`` line names another recording than ``recording`` (opened: ``rec``).

    The recording is compared by its folder or file name, as typed paths differ between working
    folders; a header without these lines (an older file) is not checked, nor the handedness of a
    recording file (the file does not say which hand it shows). ``--no-check-recording`` skips this.

    Raises
    ------
    TrackerError
        Naming ``path``, both recordings and hands, and the option that overrides.
    """
    from .errors import TrackerError

    def name(p):
        p = Path(p)
        return p.name if p.name not in ("", ".", "..") else p.resolve().name

    tracked = meta.get("recording")
    if tracked and name(tracked) != name(recording):
        raise TrackerError(path, f"was tracked on recording {tracked}, not on {recording} (--no-check-recording "
                                 "uses it anyway)")
    hand = meta.get("handedness")
    if hand and getattr(rec, "times_s", None) is None and hand != rec.handedness:
        raise TrackerError(path, f"was tracked as a {hand} hand, {recording} is a {rec.handedness} hand "
                                 "(--no-check-recording uses it anyway)")


def segmenter_from_options(depth_range, box, forearm, plane):
    """The :class:`tracker.segment.Segmenter` of ``--depth-range``, ``--box``, ``--forearm`` and ``--plane``."""
    from .errors import TrackerError
    from .segment import FOREARM_CHOICES, PLANE_CHOICES, Segmenter

    kw = {}
    if depth_range is not None:
        near_far = floats(depth_range, "--depth-range", 2, "NEAR,FAR in metres, e.g. 0.3,0.9")
        if None in near_far or not 0 <= near_far[0] < near_far[1]:
            raise TrackerError("--depth-range", f"needs 0 ≤ NEAR < FAR (metres), got {depth_range!r}")
        metres("--depth-range", depth_range, near_far)
        kw.update(z_min=near_far[0], z_max=near_far[1])
    if box is not None:
        b = floats(box, "--box", 6, "X0,Y0,Z0,X1,Y1,Z1 in metres, e.g. -0.3,-0.3,0.3,0.3,0.3,0.9")
        if any(lo is not None and hi is not None and not lo < hi for lo, hi in zip(b[:3], b[3:])):
            raise TrackerError("--box", f"each lower bound must be below its upper bound, got {box!r}")
        metres("--box", box, b)
        kw.update(box_min=tuple(b[:3]), box_max=tuple(b[3:]))
    if forearm not in FOREARM_CHOICES:
        raise TrackerError("--forearm", f"must be {' or '.join(FOREARM_CHOICES)}, got {forearm!r}")
    if plane not in PLANE_CHOICES:
        raise TrackerError("--plane", f"must be {', '.join(PLANE_CHOICES[:-1])} or {PLANE_CHOICES[-1]}, got {plane!r}")
    return Segmenter(forearm=forearm, plane=plane, **kw)


# no depth camera sees a hand this far (m): a larger value is millimetres typed for metres
FARTHEST_M = 20.0


def metres(option, text, values):
    """Refuse ``values`` (metres, None = open) beyond :data:`FARTHEST_M`: millimetres typed for metres
    (``--depth-range 300,1000``) would look for the hand where no camera sees, and every frame would
    then be lost as if there were no hand."""
    from .errors import TrackerError

    far = [v for v in values if v is not None and abs(v) > FARTHEST_M]
    if far:
        mm = ",".join("" if v is None else f"{v / 1000:g}" for v in values)
        raise TrackerError(option, f"values are in metres: {text!r} reaches {max(abs(v) for v in far):g} m, beyond "
                                   f"any depth camera (if you meant millimetres: {mm})")


def floats(text, option, n, example):
    """``n`` comma-separated numbers (an empty entry is None)."""
    from .errors import TrackerError

    parts = [p.strip() for p in text.split(",")]
    if len(parts) != n:
        raise TrackerError(option, f"needs {n} comma-separated values ({example}), got {text!r}")
    try:
        values = [None if p == "" else float(p) for p in parts]
    except ValueError:
        raise TrackerError(option, f"needs numbers ({example}), got {text!r}") from None
    if any(v is not None and not finite(v) for v in values):
        raise TrackerError(option, f"needs finite numbers, got {text!r}")
    return values


def finite(v):
    return v == v and v not in (float("inf"), float("-inf"))
