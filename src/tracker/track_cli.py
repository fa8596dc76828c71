"""``tracker track`` and ``tracker eval``: track a recording folder, score it against its truth.

``register(app, errors_exit_2)`` adds the commands to the ``tracker`` typer app. Heavy modules are
imported inside the commands so ``tracker --help`` stays fast.
"""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer


def track(
    recording: Path = typer.Argument(..., help="Recording folder (recording.yaml, depth/…)."),
    synergies: Optional[str] = typer.Option(None, "--synergies", "-s", help="Synergy bundle NAME[@VERSION] or .npz path."),
    registry: List[Path] = typer.Option(None, "-r", "--registry", help="Extra bundle registry folder (repeatable); SYNERGY_PATH and the shipped bundles follow."),
    mode: str = typer.Option("full", "--mode", help="full, reduced or hierarchical."),
    pcs: Optional[int] = typer.Option(None, "--pcs", help="Number of PCs (reduced/hierarchical)."),
    variance: float = typer.Option(0.99, "--variance", help="…or the variance the PCs must explain."),
    output: Path = typer.Option(..., "-o", "--output", help="Output CSV (one row per frame)."),
    keypoints: Optional[Path] = typer.Option(None, "--keypoints", help="Also write the 21 keypoints per frame (CSV, mm)."),
    overlay: Optional[Path] = typer.Option(None, "--overlay", help="Folder for overlay PNGs of the fit on the depth."),
    overlay_every: int = typer.Option(10, "--overlay-every", help="Overlay every N-th frame."),
    stride: int = typer.Option(3, "--stride", help="Use every K-th pixel in x and y (the paper's '1/3 sampling' is 3)."),
    smooth: int = typer.Option(1, "--smooth", help="Edge-preserving depth smoothing radius in pixels (0 = off)."),
    points: int = typer.Option(600, "--points", help="Adapt the stride (≤ --stride) to keep about this many hand points; 0 = fixed stride."),
    icp: int = typer.Option(4, "--icp", help="Non-rigid ICP iterations per frame (after 1 rigid)."),
    gn: int = typer.Option(5, "--gn", help="Gauss-Newton steps per ICP iteration."),
    damping: float = typer.Option(1.0, "--damping", help="λ on posture coordinates (paper 1; residuals in mm)."),
    model: str = typer.Option("capsules", "--model", help="Correspondence model: capsules or mesh."),
    silhouette: float = typer.Option(1.0, "--silhouette", help="Weight of the model→data silhouette term (0 = paper)."),
    prediction: float = typer.Option(1.0, "--prediction", help="Share of last frame's change added before fitting."),
    robust: float = typer.Option(8.0, "--robust", help="Cauchy scale (mm) weighting the data term; 0 = plain least squares (paper)."),
    finger_search: bool = typer.Option(True, "--finger-search/--no-finger-search", help="Finger-wise restarts when (re)initialising."),
    projected_steps: int = typer.Option(0, "--projected-steps", help="Reduced mode: last ICP iterations with all DoF, projected onto the PCs (0 = paper)."),
    paper: bool = typer.Option(False, "--paper", help="The paper's method only: no silhouette term, plain least squares, no finger search."),
    hand_model: str = typer.Option("default", "--hand-model", help="Hand model name or YAML path."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing output files."),
):
    """Track the hand through a recording; writes per-frame hand parameters and a summary."""
    import numpy as np
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
    from rich.table import Table

    from handmodel import HandModel

    from .errors import TrackerError
    from .observe import observe
    from .recording import Recording
    from .track import HandTracker, TrackerSettings

    for p in (output, keypoints):
        if p is not None and p.exists() and not overwrite:
            raise TrackerError(p, "exists and is never overwritten (use --overwrite)")
    rec = Recording.open(recording)
    bundle = None
    if synergies:
        from synergy.bundle import load_bundle

        bundle = load_bundle(synergies, registries=list(registry or []) or None)
    elif mode != "full":
        raise TrackerError("--synergies", f"mode {mode!r} needs a synergy bundle")
    hand = HandModel.load(hand_model, right=getattr(rec, "handedness", "left") == "right")
    settings = TrackerSettings(mode=mode, n_pcs=pcs, variance=None if pcs else variance, stride=stride,
                               target_points=points or None, smooth=smooth,
                               icp_iterations=icp, gn_iterations=gn, damping=damping, model=model,
                               silhouette_weight=0.0 if paper else silhouette, prediction=prediction,
                               robust_mm=0.0 if paper else robust, finger_search=finger_search and not paper,
                               projected_steps=0 if paper else projected_steps)
    tracker = HandTracker(hand, settings, synergies=bundle)
    cam = rec.camera
    rows, kps = [], []
    console = Console(stderr=True)
    with Progress(TextColumn("tracking"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[fps]} fps"),
                  TimeRemainingColumn(), console=console, transient=True) as progress:
        bar = progress.add_task("track", total=len(rec), fps="–")
        for frame in rec:
            depth = frame.depth
            bad = depth is None or np.ndim(depth) != 2 or depth.shape != (cam.height, cam.width)
            if bad:
                r = tracker.step(np.zeros((0, 3)))
                npts = 0
            else:
                ob = observe(depth, cam, stride=stride, color=frame.color, target_points=points or None, smooth=smooth)
                r = tracker.track(ob, cam)
                npts = len(ob.points)
            rows.append((frame.index, frame.time_s, r.status, r.fit_mm, r.points_used, npts, r.ms, *r.theta))
            if keypoints is not None:
                kps.append(hand.keypoints(r.theta).ravel() * 1000.0 if np.all(np.isfinite(r.theta)) else
                           np.full(hand.n_nodes * 3, np.nan))
            if overlay is not None and frame.index % max(overlay_every, 1) == 0 and not bad:
                from .plots import overlay_png

                overlay_png(overlay / f"overlay_{frame.index:06d}.png", depth, cam, hand, r.theta, r.status)
            progress.update(bar, advance=1, fps=f"{1000.0 / max(np.median([x[6] for x in rows[-30:]]), 1e-9):.0f}")
    import pandas as pd

    from handmodel.fileio import atomic_write_text

    cols = ["frame", "time_s", "status", "fit_mm", "points_used", "points", "ms", *hand.dof_names]
    df = pd.DataFrame(rows, columns=cols)
    head = (f"# recording: {recording}\n# mode: {mode}\n# synergies: {bundle.spec if bundle else ''}\n"
            f"# pcs: {tracker.n_pcs}\n# stride: {stride}\n# icp: {icp}\n# gn: {gn}\n# model: {model}\n"
            f"# hand_model: {hand.name} {hand.sha256}\n# units: metres, radians\n")
    atomic_write_text(output, head + df.to_csv(index=False, float_format="%.9g"), overwrite=True)
    if keypoints is not None:
        kcols = [f"{n}_{a}_mm" for n in hand.keypoint_names for a in "xyz"]
        kd = pd.DataFrame(np.array(kps), columns=kcols)
        kd.insert(0, "frame", df["frame"])
        atomic_write_text(keypoints, kd.to_csv(index=False, float_format="%.4f"), overwrite=True)
    table = Table(title=f"tracked {recording} ({mode}{', ' + str(tracker.n_pcs) + ' PCs' if tracker.n_pcs and mode != 'full' else ''})")
    for c in ("frames", "tracked", "lost", "reinit", "median fit mm", "median ms", "fps"):
        table.add_column(c, justify="right")
    st = df["status"]
    ms = float(df["ms"].median())
    table.add_row(str(len(df)), str(int((st == "tracked").sum())), str(int((st == "lost").sum())),
                  str(int((st == "reinit").sum())), f"{df['fit_mm'].median():.2f}", f"{ms:.1f}", f"{1000 / ms:.0f}")
    Console().print(table)
    Console().print(f"wrote {output}")


def evaluate(
    recording: Path = typer.Argument(..., help="Recording folder with truth.csv."),
    result: Path = typer.Argument(..., help="Output CSV of tracker track."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="PNG of the error per frame."),
    skip: int = typer.Option(0, "--skip", help="Leave out the first N frames (e.g. a lead-in)."),
):
    """Posture error (degrees, mean |Δ| of the 20 posture angles, as the paper), keypoint error (mm)."""
    import numpy as np
    import pandas as pd
    from rich.console import Console
    from rich.table import Table

    from handmodel import HandModel

    from .errors import TrackerError
    from .evaluate import summarise
    from .recording import Recording

    rec = Recording.open(recording)
    truth = rec.truth
    if truth is None:
        raise TrackerError(recording, "has no truth.csv to evaluate against")
    try:
        df = pd.read_csv(result, comment="#")
    except (OSError, ValueError) as exc:
        raise TrackerError(result, f"cannot read tracking output ({exc})") from None
    hand = HandModel.load(right=getattr(rec, "handedness", "left") == "right")
    missing = [c for c in hand.dof_names + ["frame", "status"] if c not in df.columns]
    if missing:
        raise TrackerError(result, f"not a tracking output: missing columns {', '.join(missing)}")
    th = df[hand.dof_names].to_numpy(float)
    tr = np.asarray(truth[hand.dof_names] if hasattr(truth, "columns") else truth, float)
    if len(tr) != len(th):
        raise TrackerError(result, f"{len(th)} frames but the recording's truth has {len(tr)}")
    summ, pe, ke = summarise(hand, th[skip:], tr[skip:], df["status"].to_numpy()[skip:], df["ms"].to_numpy()[skip:])
    table = Table(title=f"evaluation of {result.name} against {recording}")
    table.add_column("measure")
    table.add_column("value", justify="right")
    for k, v in summ.items():
        table.add_row(k, f"{v:.3f}" if isinstance(v, float) else str(v))
    Console().print(table)
    if plot is not None:
        from .plots import error_plot

        error_plot(plot, pe, ke, df["status"].to_numpy()[skip:], title=str(result.name))
        Console().print(f"wrote {plot}")


def register(app, errors_exit_2) -> None:
    app.command()(errors_exit_2(track))
    app.command("eval")(errors_exit_2(evaluate))
