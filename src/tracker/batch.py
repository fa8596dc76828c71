"""Many recordings: one :class:`tracker.run.TrackJob` each (:func:`batch_jobs`), run one by one or as
Dask tasks (:func:`track_many`), a failing recording reported in its summary row (:func:`summary_row`)
while the others go on (``tracker track`` with several recordings or ``--dask``)."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pandas as pd

from handmodel.cliutil import error_line
from handmodel.errors import ToolkitError

from .errors import TrackerError
from .run import TrackJob, TrackRun, run_job


#: Columns of the summary table of many recordings (:func:`summary_row`).
SUMMARY_COLUMNS = ("recording", "output", "frames", "tracked", "lost", "reinit", "median_fit_mm", "median_ms",
                   "wall_s", "hand_scale", "hand_check", "other_hand_better", "error")


def summary_row(job: TrackJob, run: TrackRun | None = None, error: str = "") -> dict:
    """One row of the summary of many recordings: counts and medians of a run, or the error that
    stopped it (one line naming the file)."""
    row = dict.fromkeys(SUMMARY_COLUMNS, "")
    row.update(recording=str(job.recording), output=str(job.output), error=error)
    if run is not None:
        st = run.df["status"]
        row.update(frames=len(run.df), tracked=int((st == "tracked").sum()), lost=int((st == "lost").sum()),
                   reinit=int((st == "reinit").sum()), median_fit_mm=float(run.df["fit_mm"].median()),
                   median_ms=float(run.df["ms"].median()), wall_s=float(run.wall_s), hand_scale=run.meta["hand_scale"])
        check = run.tracker.hand_check_
        if check is not None:
            row.update(hand_check=str(check), other_hand_better=bool(check.other_fits_better))
        if run.unreadable and not error:
            # its output is written (those frames lost), but the recording is damaged: said, not hidden
            row.update(error=unreadable_text(run.unreadable, len(run.df)))
    return row


def unreadable_text(problems, frames) -> str:
    """One line on a run's unreadable frames: the first one's problem and how many there were."""
    more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
    return (f"{problems[0]}{more}: {len(problems)} of {frames} frames unreadable, tracked as lost; "
            "the outputs hold every frame")


def run_job_row(job: TrackJob) -> dict:
    """:func:`run_job` as one task of many: its summary row, with a bad input or an unwritable
    output reported in the row (``error``) instead of raised, so the other recordings go on."""
    try:
        return summary_row(job, run_job(job))
    except (ToolkitError, OSError) as exc:
        return summary_row(job, error=error_line(exc).removeprefix("error: "))


def batch_jobs(recordings, outdir, template: TrackJob) -> list[TrackJob]:
    """One job per recording, its output ``OUTDIR/<name>.csv`` (``<name>`` the folder's name or the
    file's stem), with the template's ``keypoints`` and ``overlay`` as folders: ``<keypoints>/<name>.csv``
    and ``<overlay>/<name>/``; two recordings with the same name are refused (their outputs would collide)."""
    outdir = Path(outdir)
    jobs, seen = [], {}
    for r in recordings:
        r = Path(r)
        name = r.name if r.is_dir() else r.stem
        if name in seen:
            raise TrackerError(r, f"has the same name as {seen[name]}: both would write {outdir / (name + '.csv')}")
        seen[name] = r
        jobs.append(replace(template, recording=str(r), output=str(outdir / f"{name}.csv"),
                            keypoints=template.keypoints and str(Path(template.keypoints) / f"{name}.csv"),
                            overlay=template.overlay and str(Path(template.overlay) / name)))
    return jobs


def track_many(jobs, *, dask=None, on_done=None) -> pd.DataFrame:
    """Run ``jobs`` one by one here, or as Dask tasks (``dask``: ``local``, ``local:N`` or a
    scheduler address, as ``synergy fit --dask``); a failing recording is reported in its row and
    the rest go on. ``on_done(row)`` is called as each finishes. Returns the summary table
    (:data:`SUMMARY_COLUMNS`), in the order of ``jobs``."""
    rows = [None] * len(jobs)
    if dask is None:
        for i, job in enumerate(jobs):
            rows[i] = run_job_row(job)
            if on_done is not None:
                on_done(rows[i])
    else:
        # an optional extra ([dask]), loaded only when asked for; the same client set-up as synergy fit
        from distributed import as_completed

        from synergy.scale import client_for

        client, cluster = client_for(dask)
        try:
            futures = {client.submit(run_job_row, job, pure=False): i for i, job in enumerate(jobs)}
            for fut in as_completed(list(futures)):
                i = futures[fut]
                try:
                    rows[i] = fut.result()
                except Exception as exc:  # a worker lost or killed: that recording fails, the rest go on
                    rows[i] = summary_row(jobs[i], error=f"{jobs[i].recording}: the Dask task failed "
                                                         f"({type(exc).__name__}: {exc})")
                if on_done is not None:
                    on_done(rows[i])
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    return pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))
