"""Pipeline stage ``run``: a tracker over a whole recording, one recording's job and its outputs.

:func:`track_recording` (or :func:`track_realtime`) tracks every frame of a recording into a table;
:class:`TrackJob` and :func:`run_job` are the one path of ``tracker track`` and ``tracker live``
(open, track, write the tracking output of :mod:`tracker.io.tracking_file`, keypoints, overlays, Rerun);
:func:`calibrate_job` is ``tracker calibrate``'s. Many recordings: :mod:`tracker.batch`. :func:`run_job` keeps
its table as a :class:`tracker.io.tracking_file.FrameTable` and writes it without pandas (pandas is loaded
when its DataFrame is asked for: :attr:`TrackRun.df`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from handmodel.model import HandModel

from . import TRACKING_HAND
from .errors import TrackerError
from .observe import observe
from .segment import Segmenter
from .io.recording import Recording
from .io.tracking_file import FRAME_COLUMNS, FrameTable, tracking_metadata, write_keypoints, write_tracking
from .scale import calibrated_hand
from .track import FrameTracker, TrackerSettings


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


def _held(segmenter):
    """The segmenter a recording is observed with, one for all its frames (its frame buffers are reused
    frame after frame: :attr:`tracker.segment.Segmenter.buffers`); None: the defaults'."""
    return segmenter if segmenter is not None else Segmenter()


def track_recording(recording, tracker, on_frame=None, *, segmenter=None, frame_table: bool = False):
    """Track every frame of ``recording`` (anything with ``camera`` that iterates frames with
    ``index``, ``time_s``, ``depth`` in metres and ``color``) with ``tracker`` (:class:`FrameTracker`).

    A frame without a usable depth image (missing, wrong size, or a folder recording's file that
    cannot be read: :meth:`tracker.io.recording.Recording.frames_or_problems`, the frame's ``problem``) is
    tracked as empty, so it is lost. ``on_frame(frame, result, observation)`` is called after each frame
    (``observation`` None for an unusable one): progress, overlays, keypoints. Returns one row per frame
    (:data:`FRAME_COLUMNS` and the hand's DoF names): a pandas DataFrame, or with ``frame_table`` a
    :class:`tracker.io.tracking_file.FrameTable` (pandas not loaded)."""
    cam = recording.camera
    rows = []
    segmenter = _held(segmenter)
    frames = recording.frames_or_problems() if hasattr(recording, "frames_or_problems") else recording
    for frame in frames:
        ob = observe_frame(tracker, frame, cam, segmenter)
        r = tracker.step(np.zeros((0, 3))) if ob is None else tracker.track(ob, cam, color=frame.color)
        rows.append((frame.index, frame.time_s, r.status, r.fit_mm, r.points_used,
                     0 if ob is None else len(ob.points), r.ms, *r.theta))
        if on_frame is not None:
            on_frame(frame, r, ob)
    return _table(rows, tracker, frame_table)


def _table(rows, tracker, frame_table):
    """The tracked ``rows`` as :func:`track_recording` returns them: a DataFrame, or a FrameTable."""
    table = FrameTable([*FRAME_COLUMNS, *tracker.hand.dof_names], rows)
    return table if frame_table else table.to_frame()


def track_realtime(recording, tracker, budget_ms, on_frame=None, *, segmenter=None, pace: bool = False,
                   dropped=None, frame_table: bool = False):
    """:func:`track_recording` in real time: each frame is observed and fitted on a worker thread
    (:class:`tracker.realtime.FrameBudget`, or the one given as ``budget_ms``) and waited for at most
    ``budget_ms``; a frame whose fit
    overruns, or that comes while the worker is still on an earlier one, gets the last fit moved on
    (:func:`tracker.realtime.predicted_theta`, status ``"predicted"``, no points, ``observation`` None
    for ``on_frame``). With ``pace`` the frames come at the recording's own rate
    (:func:`tracker.realtime.paced`; the late ones dropped and listed in ``dropped``), as from a sensor.
    The rows are what was published, frame by frame, as a live user saw them (a DataFrame, or with
    ``frame_table`` a :class:`tracker.io.tracking_file.FrameTable`)."""
    from .realtime import FrameBudget, paced, predicted_theta
    from .track import FrameResult

    cam = recording.camera
    segmenter = _held(segmenter)
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
                theta = (predicted_theta(last, seen[0] if len(seen) == 2 else None, tracker.settings.predict.turn) if found
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
    return _table(rows, tracker, frame_table)


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
    """What :func:`run_job` did: the table (a :class:`tracker.io.tracking_file.FrameTable`; :attr:`df` as a
    DataFrame) and header written, the tracker (its hand size and handedness check), the recording, the
    wall time, the overlay frames written, the Rerun file and warnings (a spawned viewer that went away);
    ``unreadable``: why frames could not be read (each tracked as lost, the outputs written all the same)."""

    table: FrameTable
    meta: dict
    tracker: FrameTracker
    recording: object
    wall_s: float
    overlays: list
    rerun: Path | None = None
    warnings: list = field(default_factory=list)
    unreadable: list = field(default_factory=list)  # the problems of frames whose files could not be read
    dropped: list = field(default_factory=list)  # real time, paced: the frames the loop was too late for

    @cached_property
    def df(self):
        """The table as a pandas DataFrame (pandas is loaded at the first call)."""
        return self.table.to_frame()


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
            table = track_recording(rec, tracker, each, segmenter=job.segmenter, frame_table=True)
        else:
            table = track_realtime(rec, tracker, job.budget_ms, each, segmenter=job.segmenter, pace=job.pace,
                                   dropped=dropped, frame_table=True)
    except BaseException:
        if viewer is not None:
            viewer.abort()
        raise
    wall_s = time.perf_counter() - t_start
    # the size's work still under way when the recording ended (scale.budget spreads it over the frames)
    tracker.sizing.finish(tracker)
    meta = tracking_metadata(job.recording, tracker, bundle.spec if bundle else "", bundle.path if bundle else "")
    try:
        # without overwrite a file that appeared while tracking is not replaced either
        write_tracking(job.output, table, meta, overwrite=job.overwrite)
        if job.save_hand is not None:
            calibrated_hand(tracker, recording=job.recording, frames=calibration_frames).save(
                job.save_hand, overwrite=job.overwrite)
        if job.keypoints is not None:
            write_keypoints(job.keypoints, tracker.hand, table, meta, overwrite=job.overwrite)
        if overlay is not None and job.overwrite:
            # an earlier run's overlays of other frames would pass for this run's (its settings, its fits)
            stale_overlays(overlay, written)
    except BaseException:
        if viewer is not None:
            viewer.abort()
        raise
    rrd = viewer.close() if viewer is not None else None
    warnings = [viewer.warning_] if viewer is not None and viewer.warning_ else []
    return TrackRun(table, meta, tracker, rec, wall_s, written, rrd, warnings, unreadable, dropped)


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
        # the size's work still under way when the recording ended (as tracker track --save-hand does)
        tracker.sizing.finish(tracker)
        if tracker.scale_ is None:
            raise TrackerError(job.recording, f"no hand found to calibrate in its first {len(frames)} frames "
                                              "(--depth-range, --box or --forearm steer the segmentation)")
    out = calibrated_hand(tracker, recording=job.recording, frames=frames)
    out.save(output, overwrite=job.overwrite)
    return out, tracker, frames


def _bundle(job):
    """The job's synergy bundle, or None (full mode without synergies: the bundle reader and its
    schema validator are not loaded then)."""
    if not job.synergies:
        return None
    from synergy.bundle import load_bundle

    return load_bundle(job.synergies, registries=list(job.registries) or None)
