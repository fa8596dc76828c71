"""The ``tracker synth`` command: render a motion into a recording folder with ground truth.

``register(app)`` adds the command to the ``tracker`` typer app. Heavy modules are imported inside
the command so that ``tracker --help`` stays fast. Bad input raises
:class:`handmodel.errors.ToolkitError` subclasses; the app prints them on one line and exits 2.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

MOTION_HELP = "Scenario name (see --list) or a motion file: .csv joint-angle table, .txt/.dat schroeder26 postures."


def synth(
    motion: str = typer.Option("open-close", "--motion", "-m", help=MOTION_HELP),
    camera: str = typer.Option("kinect1", "--camera", "-c", help="Camera preset (tracker.cameras)."),
    noise: str = typer.Option("kinect1", "--noise", "-n", help="Noise preset: none, kinect1."),
    frames: Optional[int] = typer.Option(None, "--frames", "-f", help="Number of frames (default: the whole motion)."),
    fps: float = typer.Option(30.0, "--fps", help="Frame rate of the recording."),
    seed: int = typer.Option(0, "--seed", help="Seed of the noise (and of random scenarios)."),
    clutter: str = typer.Option("none", "--clutter", help="Extra geometry: none, forearm, table, forearm,table."),
    color: bool = typer.Option(False, "--color/--no-color", help="Also write skin-coloured colour frames."),
    hand_model: str = typer.Option("default", "--hand-model", help="Hand model name or YAML path."),
    right: bool = typer.Option(False, "--right", help="Render the right hand (mirror image, same θ)."),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="Recording folder to write."),
    list_: bool = typer.Option(False, "--list", help="List the scenarios and noise presets and exit."),
):
    """Render a hand motion with sensor noise into a recording folder (depth, truth.csv)."""
    from rich.console import Console

    from .errors import TrackerError

    console = Console()
    if list_:
        console.print(_listing())
        return
    if output is None:
        raise TrackerError("synth", "give the output folder with -o/--output")
    if frames is not None and frames < 1:
        raise TrackerError("--frames", f"must be at least 1, got {frames}")
    if not fps > 0:
        raise TrackerError("--fps", f"must be positive, got {fps}")

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from handmodel import HandModel

    from .motions import make_motion
    from .noise import NoiseModel
    from .synthetic import Clutter, as_camera, synthesize

    clut = Clutter.parse(clutter)
    nm = NoiseModel.preset(noise)
    hand = HandModel.load(hand_model, right=right)
    m = make_motion(motion, hand=hand, frames=frames, fps=fps, seed=seed)
    cam = as_camera(camera)

    err = Console(stderr=True)
    columns = (TextColumn("[progress.description]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TimeRemainingColumn())
    with Progress(*columns, console=err, transient=True, disable=not err.is_terminal) as progress:
        bar = progress.add_task(f"rendering {m.name}", total=m.frames)
        report = synthesize(m, cam, nm, output, fps=fps, seed=seed, hand=hand, clutter=clut, color=color,
                            progress=lambda done, total: progress.update(bar, completed=done))
    console.print(_summary(report, clutter, color, hand))


def _summary(rep, clutter: str, color: bool, hand):
    from rich.table import Table

    t = Table(title=f"synthetic recording {rep.path}", show_header=False)
    t.add_column("", style="bold")
    t.add_column("", overflow="fold")
    t.add_row("motion", rep.motion)
    t.add_row("frames", f"{rep.frames} at {rep.fps:g} fps ({rep.frames / rep.fps:.1f} s)")
    t.add_row("hand", f"{hand.name} ({hand.handedness})")
    t.add_row("camera", rep.camera)
    t.add_row("noise", rep.noise)
    t.add_row("clutter", clutter)
    t.add_row("colour", "yes" if color else "no")
    t.add_row("hand pixels / frame", f"{rep.hand_pixels:.0f}")
    t.add_row("hand pixels with depth", f"{100 * rep.valid_fraction:.1f} %")
    lo, hi = rep.depth_range_m
    t.add_row("hand depth", f"{1000 * lo:.0f}–{1000 * hi:.0f} mm")
    t.add_row("render / noise", f"{rep.render_ms:.2f} ms / {rep.noise_ms:.2f} ms per frame")
    t.add_row("total", f"{rep.seconds:.1f} s")
    return t


def _listing():
    from rich.table import Table

    from .motions import SCENARIOS
    from .noise import PRESETS

    t = Table(title="motions and noise presets")
    t.add_column("kind", style="bold")
    t.add_column("name")
    t.add_column("description", overflow="fold")
    for sc in SCENARIOS.values():
        t.add_row("motion", sc.name, f"{sc.description} [{sc.seconds:g} s]")
    for nm in PRESETS.values():
        parts = [p for p, on in (("axial σ(z)", nm.axial), ("lateral", nm.lateral_px > 0),
                                 ("quantisation", nm.quantize), ("shadows", nm.shadow),
                                 ("edge dropout", nm.edge_drop_prob > 0), ("random dropout", nm.random_drop_prob > 0))
                 if on]
        t.add_row("noise", nm.name, ", ".join(parts) or "noise-free")
    return t


def register(app: typer.Typer) -> None:
    """Add the ``synth`` command to the ``tracker`` app."""
    app.command("synth")(synth)
