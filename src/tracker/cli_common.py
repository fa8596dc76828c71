"""What the command modules share (:mod:`tracker.cli`, :mod:`tracker.track_cli`, :mod:`tracker.live_cli`,
:mod:`tracker.eval_cli`, :mod:`tracker.sim.cli`): the progress bar, the check that no output replaces an
input, the check that a result file belongs to the recording given, the segmenter the ``--depth-range``
/ ``--box`` / ``--forearm`` / ``--plane`` options describe; and what ``tracker track``, ``live`` and
``calibrate`` share: those options and the recording's, the output checks, the hand model and the
:class:`tracker.settings.TrackerSettings` the options ask for. The command modules import this one and
never each other's helpers; it imports only typer at the top, so ``tracker --help`` stays fast.
"""
from __future__ import annotations

from pathlib import Path

import typer

# options that several commands take, written once (the same flag, default and help everywhere)
DEPTH_RANGE = typer.Option(None, "--depth-range", help="NEAR,FAR (m): look for the hand only in this depth range [0.2,1.5].")
BOX = typer.Option(None, "--box", help="X0,Y0,Z0,X1,Y1,Z1 (m, camera frame: x right, y down, z forward; an empty entry is open): look for the hand only in this box.")
FOREARM = typer.Option("cut", "--forearm", help="cut (remove the forearm beyond the wrist) or keep (a wristband or sleeve already ends the hand) [cut].")
PLANE = typer.Option("auto", "--plane", help="The frame's largest plane (a table, floor or wall): auto (left out of the hand's search when no colour frame is used; the skin test does it otherwise), cut (always) or keep [auto].")
HAND = typer.Option(None, "--hand", help="left or right: the hand tracked, overriding the recording's (a recording file does not say; then left).")
TOPIC = typer.Option(None, "--topic", help="Depth topic of a ROS bag [found in the file].")
COLOR_TOPIC = typer.Option(None, "--color-topic", help="Colour topic of a ROS bag [found in the file].")
START = typer.Option(None, "--start", help="Recording files: first frame time (s from the first depth frame).")


def progress_bar(label: str):
    """A progress bar on stderr labelled ``label`` (off when stderr is not a terminal)."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    console = Console(stderr=True)
    # off when stderr is not a terminal: a transient bar would still leave an empty line in logs
    return Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                    console=console, transient=True, disable=not console.is_terminal)


class StartUp:
    """A tracking command's start-up without Python's cyclic garbage collector: its imports, the kernels
    numba loads from its cache and the first frame (size calibration, start search) make ~200,000
    objects that all live to the end, and each of the collector's passes over them found nothing to
    free (0.28 s of a 2.4 s ``tracker track`` of one still, ``benchmarks/bench_startup.py``).

    A context manager: the collector is paused on entry; :meth:`done` (called once the first frame's
    result is in, again at will) or the exit turns it back on as it was. In the ``tracker`` program
    (:attr:`program`, set by :func:`tracker.cli.run_command`: the process ends with its command) the objects
    made so far are frozen first (``gc.freeze``), so the collections of the frames that follow skip
    them too; a command run inside a process that goes on (a test) leaves them to the collector."""

    #: the process is the ``tracker`` program's (:func:`tracker.cli.main`, :func:`tracker.cli.run_command`)
    program = False

    def __enter__(self):
        import gc

        self._paused = gc.isenabled()
        gc.disable()
        return self

    def done(self):
        """The start-up is over: the collector runs again (if it ran before)."""
        import gc

        if self._paused:
            self._paused = False
            if StartUp.program:
                gc.freeze()
            gc.enable()

    def __exit__(self, *exc):
        self.done()


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


def say_if_compiling():
    """One line on stderr when numba's cache holds no compiled kernels (a fresh install): this call
    compiles them first, which takes minutes."""
    from .compile import cold_message

    message = cold_message()
    if message:
        typer.echo(message, err=True)


def hand_side(hand):
    """``--hand`` checked: left, right or None (the recording's)."""
    from .errors import TrackerError

    if hand is not None and hand not in ("left", "right"):
        raise TrackerError("--hand", f"must be left or right, got {hand!r}")
    return hand


def chosen_hand_model(name, paper) -> str:
    """The ``--hand-model`` asked for, else the tracker's hand (:data:`tracker.TRACKING_HAND`), or the paper's
    with ``--paper`` (:data:`tracker.PAPER_HAND`)."""
    from . import PAPER_HAND, TRACKING_HAND

    return name if name is not None else (PAPER_HAND if paper else TRACKING_HAND)


def input_file(spec):
    """The file a ``--hand-model`` or ``--synergies`` value names, or None for a shipped name."""
    return Path(spec) if spec and Path(spec).is_file() else None


def check_outputs(output, keypoints, overlay, rerun, overwrite, folder=False, save_hand=None):
    """Every output is checked before the frames are tracked: a full or read-only disk, or a folder
    where a file goes, fails now and not after minutes of tracking."""
    from handmodel.fileio import check_output

    from .errors import TrackerError

    if folder:
        check_output(output, folder=True)
        return
    if save_hand is not None:
        check_hand_file(save_hand)
    for p in (output, keypoints, rerun, save_hand):
        if p is not None and p.exists() and not overwrite and not p.is_dir():
            raise TrackerError(p, "exists and is never overwritten (use --overwrite)")
        if p is not None:
            check_output(p, overwrite=overwrite)
    if rerun is not None and rerun.suffix.lower() != ".rrd":
        raise TrackerError(rerun, "a Rerun recording must end in .rrd")
    if overlay is not None:
        check_output(overlay, folder=True)
        if not overwrite and overlay.is_dir() and any(overlay.glob("overlay_*.png")):
            raise TrackerError(overlay, "holds overlay PNGs already, never overwritten (use --overwrite)")
    outs = [p for p in (output, keypoints, overlay, rerun, save_hand) if p is not None]
    if len(set(outs)) < len(outs):
        raise TrackerError("track", "-o, --keypoints, --overlay, --rerun and --save-hand need different paths")


def check_hand_file(path):
    """A hand file must end in .yaml or .yml: --hand-model reads any other name as a shipped model's."""
    from .errors import TrackerError

    if path.suffix.lower() not in (".yaml", ".yml"):
        raise TrackerError(path, "a hand file must end in .yaml or .yml (--hand-model takes it back by that)")


#: The option of each settings field the command line sets: a settings error names the option.
OPTION_OF = {"mode": "--mode", "subspace.variance": "--variance", "subspace.n_pcs": "--pcs",
             "scale.hand_scale": "--hand-scale", "refine.unseen_prior": "--unseen-prior",
             "loss.no_hand_rejected": "--no-hand-rejected", "observe.stride": "--stride",
             "start.search_budget_ms": "--search-budget-ms", "start.detector": "--detector",
             "start.detector_accept_mm": "--detector-accept-mm", "start.presence": "--presence",
             "scale.refine": "--size-refine"}


def settings_from_options(paper, mode, pcs, variance, stride, smooth, points, icp, gn, damping, model, silhouette,
                          prediction, robust, finger_search, projected_steps, hand_scale, check_hand, *,
                          rgb_seed=False, finger_lengths=None, safety_net=None, unseen_prior=None, no_hand=None,
                          threads=None, search_budget_ms=None, detector=None,
                          detector_accept_mm=None, no_detector=False, presence=None, no_presence=False,
                          size_refine=None, keypoint_term=None):
    """The :class:`tracker.settings.TrackerSettings` of the command line: the default or the paper's,
    with every option given replacing its value, checked (:func:`checked_settings`)."""
    from .errors import TrackerError
    from .settings import TrackerSettings

    if pcs and variance is not None:  # one of them decides the PCs: the other would be ignored silently
        raise TrackerError("--pcs", f"give --pcs or --variance, not both (got {pcs} and {variance})")
    if no_detector:
        if detector or presence:
            given = f"--detector {detector}" if detector else f"--presence {presence}"
            raise TrackerError("--no-detector", f"give {given.split()[0]} or --no-detector, not both (got {given})")
        # no learned part at all: neither the keypoint CNN nor the hand-presence network
        detector, presence = "", ""
    if no_presence:
        if presence:
            raise TrackerError("--no-presence", f"give --presence or --no-presence, not both (got --presence {presence})")
        presence = ""
    groups = {
        "observe": dict(stride=stride, smooth=smooth, target_points=points or None),
        "icp": dict(icp_iterations=icp, gn_iterations=gn, damping=damping, silhouette_weight=silhouette,
                    robust_mm=robust, projected_steps=projected_steps),
        "correspond": dict(model=model), "predict": dict(share=prediction),
        "init": dict(finger_search=finger_search, threads=threads),
        "scale": dict(hand_scale=parse_hand_scale(hand_scale), finger_lengths=finger_lengths, refine=size_refine),
        "start": dict(check_hand=check_hand, rgb_seed=rgb_seed, search_budget_ms=search_budget_ms, detector=detector,
                      detector_accept_mm=detector_accept_mm, presence=presence),
        "net": dict(enabled=safety_net),
        "refine": dict(unseen_prior=unseen_prior), "loss": dict(no_hand_rejected=no_hand),
    }
    # an option not given keeps the default's value (the paper's with --paper); --points 0: all points (None)
    given = {g: {k: v for k, v in kv.items() if v is not None or (k == "target_points" and points == 0)}
             for g, kv in groups.items()}
    given["subspace"] = dict(n_pcs=pcs, variance=None if pcs else (0.99 if variance is None else variance))
    if keypoint_term is not None:
        given["refine"]["keypoints"] = dict(on=keypoint_term)
    base = TrackerSettings.paper() if paper else TrackerSettings()
    return checked_settings(base.replace(mode=mode, **given))


def checked_settings(settings):
    """``settings`` after ``settings.check()``, whose error names the command-line option of the field
    (before the synergy bundle a mode needs is loaded: a typo must not read as a missing --synergies)."""
    from .errors import TrackerError

    try:
        settings.check()
    except TrackerError as e:
        raise TrackerError(OPTION_OF.get(e.where, e.where), e.reason) from None
    return settings


def check_overlay_every(overlay_every):
    """Refuse an ``--overlay-every`` below 1 (0 drew every frame, as 1 does, without a word)."""
    from .errors import TrackerError

    if overlay_every < 1:
        raise TrackerError("--overlay-every", f"must be ≥ 1 (1 = every frame), got {overlay_every}")


def parse_hand_scale(text):
    """``--hand-scale``: "auto" or a factor, checked by :meth:`tracker.settings.ScaleSettings.check`
    (within the sizes "auto" searches: 0.05 tracked nothing and blamed the segmentation); None when
    not given."""
    from .errors import TrackerError
    from .settings import ScaleSettings

    if text is None:
        return None
    if text.strip().lower() == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        lo, hi = ScaleSettings().range
        raise TrackerError("--hand-scale", f"must be 'auto' or a factor in {lo:g}–{hi:g} (the hand model's size × "
                                           f"it), got {text!r}") from None
    checked_settings(ScaleSettings(hand_scale=value))
    return value
