"""``tracker`` command line: import, info, show, synth, track, eval, experiments.

Heavy libraries are imported inside the commands so ``tracker --help`` answers at once. Bad input
prints one line ``error: …`` on stderr and exits 2.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .cli_common import check_not_inputs, check_same_recording, progress_bar, segmenter_from_options

app = typer.Typer(name="tracker", help="Synergistic hand tracking in depth recordings.", add_completion=False,
                  no_args_is_help=True, pretty_exceptions_enable=False, rich_markup_mode=None)


from handmodel.cliutil import errors_exit_2 as _errors_exit_2  # noqa: E402


_errors = _errors_exit_2  # the shared wrapper turns OS errors into one line as well


def _camera(camera, fx, fy, cx, cy, width, height, depth_scale, depth_encoding):
    """A preset (with any given value overriding it) or a camera from explicit intrinsics."""
    from .io.cameras import Camera, preset
    from .errors import TrackerError

    given = dict(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height, depth_scale_m=depth_scale,
                 depth_encoding=depth_encoding)
    given = {k: v for k, v in given.items() if v is not None}
    if camera:
        base = preset(camera)
        if not given:
            return base
        return Camera(**{**base.to_dict(), **given, "name": f"{base.name} (modified)"})
    lack = [f"--{k}" for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in given]
    if lack:
        raise TrackerError("camera", f"give --camera PRESET or all of --fx --fy --cx --cy --width --height "
                                     f"(missing {' '.join(lack)})")
    return Camera(**{"depth_scale_m": 0.001, "depth_encoding": "uint16", **given, "name": "custom"})


def _table(title: str, rows):
    from rich.console import Console
    from rich.table import Table

    t = Table(title=title, show_header=False)
    t.add_column("field")
    t.add_column("value")
    for k, v in rows:
        t.add_row(k, str(v))
    Console(markup=False).print(t)  # paths in the title and cells are shown as typed, never read as markup


def _recording_rows(rec) -> list:
    c = rec.camera
    n = len(rec)
    times = getattr(rec, "times_s", None)  # a recording file keeps its own frame times
    # first frame to last in both, so that a file and its import (frames at its nominal rate) agree
    span = (f"{times[-1] - times[0]:.2f} s first to last in file time, {rec.fps:g} fps nominal" if times is not None and n
            else f"{max(n - 1, 0) / rec.fps:.2f} s first to last, {rec.fps:g} fps")
    source = rec.source if times is not None else rec.meta.get("source", "")
    rows = [("source", source)] if source else []
    return rows + [("frames", f"{n} ({span})"),
            ("camera", f"{c.name}, {c.width}×{c.height}"),
            ("fx, fy / cx, cy (px)", f"{c.fx:.3f}, {c.fy:.3f} / {c.cx:.3f}, {c.cy:.3f}"),
            ("depth", f"{c.depth_encoding}, {c.depth_scale_m * 1000:g} mm per unit (max {c.max_depth_m:.2f} m)"),
            ("handedness", rec.handedness if times is None else
             f"{rec.handedness} (a recording file does not say: --hand right to import or track a right hand)"),
            ("colour", "yes" if rec.has_color else "no"),
            ("truth", "yes (truth.csv)" if rec.has_truth else "no")]


def _depth_stats(rec, every: int = 1, label: str = "reading"):
    """Valid-pixel fraction and depth percentiles over every ``every``-th frame (with a progress bar)."""
    import numpy as np

    idx = range(0, len(rec), max(every, 1))
    # a recording file reads its frames in one pass in order (by index each frame is a look-up)
    frames = rec.select(every=max(every, 1)) if hasattr(rec, "select") else (rec[i] for i in idx)
    valid, samples = [], []
    rng = np.random.default_rng(0)
    with progress_bar(label) as p:
        bar = p.add_task(label, total=len(idx))
        for frame in frames:
            d = frame.depth
            ok = np.isfinite(d)
            valid.append(ok.mean())
            v = d[ok]
            samples.append(v if v.size <= 20000 else rng.choice(v, 20000, replace=False))
            p.advance(bar)
    v = np.concatenate(samples) if samples else np.empty(0)
    return len(idx), float(np.mean(valid)) if valid else float("nan"), v


#: Depth units (metres per stored unit) of common cameras: 1 mm (Kinect, D4xx, Azure Kinect, ROS 16UC1),
#: 0.125 mm (SR300/SR305), 0.1 mm and 0.25 mm (other RealSense settings).
COMMON_UNITS_M = (0.001, 0.000125, 0.0001, 0.00025)


def depth_unit_warning(depths_m, scale_m: float, near: float = 0.2, far: float = 1.5):
    """A warning when almost none of the depth (metres, finite samples) lies within ``near``–``far``,
    where the tracker looks for a hand — a wrong camera preset or depth unit puts the scene metres away
    or centimetres close and every frame is then lost — naming the common units that would put it
    there; None when the depth looks right.

    >>> import numpy as np
    >>> print(depth_unit_warning(np.array([4.8, 5.6, 7.0]), 0.001))  # SR305 frames read as millimetres
    warning: no depth lies within 0.2–1.5 m, where the tracker looks for the hand (median 5600 mm at 1 mm per unit): a wrong --camera or --depth-scale? At 0.125 mm per unit the median would be 700 mm
    >>> depth_unit_warning(np.array([0.5, 0.9, 2.0]), 0.001) is None
    True
    """
    import numpy as np

    v = np.asarray(depths_m, float)
    v = v[np.isfinite(v) & (v > 0)]
    if not v.size:
        return None
    share = lambda x: float(np.mean((x >= near) & (x <= far)))  # noqa: E731
    # 1 % of the pixels is already a hand at arm's length in a 640×480 frame
    if share(v) >= 0.01:
        return None
    median = float(np.median(v))
    fits = [u for u in COMMON_UNITS_M if not np.isclose(u, scale_m) and share(v * u / scale_m) >= 0.05]
    # the unit that puts most of the scene in range; among equals, a median nearest arm's length
    best = min(fits, key=lambda u: (-share(v * u / scale_m), abs(median * u / scale_m - 0.7)), default=None)
    hint = "" if best is None else \
        f" At {best * 1000:g} mm per unit the median would be {median * best / scale_m * 1000:.0f} mm"
    return (f"warning: {'no' if share(v) == 0 else 'hardly any'} depth lies within {near:g}–{far:g} m, where the "
            f"tracker looks for the hand (median {median * 1000:.0f} mm at {scale_m * 1000:g} mm per unit): a wrong "
            f"--camera or --depth-scale?{hint}")


@app.command("import")
@_errors
def import_(
    src: Path = typer.Argument(..., help="Folder of depth PNGs (sorted by name in natural order), or a recording "
                                         "file: RealSense .bag/.db3, ROS1/ROS2 bag (.bag, .db3, .mcap or its "
                                         "folder), Azure Kinect .mkv (camera, depth unit and times from the file)."),
    output: Path = typer.Option(..., "-o", "--output", help="Recording folder to create."),
    topic: Optional[str] = typer.Option(None, "--topic", help="ROS bag: depth image topic (default: the RealSense "
                                                            "depth stream, or the one image topic named *depth*)."),
    color_topic: Optional[str] = typer.Option(None, "--color-topic", help="ROS bag: colour image topic, resampled "
                                                                        "onto the depth pixels (default: RealSense colour)."),
    start: Optional[float] = typer.Option(None, "--start", help="Recording file: first second to import (file time "
                                                              "from its first depth frame, as tracker info shows)."),
    end: Optional[float] = typer.Option(None, "--end", help="Recording file: last second to import (included)."),
    every: int = typer.Option(1, "--every", help="Recording file: import every N-th frame (the fps divides by N)."),
    camera: Optional[str] = typer.Option(None, "--camera", help="Preset: kinect1, kinect2, sr305, sr300, nyu; "
                                                              "the options below override its values."),
    fx: Optional[float] = typer.Option(None, "--fx", help="Focal length x (px)."),
    fy: Optional[float] = typer.Option(None, "--fy", help="Focal length y (px)."),
    cx: Optional[float] = typer.Option(None, "--cx", help="Principal point x (px, pixel centres at integers)."),
    cy: Optional[float] = typer.Option(None, "--cy", help="Principal point y (px)."),
    width: Optional[int] = typer.Option(None, "--width", help="Image width (px)."),
    height: Optional[int] = typer.Option(None, "--height", help="Image height (px)."),
    depth_scale: Optional[float] = typer.Option(None, "--depth-scale",
                                                help="Metres per stored depth unit (default 0.001 = mm)."),
    depth_encoding: Optional[str] = typer.Option(None, "--depth-encoding",
                                                 help="uint16 (16-bit PNG) or nyu_rgb (G·256+B of an RGB PNG)."),
    fps: Optional[float] = typer.Option(None, "--fps", help="Frame rate (Hz) of a folder of PNGs, whose names carry no times [30]."),
    hand: str = typer.Option("left", "--hand", "--handedness", help="Handedness of the recorded hand: left or right."),
    color: Optional[Path] = typer.Option(None, "--color", "--colour", help="Folder of colour frames registered to the depth (PNG or JPEG, one per depth PNG, same name order): used for skin segmentation."),
    each: bool = typer.Option(False, "--each", help="Still frames, not a video: one recording per PNG, "
                                                  "OUTPUT/<name>/, so that tracker track OUTPUT/* fits each from "
                                                  "its own first frame."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing recording in the output folder."),
):
    """Turn a plain folder of depth PNGs (and optionally their colour frames), or a recording file,
    into a recording folder (with --each, one per PNG). (tracker info, show and track also read
    recording files in place.)"""
    import time

    from .errors import TrackerError
    from .io.recording import import_pngs, import_recording_file, is_recording_file
    from handmodel.fileio import check_output


    if not src.exists():
        raise TrackerError(src, "no such folder or file")
    if is_recording_file(src):  # a folder of PNGs may hold its recording (-o pngs/rec); it is never the source
        check_not_inputs([src], [("-o", output)])
    check_output(output, folder=True)  # a read-only or full disk fails before any frame is read
    t0 = time.perf_counter()
    if is_recording_file(src):
        given = [o for o, v in (("--camera", camera), ("--fx", fx), ("--fy", fy), ("--cx", cx), ("--cy", cy),
                                ("--width", width), ("--height", height), ("--depth-scale", depth_scale),
                                ("--depth-encoding", depth_encoding), ("--color", color),
                                ("--fps", fps), ("--each", each or None)) if v is not None]
        if given:
            raise TrackerError(src, f"{', '.join(given)} do not apply: a recording file gives its own camera, "
                                    "frame rate and colour")
        with progress_bar("importing") as p:
            bar = p.add_task("import", total=None)
            rec = import_recording_file(src, output, topic=topic, color_topic=color_topic, start_s=start, end_s=end,
                                        every=every, handedness=hand, overwrite=overwrite,
                                        progress=lambda k, n: p.update(bar, completed=k, total=n))
        _imported(src, output, rec, time.perf_counter() - t0)
        return
    given = [o for o, v in (("--topic", topic), ("--color-topic", color_topic), ("--start", start), ("--end", end),
                            ("--every", None if every == 1 else every)) if v is not None]
    if given:
        raise TrackerError(src, f"{', '.join(given)} apply to recording files (.bag, .db3, .mcap, .mkv), "
                                "not to a folder of PNGs")
    cam = _camera(camera, fx, fy, cx, cy, width, height, depth_scale, depth_encoding)
    fps_given, fps = fps is not None, 30.0 if fps is None else fps
    if each:
        from .io.recording import import_stills

        with progress_bar("importing") as p:
            bar = p.add_task("import", total=None)
            recs = import_stills(src, output, cam, fps, hand, overwrite=overwrite,
                                 progress=lambda k, n: p.update(bar, completed=k, total=n), color=color)
        _imported_each(src, output, recs, time.perf_counter() - t0)
        return
    with progress_bar("importing") as p:
        bar = p.add_task("import", total=None)
        rec = import_pngs(src, output, cam, fps, hand, overwrite=overwrite,
                          progress=lambda k, n: p.update(bar, completed=k, total=n), color=color)
    _imported(src, output, rec, time.perf_counter() - t0)
    if not fps_given:
        # PNG names carry no times: the rate is the option's (the SR305 stills lie ~0.7 s apart)
        _print(f"note: {rec.fps:g} fps assumed (PNG files carry no frame times; give --fps to set it)")


def _imported(src, output, rec, seconds):
    """The import's summary: the recording, its depth over up to 30 frames spread through it, and a
    warning when the depth unit looks wrong (checked now, not after a run that loses every frame)."""
    rows = _recording_rows(rec)
    warning = None
    if len(rec):
        n, _, v = _depth_stats(rec, max(1, len(rec) // 30), "checking depth")
        rows += _depth_rows(v, f"over {n} of {len(rec)} frames" if n < len(rec) else "")
        warning = depth_unit_warning(v, rec.camera.depth_scale_m)
    _table(f"imported {src} → {output} ({seconds:.1f} s)", rows)
    if warning:
        _print(warning)


def _imported_each(src, output, recs, seconds):
    """The summary of ``import --each``: the recordings made, their depth, and how to track them."""
    import numpy as np

    first = recs[0]
    rows = [("recordings", f"{len(recs)}, one frame each: {recs[0].path.name} … {recs[-1].path.name}"
                           if len(recs) > 1 else f"1: {first.path.name}")]
    rows += [r for r in _recording_rows(first) if r[0] not in ("source", "frames")]
    checked = recs[::max(1, len(recs) // 30)]  # up to 30 frames spread through them, as for one recording
    rng = np.random.default_rng(0)
    v = np.concatenate([rng.permutation(d[np.isfinite(d)])[:20000] for d in (r[0].depth for r in checked)])
    rows += _depth_rows(v, f"over {len(checked)} of {len(recs)} frames" if len(checked) < len(recs) else "")
    _table(f"imported {src} → {output}/<name>/ ({seconds:.1f} s)", rows)
    warning = depth_unit_warning(v, first.camera.depth_scale_m)
    if warning:
        _print(warning)
    # with the bundle that ships (synergy list shows the others): without -s there are no synergies
    _print(f"track each from its own first frame: tracker track {Path(output) / '*'} -s fingerfist -o RESULTS/")


def _depth_rows(v, note=""):
    import numpy as np

    if not v.size:
        return [("depth", "no pixel has depth")]
    q = np.percentile(v, [1, 50, 99]) * 1000
    return [("depth 1 / 50 / 99 %", f"{q[0]:.0f} / {q[1]:.0f} / {q[2]:.0f} mm" + (f" ({note})" if note else ""))]


def _print(line: str) -> None:
    from rich.console import Console

    Console(markup=False, soft_wrap=True).print(line)  # one line, as typed, never read as markup


def _note(text: str) -> None:
    """A sentence for the reader, wrapped at the terminal's width (``_print`` keeps a line whole, for paths)."""
    from rich.console import Console

    Console(markup=False).print(text)


@app.command()
@_errors
def info(
    recording: Path = typer.Argument(..., help="Recording folder, or a recording file (.bag, .db3, .mcap, .mkv)."),
    quick: bool = typer.Option(False, "--quick", help="Metadata only; do not read the frames."),
    every: int = typer.Option(1, "--every", help="Read every N-th frame for the depth statistics."),
    topic: Optional[str] = typer.Option(None, "--topic", help="ROS bag: depth image topic."),
    color_topic: Optional[str] = typer.Option(None, "--color-topic", help="ROS bag: colour image topic."),
):
    """Summary of a recording (reads and checks every frame unless --quick)."""
    from .io.base import check_recording_path

    check_recording_path(recording, topic=topic, color_topic=color_topic)  # a mistyped path: said before the readers load
    from .io.recording import Recording

    rec = Recording.open(recording, topic=topic, color_topic=color_topic)
    rows = _recording_rows(rec)
    if not quick and len(rec):
        n, valid, v = _depth_stats(rec, every, "checking frames")
        rows.append(("frames read", f"{n} (all readable)"))
        rows.append(("pixels with depth", f"{100 * valid:.1f} % (mean per frame)"))
        if v.size:
            rows += _depth_rows(v)
    _table(str(rec.path), rows)
    if not quick and len(rec):
        warning = depth_unit_warning(v, rec.camera.depth_scale_m)
        if warning:
            _print(warning)


@app.command()
@_errors
def show(
    recording: Path = typer.Argument(..., help="Recording folder, or a recording file (.bag, .db3, .mcap, .mkv)."),
    output: Path = typer.Option(..., "-o", "--output", help="PNG contact sheet to write."),
    topic: Optional[str] = typer.Option(None, "--topic", help="ROS bag: depth image topic."),
    every: int = typer.Option(0, "--every", help="Every N-th frame (default: up to 16 frames spread evenly)."),
    max_frames: int = typer.Option(64, "--max-frames", help="At most this many panels."),
    near: Optional[float] = typer.Option(None, "--near", help="Colour scale start (m; default 1st percentile)."),
    far: Optional[float] = typer.Option(None, "--far", help="Colour scale end (m; default 99th percentile)."),
    mask: bool = typer.Option(True, "--mask/--no-mask", help="Outline the hand as the tracker segments it (default settings and the options below)."),
    depth_range: Optional[str] = typer.Option(None, "--depth-range", help="NEAR,FAR (m) for the mask, as in tracker track."),
    box: Optional[str] = typer.Option(None, "--box", help="X0,Y0,Z0,X1,Y1,Z1 (m) for the mask, as in tracker track."),
    forearm: str = typer.Option("cut", "--forearm", help="cut or keep, for the mask, as in tracker track."),
    plane: str = typer.Option("auto", "--plane", help="auto, cut or keep, for the mask, as in tracker track."),
    frame: Optional[int] = typer.Option(None, "--frame", help="Only this frame (a Rerun .rrd: the logged frame "
                                                              "to draw; default its last frame with a hand)."),
    keypoints: Optional[Path] = typer.Option(None, "--keypoints", help="Keypoints CSV of tracker track "
                                             "(--keypoints kp.csv) of this recording: draw each shown frame's fitted "
                                             "skeleton, thumb orange, wrist a blue square."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing output file."),
    check_recording: bool = typer.Option(True, "--check-recording/--no-check-recording", help="Refuse a --keypoints CSV whose header names another recording (folder name) or handedness; --no-check-recording draws it anyway [on]."),
):
    """Contact sheet of depth frames, colour-mapped in mm; pixels without depth are light grey; the
    segmented hand outlined in white. With --keypoints the depth in greys (white = no depth), the mask
    outlined in green and the fitted skeletons. Given a Rerun recording of
    a tracking (tracker track --rerun out.rrd), a picture of one logged frame instead: the depth with the
    mask and the fitted skeleton, and the points and hand in 3-D (no viewer or screen needed; extra [viz])."""
    from .errors import TrackerError
    from handmodel.fileio import check_output


    check_not_inputs([recording, keypoints], [("-o", output)])
    if output.suffix.lower() != ".png":
        raise TrackerError(output, "the picture is written as PNG: name it .png")
    if output.exists() and not overwrite and not output.is_dir():
        raise TrackerError(output, "exists and is never overwritten (use --overwrite)")
    check_output(output, overwrite=overwrite)  # before the frames are read
    if recording.suffix.lower() == ".rrd":
        given = [o for o, v in (("--topic", topic), ("--every", every or None), ("--near", near), ("--far", far),
                                ("--depth-range", depth_range), ("--box", box), ("--keypoints", keypoints),
                                ("--plane", None if plane == "auto" else plane))
                 if v is not None]
        if given:
            raise TrackerError(recording, f"{', '.join(given)} {'does' if len(given) == 1 else 'do'} not apply to a "
                                          "Rerun recording (it holds the tracking's own depth and mask)")
        from .viewer import snapshot_png  # an optional extra ([viz]): loaded only for a .rrd

        snapshot_png(recording, output, frame, overwrite=overwrite)
        _print(f"wrote {output}")
        return

    if every < 0 or max_frames < 1:
        raise TrackerError("show", "--every must be ≥ 0 and --max-frames ≥ 1")
    from .io.base import check_recording_path

    check_recording_path(recording, topic=topic)  # a mistyped path: said before matplotlib and the readers load

    import numpy as np

    from .plots import contact_sheet
    from .io.recording import Recording

    segmenter = segmenter_from_options(depth_range, box, forearm, plane) if mask else None
    rec = Recording.open(recording, topic=topic)
    n = len(rec)
    if n == 0:
        raise TrackerError(recording, "has no frames")
    if frame is not None and not 0 <= frame < n:
        raise TrackerError(recording, f"has frames 0–{n - 1}, not {frame}")
    idx = [frame] if frame is not None else list(range(0, n, every)) if every > 0 else \
        sorted(set(np.linspace(0, n - 1, min(n, 16)).round().astype(int)))
    shown = idx[:max_frames]
    hand = fitted = None
    if keypoints is not None:
        from handmodel import HandModel

        from .plots import project

        hand = HandModel.load()  # its bones only: the keypoints are the fitted hand's own
        fitted, meta = _keypoints_by_frame(keypoints, hand.keypoint_names, n)
        if check_recording:
            check_same_recording(keypoints, meta, recording, rec)
    depths, masks, times = [], [], []
    with progress_bar("reading") as p:
        bar = p.add_task("read", total=len(shown))
        for i in shown:
            frame = rec[i]
            depths.append(frame.depth * 1000.0)
            times.append(frame.time_s)
            if segmenter is not None:
                from .observe import observe

                masks.append(observe(frame.depth, rec.camera, segmenter=segmenter, color=frame.color).mask)
            p.advance(bar)
    # what the segmenter kept, before any fit tests it is a hand (a mug, a door's edge: tracker track says so)
    key = ["grey = no depth", "white = segmented"] if fitted is None else \
        ["white = no depth", "green = segmented", "fitted skeletons: thumb orange, wrist blue"]
    if segmenter is None:
        key.remove(key[1])
    skeletons = None if fitted is None else \
        [None if fitted.get(i) is None else np.stack(project(fitted[i], rec.camera), 1) for i in shown]
    lo, hi = contact_sheet(
        output, depths, [f"#{i}  {t:.2f} s" for i, t in zip(shown, times)],
        f"{rec.path.name}: {n} frames, {rec.camera.name} {rec.camera.width}×{rec.camera.height}; " + "; ".join(key),
        near_mm=None if near is None else near * 1000, far_mm=None if far is None else far * 1000,
        overwrite=overwrite, masks=masks if segmenter is not None else None, skeletons=skeletons, hand=hand)
    valid = np.mean([np.isfinite(d).mean() for d in depths])
    drawn = [] if fitted is None else [("fitted skeletons", f"{sum(fitted.get(i) is not None for i in shown)} of "
                                                           f"{len(shown)} frames shown ({keypoints})")]
    _table(f"wrote {output}", drawn + [
        ("frames shown", f"{len(shown)} of {n}"
         + (f" (the first {max_frames} of {len(idx)} selected)" if len(idx) > len(shown) else "")),
        ("colour scale", f"{lo:.0f}–{hi:.0f} mm"), ("pixels with depth", f"{100 * valid:.1f} %")])
    warning = depth_unit_warning(np.concatenate([np.ravel(d) for d in depths]) / 1000.0, rec.camera.depth_scale_m)
    if warning:
        _print(warning)
    if segmenter is not None and fitted is None:
        _note("the outline is what the segmenter kept, not yet tested to be a hand: tracker track says when "
              "a frame has none (a mug, a wall)")


def _keypoints_by_frame(path, names, n_frames):
    """``(frames, header)``: frame index → (K, 3) keypoints in metres of a keypoints CSV (``tracker track
    --keypoints``, :func:`tracker.io.tracking_file.read_keypoints`), frames without a fit (NaN) left out, and its
    ``# key: value`` header; refused when its columns or frames do not fit the recording."""
    import numpy as np
    import pandas as pd

    from .errors import TrackerError
    from .io.tracking_file import read_keypoints

    df, meta = read_keypoints(path, names)
    cols = [f"{k}_{a}_mm" for k in names for a in "xyz"]
    frames = pd.to_numeric(df["frame"], errors="coerce").to_numpy(float)
    if len(frames) and (not np.isfinite(frames).all() or frames.min() < 0 or frames.max() >= n_frames):
        raise TrackerError(path, f"has frames up to {np.nanmax(frames):g}, the recording {n_frames} "
                                 "(keypoints of another recording?)")
    xyz = df[cols].apply(pd.to_numeric, errors="coerce").to_numpy(float).reshape(len(df), len(names), 3) / 1000.0
    return {int(f): k for f, k in zip(frames, xyz) if np.isfinite(k).all() and (k[:, 2] > 0).all()}, meta


@app.command("compile")
@_errors
def compile_kernels():
    """Compile the tracker's kernels for this machine once (numba's cache, a few minutes; run it after
    pip install, as make does): the first tracker track then starts at once."""
    from .compile import main as compile_main

    compile_main()


# the synth and experiments commands live with the synthetic lab; tracker.sim.cli imports only typer
# at the top (the lab's libraries load when a command runs), as the track, live, calibrate and eval
# modules do, so registering them keeps --help fast
from tracker import eval_cli, live_cli, track_cli  # noqa: E402
from tracker.sim import cli as sim_cli  # noqa: E402

sim_cli.register(app, _errors_exit_2)
track_cli.register(app, _errors_exit_2)
live_cli.register(app, _errors_exit_2)
eval_cli.register(app, _errors_exit_2)


def run_command() -> None:
    """The command of ``sys.argv`` as the ``tracker`` program runs it, ending as typer ends every command
    (``SystemExit``): for code that goes on after it (a test); the program itself is :func:`main`.

    ``gc.freeze()`` on the way out: the interpreter's shutdown would otherwise walk the ~200,000 objects
    of numpy, pandas, numba and the loaded kernels with the cyclic collector, ~0.4 s of a 2.7 s ``tracker
    track`` of one still (``benchmarks/bench_startup.py``), to free memory the process is about to give
    back anyway; a tracking command freezes its start-up's objects as soon as it has started
    (:class:`tracker.cli_common.StartUp`). Only in the program: ``app`` called in a process that goes on
    (a test's ``CliRunner``) collects as usual."""
    import gc

    from .cli_common import StartUp

    StartUp.program = True
    try:
        app()
    finally:
        gc.freeze()


def main() -> None:
    """The ``tracker`` program (its console script, ``python -m tracker.cli``): :func:`run_command`, then
    the process ends with the command's exit status at once (:func:`_end_now`)."""
    try:
        run_command()
    except SystemExit as exc:
        _end_now(exc.code)
        raise


def _end_now(code) -> None:
    """End the process with exit status ``code`` (``SystemExit.code``: None or a number) without the
    interpreter's teardown, after what of it matters: other threads joined (a worker pool's idle threads
    let go), every ``atexit`` callback run in its order (temporary folders, process pools, a coverage
    collector), Python's and the C library's output buffers flushed.

    The teardown frees what the process is about to give back whole: the loaded kernels' LLVM modules,
    onnxruntime's session, every module's objects, 0.07 s of a one-still ``tracker track`` on an idle
    machine and 0.1 s or more under load (``benchmarks/bench_startup.py``; perf: LLVM's destructors,
    ``free``, module clean-up). Returns, leaving the exit to the interpreter, where it cannot end the
    process as the interpreter would: a ``code`` that is not a number (printed, then status 1), an
    output stream that cannot be flushed (status 120 and a message), a Python without the hooks
    (``threading._shutdown``, ``atexit._run_exitfuncs``: CPython's own exit calls them)."""
    import atexit
    import os
    import sys
    import threading

    shutdown, callbacks = getattr(threading, "_shutdown", None), getattr(atexit, "_run_exitfuncs", None)
    if not (code is None or isinstance(code, int)) or shutdown is None or callbacks is None:
        return
    shutdown()
    callbacks()  # each runs once: the interpreter's exit, if it still comes, finds none left
    try:
        for stream in (sys.stdout, sys.stderr):
            if stream is not None:
                stream.flush()
    except (OSError, ValueError):  # a closed pipe, a closed stream: the interpreter's exit says so
        return
    import ctypes

    ctypes.CDLL(None).fflush(None)  # what C libraries wrote with stdio (the process's own libc)
    os._exit(code or 0)


if __name__ == "__main__":
    main()
