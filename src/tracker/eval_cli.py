"""``tracker eval``: score a tracking output against its recording's truth (posture error in degrees,
keypoint error in mm, optionally a plot of both per frame).

``register(app, errors_exit_2)`` adds the command to the ``tracker`` typer app; heavy modules are
imported inside it so ``tracker --help`` stays fast.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .cli_common import check_not_inputs, check_same_recording


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


def register(app, errors_exit_2) -> None:
    app.command("eval")(errors_exit_2(evaluate))
