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


def _errors(fn):
    """The shared one-line error wrapper, plus OS errors (unreadable or unwritable paths)."""
    import functools

    inner = _errors_exit_2(fn)

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return inner(*args, **kwargs)
        except OSError as err:
            where = f"{err.filename}: " if getattr(err, "filename", None) else ""
            typer.echo(f"error: {where}{err.strerror or err}", err=True)
            raise typer.Exit(2) from None

    return wrapper


def _camera(camera, fx, fy, cx, cy, width, height, depth_scale, depth_encoding):
    """A preset (with any given value overriding it) or a camera from explicit intrinsics."""
    from .cameras import Camera, preset
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


def _progress(label: str):
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    console = Console(stderr=True)
    # off when stderr is not a terminal: a transient bar would still leave an empty line in logs
    return Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                    console=console, transient=True, disable=not console.is_terminal)


def _table(title: str, rows):
    from rich.console import Console
    from rich.table import Table

    t = Table(title=title, show_header=False)
    t.add_column("field")
    t.add_column("value")
    for k, v in rows:
        t.add_row(k, str(v))
    Console().print(t)


def _recording_rows(rec) -> list:
    c = rec.camera
    n = len(rec)
    return [("frames", f"{n} ({n / rec.fps:.2f} s at {rec.fps:g} fps)"),
            ("camera", f"{c.name}, {c.width}×{c.height}"),
            ("fx, fy / cx, cy (px)", f"{c.fx:.3f}, {c.fy:.3f} / {c.cx:.3f}, {c.cy:.3f}"),
            ("depth", f"{c.depth_encoding}, {c.depth_scale_m * 1000:g} mm per unit (max {c.max_depth_m:.2f} m)"),
            ("handedness", rec.handedness), ("colour", "yes" if rec.has_color else "no"),
            ("truth", "yes (truth.csv)" if rec.has_truth else "no")]


def _depth_stats(rec, every: int = 1, label: str = "reading"):
    """Valid-pixel fraction and depth percentiles over every ``every``-th frame (with a progress bar)."""
    import numpy as np

    idx = range(0, len(rec), max(every, 1))
    valid, samples = [], []
    rng = np.random.default_rng(0)
    with _progress(label) as p:
        bar = p.add_task(label, total=len(idx))
        for i in idx:
            d = rec[i].depth
            ok = np.isfinite(d)
            valid.append(ok.mean())
            v = d[ok]
            samples.append(v if v.size <= 20000 else rng.choice(v, 20000, replace=False))
            p.advance(bar)
    v = np.concatenate(samples) if samples else np.empty(0)
    return len(idx), float(np.mean(valid)) if valid else float("nan"), v


@app.command("import")
@_errors
def import_(
    src: Path = typer.Argument(..., help="Folder of depth PNGs (sorted by name in natural order)."),
    output: Path = typer.Option(..., "-o", "--output", help="Recording folder to create."),
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
    fps: float = typer.Option(30.0, "--fps", help="Frame rate (Hz)."),
    hand: str = typer.Option("left", "--hand", "--handedness", help="Handedness of the recorded hand: left or right."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing recording in the output folder."),
):
    """Turn a plain folder of depth PNGs into a recording."""
    import time

    from .recording import import_pngs

    cam = _camera(camera, fx, fy, cx, cy, width, height, depth_scale, depth_encoding)
    t0 = time.perf_counter()
    with _progress("importing") as p:
        bar = p.add_task("import", total=None)
        rec = import_pngs(src, output, cam, fps, hand, overwrite=overwrite,
                          progress=lambda k, n: p.update(bar, completed=k, total=n))
    _table(f"imported {src} → {output} ({time.perf_counter() - t0:.1f} s)", _recording_rows(rec))


@app.command()
@_errors
def info(
    recording: Path = typer.Argument(..., help="Recording folder."),
    quick: bool = typer.Option(False, "--quick", help="Metadata only; do not read the frames."),
    every: int = typer.Option(1, "--every", help="Read every N-th frame for the depth statistics."),
):
    """Summary of a recording (reads and checks every frame unless --quick)."""
    import numpy as np

    from .recording import Recording

    rec = Recording.open(recording)
    rows = _recording_rows(rec)
    if not quick and len(rec):
        n, valid, v = _depth_stats(rec, every, "checking frames")
        rows.append(("frames read", f"{n} (all readable)"))
        rows.append(("pixels with depth", f"{100 * valid:.1f} % (mean per frame)"))
        if v.size:
            q = np.percentile(v, [1, 50, 99]) * 1000
            rows.append(("depth 1 / 50 / 99 %", f"{q[0]:.0f} / {q[1]:.0f} / {q[2]:.0f} mm"))
    _table(str(rec.path), rows)


@app.command()
@_errors
def show(
    recording: Path = typer.Argument(..., help="Recording folder."),
    output: Path = typer.Option(..., "-o", "--output", help="PNG contact sheet to write."),
    every: int = typer.Option(0, "--every", help="Every N-th frame (default: up to 16 frames spread evenly)."),
    max_frames: int = typer.Option(64, "--max-frames", help="At most this many panels."),
    near: Optional[float] = typer.Option(None, "--near", help="Colour scale start (m; default 1st percentile)."),
    far: Optional[float] = typer.Option(None, "--far", help="Colour scale end (m; default 99th percentile)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing output file."),
):
    """Contact sheet of depth frames, colour-mapped in mm; pixels without depth are light grey."""
    import io

    import numpy as np
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from handmodel.fileio import atomic_write_bytes

    from .errors import TrackerError
    from .recording import Recording

    if output.exists() and not overwrite:
        raise TrackerError(output, "exists and is never overwritten (use --overwrite)")
    if every < 0 or max_frames < 1:
        raise TrackerError("show", "--every must be ≥ 0 and --max-frames ≥ 1")
    rec = Recording.open(recording)
    n = len(rec)
    if n == 0:
        raise TrackerError(recording, "has no frames")
    idx = list(range(0, n, every)) if every > 0 else sorted(set(np.linspace(0, n - 1, min(n, 16)).round().astype(int)))
    shown = idx[:max_frames]
    depths = []
    with _progress("reading") as p:
        bar = p.add_task("read", total=len(shown))
        for i in shown:
            depths.append(rec[i].depth * 1000.0)
            p.advance(bar)
    finite = np.concatenate([d[np.isfinite(d)] for d in depths])
    lo, hi = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
    lo = lo if near is None else near * 1000
    hi = hi if far is None else far * 1000
    if not hi > lo:
        hi = lo + 1.0
    cols = int(np.ceil(np.sqrt(len(shown))))
    rows = int(np.ceil(len(shown) / cols))
    aspect = rec.camera.height / rec.camera.width
    fig = Figure(figsize=(2.6 * cols + 0.8, 2.6 * aspect * rows + 0.9), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, cols, squeeze=False)
    cmap = colormaps["viridis"].with_extremes(bad="0.85")  # grey is not in viridis: no data stands out
    im = None
    for ax, i, d in zip(axes.ravel(), shown, depths):
        im = ax.imshow(np.ma.masked_invalid(d), cmap=cmap, vmin=lo, vmax=hi, interpolation="nearest")
        ax.set_title(f"#{i}  {i / rec.fps:.2f} s", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in axes.ravel()[len(shown):]:
        ax.set_axis_off()
    fig.suptitle(f"{rec.path.name}: {n} frames, {rec.camera.name} {rec.camera.width}×{rec.camera.height}; "
                 f"grey = no depth", fontsize=9)
    fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.8, label="depth (mm)")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    atomic_write_bytes(output, buf.getvalue(), overwrite=True)
    valid = np.mean([np.isfinite(d).mean() for d in depths])
    _table(f"wrote {output}", [
        ("frames shown", f"{len(shown)} of {n}"
         + (f" (the first {max_frames} of {len(idx)} selected)" if len(idx) > len(shown) else "")),
        ("colour scale", f"{lo:.0f}–{hi:.0f} mm"), ("pixels with depth", f"{100 * valid:.1f} %")])


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

    from rich.table import Table

    with Progress(console=Console(stderr=True), transient=True) as p:
        bar = p.add_task("experiments", total=None)
        res = report(output, quick=quick,
                     progress=lambda k, n, name: p.update(bar, completed=k, total=n, description=name))
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
    Console().print(t)


from tracker import synth_cli, track_cli  # noqa: E402

app.command("synth")(_errors_exit_2(synth_cli.synth))
track_cli.register(app, _errors_exit_2)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
