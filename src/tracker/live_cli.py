"""``tracker live`` and ``tracker calibrate``: track the hand live from a RealSense camera (or a
``.bag`` played back) through ``tracker track``'s pipeline, and write the user's hand calibrated on a
recording's first frames as a hand file for ``--hand-model``.

``register(app, errors_exit_2)`` adds the commands to the ``tracker`` typer app. They only parse, call
:mod:`tracker.run`, print and draw progress; heavy modules (and the optional pyrealsense2) are imported
inside them so ``tracker --help`` stays fast.
"""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import List, Optional

import typer

from .cli_common import (BOX, COLOR_TOPIC, DEPTH_RANGE, FOREARM, HAND, PLANE, START, TOPIC, check_hand_file,
                         check_not_inputs, check_outputs, check_overlay_every, chosen_hand_model, hand_side,
                         input_file, progress_bar, say_if_compiling, segmenter_from_options,
                         settings_from_options, StartUp)


def live(
    output: Path = typer.Option(..., "-o", "--output", help="Output CSV (one row per frame)."),
    playback: Optional[Path] = typer.Option(None, "--playback", help="Play a recorded RealSense .bag back through librealsense instead of a camera (as recorded, every frame)."),
    serial: Optional[str] = typer.Option(None, "--serial", help="Camera serial number [the first camera found]."),
    width: int = typer.Option(640, "--width", help="Depth stream width asked of the camera (px)."),
    height: int = typer.Option(480, "--height", help="Depth stream height (px)."),
    fps: int = typer.Option(30, "--fps", help="Depth stream rate asked of the camera (Hz)."),
    color: bool = typer.Option(False, "--color/--no-color", "--colour/--no-colour", help="Also take the colour stream, aligned to the depth (skin segmentation) [off]."),
    frames: Optional[int] = typer.Option(None, "--frames", help="Stop after N frames."),
    seconds: Optional[float] = typer.Option(None, "--seconds", help="Stop after this many seconds of stream time."),
    hand: str = typer.Option("left", "--hand", "--handedness", help="The hand in front of the camera: left or right."),
    save: Optional[Path] = typer.Option(None, "--save", help="Also keep the frames as a recording folder (tracker track can replay it)."),
    keypoints: Optional[Path] = typer.Option(None, "--keypoints", help="Also write the 21 keypoints per frame (CSV, mm)."),
    overlay: Optional[Path] = typer.Option(None, "--overlay", help="Folder for overlay PNGs of the fit on the depth."),
    overlay_every: int = typer.Option(10, "--overlay-every", help="Overlay every N-th frame."),
    rerun: Optional[Path] = typer.Option(None, "--rerun", help="Write a Rerun recording (.rrd) of the session (extra [viz])."),
    rerun_spawn: bool = typer.Option(False, "--rerun-spawn", help="The live view: stream to a Rerun viewer started now (needs a screen; extra [viz])."),
    synergies: Optional[str] = typer.Option(None, "--synergies", "-s", help="Synergy bundle NAME[@VERSION] or .npz path."),
    registry: List[Path] = typer.Option(None, "-r", "--registry", help="Extra bundle registry folder (repeatable)."),
    mode: str = typer.Option("full", "--mode", help="full, reduced or hierarchical."),
    pcs: Optional[int] = typer.Option(None, "--pcs", help="Number of PCs (reduced/hierarchical)."),
    variance: Optional[float] = typer.Option(None, "--variance", help="…or the variance the PCs must explain [0.99]."),
    paper: bool = typer.Option(False, "--paper", help="The paper's method (as tracker track --paper)."),
    hand_model: Optional[str] = typer.Option(None, "--hand-model", help="Hand model name or YAML path [human; default, the paper's, with --paper]."),
    check_hand: bool = typer.Option(True, "--check-hand/--no-check-hand", help="Check the handedness on the first frame [on]."),
    hand_scale: Optional[str] = typer.Option(None, "--hand-scale", help="Hand size factor, or 'auto' (as tracker track) [auto; 1 with --paper]."),
    no_detector: bool = typer.Option(False, "--no-detector", help="No learned detector (the keypoint CNN, the hand-presence network): every start is the full search (as tracker track --no-detector)."),
    no_presence: bool = typer.Option(False, "--no-presence", help="No hand-presence network: every region is searched (as tracker track --no-presence)."),
    depth_range: Optional[str] = DEPTH_RANGE,
    box: Optional[str] = BOX,
    forearm: str = FOREARM,
    plane: str = PLANE,
    realtime: Optional[bool] = typer.Option(None, "--realtime/--no-realtime", help="Keep up with the sensor: fits run on a worker, and a frame whose fit takes longer than --budget-ms gets the last fit moved on (status predicted); a playback is paced at its own rate [on for a camera, off for --playback]."),
    budget_ms: Optional[float] = typer.Option(None, "--budget-ms", help="Real time: how long a frame waits for its fit (ms) [one frame period]."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing output files."),
):
    """Track the hand live from a RealSense camera (extra [realsense]) with the pipeline of tracker
    track and its outputs; Ctrl-C stops and still writes them (a second Ctrl-C aborts)."""
    from handmodel.fileio import check_output

    from .errors import TrackerError

    if hand not in ("left", "right"):
        raise TrackerError("--hand", f"must be left or right, got {hand!r}")
    if (frames is not None and frames < 1) or (seconds is not None and not seconds > 0):
        raise TrackerError("live", "--frames and --seconds must be positive")
    if budget_ms is not None and not (budget_ms > 0 and math.isfinite(budget_ms)):
        raise TrackerError("--budget-ms", f"must be a positive number of ms, got {budget_ms:g}")
    hand_model = chosen_hand_model(hand_model, paper)
    check_not_inputs([playback, input_file(hand_model), input_file(synergies)],
                      [("-o", output), ("--keypoints", keypoints), ("--overlay", overlay), ("--rerun", rerun),
                       ("--save", save)])
    check_outputs(output, keypoints, overlay, rerun, overwrite)
    if save is not None:
        check_output(save, folder=True)
        if save.exists() and any(save.iterdir()) and not overwrite:
            raise TrackerError(save, "exists and is not empty (never overwritten; use --overwrite)")
    check_overlay_every(overlay_every)
    if playback is not None and not playback.is_file():
        # said now, not after the modules below and pyrealsense2 load (RealSenseSource says the same)
        raise TrackerError(playback, "no such file to play back")
    # the collector is off until the first frame's result is in (cli_common.StartUp)
    with StartUp() as start_up:
        segmenter = segmenter_from_options(depth_range, box, forearm, plane)
        settings = settings_from_options(paper, mode, pcs, variance, None, None, None, None, None, None, None, None, None, None,
                             None, None, hand_scale, check_hand, no_detector=no_detector, no_presence=no_presence)

        # heavy modules (and the optional pyrealsense2) load here, so `tracker --help` answers at once
        import signal

        from rich.console import Console

        from .live import RealSenseSource
        from .io.recording import RecordingWriter
        from .run import TrackJob, run_job

        say_if_compiling()

        source = RealSenseSource(playback, serial=serial, width=width, height=height, fps=fps, color=color,
                                 max_frames=frames, max_seconds=seconds, handedness=hand)
        err = Console(stderr=True, markup=False)
        job = TrackJob(recording=str(playback) if playback is not None else f"realsense {source.name}",
                       output=str(output), settings=settings, synergies=synergies,
                       registries=tuple(str(r) for r in registry or ()), hand_model=hand_model, segmenter=segmenter,
                       keypoints=None if keypoints is None else str(keypoints),
                       overlay=None if overlay is None else str(overlay), overlay_every=overlay_every,
                       rerun=None if rerun is None else str(rerun), rerun_spawn=rerun_spawn, overwrite=overwrite,
                       handedness=hand, hand_scale_asked=hand_scale is not None,
                       budget_ms=budget_ms if budget_ms is not None else 1000.0 / source.fps, pace=playback is not None)
        if not (playback is None if realtime is None else realtime):
            job = replace(job, budget_ms=None, pace=False)

        def interrupted(signum, stack):
            # the first Ctrl-C ends the stream after this frame and the outputs are written; a second aborts
            source.stop()
            err.print("stopping after this frame (Ctrl-C again to abort without outputs)")
            signal.signal(signal.SIGINT, previous)

        previous = signal.signal(signal.SIGINT, interrupted)
        writer = None
        try:
            if save is not None:
                writer = RecordingWriter(save, source.camera, source.fps, hand, overwrite=overwrite,
                                         source=f"tracker live, {source.name}")
            with source, progress_bar(f"tracking {source.name}") as progress:
                bar = progress.add_task("live", total=frames)

                def on_frame(frame, r, ob):
                    if writer is not None:
                        writer.write(frame.depth, frame.color if source._color and frame.color is not None else None)
                    progress.advance(bar)
                    start_up.done()

                run = run_job(job, on_frame, source=source)
            if writer is not None:
                writer.close()
        finally:
            signal.signal(signal.SIGINT, previous)
    df = run.df
    st = df["status"]
    console = Console(markup=False)  # paths are printed as typed, never read as markup
    console.print(f"{source.name}: {len(df)} frames, {int((st == 'tracked').sum())} tracked, "
                  f"{int((st == 'lost').sum())} lost, {int((st == 'reinit').sum())} reinit"
                  + (f", {int((st == 'predicted').sum())} predicted (fit pending), {len(run.dropped)} dropped (late)"
                     if job.budget_ms is not None else "") + "; "
                  f"median fit {df['fit_mm'].median():.2f} mm, median {df['ms'].median():.1f} ms a frame, "
                  f"{len(df) / run.wall_s if run.wall_s > 0 else 0:.1f} fps overall")
    if run.tracker.hand_check_ is not None and run.tracker.hand_check_.other_fits_better:
        console.print(f"warning: {hand} hand tracked, but {run.tracker.hand_check_}")
    for p in (output, keypoints, run.rerun, save):
        if p is not None:
            console.print(f"wrote {p}")
    if overlay is not None:
        console.print(f"wrote {len(run.overlays)} overlay{'s' * (len(run.overlays) != 1)} to {overlay}")
    for w in run.warnings:
        console.print(f"warning: {w}")


def calibrate(
    recording: Path = typer.Argument(..., help="Recording folder or file whose first frames show the user's hand (open, fingers apart, is best)."),
    output: Path = typer.Option(..., "-o", "--output", help="The hand file to write (.yaml): tracker track --hand-model takes it back."),
    synergies: Optional[str] = typer.Option(None, "--synergies", "-s", help="Synergy bundle NAME[@VERSION] or .npz path (the start search's postures, as tracker track)."),
    registry: List[Path] = typer.Option(None, "-r", "--registry", help="Extra bundle registry folder (repeatable)."),
    hand_model: Optional[str] = typer.Option(None, "--hand-model", help="The hand model calibrated: a name or YAML path [human, as tracker track]."),
    finger_lengths: Optional[bool] = typer.Option(None, "--finger-lengths/--no-finger-lengths", help="Also estimate each finger's length factor [on]."),
    frames: Optional[int] = typer.Option(None, "--frames", help="Read at most this many frames [60; with --each 5]."),
    each: bool = typer.Option(False, "--each", help="The frames are stills or postures far apart (e.g. a folder of PNGs imported as one recording with tracker import DIR): fit each from its own start instead of tracking from frame to frame; the size is their median, the finger lengths come from all of them."),
    depth_range: Optional[str] = DEPTH_RANGE,
    box: Optional[str] = BOX,
    forearm: str = FOREARM,
    plane: str = PLANE,
    hand: Optional[str] = HAND,
    topic: Optional[str] = TOPIC,
    color_topic: Optional[str] = COLOR_TOPIC,
    start: Optional[float] = START,
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing hand file."),
):
    """Estimate the user's hand (size, and finger lengths) on a recording's first frames and write it
    as a hand file: track later recordings on it with tracker track --hand-model FILE (no
    re-estimation, so every recording of that user gets the same hand)."""
    from handmodel.fileio import check_output

    from .errors import TrackerError

    if frames is None:
        # stills: a few postures apart tell finger lengths apart (tracker.scale.finger_scales)
        frames = 5 if each else 60
    if frames < 1:
        raise TrackerError("--frames", f"must be positive, got {frames}")
    check_hand_file(output)
    hand_model = chosen_hand_model(hand_model, False)
    check_not_inputs([recording, input_file(hand_model), input_file(synergies)], [("-o", output)])
    if output.exists() and not overwrite and not output.is_dir():
        raise TrackerError(output, "exists and is never overwritten (use --overwrite)")
    check_output(output, overwrite=overwrite)
    from .io.base import check_recording_path

    # a mistyped path: said now, before the modules below load
    check_recording_path(recording, topic=topic, color_topic=color_topic, handedness=hand_side(hand))
    # the collector is off until the first frame is in (cli_common.StartUp)
    with StartUp() as start_up:
        segmenter = segmenter_from_options(depth_range, box, forearm, plane)
        settings = settings_from_options(False, "full", None, 0.99, None, None, None, None, None, None, None, None, None, None,
                             None, None, "auto", False)
        if finger_lengths is not None:
            settings = settings.replace(scale=dict(finger_lengths=finger_lengths))

        # heavy modules load here, not at import time, so `tracker --help` answers at once
        from rich.console import Console
        from rich.table import Table

        from .run import TrackJob, calibrate_job

        say_if_compiling()

        job = TrackJob(recording=str(recording), output="", settings=settings, synergies=synergies,
                       registries=tuple(str(r) for r in registry or ()), hand_model=hand_model, segmenter=segmenter,
                       overwrite=overwrite, hand=hand_side(hand), topic=topic, color_topic=color_topic, start_s=start)
        with progress_bar("calibrating") as progress:
            bar = progress.add_task("calibrate", total=None)

            def on_frame(frame, r, ob):
                progress.advance(bar)
                start_up.done()

            out, tracker, used = calibrate_job(job, output, max_frames=frames, each=each, on_frame=on_frame)
    cal = out.calibration
    how = "each from its own start" if each else "tracked"
    table = Table(title=f"hand calibrated on {recording} ({len(used)} frames {how}: {used[0]}–{used[-1]})")
    table.add_column("")
    table.add_column("factor", justify="right")
    table.add_column("estimates / spread", justify="right")
    spread = f"± {100 * cal['scale_spread']:.1f} %" if cal["scale_spread"] is not None else "one estimate"
    table.add_row(f"size (× {tracker.base_hand.name})", f"{cal['hand_scale']:.4f}",
                  f"{', '.join(f'{e:.4f}' for e in cal['scale_estimates'])} ({spread})")
    est = cal.get("finger_estimates") or {}
    for name, f in (cal["finger_lengths"] or {}).items():
        e = est.get(name) or {}
        # the frames' agreement: a finger they disagree on is shrunk towards the model's proportions
        if e.get("unshrunk") is None:
            seen = "no minimum: kept at 1" if e else ""
        elif e.get("se_log") is None:
            seen = f"{e['unshrunk']:.3f} (one frame: kept at 1)"
        else:
            seen = f"{e['unshrunk']:.3f} ± {100 * e['se_log']:.1f} %"
        table.add_row(f"{name} length", f"{f:.3f}", seen)
    console = Console(markup=False)  # paths are printed as typed, never read as markup
    console.print(table)
    if len(cal["scale_estimates"]) < tracker.settings.scale.frames:
        console.print(f"warning: {len(cal['scale_estimates'])} size estimates of {tracker.settings.scale.frames} "
                      "(the hand was lost or the frames ran out); a longer recording settles it better")
    console.print(f"wrote {output} ({out.handedness} hand; track on it with --hand-model {output})")


def register(app, errors_exit_2) -> None:
    app.command()(errors_exit_2(calibrate))
    app.command()(errors_exit_2(live))
