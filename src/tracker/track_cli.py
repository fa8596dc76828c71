"""``tracker track``: track one recording, or many (one by one or on Dask), and say what the tracking
found.

``register(app, errors_exit_2)`` adds the command to the ``tracker`` typer app. It only parses, calls
:mod:`tracker.run` (many recordings: :mod:`tracker.batch`), prints and draws progress; heavy modules are
imported inside it so ``tracker --help`` stays fast. What it shares with ``tracker live`` and ``tracker
calibrate`` (options, output checks, the settings of the options) is :mod:`tracker.cli_common`'s.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import List, Optional

import typer

from .cli_common import (BOX, COLOR_TOPIC, DEPTH_RANGE, FOREARM, HAND, PLANE, START, TOPIC, check_not_inputs,
                         check_outputs, check_overlay_every, chosen_hand_model, hand_side, input_file,
                         progress_bar, say_if_compiling, segmenter_from_options, settings_from_options, StartUp)


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
    size_refine: Optional[str] = typer.Option(None, "--size-refine", help="With --hand-scale auto, how the frames after the first refine the size: checked (around the tracked fit, spread over frames; a frame searched only where the fit is poor), local (around the tracked fit only) or search (each of the first frames searched: slow frames 1-4; realistic scenes 2.81 against 2.89 mm) [checked]."),
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
    detector: Optional[str] = typer.Option(None, "--detector", help="The depth keypoint detector whose hand the searches start from (starts, size calibration, the safety net's search beyond the tracked pose), the full search only where that fits poorly: a name or file under models/detectors/ [hand-keypoints-cnn, the shipped keypoint CNN; none with --paper]."),
    presence: Optional[str] = typer.Option(None, "--presence", help="The hand-presence network asked before a start searches whether its region is a hand at all (a region it calls no hand is lost without a search, unless the detected hand fits it as an accepted start does): a name or file under models/detectors/ [hand-presence-cnn, the shipped network; none with --paper]."),
    no_presence: bool = typer.Option(False, "--no-presence", help="No hand-presence network: every region is searched and the fit's rejections decide whether it is a hand."),
    keypoint_term: Optional[bool] = typer.Option(None, "--keypoint-term/--no-keypoint-term", help="The keypoint CNN's keypoints in each tracked frame's fit where the last fit left joints without data (a fist's fingers): nearer on fists seen from the side, farther on grasps seen from the back, which the synergy prior fills [off]."),
    no_detector: bool = typer.Option(False, "--no-detector", help="No learned detector (the keypoint CNN, the hand-presence network): every start is the full search (as with --paper)."),
    detector_accept_mm: Optional[float] = typer.Option(None, "--detector-accept-mm", help="The score (mm) at or under which the detected hand's fit is the start and the full search does not run [1.5; 0 = the search always runs]."),
    search_budget_ms: Optional[float] = typer.Option(None, "--search-budget-ms", help="A start search's budget in ms: once spent, its optional stages are skipped and its best start so far converged (the result then depends on the machine's speed; the summary counts the searches cut) [0 = none]."),
    threads: Optional[int] = typer.Option(None, "--threads", min=0, help="Threads for the fits of a start search (the first frame, a lost frame, the safety net); the result is the same for any count [0 = the cores, at most 4; never more than the cores; 1 per recording with --dask]."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing output files."),
):
    """Track the hand through one or many recordings; writes per-frame hand parameters and a summary."""
    from .errors import TrackerError

    if rgb_seed:
        from .rgb import require_mediapipe  # light: finds mediapipe without importing it

        require_mediapipe("--rgb-seed")

    hand_model = chosen_hand_model(hand_model, paper)
    check_not_inputs([*recordings, input_file(hand_model), input_file(synergies)],
                      [("-o", output), ("--keypoints", keypoints), ("--overlay", overlay), ("--rerun", rerun),
                       ("--save-hand", save_hand)])
    if len(recordings) > 1 or dask is not None:
        per_file = [n for n, v in (("--rerun", rerun), ("--rerun-spawn", rerun_spawn), ("--save-hand", save_hand)) if v]
        if per_file:
            raise TrackerError(per_file[0], "is for one recording; with several, -o is a folder of NAME.csv "
                                            "and summary.csv, --keypoints and --overlay folders of NAME.csv and "
                                            "NAME/ (track a recording alone for its other outputs)")
        check_outputs(output, None, None, None, overwrite, folder=True)
        for name, folder in (("--keypoints", keypoints), ("--overlay", overlay)):
            if folder is not None:
                if folder.resolve() == output.resolve():
                    raise TrackerError(name, f"needs a folder of its own, not -o's ({folder})")
                check_outputs(folder, None, None, None, overwrite, folder=True)
    else:
        check_outputs(output, keypoints, overlay, rerun, overwrite, save_hand=save_hand)
    check_overlay_every(overlay_every)
    if len(recordings) == 1 and dask is None:
        from .io.base import check_recording_path

        # a mistyped path fails now, not after ~1 s of the imports below (io.base loads no numpy); with
        # several, each failing one is a row of the summary and the others are tracked
        check_recording_path(recordings[0], topic=topic, color_topic=color_topic, handedness=hand_side(hand))
    # the collector is off until the first frame's result is in (cli_common.StartUp)
    with StartUp() as start_up:
        segmenter = segmenter_from_options(depth_range, box, forearm, plane)
        # Dask's workers already run recordings side by side
        threads = 1 if threads is None and dask is not None else threads
        settings = settings_from_options(paper, mode, pcs, variance, stride, smooth, points, icp, gn, damping, model, silhouette,
                             prediction, robust, finger_search, projected_steps, hand_scale, check_hand,
                             rgb_seed=rgb_seed, finger_lengths=finger_lengths, safety_net=safety_net,
                             unseen_prior=unseen_prior, no_hand=no_hand, threads=threads,
                             search_budget_ms=search_budget_ms, detector=detector,
                             detector_accept_mm=detector_accept_mm, no_detector=no_detector, presence=presence,
                             no_presence=no_presence, size_refine=size_refine, keypoint_term=keypoint_term)

        # heavy modules load here, not at import time, so `tracker --help` answers at once
        from .run import TrackJob

        say_if_compiling()

        job = TrackJob(recording=str(recordings[0]), output=str(output), settings=settings, synergies=synergies,
                       registries=tuple(str(r) for r in registry or ()), hand_model=hand_model, segmenter=segmenter,
                       keypoints=None if keypoints is None else str(keypoints),
                       overlay=None if overlay is None else str(overlay), overlay_every=overlay_every,
                       rerun=None if rerun is None else str(rerun), rerun_spawn=rerun_spawn, overwrite=overwrite,
                       hand=hand_side(hand), topic=topic, color_topic=color_topic, start_s=start, end_s=end, every=every,
                       save_hand=None if save_hand is None else str(save_hand), hand_scale_asked=hand_scale is not None)
        if len(recordings) > 1 or dask is not None:
            start_up.done()  # the modules are loaded; the recordings are tracked with the collector on
            _track_many(recordings, output, job, dask, overwrite)
            return
        _track_one(job, recordings[0], output, keypoints, overlay, mode, paper, start_up)


def _track_one(job, recording, output, keypoints, overlay, mode, paper, start_up):
    """One recording: progress bar, outputs, the result table; ``start_up`` (:class:`StartUp`) is done at
    the first frame's result."""
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

        def each(frame, r, ob):
            progress.advance(bar)
            start_up.done()

        run = run_job(job, each, source=rec)
    # the table without pandas (run.table: its import is ~0.2 s of a one-still run)
    rows, tracker, rec, wall_s = run.table, run.tracker, run.recording, run.wall_s
    n_pcs = f", {tracker.n_pcs} PCs" if tracker.n_pcs and mode != "full" else ""
    table = Table(title=f"tracked {recording} ({mode}{n_pcs}{', paper' if paper else ''})")
    for c in ("frames", "tracked", "lost", "reinit", "median fit mm", "median ms", "fps median", "fps run"):
        table.add_column(c, justify="right")
    st = rows.column("status")
    found = [s != "lost" for s in st]
    # the median frame's rate counts frames with a hand only (a lost frame costs nothing and would show a
    # rate no tracking reached); the run's rate is the wall time of everything (reading, segmenting, the
    # start search, overlays); one decimal so a slow run never shows as 0
    ms = _median([m for m, f in zip(rows.column("ms"), found) if f]) if any(found) else float("nan")
    table.add_row(str(len(rows)), str(st.count("tracked")), str(st.count("lost")),
                  str(st.count("reinit")), f"{_median(rows.column('fit_mm')):.2f}" if any(found) else "-",
                  f"{ms:.1f}" if any(found) else "-", f"{1000 / ms:.1f}" if ms > 0 else "-",
                  f"{len(rows) / wall_s:.1f}" if wall_s > 0 else "-")
    console = Console(markup=False)  # paths are printed as typed, never read as markup
    console.print(table)
    if tracker.stats.no_hand:
        # what was segmented was too small to start from, or its fit left too much unexplained to be a hand
        # (LossSettings.start_min_pixels, no_hand_rejected)
        st, few, out = tracker.settings, tracker.stats.too_few, tracker.stats.size_out
        absent = tracker.stats.not_hands
        why = [f"{few} with fewer than {st.loss.start_min_pixels} pixels to start from"] if few else []
        if absent:
            why.append(f"{absent} that the hand-presence network ({st.start.presence}) called no hand "
                       f"(p < {st.start.presence_below:g})")
        if tracker.stats.no_hand > few + out + absent:
            why.append(f"{tracker.stats.no_hand - few - out - absent} whose fit rejected more than "
                       f"{st.loss.no_hand_rejected:.0%} of the points")
        if out:
            lo, hi = st.scale.range
            why.append(f"{out} fitted at the end of the hand sizes searched ({lo:g}–{hi:g}× the model)")
        console.print(f"no hand: on {tracker.stats.no_hand} frame{'s' * (tracker.stats.no_hand != 1)} what was segmented is no "
                      f"hand ({'; '.join(why)}); those frames are lost, without θ")
    stats, start = tracker.stats, tracker.settings.start
    for n, line in ((stats.hands_fitted, "the hand-presence network called {} no hand where the detected hand fitted "
                                         f"within {start.detector_accept_mm:g} mm: searched as hands"),
                    (stats.jumps_refused, "on {} the tracked points left the predicted hand, or its fit was "
                                          "doubtful, on a region the hand-presence network called no hand: the "
                                          "prediction given (status predicted)"),
                    (stats.surface_starts, "on {} the region segmented was no hand, and the start began on the hand "
                                           "the keypoint CNN found along its surface (an arm's far end)"),
                    (stats.wrist_cuts, "on {} the points more than " + f"{start.detector_wrist_m:g} m behind the "
                                       "detected wrist (an arm the segmentation kept) were left out"),
                    (stats.keypoint_frames, "on {} the keypoint CNN's keypoints joined the fit (joints the depth "
                                            "data left unseen, e.g. a fist's fingers; refine.keypoints)")):
        if n:
            console.print(line.format(f"{n} frame{'s' * (n != 1)}"))
    if len(rows) and not any(found):
        why = ("nothing segmented looks like a hand" if tracker.stats.no_hand
               else "nothing segmented where a hand can be")
        console.print(f"warning: no hand found in any frame of {recording}: {why} ({_no_hand_hints(job, tracker)})")
    if tracker.base_hand.calibration and tracker.settings.scale.hand_scale != "auto":
        console.print(f"hand: the calibrated hand of {tracker.base_hand.path} (size {tracker.base_hand.calibration['hand_scale']}"
                      " in the file), not estimated again")
    elif tracker.scale_ is not None and tracker.settings.scale.hand_scale == "auto" and any(found):
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
    elif tracker.scale_ is not None and any(found):
        console.print(f"hand size: {run.meta['hand_scale']}")
    if tracker.stats.size_starts:
        console.print(f"start: the fit replaced on {tracker.stats.size_starts} of the size-refining frames by their own "
                      "search's, which scored better")
    if tracker.settings.net.enabled and tracker.settings.mode != "reduced" and len(rows):
        runs = tracker.stats.net_runs
        cost = f", {tracker.stats.net_ms / runs:.0f} ms per run" if runs else ""
        wrong = f" (on {tracker.stats.net_wrong_way} the hand pointed against the arm)" if tracker.stats.net_wrong_way else ""
        console.print(f"safety net: ran on {runs}/{len(rows)} frames ({runs / len(rows):.0%}){wrong}, replaced "
                      f"{tracker.stats.net_replaced}{cost}; re-centred {tracker.stats.recentred}")
    if tracker.settings.start.search_budget_ms and tracker.stats.searches:
        st = tracker.stats
        console.print(f"start searches: {st.searches}, {st.searches_cut} cut short by the "
                      f"{tracker.settings.start.search_budget_ms:g} ms budget; {st.search_ms / st.searches:.0f} ms each"
                      + (f"; the net's cut short on {st.net_cut} frames" if st.net_cut else ""))
    if tracker.settings.start.detector:
        st = tracker.stats
        # the size calibration's frames detect too but are not starts: counted in the hands found only
        console.print(f"detector: {tracker.settings.start.detector} found a hand {st.detector_seeds} times (starts, "
                      f"size calibration, the net's searches); starts from its hand alone: {st.detector_starts}, with the "
                      f"full search: {st.searches}")
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
        raise TrackerError(recording, unreadable_text(run.unreadable, len(rows)))


def _median(values) -> float:
    """The median of ``values`` without the NaN ones, NaN when none is left: pandas' ``Series.median``
    (numpy's median of the values kept), without pandas."""
    import numpy as np

    x = np.asarray(values, dtype=float)
    x = x[~np.isnan(x)]
    return float(np.median(x)) if x.size else float("nan")


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
            check_outputs(None, None, Path(j.overlay), None, overwrite)
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


def register(app, errors_exit_2) -> None:
    app.command()(errors_exit_2(track))
