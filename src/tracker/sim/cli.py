"""The synthetic lab's commands: ``tracker synth`` (render a motion into a recording folder with
ground truth), ``tracker experiments`` (the paper's experiments, written as a report) and
``tracker train-detector`` (the hand detectors trained on our renders: the part forest,
:mod:`tracker.sim.train_detector`, or the keypoint CNN, :mod:`tracker.sim.train_cnn`).

``register(app, wrap)`` adds them to the ``tracker`` typer app. The library modules (numba, pandas,
matplotlib behind them) are imported inside the commands, not at the top, so that ``tracker --help``
stays fast. Bad input raises :class:`handmodel.errors.ToolkitError` subclasses; with the app's
``wrap`` they print on one line and exit 2.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .. import TRACKING_HAND

MOTION_HELP = "Scenario name (see --list) or a motion file: .csv joint-angle table, .txt/.dat schroeder26 postures."


def synth(
    motion: str = typer.Option("open-close", "--motion", "-m", help=MOTION_HELP),
    camera: str = typer.Option("kinect1", "--camera", "-c", help="Camera preset (tracker.io.cameras)."),
    noise: str = typer.Option("kinect1", "--noise", "-n", help="Noise preset: none, kinect1, sr305 (= realsense), d4xx."),
    frames: Optional[int] = typer.Option(None, "--frames", "-f", help="Number of frames (default: the whole motion)."),
    fps: float = typer.Option(30.0, "--fps", help="Frame rate of the recording."),
    seed: int = typer.Option(0, "--seed", help="Seed of the noise (and of random scenarios)."),
    clutter: str = typer.Option("none", "--clutter", help="Extra geometry, comma-separated: forearm, sleeve (sleeved "
                                "forearm), torso or torso=GAP_M (0.03-0.30 m behind the hand), table, object/box/cylinder; "
                                "or none."),
    hand_scale: float = typer.Option(1.0, "--hand-scale", help="Rendered hand size relative to the model (0.5-2; "
                                     "real adult hands are about 0.8-1.7 x the default model)."),
    finger_scale: Optional[str] = typer.Option(None, "--finger-scale", help="Finger length factors (0.7-1.3): one "
                                               "for all, five (thumb,index,middle,ring,pinky) or name=factor pairs."),
    color: bool = typer.Option(False, "--color/--no-color", help="Also write skin-coloured colour frames."),
    hand_model: str = typer.Option(TRACKING_HAND, "--hand-model", help="Hand model name or YAML path [human: the hand tracker track fits; default: the paper's]."),
    right: bool = typer.Option(False, "--right", help="Render the right hand (mirror image, same θ)."),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="Recording folder to write."),
    list_: bool = typer.Option(False, "--list", help="List the scenarios and noise presets and exit."),
):
    """Render a hand motion with sensor noise into a recording folder (depth, truth.csv)."""
    from rich.console import Console

    from handmodel.fileio import check_output

    from ..errors import TrackerError

    console = Console(markup=False)  # names and paths are shown as typed, never read as markup
    if list_:
        console.print(_listing())
        return
    if output is None:
        raise TrackerError("synth", "give the output folder with -o/--output")
    check_output(output, folder=True)  # a read-only or full disk fails before anything is rendered
    if frames is not None and frames < 1:
        raise TrackerError("--frames", f"must be at least 1, got {frames}")
    if not fps > 0:
        raise TrackerError("--fps", f"must be positive, got {fps}")

    # the lab's libraries (numba kernels, pandas) load here, not at the top: ``tracker --help`` stays fast
    from rich.markup import escape
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from handmodel import HandModel

    from .hands import HandShape
    from .motions import make_motion
    from .noise import NoiseModel
    from ..io.cameras import as_camera
    from .clutter import Clutter
    from .synthesize import synthesize

    clut = Clutter.parse(clutter)
    nm = NoiseModel.preset(noise)
    shape = HandShape.parse(hand_scale, finger_scale)
    hand = HandModel.load(hand_model, right=right)
    m = make_motion(motion, hand=shape.apply(hand), frames=frames, fps=fps, seed=seed)
    cam = as_camera(camera)

    err = Console(stderr=True)
    columns = (TextColumn("[progress.description]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TimeRemainingColumn())
    with Progress(*columns, console=err, transient=True, disable=not err.is_terminal) as progress:
        bar = progress.add_task(f"rendering {escape(m.name)}", total=m.frames)
        report = synthesize(m, cam, nm, output, fps=fps, seed=seed, hand=hand, clutter=clut, color=color, shape=shape,
                            progress=lambda done, total: progress.update(bar, completed=done))
    console.print(_summary(report, "none" if clut is None else clut.describe(), color, hand))


def _summary(rep, clutter: str, color: bool, hand):
    from rich.table import Table

    t = Table(title=f"synthetic recording {rep.path}", show_header=False)
    t.add_column("", style="bold")
    t.add_column("", overflow="fold")
    t.add_row("motion", rep.motion)
    t.add_row("frames", f"{rep.frames} at {rep.fps:g} fps ({rep.frames / rep.fps:.1f} s)")
    t.add_row("hand", f"{hand.name} ({hand.handedness}), rendered × {rep.hand_scale:g}: "
                      f"{rep.hand_length_mm:.0f} mm wrist to middle tip")
    t.add_row("camera", rep.camera)
    t.add_row("noise", rep.noise)
    t.add_row("clutter", clutter)
    t.add_row("colour", "yes" if color else "no")
    t.add_row("hand pixels / frame", f"{rep.hand_pixels:.0f}")
    t.add_row("hand pixels with depth", f"{100 * rep.valid_fraction:.1f} %")
    t.add_row("clutter pixels / frame", f"{rep.clutter_pixels:.0f}")
    lo, hi = rep.depth_range_m
    t.add_row("hand depth", f"{1000 * lo:.0f}–{1000 * hi:.0f} mm")
    t.add_row("render / noise", f"{rep.render_ms:.2f} ms / {rep.noise_ms:.2f} ms per frame")
    t.add_row("total", f"{rep.seconds:.1f} s")
    return t


def _listing():
    from rich.table import Table

    from .motions import SCENARIOS
    from .noise import ALIASES, PRESETS

    t = Table(title="motions and noise presets")
    t.add_column("kind", style="bold")
    t.add_column("name")
    t.add_column("description", overflow="fold")
    for sc in SCENARIOS.values():
        t.add_row("motion", sc.name, f"{sc.description} [{sc.seconds:g} s]")
    for nm in PRESETS.values():
        parts = [p for p, on in (("axial σ(z)", nm.axial), ("lateral", nm.lateral_px > 0),
                                 ("quantisation", nm.quantize), ("shadows", nm.shadow),
                                 ("edge dropout", nm.edge_drop_prob > 0), ("flying pixels", nm.flying_prob > 0),
                                 ("grazing holes", nm.grazing_deg is not None), ("dark holes", nm.dark_drop_prob > 0),
                                 ("depth steps", nm.depth_step_m > 0), ("random dropout", nm.random_drop_prob > 0))
                 if on]
        alias = [a for a, n in ALIASES.items() if n == nm.name]
        t.add_row("noise", nm.name + (f" (= {', '.join(alias)})" if alias else ""), ", ".join(parts) or "noise-free")
    return t


def experiments(
    output: Path = typer.Option(..., "-o", "--output", help="Report folder (report.md + PNGs)."),
    quick: bool = typer.Option(False, "--quick", help="Fewer sequences and settings (a few minutes)."),
    only: Optional[str] = typer.Option(None, "--only", help="Run one part: paper (the paper's experiments), "
                                       "realistic (clutter x sensor noise x hand size) or real (needs --real-data)."),
    jobs: int = typer.Option(1, "--jobs", "-j", min=1, help="Worker processes (the parts run side by side)."),
    real_data: Optional[Path] = typer.Option(None, "--real-data", help="Folder of labelled real SR305 frames "
                                             "(../shared/data/realsense_sr305_lada): their section and overlays."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the report a folder holds already."),
):
    """Reproduce the paper's experiments on our renderer, and realistic scenes (clutter, RealSense and
    Kinect v1 noise, hand sizes); writes report.md with tables and plots."""
    from handmodel.fileio import check_output

    from ..errors import TrackerError

    # before the progress bar: an error inside it would follow the bar's blank line
    if only == "real" and real_data is None:
        raise TrackerError("experiments", "the real part needs the labelled frames' folder (--real-data)")
    if real_data is not None and not (real_data / "labels" / "labels.json").is_file():
        raise TrackerError(str(real_data / "labels" / "labels.json"), "no frame labels here (--real-data)")
    from ..cli_common import check_not_inputs

    # the labelled frames are third-party data: the report (and its real/ overlays) never goes among them
    check_not_inputs([real_data], [("-o", output)])
    if (output / "report.md").exists() and not overwrite:
        raise TrackerError(output, "holds a report already, never overwritten (use --overwrite)")
    check_output(output, folder=True)  # minutes of experiments must not end in a read-only or full disk
    from rich.console import Console
    from rich.progress import Progress
    from rich.table import Table

    from .report import report  # here, not at the top: it loads the tracker, numba and matplotlib

    with Progress(console=Console(stderr=True), transient=True) as p:
        bar = p.add_task("experiments", total=None)
        res = report(output, quick=quick, parts=None if only is None else [only], jobs=jobs, real_data=real_data,
                     progress=lambda k, n, name: p.update(bar, completed=k, total=n, description=name))
    if res.get("real") is not None:
        t = Table(title=f"real labelled frames (details: {output / 'report.md'})")
        for c in ("frame", "size", "worst tip px", "wrist px", "in mask", "all floors"):
            t.add_column(c, justify="left" if c == "frame" else "right")
        for r in res["real"]:
            t.add_row(r["name"], f"{r['scale']:.2f}", f"{max(r['tips_px'].values()):.0f}", f"{r['wrist_px']:.0f}",
                      f"{100 * r['in_mask']:.0f} %", "yes" if r["ok"] else "no")
        Console().print(t)
    if res.get("realistic") is not None:
        _print_realistic(res["realistic"], output)
    if "modes" not in res:
        return
    t = Table(title=f"experiments (details: {output / 'report.md'})")
    for c in ("variant", "noise-free °", "Kinect v1 noise °", "fps"):
        t.add_column(c, justify="left" if c == "variant" else "right")
    for label, m in res["modes"].items():
        t.add_row(label, f"{m['error_deg']:.2f}", f"{res['noise'][label]['error_deg']:.2f}", f"{m['fps']:.0f}")
    occ = res["occlusion"]
    t.add_row("occluded grasp: full / reduced", f"{occ['full']:.1f} / {occ['reduced']:.1f}", "", "")
    sf = res["single"]
    t.add_row("single frame, hierarchical (mean / median)", f"{sf['hierarchical'][0]:.2f} / {sf['hierarchical'][1]:.2f}",
              "", "")
    Console(markup=False).print(t)


def train_detector(
    output: Path = typer.Option(..., "-o", "--output", help="Folder to write the model into (forest: "
                                "hand-parts-VERSION.npz; cnn: hand-keypoints-cnn-VERSION.onnx and .json; presence: "
                                "hand-presence-cnn-VERSION.onnx and .json)."),
    family: str = typer.Option("forest", "--family", help="forest (hand-part random forest, scikit-learn), cnn "
                               "(keypoint CNN on the hand's box, PyTorch; needs pip install '.[train]') or presence "
                               "(is the segmented region a hand: a small CNN on the same box, PyTorch)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the training scenes, pixels, features and trees (the "
                             "held-out scenes use other seeds)."),
    crops: Optional[int] = typer.Option(None, "--crops", min=1, help="Training crops drawn by the renderer "
                                        "[forest: 600, cnn: 4000; presence: whole frames, 2000]."),
    epochs: int = typer.Option(16, "--epochs", min=1, help="cnn and presence: passes over the training crops."),
    head: str = typer.Option("heatmap", "--head", help="cnn: heatmap (soft-argmax) or regression."),
    segmented: int = typer.Option(100, "--segmented", min=0, help="cnn: held-out whole frames evaluated through the "
                                  "tracker's segmentation."),
    hand_less: float = typer.Option(0.25, "--hand-less", min=0.0, max=1.0, help="presence: the share of training "
                                    "frames drawn without a hand (an object, torso, table) [0.25; 1.0.0: 0]."),
    trees: int = typer.Option(3, "--trees", min=1, help="Trees in the forest."),
    depth: int = typer.Option(20, "--depth", min=1, help="Largest tree depth."),
    features: int = typer.Option(400, "--features", min=2, help="Offset pairs the trees choose from."),
    heldout: int = typer.Option(200, "--heldout", min=1, help="Held-out synthetic crops (presence: whole frames) "
                                "evaluated."),
    real_data: Optional[Path] = typer.Option(None, "--real-data", help="Folder of labelled real SR305 stills "
                                             "(../shared/data/realsense_sr305_lada): evaluated, never trained on."),
    orientations: str = typer.Option("sphere", "--orientations", help="Hand orientations drawn: sphere (any) or "
                                     "user (palm, back or side to the camera, turned ±90°, tilted ±50°)."),
    version: str = typer.Option("1.0.0", "--version", help="Version in the file name and manifest."),
    jobs: int = typer.Option(2, "--jobs", "-j", min=1, help="Cores for fitting the trees (cnn: processes drawing "
                            "the crops; torch trains on 2 threads)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a model file of that version."),
):
    """Train a hand detector on rendered depth crops (the hand-part forest, or with --family cnn the
    keypoint CNN), evaluate it on held-out scenes (and the labelled real stills with --real-data) and
    write the sealed model with its manifest."""
    import re
    import sys

    from handmodel.fileio import check_output

    from ..errors import TrackerError

    if not re.fullmatch(r"\d+\.\d+\.\d+", version):
        raise TrackerError("--version", f"must be MAJOR.MINOR.PATCH, got {version!r}")
    if orientations not in ("sphere", "user"):
        raise TrackerError("--orientations", f"must be sphere or user, got {orientations!r}")
    if real_data is not None and not (real_data / "labels" / "labels.json").is_file():
        raise TrackerError(str(real_data / "labels" / "labels.json"), "no frame labels here (--real-data)")
    if family not in ("forest", "cnn", "presence"):
        raise TrackerError("--family", f"must be forest, cnn or presence, got {family!r}")
    if head not in ("heatmap", "regression"):
        raise TrackerError("--head", f"must be heatmap or regression, got {head!r}")
    name = {"forest": f"hand-parts-{version}.npz", "cnn": f"hand-keypoints-cnn-{version}.json",
            "presence": f"hand-presence-cnn-{version}.json"}[family]
    if (output / name).exists() and not overwrite:
        raise TrackerError(str(output / name), "exists (use --overwrite or --version)")
    check_output(output, folder=True)
    from rich.console import Console

    from .dataset import DataRecipe

    if family == "presence":
        return _train_presence(output, seed=seed, scenes=crops or 2000, epochs=epochs, heldout=heldout,
                               real_data=real_data, recipe=DataRecipe(orientations=orientations), version=version,
                               jobs=jobs, overwrite=overwrite, hand_less=hand_less)
    if family == "cnn":
        return _train_cnn(output, seed=seed, crops=crops or 4000, epochs=epochs, head=head, heldout=heldout,
                          segmented=segmented, real_data=real_data, recipe=DataRecipe(orientations=orientations),
                          version=version, jobs=jobs, overwrite=overwrite)
    from .train_detector import TrainSettings, build

    err = Console(stderr=True, markup=False)
    settings = TrainSettings(n_crops=crops or 600, n_trees=trees, max_depth=depth, n_features=features, jobs=jobs,
                             max_features=min(40, features))
    command = "tracker train-detector " + " ".join(sys.argv[2:]) if len(sys.argv) > 1 else ""
    path, manifest = build(output, seed=seed, recipe=DataRecipe(orientations=orientations), settings=settings, heldout=heldout, real_data=real_data,
                           version=version, command=command, progress=err.print, overwrite=overwrite)
    m = manifest["metrics"]
    h = m["heldout"]
    out = Console(markup=False)
    out.print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB, {manifest['training']['seconds']['total']:.0f} s)")
    out.print(f"held-out synthetic ({h['crops']} crops): keypoints found {100 * h['found_share']:.0f} %, "
              f"median {h['px_median']} px / {h['mm_median']} mm, mean {h['mm_mean']} mm; "
              f"part accuracy {100 * h['hand_part_accuracy']:.0f} %")
    if "real_sr305" in m:
        r = m["real_sr305"]
        out.print(f"real SR305 stills ({r['frames']}): tips median {r['tips_px_median']} px, "
                  f"{r['tips_within_15px']}/{r['tips']} tips within 15 px")


def _train_cnn(output, *, seed, crops, epochs, head, heldout, segmented, real_data, recipe, version, jobs, overwrite):
    """``train-detector --family cnn``: :func:`tracker.sim.train_cnn.build` and its figures."""
    import sys

    from rich.console import Console

    from .train_cnn import CnnSettings, build, require_torch

    require_torch()
    err = Console(stderr=True, markup=False)
    command = "tracker train-detector " + " ".join(sys.argv[2:]) if len(sys.argv) > 1 else ""
    settings = CnnSettings(head=head, n_crops=crops, epochs=epochs, jobs=jobs)
    path, manifest = build(output, seed=seed, recipe=recipe, settings=settings, heldout=heldout, segmented=segmented,
                           real_data=real_data, version=version, command=command, progress=err.print,
                           overwrite=overwrite)
    m = manifest["metrics"]
    h, j = m["heldout"]["true_box"], m["heldout"]["jittered_box"]
    out = Console(markup=False)
    out.print(f"wrote {path} and {path.with_suffix('.onnx').name} ({manifest['training']['seconds']['total']:.0f} s)")
    out.print(f"held-out synthetic ({m['heldout']['crops']} crops): median {h['mm_median']} mm / {h['px_median']} px "
              f"(true box), {j['mm_median']} mm (jittered box); centroid {m['heldout']['centroid_mm_median']} mm")
    if "all" in m["segmented"]:
        out.print(f"held-out whole frames through the segmentation ({m['segmented']['with_keypoints']} of "
                  f"{m['segmented']['frames']}): median {m['segmented']['all']['mm_median']} mm")
    if "real_sr305" in m:
        r = m["real_sr305"]
        out.print(f"real SR305 stills ({r['frames']}): tips median {r['tips_px_median']} px, "
                  f"{r['tips_within_15px']}/{r['tips']} tips within 15 px")


def _train_presence(output, *, seed, scenes, epochs, heldout, real_data, recipe, version, jobs, overwrite, hand_less):
    """``train-detector --family presence``: :func:`tracker.sim.train_presence.build` and its figures."""
    import sys

    from rich.console import Console

    from .train_cnn import require_torch
    from .train_presence import PresenceSettings, build

    require_torch()
    err = Console(stderr=True, markup=False)
    command = "tracker train-detector " + " ".join(sys.argv[2:]) if len(sys.argv) > 1 else ""
    settings = PresenceSettings(n_scenes=scenes, epochs=epochs, p_hand_less=hand_less)
    path, manifest = build(output, seed=seed, recipe=recipe, settings=settings, heldout=heldout, real_data=real_data,
                           version=version, command=command, jobs=jobs, progress=err.print, overwrite=overwrite)
    h = manifest["metrics"]["heldout"]
    out = Console(markup=False)
    out.print(f"wrote {path} and {path.with_suffix('.onnx').name} ({manifest['training']['seconds']['total']:.0f} s)")
    out.print(f"held-out synthetic ({h['crops']} crops, {h['hands']} hands): ROC AUC {h['auc']} (the segmentation's "
              f"boxes: {h['auc_segmented']})")
    if "real" in manifest["metrics"]:
        r = manifest["metrics"]["real"]
        out.print(f"real: SR305 stills' lowest hand probability {r['stills_min']}; hand-less frames "
                  f"{', '.join(f'{p:.3f}' for p in r['hand_less_frames'])}")


def register(app: typer.Typer, wrap=None) -> None:
    """Add the ``synth``, ``experiments`` and ``train-detector`` commands to the ``tracker`` app.

    ``wrap`` decorates each command (the app's one-line error handler); ``None`` adds them as they are.
    """
    wrap = wrap or (lambda fn: fn)
    app.command("experiments")(wrap(experiments))  # before synth: the order of ``tracker --help``
    app.command("synth")(wrap(synth))
    app.command("train-detector")(wrap(train_detector))


def _print_realistic(rows, output):
    """The realistic scenes by scene (mean over sensors and sizes), with and without colour: 6 lines."""
    import numpy as np
    from rich.console import Console
    from rich.table import Table

    kinds = [c for c in (True, False) if any(r.get("color", True) == c for r in rows)]
    t = Table(title=f"realistic scenes: keypoint error, runs within 10 mm, lost frames (details: {output / 'report.md'})")
    t.add_column("scene")
    for c in kinds:
        name = "colour" if c else "depth only"
        for col in (f"{name} mm", "≤ 10 mm", "lost"):
            t.add_column(col, justify="right")
    for scene in dict.fromkeys(r["scene"] for r in rows):
        cells = []
        for c in kinds:
            sel = [r for r in rows if r["scene"] == scene and r.get("color", True) == c]
            kp = np.array([r["keypoint_mm"] for r in sel], float)
            cells += [f"{np.nanmean(kp):.1f}" if np.isfinite(kp).any() else "—", f"{np.sum(kp <= 10.0)}/{len(sel)}",
                      f"{100 * np.mean([r['lost'] for r in sel]):.0f} %"]
        t.add_row(scene, *cells)
    Console().print(t)

