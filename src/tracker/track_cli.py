"""``tracker track``, ``tracker live``, ``tracker calibrate`` and ``tracker eval``: track one recording,
many (one by one or on Dask) or a live RealSense camera, write the user's calibrated hand as a hand
file, and score a tracking against a recording's truth.

``register(app, errors_exit_2)`` adds the commands to the ``tracker`` typer app. The commands only
parse, call :mod:`tracker.run`, print and draw progress; heavy modules are imported inside them so
``tracker --help`` stays fast.
"""
from __future__ import annotations

import math
import os
from dataclasses import replace
from pathlib import Path
from typing import List, Optional

import typer

from .cli_common import check_not_inputs, check_same_recording, progress_bar, segmenter_from_options

# options that several commands take, written once (the same flag, default and help everywhere)
DEPTH_RANGE = typer.Option(None, "--depth-range", help="NEAR,FAR (m): look for the hand only in this depth range [0.2,1.5].")
BOX = typer.Option(None, "--box", help="X0,Y0,Z0,X1,Y1,Z1 (m, camera frame: x right, y down, z forward; an empty entry is open): look for the hand only in this box.")
FOREARM = typer.Option("cut", "--forearm", help="cut (remove the forearm beyond the wrist) or keep (a wristband or sleeve already ends the hand) [cut].")
PLANE = typer.Option("auto", "--plane", help="The frame's largest plane (a table, floor or wall): auto (left out of the hand's search when no colour frame is used; the skin test does it otherwise), cut (always) or keep [auto].")
HAND = typer.Option(None, "--hand", help="left or right: the hand tracked, overriding the recording's (a recording file does not say; then left).")
TOPIC = typer.Option(None, "--topic", help="Depth topic of a ROS bag [found in the file].")
COLOR_TOPIC = typer.Option(None, "--color-topic", help="Colour topic of a ROS bag [found in the file].")
START = typer.Option(None, "--start", help="Recording files: first frame time (s from the first depth frame).")


def track(
    recordings: List[Path] = typer.Argument(..., help="Recording folder(s) (recording.yaml, depth/…) or recording files; with several, -o is a folder."),
    synergies: Optional[str] = typer.Option(None, "--synergies", "-s", help="Synergy bundle NAME[@VERSION] or .npz path."),
    registry: List[Path] = typer.Option(None, "-r", "--registry", help="Extra bundle registry folder (repeatable); SYNERGY_PATH and the shipped bundles follow."),
    mode: str = typer.Option("full", "--mode", help="full, reduced or hierarchical."),
    pcs: Optional[int] = typer.Option(None, "--pcs", help="Number of PCs (reduced/hierarchical)."),
    variance: Optional[float] = typer.Option(None, "--variance", help="…or the variance the PCs must explain [0.99]."),
    output: Path = typer.Option(..., "-o", "--output", help="Output CSV (one row per frame); with several recordings (or --dask) a folder: NAME.csv per recording and summary.csv."),
    keypoints: Optional[Path] = typer.Option(None, "--keypoints", help="Also write the 21 keypoints per frame (CSV, mm); with several recordings a folder: NAME.csv per recording."),
    overlay: Optional[Path] = typer.Option(None, "--overlay", help="Folder for overlay PNGs of the fit on the depth; with several recordings NAME/ in it per recording."),
    overlay_every: int = typer.Option(10, "--overlay-every", help="Overlay every N-th frame."),
    rerun: Optional[Path] = typer.Option(None, "--rerun", help="Write a Rerun recording (.rrd) of the depth, segmentation, points used, fitted hand, fit error and fps per frame (extra [viz])."),
    rerun_spawn: bool = typer.Option(False, "--rerun-spawn", help="Stream the same to a Rerun viewer started now (needs a screen; extra [viz])."),
    dask: Optional[str] = typer.Option(None, "--dask", help="Track the recordings as Dask tasks: local, local:N (N worker processes) or a scheduler address."),
    paper: bool = typer.Option(False, "--paper", help="Start from the paper's method (fixed stride 3, no smoothing, plain least squares, no silhouette term, no normal test, no start search); the options below change it."),
    stride: Optional[int] = typer.Option(None, "--stride", help="Use every K-th pixel in x and y [3; the paper's '1/3 sampling' is 3]."),
    smooth: Optional[int] = typer.Option(None, "--smooth", help="Edge-preserving depth smoothing radius in pixels [1; paper 0 = off]."),
    points: Optional[int] = typer.Option(None, "--points", help="Adapt the stride (≤ --stride) to keep about this many hand points [600; 0 = fixed stride, the paper's]."),
    icp: Optional[int] = typer.Option(None, "--icp", help="Non-rigid ICP iterations per frame, after 1 rigid [4]."),
    gn: Optional[int] = typer.Option(None, "--gn", help="Gauss-Newton steps per ICP iteration [5]."),
    damping: Optional[float] = typer.Option(None, "--damping", help="λ on posture coordinates [1, the paper's; residuals in mm]."),
    model: Optional[str] = typer.Option(None, "--model", help="Correspondence model: capsules or mesh [capsules]."),
    silhouette: Optional[float] = typer.Option(None, "--silhouette", help="Weight of the model→data silhouette term [1; paper 0]."),
    prediction: Optional[float] = typer.Option(None, "--prediction", help="Share of last frame's change added before fitting [1]."),
    robust: Optional[float] = typer.Option(None, "--robust", help="Cauchy scale (mm) weighting the data term [8; 0 = plain least squares, the paper's]."),
    finger_search: Optional[bool] = typer.Option(None, "--finger-search/--no-finger-search", help="Finger-wise restarts when (re)initialising [on; paper off]."),
    projected_steps: Optional[int] = typer.Option(None, "--projected-steps", help="Reduced mode: last ICP iterations with all DoF, projected onto the PCs [0, the paper's]."),
    hand_model: Optional[str] = typer.Option(None, "--hand-model", help="Hand model name or YAML path; a hand file written by tracker calibrate or --save-hand is tracked as it is (its size is in it; --hand-scale auto estimates again) [human: the shipped hand with its finger bases on the human metacarpal arc; default, the paper's, with --paper]."),
    save_hand: Optional[Path] = typer.Option(None, "--save-hand", help="Also write the hand calibrated on the first frames (size, and finger lengths when estimated) as a YAML hand file for --hand-model."),
    finger_lengths: Optional[bool] = typer.Option(None, "--finger-lengths/--no-finger-lengths", help="With --hand-scale auto, also estimate each finger's length once the size is settled [on; paper off]."),
    check_hand: bool = typer.Option(True, "--check-hand/--no-check-hand", help="On the first frame also fit the mirror-image hand and warn when it fits clearly better (one more start search) [on]."),
    safety_net: Optional[bool] = typer.Option(None, "--safety-net/--no-safety-net", help="Test every tracked frame and run the cheap start search on a doubtful one, keeping the better estimate (in reduced mode the far-points test only: a fit that leaves most of the cloud far away is lost) [on; paper off]."),
    no_hand: Optional[float] = typer.Option(None, "--no-hand-rejected", help="A start (first frame, after a loss) whose fit rejects more than this share of its points found no hand: the frame is lost, without θ [0.2; 0 = off, as with --paper]."),
    unseen_prior: Optional[float] = typer.Option(None, "--unseen-prior", help="Share of the way per tracked frame that joints no data point constrains (fingers curled away from the camera) move to their most likely values given the seen joints, by the synergy bundle; a start moves them all the way (full and hierarchical modes; 0 = off) [0.5; paper 0]."),
    hand_scale: Optional[str] = typer.Option(None, "--hand-scale", help="The user's hand size as a factor on the hand model, or 'auto': estimated from the first frames (written to the output header as hand_scale; pass it back to reuse it, or keep the hand with --save-hand) [auto; 1 with --paper or a calibrated --hand-model file]."),
    depth_range: Optional[str] = DEPTH_RANGE,
    box: Optional[str] = BOX,
    forearm: str = FOREARM,
    plane: str = PLANE,
    hand: Optional[str] = HAND,
    topic: Optional[str] = TOPIC,
    color_topic: Optional[str] = COLOR_TOPIC,
    start: Optional[float] = START,
    end: Optional[float] = typer.Option(None, "--end", help="Recording files: last frame time (s from the first depth frame)."),
    every: int = typer.Option(1, "--every", help="Recording files: track every N-th frame."),
    rgb_seed: bool = typer.Option(False, "--rgb-seed", help="Start searches also from the hand fitted to MediaPipe's keypoints on the colour frames, lifted with the depth (extra [rgb])."),
    search_budget_ms: Optional[float] = typer.Option(None, "--search-budget-ms", help="A start search's budget in ms: once spent, its optional stages are skipped and its best start so far converged (the result then depends on the machine's speed; the summary counts the searches cut) [0 = none]."),
    threads: Optional[int] = typer.Option(None, "--threads", min=0, help="Threads for the fits of a start search (the first frame, a lost frame, the safety net); the result is the same for any count [0 = the cores, at most 4; never more than the cores; 1 per recording with --dask]."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing output files."),
):
    """Track the hand through one or many recordings; writes per-frame hand parameters and a summary."""
    from .errors import TrackerError

    if rgb_seed:
        from .rgb import require_mediapipe  # light: finds mediapipe without importing it

        require_mediapipe("--rgb-seed")

    hand_model = _hand_model(hand_model, paper)
    check_not_inputs([*recordings, _input_file(hand_model), _input_file(synergies)],
                      [("-o", output), ("--keypoints", keypoints), ("--overlay", overlay), ("--rerun", rerun),
                       ("--save-hand", save_hand)])
    if len(recordings) > 1 or dask is not None:
        per_file = [n for n, v in (("--rerun", rerun), ("--rerun-spawn", rerun_spawn), ("--save-hand", save_hand)) if v]
        if per_file:
            raise TrackerError(per_file[0], "is for one recording; with several, -o is a folder of NAME.csv "
                                            "and summary.csv, --keypoints and --overlay folders of NAME.csv and "
                                            "NAME/ (track a recording alone for its other outputs)")
        _check_outputs(output, None, None, None, overwrite, folder=True)
        for name, folder in (("--keypoints", keypoints), ("--overlay", overlay)):
            if folder is not None:
                if folder.resolve() == output.resolve():
                    raise TrackerError(name, f"needs a folder of its own, not -o's ({folder})")
                _check_outputs(folder, None, None, None, overwrite, folder=True)
    else:
        _check_outputs(output, keypoints, overlay, rerun, overwrite, save_hand=save_hand)
    _check_every(overlay_every)
    segmenter = segmenter_from_options(depth_range, box, forearm, plane)
    # Dask's workers already run recordings side by side
    threads = 1 if threads is None and dask is not None else threads
    settings = _settings(paper, mode, pcs, variance, stride, smooth, points, icp, gn, damping, model, silhouette,
                         prediction, robust, finger_search, projected_steps, hand_scale, check_hand,
                         rgb_seed=rgb_seed, finger_lengths=finger_lengths, safety_net=safety_net,
                         unseen_prior=unseen_prior, no_hand=no_hand, threads=threads,
                         search_budget_ms=search_budget_ms)

    # heavy modules load here, not at import time, so `tracker --help` answers at once
    from .run import TrackJob

    _say_if_compiling()

    job = TrackJob(recording=str(recordings[0]), output=str(output), settings=settings, synergies=synergies,
                   registries=tuple(str(r) for r in registry or ()), hand_model=hand_model, segmenter=segmenter,
                   keypoints=None if keypoints is None else str(keypoints),
                   overlay=None if overlay is None else str(overlay), overlay_every=overlay_every,
                   rerun=None if rerun is None else str(rerun), rerun_spawn=rerun_spawn, overwrite=overwrite,
                   hand=_hand_side(hand), topic=topic, color_topic=color_topic, start_s=start, end_s=end, every=every,
                   save_hand=None if save_hand is None else str(save_hand), hand_scale_asked=hand_scale is not None)
    if len(recordings) > 1 or dask is not None:
        _track_many(recordings, output, job, dask, overwrite)
        return
    _track_one(job, recordings[0], output, keypoints, overlay, mode, paper)


def _say_if_compiling():
    """One line on stderr when numba's cache holds no compiled kernels (a fresh install): this call
    compiles them first, which takes minutes."""
    from .compile import cold_message

    message = cold_message()
    if message:
        typer.echo(message, err=True)


def _hand_side(hand):
    from .errors import TrackerError

    if hand is not None and hand not in ("left", "right"):
        raise TrackerError("--hand", f"must be left or right, got {hand!r}")
    return hand


def _hand_model(name, paper) -> str:
    """The ``--hand-model`` asked for, else the tracker's hand (:data:`tracker.TRACKING_HAND`), or the paper's
    with ``--paper`` (:data:`tracker.PAPER_HAND`)."""
    from . import PAPER_HAND, TRACKING_HAND

    return name if name is not None else (PAPER_HAND if paper else TRACKING_HAND)


def _input_file(spec):
    """The file a ``--hand-model`` or ``--synergies`` value names, or None for a shipped name."""
    return Path(spec) if spec and Path(spec).is_file() else None


def _check_outputs(output, keypoints, overlay, rerun, overwrite, folder=False, save_hand=None):
    """Every output is checked before the frames are tracked: a full or read-only disk, or a folder
    where a file goes, fails now and not after minutes of tracking."""
    from handmodel.fileio import check_output

    from .errors import TrackerError

    if folder:
        check_output(output, folder=True)
        return
    if save_hand is not None:
        _check_hand_file(save_hand)
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


def _check_hand_file(path):
    """A hand file must end in .yaml or .yml: --hand-model reads any other name as a shipped model's."""
    from .errors import TrackerError

    if path.suffix.lower() not in (".yaml", ".yml"):
        raise TrackerError(path, "a hand file must end in .yaml or .yml (--hand-model takes it back by that)")


#: The option of each settings field the command line sets: a settings error names the option.
_OPTION_OF = {"mode": "--mode", "subspace.variance": "--variance", "subspace.n_pcs": "--pcs",
              "scale.hand_scale": "--hand-scale", "refine.unseen_prior": "--unseen-prior",
              "loss.no_hand_rejected": "--no-hand-rejected", "observe.stride": "--stride",
              "start.search_budget_ms": "--search-budget-ms"}


def _settings(paper, mode, pcs, variance, stride, smooth, points, icp, gn, damping, model, silhouette, prediction,
              robust, finger_search, projected_steps, hand_scale, check_hand, *, rgb_seed=False, finger_lengths=None,
              safety_net=None, unseen_prior=None, no_hand=None, threads=None, search_budget_ms=None):
    """The :class:`tracker.settings.TrackerSettings` of the command line: the default or the paper's,
    with every option given replacing its value, checked (:func:`_checked`)."""
    from .errors import TrackerError
    from .settings import TrackerSettings

    if pcs and variance is not None:  # one of them decides the PCs: the other would be ignored silently
        raise TrackerError("--pcs", f"give --pcs or --variance, not both (got {pcs} and {variance})")
    groups = {
        "observe": dict(stride=stride, smooth=smooth, target_points=points or None),
        "icp": dict(icp_iterations=icp, gn_iterations=gn, damping=damping, silhouette_weight=silhouette,
                    robust_mm=robust, projected_steps=projected_steps),
        "correspond": dict(model=model), "predict": dict(share=prediction),
        "init": dict(finger_search=finger_search, threads=threads),
        "scale": dict(hand_scale=_hand_scale(hand_scale), finger_lengths=finger_lengths),
        "start": dict(check_hand=check_hand, rgb_seed=rgb_seed, search_budget_ms=search_budget_ms),
        "net": dict(enabled=safety_net),
        "refine": dict(unseen_prior=unseen_prior), "loss": dict(no_hand_rejected=no_hand),
    }
    # an option not given keeps the default's value (the paper's with --paper); --points 0: all points (None)
    given = {g: {k: v for k, v in kv.items() if v is not None or (k == "target_points" and points == 0)}
             for g, kv in groups.items()}
    given["subspace"] = dict(n_pcs=pcs, variance=None if pcs else (0.99 if variance is None else variance))
    base = TrackerSettings.paper() if paper else TrackerSettings()
    return _checked(base.replace(mode=mode, **given))


def _checked(settings):
    """``settings`` after ``settings.check()``, whose error names the command-line option of the field
    (before the synergy bundle a mode needs is loaded: a typo must not read as a missing --synergies)."""
    from .errors import TrackerError

    try:
        settings.check()
    except TrackerError as e:
        raise TrackerError(_OPTION_OF.get(e.where, e.where), e.reason) from None
    return settings


def _track_one(job, recording, output, keypoints, overlay, mode, paper):
    """One recording: progress bar, outputs, the result table."""
    from rich.console import Console
    from rich.table import Table

    from .run import open_job_recording, run_job

    rec = open_job_recording(job)
    if getattr(rec, "damage", ""):
        # said before the frames are tracked, as tracker info says it; the frames up to the damage are tracked
        Console(stderr=True, markup=False, soft_wrap=True).print(
            f"warning: {recording}: {rec.damage}; tracking the {len(rec)} frame{'s' * (len(rec) != 1)} it holds")
    with progress_bar("tracking") as progress:
        bar = progress.add_task("track", total=_length(rec))
        run = run_job(job, lambda frame, r, ob: progress.advance(bar), source=rec)
    df, tracker, rec, wall_s = run.df, run.tracker, run.recording, run.wall_s
    n_pcs = f", {tracker.n_pcs} PCs" if tracker.n_pcs and mode != "full" else ""
    table = Table(title=f"tracked {recording} ({mode}{n_pcs}{', paper' if paper else ''})")
    for c in ("frames", "tracked", "lost", "reinit", "median fit mm", "median ms", "fps median", "fps run"):
        table.add_column(c, justify="right")
    st = df["status"]
    found = st != "lost"
    # the median frame's rate counts frames with a hand only (a lost frame costs nothing and would show a
    # rate no tracking reached); the run's rate is the wall time of everything (reading, segmenting, the
    # start search, overlays); one decimal so a slow run never shows as 0
    ms = float(df["ms"][found].median()) if found.any() else float("nan")
    table.add_row(str(len(df)), str(int((st == "tracked").sum())), str(int((~found).sum())),
                  str(int((st == "reinit").sum())), f"{df['fit_mm'].median():.2f}" if found.any() else "-",
                  f"{ms:.1f}" if found.any() else "-", f"{1000 / ms:.1f}" if ms > 0 else "-",
                  f"{len(df) / wall_s:.1f}" if wall_s > 0 else "-")
    console = Console(markup=False)  # paths are printed as typed, never read as markup
    console.print(table)
    if tracker.stats.no_hand:
        # what was segmented was too small to start from, or its fit left too much unexplained to be a hand
        # (LossSettings.start_min_pixels, no_hand_rejected)
        st, few, out = tracker.settings, tracker.stats.too_few, tracker.stats.size_out
        why = [f"{few} with fewer than {st.loss.start_min_pixels} pixels to start from"] if few else []
        if tracker.stats.no_hand > few + out:
            why.append(f"{tracker.stats.no_hand - few - out} whose fit rejected more than {st.loss.no_hand_rejected:.0%} of the points")
        if out:
            lo, hi = st.scale.range
            why.append(f"{out} fitted at the end of the hand sizes searched ({lo:g}–{hi:g}× the model)")
        console.print(f"no hand: on {tracker.stats.no_hand} frame{'s' * (tracker.stats.no_hand != 1)} what was segmented is no "
                      f"hand ({'; '.join(why)}); those frames are lost, without θ")
    if len(df) and not found.any():
        why = ("nothing segmented looks like a hand" if tracker.stats.no_hand
               else "nothing segmented where a hand can be")
        console.print(f"warning: no hand found in any frame of {recording}: {why} ({_no_hand_hints(job, tracker)})")
    if tracker.base_hand.calibration and tracker.settings.scale.hand_scale != "auto":
        console.print(f"hand: the calibrated hand of {tracker.base_hand.path} (size {tracker.base_hand.calibration['hand_scale']}"
                      " in the file), not estimated again")
    elif tracker.scale_ is not None and tracker.settings.scale.hand_scale == "auto" and found.any():
        # the size a later run takes back with --hand-scale (it is in the output header too); on a
        # calibrated hand file a number is refused (it would scale that hand twice): the file it saves
        if job.save_hand:
            reuse = f"--hand-model {job.save_hand}"
        elif tracker.base_hand.calibration:
            reuse = "--save-hand FILE, then --hand-model FILE"
        elif tracker.finger_scales_:
            # a number carries the size only: the finger lengths come back with the hand file
            reuse = f"--hand-scale {tracker.scale_:.4f} (the size only) or --save-hand FILE (with the finger lengths)"
        else:
            reuse = f"--hand-scale {tracker.scale_:.4f} or --save-hand FILE"
        console.print(f"hand size: {run.meta['hand_scale']}; reuse it with {reuse}")
    elif tracker.scale_ is not None and found.any():
        console.print(f"hand size: {run.meta['hand_scale']}")
    if tracker.stats.size_starts:
        console.print(f"start: the fit replaced on {tracker.stats.size_starts} of the size-refining frames by their own "
                      "search's, which scored better")
    if tracker.settings.net.enabled and tracker.settings.mode != "reduced" and len(df):
        runs = tracker.stats.net_runs
        cost = f", {tracker.stats.net_ms / runs:.0f} ms per run" if runs else ""
        wrong = f" (on {tracker.stats.net_wrong_way} the hand pointed against the arm)" if tracker.stats.net_wrong_way else ""
        console.print(f"safety net: ran on {runs}/{len(df)} frames ({runs / len(df):.0%}){wrong}, replaced "
                      f"{tracker.stats.net_replaced}{cost}; re-centred {tracker.stats.recentred}")
    if tracker.settings.start.search_budget_ms and tracker.stats.searches:
        st = tracker.stats
        console.print(f"start searches: {st.searches}, {st.searches_cut} cut short by the "
                      f"{tracker.settings.start.search_budget_ms:g} ms budget; {st.search_ms / st.searches:.0f} ms each")
    if tracker.settings.start.rgb_seed:
        # a recording without colour (or a hand MediaPipe never found) leaves the depth-only start
        console.print(f"colour seed: {tracker.stats.rgb_seeds} start searches seeded by colour keypoints"
                      + ("" if tracker.stats.rgb_seeds else " (no colour frames, or no hand found in them)"))
    if tracker.hand_check_ is not None and tracker.hand_check_.other_fits_better:
        console.print(f"warning: {rec.handedness} hand tracked, but {tracker.hand_check_}")
    console.print(f"wrote {output}")
    if keypoints is not None:
        console.print(f"wrote {keypoints}")
    if overlay is not None:
        console.print(f"wrote {len(run.overlays)} overlay{'s' * (len(run.overlays) != 1)} to {overlay}")
    if run.rerun is not None:
        console.print(f"wrote {run.rerun}")
    if job.save_hand is not None:
        console.print(f"wrote {job.save_hand} (the calibrated hand; track on it with --hand-model {job.save_hand})")
    for w in run.warnings:
        console.print(f"warning: {w}")
    if run.unreadable:
        from .errors import TrackerError
        from .batch import unreadable_text

        # the outputs are written; the damaged input still ends the command with the error code
        raise TrackerError(recording, unreadable_text(run.unreadable, len(df)))


def _length(source):
    """Frames of a source, None when it does not know (a live camera)."""
    try:
        return len(source)
    except TypeError:
        return None


def _track_many(recordings, outdir, template, dask, overwrite):
    """Many recordings, one by one or on Dask: NAME.csv each, summary.csv, the summary table; the
    failing ones are reported last, one line each, and make the exit status 2."""
    from rich.console import Console
    from rich.table import Table

    from handmodel.cliutil import print_error
    from handmodel.fileio import atomic_write_text, check_output

    from .errors import TrackerError
    from .batch import batch_jobs, track_many

    jobs = batch_jobs(recordings, outdir, template)
    summary = Path(outdir) / "summary.csv"
    outputs = [Path(j.output) for j in jobs] + [summary] + [Path(j.keypoints) for j in jobs if j.keypoints]
    check_not_inputs(recordings, [("-o", p) for p in outputs])
    for p in outputs:
        if p.exists() and not overwrite:
            raise TrackerError(p, "exists and is never overwritten (use --overwrite)")
        check_output(p, overwrite=overwrite)
    for j in jobs:
        if j.overlay:
            _check_outputs(None, None, Path(j.overlay), None, overwrite)
    with progress_bar(f"tracking {len(jobs)} recordings" + (f" on Dask ({dask})" if dask else "")) as progress:
        bar = progress.add_task("recordings", total=len(jobs))
        table = track_many(jobs, dask=dask, on_done=lambda row: progress.advance(bar))
    atomic_write_text(summary, table.to_csv(index=False, float_format="%.4f"), overwrite=overwrite)
    # short headers and fps as the run's (wall time, as the one-recording table's "fps run"), so a
    # readable name and all the numbers fit 100 columns
    heads = ("frames", "tracked", "lost", "reinit", "fit mm", "ms", "fps", "result")
    rows = []
    for row in table.to_dict("records"):
        ok = not row["error"]
        fps = row["frames"] / row["wall_s"] if ok and row["wall_s"] else None
        rows.append((Path(row["recording"]).name, *(str(row[k]) if ok else "-" for k in ("frames", "tracked", "lost", "reinit")),
                     f"{row['median_fit_mm']:.2f}" if ok else "-", _short(row["median_ms"]) if ok else "-",
                     "-" if fps is None else _short(fps),
                     "failed" if not ok else "other hand?" if row["other_hand_better"] in (True, "True") else "ok"))
    console = Console(markup=False)  # paths are printed as typed, never read as markup
    # the name takes what the numbers leave (each column 3 more for padding and its rule), one line cut
    # with …: folded or squeezed by rich, a 100-column terminal left 9 characters a line of it
    numbers = sum(max(len(h), *(len(r[k + 1]) for r in rows)) for k, h in enumerate(heads))
    t = Table(title=f"tracked {len(jobs)} recordings" + (f" on Dask ({dask})" if dask else ""))
    # 7 keeps a name's start and its end (middle_cut: "20…_110") and leaves 45 columns of numbers at 80, as
    # many as they take with 5-character times (a loaded machine's 1-frame start took 1000 ms or more, and
    # at 10 the name pushed the header "result" off an 80-column table)
    width = max(7, console.width - numbers - 3 * len(heads) - 4)
    t.add_column("name", no_wrap=True, overflow="ellipsis", max_width=width)
    for c in heads:
        t.add_column(c, justify="left" if c == "result" else "right", no_wrap=True)
    shared = len(os.path.commonprefix([r[0] for r in rows])) if len(rows) > 1 else 0
    for r in rows:
        t.add_row(middle_cut(r[0], width, shared), *r[1:])
    console.print(t)
    for row in table.to_dict("records"):
        if row["other_hand_better"] in (True, "True"):
            console.print(f"warning: {Path(row['recording']).name}: {row['hand_check']}")
    also = "".join(f", {what} in {folder}" for what, folder in (("NAME.csv keypoints", template.keypoints),
                                                                 ("NAME/ overlays", template.overlay)) if folder)
    console.print(f"wrote {summary} (the outputs beside it: NAME.csv{also})")
    failed = table[table["error"] != ""]
    for err in failed["error"]:  # after the table, one line each, nothing printed after them
        print_error(err)
    if len(failed):
        raise typer.Exit(2)


def _short(x: float) -> str:
    """A time or a rate in at most 5 characters: one decimal below 100, none above (a still's start
    search, 3008.4 ms, was cut to "3008…" at 80 columns)."""
    return f"{x:.1f}" if abs(x) < 100 else f"{x:.0f}"


def middle_cut(name: str, width: int, shared: int = 0) -> str:
    """``name`` cut to ``width`` characters in its middle, where recordings of one session share their
    date (the 19 SR305 stills all read "20210326-23…" cut at the end), keeping its start and its end.
    ``shared``: how many leading characters every name of the table has in common; the cut then falls
    inside them when what follows fits, so that the part telling the names apart stays whole (at 80
    columns a new user's two takes both read "202…15_140" / "202…36_110", the takes' own digits cut).

    >>> middle_cut("20210326-230536_110", 12), middle_cut("short", 12)
    ('202…0536_110', 'short')
    >>> middle_cut("20210326-231615_140", 10), middle_cut("20210326-231615_140", 10, shared=11)
    ('202…15_140', '2…1615_140')
    """
    if len(name) <= width:
        return name
    rest = name[shared:]
    if 0 < shared and len(rest) + 2 <= width:
        return name[:width - 1 - len(rest)] + "…" + rest
    head = max((width - 1) // 3, 1)
    return name[:head] + "…" + name[len(name) - (width - 1 - head):]


def _check_every(overlay_every):
    """Refuse an ``--overlay-every`` below 1 (0 drew every frame, as 1 does, without a word)."""
    from .errors import TrackerError

    if overlay_every < 1:
        raise TrackerError("--overlay-every", f"must be ≥ 1 (1 = every frame), got {overlay_every}")


def _no_hand_hints(job, tracker) -> str:
    """What to check when no frame had a hand: the options given that can leave the hand out or
    misfit it first, then the camera preset and depth unit."""
    from .segment import Segmenter

    seg, default, st = job.segmenter or Segmenter(), Segmenter(), tracker.settings
    hints = []
    if (seg.z_min, seg.z_max) != (default.z_min, default.z_max):
        hints.append(f"the --depth-range {seg.z_min:g},{seg.z_max:g} m given")
    if seg.box_min is not None or seg.box_max is not None:
        hints.append("the --box given")
    if seg.forearm == "keep":
        hints.append("--forearm keep (the arm is fitted with the hand)")
    if st.scale.hand_scale != "auto" and not getattr(tracker.base_hand, "calibration", None):
        hints.append(f"the hand size {float(st.scale.hand_scale):g} given (--hand-scale auto estimates it)")
    if tracker.stats.no_hand > tracker.stats.too_few:
        # a mirror-image hand leaves more of a real hand unexplained: tracked as the left hand, 7 of the 19
        # labelled right-hand SR305 stills were "no hand"
        hints.append(f"that the hand is the {tracker.base_hand.handedness} one (--hand)")
    hints.append("the camera preset and depth unit (tracker info)" if hints
                 else "check the camera preset and depth unit with tracker info, or give --depth-range / --box")
    return ("check " + ", ".join(hints[:-1]) + " and " + hints[-1]) if len(hints) > 1 else hints[0]


def _hand_scale(text):
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
    _checked(ScaleSettings(hand_scale=value))
    return value


def evaluate(
    recording: Path = typer.Argument(..., help="Recording folder with truth.csv."),
    result: Path = typer.Argument(..., help="Output CSV of tracker track."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="PNG of the error per frame."),
    skip: int = typer.Option(0, "--skip", help="Leave out the first N frames (e.g. a lead-in)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --plot file."),
    check_recording: bool = typer.Option(True, "--check-recording/--no-check-recording", help="Refuse results whose header names another recording (folder name) or handedness than RECORDING's; --no-check-recording evaluates them anyway (a recording renamed since) [on]."),
):
    """Posture error (degrees, mean |Δ| of the 20 posture angles, as the paper), keypoint error (mm)."""
    from handmodel.fileio import check_output

    from .errors import TrackerError

    check_not_inputs([recording, result], [("--plot", plot)])
    if plot is not None:
        if plot.exists() and not overwrite and not plot.is_dir():
            raise TrackerError(plot, "exists and is never overwritten (use --overwrite)")
        check_output(plot, overwrite=overwrite)
    # heavy modules load here, not at import time, so `tracker --help` answers at once
    import numpy as np
    from rich.console import Console
    from rich.table import Table

    from handmodel import HandModel

    from .evaluate import summarise
    from .plots import error_plot
    from .io.recording import Recording
    from .io.tracking_file import read_tracking, tracked_hand
    from .sim.hands import truth_hand

    rec = Recording.open(recording)
    truth = rec.truth
    if truth is None:
        raise TrackerError(recording, "has no truth.csv to evaluate against")
    df, meta = read_tracking(result)
    if check_recording:
        check_same_recording(result, meta, recording, rec)
    # θ on the hand tracked (its file, size and finger lengths), the truth on the hand rendered
    hand = tracked_hand(meta, result)
    shown = truth_hand(recording) or HandModel.load(right=rec.handedness == "right")
    th = df[hand.dof_names].to_numpy(float)
    tr = np.asarray(truth[hand.dof_names] if hasattr(truth, "columns") else truth, float)
    if len(tr) != len(th):
        raise TrackerError(result, f"{len(th)} frames but the recording's truth has {len(tr)}")
    summ, pe, ke = summarise(hand, th[skip:], tr[skip:], df["status"].to_numpy()[skip:], df["ms"].to_numpy()[skip:],
                             truth_hand=shown)
    table = Table(title=f"evaluation of {result.name} against {recording}")
    table.add_column("measure")
    table.add_column("value", justify="right")
    for k, v in summ.items():
        table.add_row(k, f"{v:.3f}" if isinstance(v, float) else str(v))
    console = Console(markup=False)  # file names are printed as typed, never read as markup
    if plot is not None:  # before the table: an error must be the last thing printed
        error_plot(plot, pe, ke, df["status"].to_numpy()[skip:], title=f"{result.name} on {Path(recording).name}",
                   frames=df["frame"].to_numpy()[skip:])
    console.print(table)
    if plot is not None:
        console.print(f"wrote {plot}")


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
    hand_model = _hand_model(hand_model, paper)
    check_not_inputs([playback, _input_file(hand_model), _input_file(synergies)],
                      [("-o", output), ("--keypoints", keypoints), ("--overlay", overlay), ("--rerun", rerun),
                       ("--save", save)])
    _check_outputs(output, keypoints, overlay, rerun, overwrite)
    if save is not None:
        check_output(save, folder=True)
        if save.exists() and any(save.iterdir()) and not overwrite:
            raise TrackerError(save, "exists and is not empty (never overwritten; use --overwrite)")
    _check_every(overlay_every)
    segmenter = segmenter_from_options(depth_range, box, forearm, plane)
    settings = _settings(paper, mode, pcs, variance, None, None, None, None, None, None, None, None, None, None,
                         None, None, hand_scale, check_hand)

    # heavy modules (and the optional pyrealsense2) load here, so `tracker --help` answers at once
    import signal

    from rich.console import Console

    from .live import RealSenseSource
    from .io.recording import RecordingWriter
    from .run import TrackJob, run_job

    _say_if_compiling()

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
    _check_hand_file(output)
    hand_model = _hand_model(hand_model, False)
    check_not_inputs([recording, _input_file(hand_model), _input_file(synergies)], [("-o", output)])
    if output.exists() and not overwrite and not output.is_dir():
        raise TrackerError(output, "exists and is never overwritten (use --overwrite)")
    check_output(output, overwrite=overwrite)
    segmenter = segmenter_from_options(depth_range, box, forearm, plane)
    settings = _settings(False, "full", None, 0.99, None, None, None, None, None, None, None, None, None, None,
                         None, None, "auto", False)
    if finger_lengths is not None:
        settings = settings.replace(scale=dict(finger_lengths=finger_lengths))

    # heavy modules load here, not at import time, so `tracker --help` answers at once
    from rich.console import Console
    from rich.table import Table

    from .run import TrackJob, calibrate_job

    _say_if_compiling()

    job = TrackJob(recording=str(recording), output="", settings=settings, synergies=synergies,
                   registries=tuple(str(r) for r in registry or ()), hand_model=hand_model, segmenter=segmenter,
                   overwrite=overwrite, hand=_hand_side(hand), topic=topic, color_topic=color_topic, start_s=start)
    with progress_bar("calibrating") as progress:
        bar = progress.add_task("calibrate", total=None)
        out, tracker, used = calibrate_job(job, output, max_frames=frames, each=each,
                                           on_frame=lambda frame, r, ob: progress.advance(bar))
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
    app.command()(errors_exit_2(track))
    app.command()(errors_exit_2(calibrate))
    app.command()(errors_exit_2(live))
    app.command("eval")(errors_exit_2(evaluate))
