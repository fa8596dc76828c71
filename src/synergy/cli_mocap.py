"""``synergy simulate`` and ``synergy angles``: mocap trials in, C3D or joint-angle tables out."""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer


def _console(stderr: bool = False):
    from rich.console import Console

    return Console(stderr=stderr)


def register(app, errors_exit_2) -> None:
    """Add the commands to the ``synergy`` typer app (works when cli.py runs as __main__ too)."""
    app.command()(errors_exit_2(simulate))
    app.command()(errors_exit_2(angles))


def simulate(
    out: Path = typer.Option(..., "-o", "--out", help="Output folder for the C3D files (created)."),
    motions: str = typer.Option("all", "--motions", help="Comma-separated motions, or 'all'."),
    trials: int = typer.Option(2, "--trials", help="Trials per motion (different seeds)."),
    markers: str = typer.Option("hand16", "--markers", help="Marker set to simulate."),
    hand: str = typer.Option("left", "--hand", help="left or right."),
    duration: float = typer.Option(4.0, "--duration", help="Seconds per trial."),
    rate: float = typer.Option(100.0, "--rate", help="Frame rate (Hz)."),
    noise_mm: float = typer.Option(0.3, "--noise-mm", help="Marker noise σ (mm)."),
    gaps: float = typer.Option(0.02, "--gaps", help="Fraction of each marker's samples lost in occlusion gaps."),
    scale: float = typer.Option(1.0, "--scale", help="Subject's hand size relative to the default hand."),
    units: str = typer.Option("mm", "--units", help="C3D length unit: mm, cm or m."),
    prefix: str = typer.Option("Sim", "--prefix", help="Subject prefix of the labels ('' for none)."),
    seed: int = typer.Option(0, "--seed"),
):
    """Simulate mocap trials of procedural hand motions (C3D + ground-truth angles + task map)."""
    import numpy as np
    import pandas as pd
    import yaml
    from rich.progress import Progress
    from rich.table import Table

    from handmodel import HandModel
    from handmodel.fileio import atomic_write_text
    from synergy.c3d import TASK_EVENT, write_c3d
    from synergy.errors import SynergyError
    from synergy.simulate import MOTIONS, motion, simulate_markers

    names = list(MOTIONS) if motions == "all" else [m.strip() for m in motions.split(",") if m.strip()]
    for n in names:
        if n not in MOTIONS:
            raise SynergyError(n, f"unknown motion (known: {', '.join(MOTIONS)})")
    if units not in ("mm", "cm", "m"):
        raise SynergyError("--units", f"must be mm, cm or m, got {units!r}")
    if trials < 1 or duration <= 0 or rate <= 0:
        raise SynergyError("simulate", "--trials, --duration and --rate must be positive")
    dof = HandModel.load().dof_names
    rows = []
    task_rules = []
    with Progress(console=_console(stderr=True), transient=True) as progress:
        bar = progress.add_task("simulating", total=len(names) * trials)
        for n in names:
            for k in range(trials):
                s = seed * 1000 + names.index(n) * 100 + k
                th, task = motion(n, duration_s=duration, rate=rate, seed=s)
                tr = simulate_markers(th, markers, hand=hand, scale=scale, noise_mm=noise_mm, gap_fraction=gaps,
                                      rate=rate, seed=s + 7, motion_name=n, task=task)
                stem = f"{n}_{k + 1:02d}"
                path = out / f"{stem}.c3d"
                if path.exists():
                    raise SynergyError(path, "exists and is never overwritten (choose another -o)")
                write_c3d(path, tr.points, tr.labels, rate, units=units, prefix=prefix,
                          events=[(f"{TASK_EVENT}{task}", 0.0, "General")])
                truth = pd.DataFrame(th, columns=dof)
                truth.insert(0, "time_s", np.arange(len(th)) / rate)
                atomic_write_text(out / "truth" / f"{stem}.csv",
                                  f"# motion: {n}\n# task: {task}\n# scale: {scale}\n# hand: {hand}\n"
                                  + truth.to_csv(index=False, float_format="%.9g"), overwrite=False)
                rows.append((path.name, n, task, len(th), f"{100 * np.isnan(tr.points[..., 0]).mean():.1f}"))
                task_rules.append({"glob": f"{stem}.c3d", "task": task})
                progress.advance(bar)
    atomic_write_text(out / "tasks.yaml", yaml.safe_dump({"rules": task_rules}, sort_keys=False), overwrite=True)
    table = Table(title=f"simulated {len(rows)} trials → {out}")
    for c in ("file", "motion", "task", "frames", "gap %"):
        table.add_column(c)
    for r in rows:
        table.add_row(*map(str, r))
    _console().print(table)


def angles(
    files: List[Path] = typer.Argument(..., help="C3D trials."),
    markers: str = typer.Option(..., "--markers", help="Marker set name or YAML file."),
    hand: str = typer.Option("left", "--hand", help="left or right."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder: one CSV per trial (never overwritten)."),
    smooth_hz: Optional[float] = typer.Option(None, "--smooth-hz", help="Low-pass the markers (Hz) before IK."),
    static: Optional[Path] = typer.Option(None, "--static", help="Calibrate on this static trial instead of each trial."),
    no_calibration: bool = typer.Option(False, "--no-calibration", help="Use the model as it is."),
):
    """Convert C3D trials to joint-angle tables (marker IK), with a summary per trial."""
    import time

    import numpy as np
    from rich.progress import Progress
    from rich.table import Table

    from handmodel import HandModel
    from synergy.angles import markers_to_angles, write_angles_csv
    from synergy.c3d import read_c3d
    from synergy.calibrate import calibrate
    from synergy.errors import SynergyError
    from synergy.markers import load_markerset

    ms = load_markerset(markers)
    targets = [(f, out / f"{f.stem}.csv") for f in files]
    for f, dst in targets:
        if dst.exists():
            raise SynergyError(dst, "exists and is never overwritten (choose another -o)")
    cal = "trial"
    if no_calibration:
        cal = None
    elif static is not None:
        cal = calibrate(read_c3d(static), ms.for_hand(hand), HandModel.load(right=hand == "right"),
                        right=hand == "right")
        cal.source = str(static)
    rows = []
    failed = 0
    with Progress(console=_console(stderr=True), transient=True) as progress:
        bar = progress.add_task("converting", total=len(files))
        for f, dst in targets:
            progress.update(bar, description=f"{f.name}")
            try:
                data = read_c3d(f)
                t0 = time.perf_counter()
                df = markers_to_angles(data, ms, hand=hand, calibration=cal, smooth_hz=smooth_hz)
                dt = time.perf_counter() - t0
                write_angles_csv(df, dst)
            except SynergyError as err:  # one bad trial does not stop the others
                _console(stderr=True).print(f"error: {err}")
                failed += 1
                progress.advance(bar)
                continue
            r = df["residual_mm"].to_numpy()
            rows.append((f.name, len(df), f"{100 * df.attrs['gap_fraction']:.1f}",
                         f"{np.nanmedian(r):.2f}", f"{np.nanpercentile(r, 95):.2f}",
                         f"{100 * (df['quality'] == 'ok').mean():.1f}", f"{df.attrs['calibration']['scale']:.3f}",
                         f"{len(df) / dt:,.0f}"))
            progress.advance(bar)
    table = Table(title=f"marker IK ({ms.name}, {hand} hand) → {out}")
    for c in ("trial", "frames", "gap %", "residual median mm", "residual 95th mm", "ok %", "hand scale", "frames/s"):
        table.add_column(c, justify="right")
    for r in rows:
        table.add_row(*map(str, r))
    _console().print(table)
    if failed:
        raise typer.Exit(2)
