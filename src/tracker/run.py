"""Pipeline stage ``run``: a tracker over a whole recording, and the tracking-output file.

The tracking output is a CSV with ``# key: value`` header lines (recording, mode, synergies, PCs,
settings, hand model and its hash, units), then one row per frame: ``frame, time_s, status, fit_mm,
points_used, points, ms`` and the 26 DoF columns (metres, radians). :func:`write_tracking` and :func:`read_tracking` are its one writer and
reader (``tracker track`` writes it; ``tracker eval``, the experiments and users read it);
:func:`write_keypoints` and :func:`read_keypoints` those of the keypoints CSV (``tracker track
--keypoints``, read by ``tracker show --keypoints``).

>>> import io, numpy as np, pandas as pd
>>> df = pd.DataFrame([[0, 0.0, "reinit", 1.5, 300, 310, 20.0] + [0.0] * 26],
...                   columns=list(FRAME_COLUMNS) + list(DOF_NAMES))
>>> text = tracking_csv(df, {"mode": "full", "units": "metres, radians"})
>>> back, meta = parse_tracking(io.StringIO(text), "example.csv")
>>> meta["mode"], back["status"].tolist()
('full', ['reinit'])
"""
from __future__ import annotations

import io
import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from handmodel.cliutil import error_line
from handmodel.dofs import DOF_NAMES
from handmodel.errors import ToolkitError
from handmodel.fileio import atomic_write_text
from handmodel.model import HandModel

from . import TRACKING_HAND
from .errors import TrackerError
from .observe import observe
from .io.recording import Recording
from .scale import calibrated_hand, shaped_hand
from .track import FrameTracker, TrackerSettings

FRAME_COLUMNS = ("frame", "time_s", "status", "fit_mm", "points_used", "points", "ms")
#: A frame's status: followed from the last frame, lost (no hand), found by a fresh search, or — in
#: real time only (:func:`track_realtime`) — predicted (its fit was pending: the last fit moved on)
STATUSES = ("tracked", "lost", "reinit", "predicted")


def observe_frame(tracker, frame, camera, segmenter=None, *, window=True):
    """The tracker's :func:`tracker.observe.observe` of one recorded ``frame`` (in the hand's predicted
    window unless ``window`` is False: :meth:`FrameTracker.segment_window`), or None when the frame has
    no usable depth image (missing, wrong size). ``tracker track``, ``tracker calibrate`` and
    ``tracker live`` observe their frames through it, so the same frames give the same hand."""
    depth = frame.depth
    if depth is None or np.ndim(depth) != 2 or np.shape(depth) != (camera.height, camera.width):
        return None
    return observe(depth, camera, tracker.settings.observe, segmenter=segmenter, color=frame.color,
                   window=tracker.segment_window(camera) if window else None)


def track_recording(recording, tracker, on_frame=None, *, segmenter=None) -> pd.DataFrame:
    """Track every frame of ``recording`` (anything with ``camera`` that iterates frames with
    ``index``, ``time_s``, ``depth`` in metres and ``color``) with ``tracker`` (:class:`FrameTracker`).

    A frame without a usable depth image (missing, wrong size, or a folder recording's file that
    cannot be read: :meth:`tracker.io.recording.Recording.frames_or_problems`, the frame's ``problem``) is
    tracked as empty, so it is lost. ``on_frame(frame, result, observation)`` is called after each frame
    (``observation`` None for an unusable one): progress, overlays, keypoints. Returns one row per frame
    (:data:`FRAME_COLUMNS` and the hand's DoF names)."""
    cam = recording.camera
    rows = []
    frames = recording.frames_or_problems() if hasattr(recording, "frames_or_problems") else recording
    for frame in frames:
        ob = observe_frame(tracker, frame, cam, segmenter)
        r = tracker.step(np.zeros((0, 3))) if ob is None else tracker.track(ob, cam, color=frame.color)
        rows.append((frame.index, frame.time_s, r.status, r.fit_mm, r.points_used,
                     0 if ob is None else len(ob.points), r.ms, *r.theta))
        if on_frame is not None:
            on_frame(frame, r, ob)
    return pd.DataFrame(rows, columns=[*FRAME_COLUMNS, *tracker.hand.dof_names])


def track_realtime(recording, tracker, budget_ms, on_frame=None, *, segmenter=None, pace: bool = False,
                   dropped=None) -> pd.DataFrame:
    """:func:`track_recording` in real time: each frame is observed and fitted on a worker thread
    (:class:`tracker.realtime.FrameBudget`, or the one given as ``budget_ms``) and waited for at most
    ``budget_ms``; a frame whose fit
    overruns, or that comes while the worker is still on an earlier one, gets the last fit moved on
    (:func:`tracker.realtime.predicted_theta`, status ``"predicted"``, no points, ``observation`` None
    for ``on_frame``). With ``pace`` the frames come at the recording's own rate
    (:func:`tracker.realtime.paced`; the late ones dropped and listed in ``dropped``), as from a sensor.
    The rows are what was published, frame by frame, as a live user saw them."""
    from .realtime import FrameBudget, paced, predicted_theta
    from .track import FrameResult

    cam = recording.camera
    frames = recording.frames_or_problems() if hasattr(recording, "frames_or_problems") else recording
    if pace:
        frames = paced(frames, recording.fps, dropped=dropped)

    def fit(frame):
        ob = observe_frame(tracker, frame, cam, segmenter)
        r = tracker.step(np.zeros((0, 3))) if ob is None else tracker.track(ob, cam, color=frame.color)
        # a late fit counts too: the frames after it are predicted from it
        fitted[:] = [*fitted[-1:], r.theta]
        return r, ob

    # a FrameBudget given is used as it is (its budget may be changed between frames)
    budget = budget_ms if isinstance(budget_ms, FrameBudget) else FrameBudget(budget_ms)
    rows, fitted = [], []
    try:
        for frame in frames:
            t0 = time.perf_counter()
            done = budget(fit, frame)
            if done is not None:
                r, ob = done
            else:
                ob, seen = None, list(fitted)  # a copy: the worker may be replacing it
                last = seen[-1] if seen else None
                found = last is not None and np.all(np.isfinite(last))
                theta = (predicted_theta(last, seen[0] if len(seen) == 2 else None) if found
                         else np.full(tracker.hand.n_dofs, np.nan))
                r = FrameResult(theta, "predicted" if found else "lost", float("nan"), 0, 0,
                                (time.perf_counter() - t0) * 1000.0)
            rows.append((frame.index, frame.time_s, r.status, r.fit_mm, r.points_used,
                         0 if ob is None else len(ob.points), r.ms, *r.theta))
            if on_frame is not None:
                on_frame(frame, r, ob)
        budget.wait()  # the last fit ends before the tracker's state is read (size, hand check)
    finally:
        budget.close()
    return pd.DataFrame(rows, columns=[*FRAME_COLUMNS, *tracker.hand.dof_names])


def tracking_metadata(recording_path, tracker, synergies_spec="", synergies_file="") -> dict:
    """The header of a tracking output: what was tracked, how, with which hand model and which synergy
    bundle (``synergies_file``: the bundle file read, since one name@version may be in two registries)."""
    # the model file's identity (a resized hand is that file plus hand_scale)
    st, hand = tracker.settings, getattr(tracker, "base_hand", tracker.hand)
    return {"recording": str(recording_path), "mode": st.mode, "synergies": synergies_spec or "",
            "synergies_file": str(synergies_file or ""),
            "pcs": "" if tracker.n_pcs is None else str(tracker.n_pcs), "stride": str(st.observe.stride),
            "icp": str(st.icp.icp_iterations), "gn": str(st.icp.gn_iterations), "model": st.correspond.model,
            "hand_model": f"{hand.name} {hand.sha256}", "handedness": hand.handedness,
            "hand_model_file": str(hand.path), "hand_calibration": _calibration_text(hand),
            "hand_scale": _scale_text(tracker), "hand_shape": _shape_text(tracker),
            "hand_check": str(getattr(tracker, "hand_check_", None) or ""), "units": "metres, radians"}


def _calibration_text(hand) -> str:
    """For a calibrated hand file (:meth:`handmodel.HandModel.save` of :func:`tracker.scale.calibrated_hand`):
    where its hand came from, so the header says the size is in the file, not in ``hand_scale``."""
    cal = getattr(hand, "calibration", None)
    if not cal:
        return ""
    base = hand.provenance.get("base_model") or {}
    fingers = cal.get("finger_lengths")
    tail = f", finger lengths {', '.join(f'{k} {v:.3f}' for k, v in fingers.items())}" if fingers else ""
    return (f"this file's hand: size {cal.get('hand_scale')} × {base.get('name')} {base.get('sha256')}{tail}, "
            f"calibrated on {cal.get('recording')}")


def _scale_text(tracker) -> str:
    """The hand size tracked with (a factor on the hand model), how it was set, and an automatic
    calibration's per-frame estimates: ``--hand-scale`` takes the number back."""
    scale = getattr(tracker, "scale_", None)
    if scale is None:
        return ""
    est = getattr(tracker, "scale_estimates_", [])
    fingers = getattr(tracker, "finger_scales_", None)
    # per-finger length factors (finger_lengths) follow the size, in the hand model's finger order
    tail = f"; finger lengths {', '.join(f'{k} {v:.3f}' for k, v in fingers.items())}" if fingers else ""
    if tracker.settings.scale.hand_scale != "auto":
        given = "the hand file's calibrated hand as it is" if getattr(tracker.base_hand, "calibration", None) else "given"
        return f"{scale:.4f} ({given}){tail}"
    return f"{scale:.4f} (auto, median of {', '.join(f'{e:.4f}' for e in est)}){tail}"


def _shape_text(tracker) -> str:
    """The tracked hand's shape on the header's model as JSON (``{"scale": s, "fingers": {name: factor}}``),
    for :func:`tracked_hand` to rebuild it; empty when the model was tracked as it is."""
    scale = getattr(tracker, "scale_", None)
    if scale is None:
        return ""
    fingers = getattr(tracker, "finger_scales_", None) or {}
    return json.dumps({"scale": float(scale), "fingers": {k: float(v) for k, v in fingers.items()}})


def tracked_hand(meta, where="tracking output") -> HandModel:
    """The hand a tracking output was tracked with, rebuilt from its header (``meta``): the model file
    it names (its SHA-256 checked), in the handedness tracked, resized by ``hand_shape`` — so its
    keypoints are the ones the tracker fitted (the default model for an output without these keys).

    Raises
    ------
    TrackerError
        Naming ``where``: the model file is gone or changed, or ``hand_shape`` is not readable.
    """
    name, _, sha = str(meta.get("hand_model", "default")).partition(" ")
    source = meta.get("hand_model_file") or name or "default"
    try:
        hand = HandModel.load(source, right=meta.get("handedness") == "right")
    except ToolkitError as exc:
        raise TrackerError(where, f"its hand model {source} cannot be loaded ({error_line(exc).removeprefix('error: ')})") from None
    if sha and hand.sha256 != sha:
        raise TrackerError(where, f"was tracked with hand model {name} {sha[:12]}…, but {source} is now "
                                  f"{hand.sha256[:12]}… (changed since)")
    text = meta.get("hand_shape") or ""
    if not text:
        return hand
    try:
        shape = json.loads(text)
        return shaped_hand(hand, float(shape["scale"]), {str(k): float(v) for k, v in shape.get("fingers", {}).items()})
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise TrackerError(where, f"hand_shape in its header is not readable ({exc})") from None


def tracking_csv(df, meta) -> str:
    """The tracking output's text: ``# key: value`` lines, then the table."""
    head = "".join(f"# {k}: {v}\n" for k, v in meta.items())
    return head + df.to_csv(index=False, float_format="%.9g")


def write_tracking(path, df, meta, *, overwrite=False) -> Path:
    """Write a tracking output atomically (never over an existing file unless ``overwrite``)."""
    _check_table(df, path)
    return atomic_write_text(path, tracking_csv(df, meta), overwrite=overwrite)


def _split_header(stream):
    """``(metadata, table lines)`` of a text stream whose ``# key: value`` lines are its header."""
    meta = {}
    lines = []
    for line in stream:
        if line.startswith("#"):
            k, sep, v = line[1:].partition(":")
            if sep:
                meta[k.strip()] = v.strip()
        else:
            lines.append(line)
    return meta, lines


def parse_tracking(stream, where):
    """``(table, metadata)`` of a tracking output read from a text stream; ``where`` names it in errors."""
    meta, lines = _split_header(stream)
    try:
        df = pd.read_csv(io.StringIO("".join(lines)))
    except (ValueError, pd.errors.ParserError) as exc:
        raise TrackerError(where, f"cannot read tracking output ({exc})") from None
    _check_table(df, where)
    return df, meta


def read_tracking(path):
    """``(table, metadata)`` of a tracking output file (see :func:`write_tracking`)."""
    try:
        with open(path, encoding="utf-8") as f:
            return parse_tracking(f, path)
    except UnicodeDecodeError:
        raise TrackerError(path, "not a tracking output (not UTF-8 text)") from None


def _check_table(df, where):
    missing = [c for c in (*FRAME_COLUMNS, *DOF_NAMES) if c not in df.columns]
    if missing:
        raise TrackerError(where, f"not a tracking output: missing columns {', '.join(missing)}")
    bad = sorted(set(df["status"].astype(str)) - set(STATUSES))
    if bad:
        raise TrackerError(where, f"unknown status {', '.join(bad)} (expected {', '.join(STATUSES)})")


def keypoints_table(hand, df) -> pd.DataFrame:
    """The 21 keypoints of every tracked frame in mm (NaN where θ is not finite), one row per frame."""
    th = df[list(hand.dof_names)].to_numpy(float)
    kps = np.full((len(th), hand.n_nodes * 3), np.nan)
    ok = np.isfinite(th).all(1)
    if ok.any():
        kps[ok] = hand.keypoints(th[ok]).reshape(int(ok.sum()), -1) * 1000.0
    kd = pd.DataFrame(kps, columns=[f"{n}_{a}_mm" for n in hand.keypoint_names for a in "xyz"])
    kd.insert(0, "frame", df["frame"].to_numpy())
    return kd


#: Header keys of a keypoints CSV: the tracking output's, so ``tracker show`` can tell keypoints of
#: another recording (a file without them, written before they were, is read as it is).
KEYPOINTS_HEADER = ("recording", "handedness")


def write_keypoints(path, hand, df, meta, *, overwrite=False) -> Path:
    """Write the keypoints CSV of a tracking (:func:`keypoints_table` of ``df`` on ``hand``) atomically,
    after ``# recording:`` and ``# handedness:`` lines taken from its header ``meta``; it is never written
    over an existing file unless ``overwrite``. :func:`read_keypoints` reads it."""
    head = "".join(f"# {k}: {meta[k]}\n" for k in KEYPOINTS_HEADER if k in meta)
    return atomic_write_text(path, head + keypoints_table(hand, df).to_csv(index=False, float_format="%.4f"),
                             overwrite=overwrite)


def read_keypoints(path, names):
    """``(table, metadata)`` of a keypoints CSV of :func:`write_keypoints` (its header may be absent),
    whose keypoints must include ``names``.

    Raises
    ------
    TrackerError
        Naming ``path``: not readable, or not a keypoints CSV (the first missing columns).
    """
    try:
        with open(path, encoding="utf-8") as f:
            meta, lines = _split_header(f)
        df = pd.read_csv(io.StringIO("".join(lines)))
    except (OSError, ValueError, pd.errors.ParserError) as exc:  # UnicodeDecodeError is a ValueError
        raise TrackerError(path, f"cannot read a keypoints CSV ({type(exc).__name__}: {exc})") from None
    cols = [f"{k}_{a}_mm" for k in names for a in "xyz"]
    missing = [c for c in ["frame", *cols] if c not in df.columns]
    if missing:
        raise TrackerError(path, f"not a keypoints CSV of tracker track (missing {', '.join(missing[:3])}"
                                 f"{' …' if len(missing) > 3 else ''})")
    return df, meta


# ----------------------------------------------------------------------------- one run, many runs
@dataclass(frozen=True)
class TrackJob:
    """One recording to track and where its outputs go, as plain picklable values (a Dask task or
    another process runs it the same way as this one).

    Parameters
    ----------
    recording : the recording (a folder, or a file :class:`tracker.io.recording.Recording` opens)
    output : the tracking output CSV
    settings : :class:`tracker.track.TrackerSettings`
    synergies, registries : the synergy bundle spec and extra registry folders (None: full mode only)
    hand_model : hand model name or YAML path (mirrored for a right-handed recording; :data:`tracker.TRACKING_HAND`
        when not given)
    segmenter : :class:`tracker.segment.Segmenter` (None: its defaults)
    keypoints, overlay, overlay_every : the keypoints CSV, the overlay PNG folder and its frame step
    rerun, rerun_spawn : the Rerun ``.rrd`` to write, and whether to stream to a spawned viewer
    overwrite : replace existing outputs
    handedness : the hand tracked when the source does not say (a live camera)
    hand : ``left``/``right`` overriding what the recording says (a recording file says nothing)
    topic, color_topic : depth and colour topics of a ROS bag (None: found in the file)
    start_s, end_s, every : a recording file's frames from ``start_s`` to ``end_s`` (s of file time),
        every ``every``-th
    save_hand : write the hand calibrated in this run to this YAML file (:func:`tracker.scale.calibrated_hand`)
    budget_ms, pace : real time (:func:`track_realtime`): each fit waited for at most ``budget_ms`` (None:
        every frame fitted in turn), the frames paced at the recording's rate
    hand_scale_asked : ``settings.scale.hand_scale`` was asked for (``--hand-scale``). A calibrated hand file
        (``hand_model``) is tracked as it is (size 1) unless ``"auto"`` was asked, which estimates the
        size again on it; a number other than 1 with such a file is refused (it would scale the
        calibrated hand a second time)
    """

    recording: str
    output: str
    settings: TrackerSettings = field(default_factory=TrackerSettings)
    synergies: str | None = None
    registries: tuple = ()
    hand_model: str = TRACKING_HAND
    segmenter: object = None
    keypoints: str | None = None
    overlay: str | None = None
    overlay_every: int = 10
    rerun: str | None = None
    rerun_spawn: bool = False
    overwrite: bool = False
    handedness: str = "left"
    hand: str | None = None
    topic: str | None = None
    color_topic: str | None = None
    start_s: float | None = None
    end_s: float | None = None
    every: int = 1
    save_hand: str | None = None
    hand_scale_asked: bool = False
    budget_ms: float | None = None
    pace: bool = False


def open_job_recording(job: TrackJob):
    """The recording of ``job`` as its options ask: handedness, topics, and for a recording file the
    time range and frame step (a folder refuses them: its frames are already chosen)."""
    rec = Recording.open(job.recording, topic=job.topic, color_topic=job.color_topic, handedness=job.hand)
    if job.start_s is not None or job.end_s is not None or job.every != 1:
        if not hasattr(rec, "select"):
            raise TrackerError(job.recording, "--start, --end and --every are for recording files (.bag, .db3, .mcap, .mkv)")
        rec = rec.select(start_s=job.start_s, end_s=job.end_s, every=job.every)
    return rec


@dataclass
class TrackRun:
    """What :func:`run_job` did: the table and header written, the tracker (its hand size and
    handedness check), the recording, the wall time, the overlay frames written, the Rerun file and
    warnings (a spawned viewer that went away); ``unreadable``: why frames could not be read (each
    tracked as lost, the outputs written all the same)."""

    df: pd.DataFrame
    meta: dict
    tracker: FrameTracker
    recording: object
    wall_s: float
    overlays: list
    rerun: Path | None = None
    warnings: list = field(default_factory=list)
    unreadable: list = field(default_factory=list)  # the problems of frames whose files could not be read
    dropped: list = field(default_factory=list)  # real time, paced: the frames the loop was too late for


def run_job(job: TrackJob, on_frame=None, *, source=None) -> TrackRun:
    """Track ``job.recording`` (or ``source``, an open recording-like source such as a live camera)
    and write its outputs: the tracking CSV, optional keypoints, overlays and Rerun file.

    ``on_frame(frame, result, observation)`` is called after each frame, after the overlay and
    viewer have had it. Outputs are written only after the last frame, each atomically."""
    rec = source if source is not None else open_job_recording(job)
    if job.settings.mode != "full" and not job.synergies:
        raise TrackerError("--synergies", f"mode {job.settings.mode!r} needs a synergy bundle")
    bundle = _bundle(job)
    handedness = getattr(rec, "handedness", None) or job.handedness
    hand = HandModel.load(job.hand_model, right=handedness == "right")
    settings = settings_for_hand(hand, job.settings, job.hand_scale_asked)
    if job.save_hand is not None and settings.scale.hand_scale != "auto":
        raise TrackerError(job.save_hand, "nothing to save: this run does not calibrate the hand (its size is "
                                          f"{'in the hand file' if hand.calibration else 'given'}; "
                                          "--hand-scale auto estimates it)")
    tracker = FrameTracker(hand, settings, synergies=bundle)
    cam = rec.camera
    overlay = None if job.overlay is None else Path(job.overlay)
    if overlay is not None:
        # matplotlib loads only for overlays: a tracking run without them starts ~0.3 s sooner
        from .plots import overlay_png
    viewer = None
    if job.rerun is not None or job.rerun_spawn:
        from .viewer import RerunLog  # an optional extra ([viz]): loaded only when asked for

        viewer = RerunLog(cam, job.rerun, spawn=job.rerun_spawn, overwrite=job.overwrite,
                          name=f"tracker {Path(str(job.recording)).name}")
    written, unreadable, dropped = [], [], []
    calibration_frames, settled = [], [False]

    def each(frame, r, ob):
        if getattr(frame, "problem", ""):
            unreadable.append(frame.problem)
        if job.save_hand is not None and not settled[0]:
            # the frames tracked until the size was settled, this one included
            calibration_frames.append(frame.index)
            settled[0] = calibration_done(tracker)
        if overlay is not None and ob is not None and frame.index % max(job.overlay_every, 1) == 0:
            # the title says which frame and how well it fits, so an overlay is judged on its own
            fit = f", fit {r.fit_mm:.1f} mm" if np.isfinite(r.fit_mm) else ""
            overlay_png(overlay / overlay_name(frame.index), frame.depth, cam, tracker.hand, r.theta,
                        f"frame {frame.index} ({frame.time_s:.2f} s): {r.status}{fit}", mask=ob.mask)
            written.append(frame.index)
        if viewer is not None:
            viewer.log_frame(frame, r, ob, tracker.hand)
        if on_frame is not None:
            on_frame(frame, r, ob)

    t_start = time.perf_counter()
    try:
        if job.budget_ms is None:
            df = track_recording(rec, tracker, each, segmenter=job.segmenter)
        else:
            df = track_realtime(rec, tracker, job.budget_ms, each, segmenter=job.segmenter, pace=job.pace,
                                dropped=dropped)
    except BaseException:
        if viewer is not None:
            viewer.abort()
        raise
    wall_s = time.perf_counter() - t_start
    meta = tracking_metadata(job.recording, tracker, bundle.spec if bundle else "", bundle.path if bundle else "")
    try:
        # without overwrite a file that appeared while tracking is not replaced either
        write_tracking(job.output, df, meta, overwrite=job.overwrite)
        if job.save_hand is not None:
            calibrated_hand(tracker, recording=job.recording, frames=calibration_frames).save(
                job.save_hand, overwrite=job.overwrite)
        if job.keypoints is not None:
            write_keypoints(job.keypoints, tracker.hand, df, meta, overwrite=job.overwrite)
        if overlay is not None and job.overwrite:
            # an earlier run's overlays of other frames would pass for this run's (its settings, its fits)
            stale_overlays(overlay, written)
    except BaseException:
        if viewer is not None:
            viewer.abort()
        raise
    rrd = viewer.close() if viewer is not None else None
    warnings = [viewer.warning_] if viewer is not None and viewer.warning_ else []
    return TrackRun(df, meta, tracker, rec, wall_s, written, rrd, warnings, unreadable, dropped)


def overlay_name(index: int) -> str:
    """The file name of frame ``index``'s overlay PNG."""
    return f"overlay_{index:06d}.png"


def stale_overlays(folder, written) -> list[Path]:
    """Remove the overlay PNGs (:func:`overlay_name`) in ``folder`` of frames not in ``written`` (an
    earlier run's, left by ``--overwrite``); returns them. Other files are left alone."""
    keep = {overlay_name(i) for i in written}
    gone = [p for p in sorted(Path(folder).glob("overlay_*.png"))
            if p.name not in keep and p.stem[8:].isdigit() and p.name == overlay_name(int(p.stem[8:])) and p.is_file()]
    for p in gone:
        p.unlink()
    return gone


def settings_for_hand(hand, settings, hand_scale_asked=False):
    """The settings to track ``hand`` with: a calibrated hand file (``hand.calibration``) is tracked
    at size 1 — its size and finger lengths are in the file — unless ``hand_scale_asked`` and
    ``"auto"`` (estimate again on the file's hand). A size other than 1 asked for with such a file is
    refused: it would scale the calibrated hand a second time (the number a calibrating run printed is
    already in the file)."""
    cal = getattr(hand, "calibration", None)
    if not cal:
        return settings
    if hand_scale_asked and settings.scale.hand_scale != "auto":
        if float(settings.scale.hand_scale) != 1.0:
            raise TrackerError(hand.path, f"is a calibrated hand (size {cal.get('hand_scale')} already in it): "
                                          f"--hand-scale {settings.scale.hand_scale:g} would scale it again; leave "
                                          "--hand-scale out to track on it as it is, or give --hand-scale auto "
                                          "to estimate the size again on it")
        return settings
    if hand_scale_asked:
        return settings
    return settings.replace(scale=dict(hand_scale=1.0))


def calibration_done(tracker) -> bool:
    """Whether ``tracker``'s automatic size (and, with ``finger_lengths``, the finger lengths) is
    settled: the estimates of ``scale.frames`` frames are in."""
    st = tracker.settings.scale
    if st.hand_scale != "auto" or tracker.scale_ is None:
        return st.hand_scale != "auto"
    done = len(tracker.scale_estimates_) >= st.frames
    return done and (not st.finger_lengths or tracker.finger_scales_ is not None)


def calibrate_job(job: TrackJob, output, *, max_frames=60, on_frame=None, each=False):
    """``tracker calibrate``: track ``job.recording``'s first frames only until the hand's size (and
    finger lengths) is settled (:func:`calibration_done`, at most ``max_frames`` frames), then write
    the calibrated hand to ``output`` (:func:`tracker.scale.calibrated_hand`, never over an existing
    file unless ``job.overwrite``). Returns ``(hand, tracker, frames)``: the hand written, the tracker
    and the frame indices tracked. A recording that ends first, or in which no frame could be
    calibrated, is refused when there is no size at all; fewer estimates than ``scale_frames`` are
    written as they are (the record lists them). ``each``: the first ``max_frames`` frames are stills
    or postures far apart, each fitted from its own start (:meth:`FrameTracker.calibrate_each`)."""
    rec = open_job_recording(job)
    bundle = _bundle(job)
    hand = HandModel.load(job.hand_model, right=(getattr(rec, "handedness", None) or job.handedness) == "right")
    tracker = FrameTracker(hand, job.settings.replace(scale=dict(hand_scale="auto")), synergies=bundle)
    cam, frames = rec.camera, []

    if each:
        obs = []
        for frame in rec:
            # stills, each fitted from its own start: the whole frame, as tracker.calibrate_each reads them
            ob = observe_frame(tracker, frame, cam, job.segmenter, window=False)
            if ob is not None:
                obs.append((frame.index, ob))
            if on_frame is not None:
                on_frame(frame, None, ob)
            if len(obs) >= max_frames:
                break
        try:
            used = tracker.calibrate_each([ob for _, ob in obs], cam)
        except TrackerError as exc:
            raise TrackerError(job.recording, exc.reason) from None
        frames = [obs[k][0] for k in used]
    else:
        for frame in rec:
            # as tracker track observes them (the hand's window once it is tracked): the same hand as --save-hand
            ob = observe_frame(tracker, frame, cam, job.segmenter)
            r = tracker.step(np.zeros((0, 3))) if ob is None else tracker.track(ob, cam, color=frame.color)
            frames.append(frame.index)
            if on_frame is not None:
                on_frame(frame, r, ob)
            if calibration_done(tracker) or len(frames) >= max_frames:
                break
        if tracker.scale_ is None:
            raise TrackerError(job.recording, f"no hand found to calibrate in its first {len(frames)} frames "
                                              "(--depth-range, --box or --forearm steer the segmentation)")
    out = calibrated_hand(tracker, recording=job.recording, frames=frames)
    out.save(output, overwrite=job.overwrite)
    return out, tracker, frames


#: Columns of the summary table of many recordings (:func:`summary_row`).
SUMMARY_COLUMNS = ("recording", "output", "frames", "tracked", "lost", "reinit", "median_fit_mm", "median_ms",
                   "wall_s", "hand_scale", "hand_check", "other_hand_better", "error")


def summary_row(job: TrackJob, run: TrackRun | None = None, error: str = "") -> dict:
    """One row of the summary of many recordings: counts and medians of a run, or the error that
    stopped it (one line naming the file)."""
    row = dict.fromkeys(SUMMARY_COLUMNS, "")
    row.update(recording=str(job.recording), output=str(job.output), error=error)
    if run is not None:
        st = run.df["status"]
        row.update(frames=len(run.df), tracked=int((st == "tracked").sum()), lost=int((st == "lost").sum()),
                   reinit=int((st == "reinit").sum()), median_fit_mm=float(run.df["fit_mm"].median()),
                   median_ms=float(run.df["ms"].median()), wall_s=float(run.wall_s), hand_scale=run.meta["hand_scale"])
        check = run.tracker.hand_check_
        if check is not None:
            row.update(hand_check=str(check), other_hand_better=bool(check.other_fits_better))
        if run.unreadable and not error:
            # its output is written (those frames lost), but the recording is damaged: said, not hidden
            row.update(error=unreadable_text(run.unreadable, len(run.df)))
    return row


def unreadable_text(problems, frames) -> str:
    """One line on a run's unreadable frames: the first one's problem and how many there were."""
    more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
    return (f"{problems[0]}{more}: {len(problems)} of {frames} frames unreadable, tracked as lost; "
            "the outputs hold every frame")


def run_job_row(job: TrackJob) -> dict:
    """:func:`run_job` as one task of many: its summary row, with a bad input or an unwritable
    output reported in the row (``error``) instead of raised, so the other recordings go on."""
    try:
        return summary_row(job, run_job(job))
    except (ToolkitError, OSError) as exc:
        return summary_row(job, error=error_line(exc).removeprefix("error: "))


def batch_jobs(recordings, outdir, template: TrackJob) -> list[TrackJob]:
    """One job per recording, its output ``OUTDIR/<name>.csv`` (``<name>`` the folder's name or the
    file's stem), with the template's ``keypoints`` and ``overlay`` as folders: ``<keypoints>/<name>.csv``
    and ``<overlay>/<name>/``; two recordings with the same name are refused (their outputs would collide)."""
    outdir = Path(outdir)
    jobs, seen = [], {}
    for r in recordings:
        r = Path(r)
        name = r.name if r.is_dir() else r.stem
        if name in seen:
            raise TrackerError(r, f"has the same name as {seen[name]}: both would write {outdir / (name + '.csv')}")
        seen[name] = r
        jobs.append(replace(template, recording=str(r), output=str(outdir / f"{name}.csv"),
                            keypoints=template.keypoints and str(Path(template.keypoints) / f"{name}.csv"),
                            overlay=template.overlay and str(Path(template.overlay) / name)))
    return jobs


def _bundle(job):
    """The job's synergy bundle, or None (full mode without synergies: the bundle reader and its
    schema validator are not loaded then)."""
    if not job.synergies:
        return None
    from synergy.bundle import load_bundle

    return load_bundle(job.synergies, registries=list(job.registries) or None)


def track_many(jobs, *, dask=None, on_done=None) -> pd.DataFrame:
    """Run ``jobs`` one by one here, or as Dask tasks (``dask``: ``local``, ``local:N`` or a
    scheduler address, as ``synergy fit --dask``); a failing recording is reported in its row and
    the rest go on. ``on_done(row)`` is called as each finishes. Returns the summary table
    (:data:`SUMMARY_COLUMNS`), in the order of ``jobs``."""
    rows = [None] * len(jobs)
    if dask is None:
        for i, job in enumerate(jobs):
            rows[i] = run_job_row(job)
            if on_done is not None:
                on_done(rows[i])
    else:
        # an optional extra ([dask]), loaded only when asked for; the same client set-up as synergy fit
        from distributed import as_completed

        from synergy.scale import client_for

        client, cluster = client_for(dask)
        try:
            futures = {client.submit(run_job_row, job, pure=False): i for i, job in enumerate(jobs)}
            for fut in as_completed(list(futures)):
                i = futures[fut]
                try:
                    rows[i] = fut.result()
                except Exception as exc:  # a worker lost or killed: that recording fails, the rest go on
                    rows[i] = summary_row(jobs[i], error=f"{jobs[i].recording}: the Dask task failed "
                                                         f"({type(exc).__name__}: {exc})")
                if on_done is not None:
                    on_done(rows[i])
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    return pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))
