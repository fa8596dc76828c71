"""``tracker`` command line: import, info, show, synth, track, eval, experiments.

Heavy libraries are imported inside the commands so ``tracker --help`` answers at once. Bad input
prints one line ``error: …`` on stderr and exits 2.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

app = typer.Typer(name="tracker", help="Synergistic hand tracking in depth recordings.", add_completion=False,
                  no_args_is_help=True, pretty_exceptions_enable=False, rich_markup_mode=None)


from handmodel.cliutil import errors_exit_2 as _errors_exit_2  # noqa: E402


def _camera(camera, fx, fy, cx, cy, width, height, depth_scale):
    from .cameras import Camera, preset
    from .errors import TrackerError

    if camera:
        return preset(camera)
    if None in (fx, fy, cx, cy, width, height):
        raise TrackerError("camera", "give --camera PRESET or all of --fx --fy --cx --cy --width --height")
    return Camera(width, height, fx, fy, cx, cy, depth_scale, "uint16", "custom")


@app.command("import")
@_errors_exit_2
def import_(
    src: Path = typer.Argument(..., help="Folder of depth PNGs (sorted by name, natural order)."),
    output: Path = typer.Option(..., "-o", "--output", help="Recording folder to create."),
    camera: Optional[str] = typer.Option(None, "--camera", help="Preset: kinect1, kinect2, sr305, sr300, nyu."),
    fx: Optional[float] = typer.Option(None, "--fx"), fy: Optional[float] = typer.Option(None, "--fy"),
    cx: Optional[float] = typer.Option(None, "--cx"), cy: Optional[float] = typer.Option(None, "--cy"),
    width: Optional[int] = typer.Option(None, "--width"), height: Optional[int] = typer.Option(None, "--height"),
    depth_scale: float = typer.Option(0.001, "--depth-scale", help="Metres per stored depth unit."),
    fps: float = typer.Option(30.0, "--fps"),
    hand: str = typer.Option("left", "--hand", help="Handedness of the recorded hand."),
):
    """Turn a plain folder of depth PNGs into a recording."""
    from rich.console import Console
    from rich.progress import Progress

    from .recording import import_pngs

    cam = _camera(camera, fx, fy, cx, cy, width, height, depth_scale)
    with Progress(console=Console(stderr=True), transient=True) as p:
        bar = p.add_task("importing", total=None)
        rec = import_pngs(src, output, cam, fps, hand, progress=lambda k, n: p.update(bar, completed=k, total=n))
    _info(rec)


def _info(rec):
    import numpy as np
    from rich.console import Console
    from rich.table import Table

    c = rec.camera
    first = rec[0].depth if len(rec) else None
    t = Table(title=str(rec.path))
    t.add_column("field")
    t.add_column("value", justify="right")
    rows = [("frames", len(rec)), ("fps", f"{rec.fps:g}"), ("camera", f"{c.name} {c.width}×{c.height}"),
            ("fx, fy, cx, cy", f"{c.fx:.2f}, {c.fy:.2f}, {c.cx:.2f}, {c.cy:.2f}"),
            ("depth", f"{c.depth_encoding}, {c.depth_scale * 1000:g} mm/unit"), ("hand", rec.handedness),
            ("truth", "yes" if rec.truth is not None else "no")]
    if first is not None and np.isfinite(first).any():
        rows.append(("frame 0 depth 5/50/95 %", " / ".join(f"{x:.3f}" for x in np.nanpercentile(first, [5, 50, 95])) + " m"))
    for k, v in rows:
        t.add_row(k, str(v))
    Console().print(t)


@app.command()
@_errors_exit_2
def info(recording: Path = typer.Argument(..., help="Recording folder.")):
    """Summary of a recording."""
    from .recording import Recording

    _info(Recording.open(recording))


@app.command()
@_errors_exit_2
def show(
    recording: Path = typer.Argument(..., help="Recording folder."),
    output: Path = typer.Option(..., "-o", "--output", help="PNG contact sheet to write."),
    every: int = typer.Option(0, "--every", help="Every N-th frame (default: up to 16 spread frames)."),
    overwrite: bool = typer.Option(False, "--overwrite"),
):
    """Contact sheet of depth frames (NaN = no data drawn in grey)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from handmodel.fileio import atomic_write_bytes

    from .errors import TrackerError
    from .recording import Recording

    if output.exists() and not overwrite:
        raise TrackerError(output, "exists and is never overwritten (use --overwrite)")
    rec = Recording.open(recording)
    n = len(rec)
    if n == 0:
        raise TrackerError(recording, "has no frames")
    idx = list(range(0, n, every)) if every > 0 else sorted(set(np.linspace(0, n - 1, min(n, 16)).astype(int)))
    idx = idx[:64]
    cols = int(np.ceil(np.sqrt(len(idx))))
    rows = int(np.ceil(len(idx) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3 * cols, 2.4 * rows), squeeze=False)
    cmap = matplotlib.colormaps["viridis"].copy()
    cmap.set_bad("0.8")
    lo = hi = None
    for ax, i in zip(axes.ravel(), idx):
        d = rec[i].depth
        if lo is None and np.isfinite(d).any():
            lo, hi = np.nanpercentile(d, [1, 99])
        ax.imshow(np.ma.masked_invalid(d), cmap=cmap, vmin=lo, vmax=hi)
        ax.set_title(f"frame {i}", fontsize=8)
        ax.set_axis_off()
    for ax in axes.ravel()[len(idx):]:
        ax.set_axis_off()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    atomic_write_bytes(output, buf.getvalue(), overwrite=True)
    typer.echo(f"wrote {output} ({len(idx)} frames)")


@app.command()
@_errors_exit_2
def experiments(
    output: Path = typer.Option(..., "-o", "--output", help="Report folder (report.md + PNGs)."),
    quick: bool = typer.Option(False, "--quick", help="Fewer sequences and settings (a few minutes)."),
):
    """Reproduce the paper's experiments on our renderer; writes report.md with tables and plots."""
    from rich.console import Console
    from rich.progress import Progress

    from .experiments import report

    with Progress(console=Console(stderr=True), transient=True) as p:
        bar = p.add_task("experiments", total=7)
        res = report(output, quick=quick, progress=lambda k, n, name: p.update(bar, completed=k, description=name))
    m = res["modes"]
    Console().print(f"full {m['full']['error_deg']:.2f}°, reduced {m['reduced']['error_deg']:.2f}°, hierarchical "
                    f"{m['hierarchical']['error_deg']:.2f}°; occluded grasp full {res['occlusion']['full']:.1f}° vs "
                    f"reduced {res['occlusion']['reduced']:.1f}°; wrote {output / 'report.md'}")


from tracker import synth_cli, track_cli  # noqa: E402

app.command("synth")(_errors_exit_2(synth_cli.synth))
track_cli.register(app, _errors_exit_2)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
