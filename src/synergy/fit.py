"""Fitting synergies from trials: files (angle tables, schroeder26 postures, C3D) → trials →
sufficient statistics → a new bundle, optionally one bundle per task.

Examples
--------
>>> import numpy as np, tempfile, os
>>> folder = tempfile.mkdtemp()
>>> rng = np.random.default_rng(0)
>>> for i in range(2):
...     np.savetxt(os.path.join(folder, f"t{i}.txt"), rng.normal(size=(60, 26)) * 0.1)
>>> trials = [read_trial(os.path.join(folder, f"t{i}.txt"), task="grasp") for i in range(2)]
>>> b = bundle_from_trials(trials, "demo", n_components=0.9, registry=folder)
>>> b.spec, b.manifest["n_trials"], b.manifest["heldout"]["method"]
('demo@1.0.0', 2, 'leave-one-trial-out')
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from handmodel.dofs import POSTURE_DOF_NAMES
from handmodel.fileio import sha256_file
from synergy.angles import IP_COUPLING_SD_DEG, POOR_TRIAL_SHARE, check_handedness, markers_to_angles
from synergy.bundle import Bundle, read_bundle, save_bundle
from synergy.c3d import read_c3d, task_from_events
from synergy.calibrate import Calibration
from synergy.errors import MarkerSetError, SynergyError, TaskMapError
from synergy.markers import MarkerSet, available_markersets, choose_markerset, load_markerset
from synergy.pca import SufficientStats, SynergyModel
from synergy.pca_analysis import heldout_curve
from synergy.postures import check_csv_header, postures_from_table, read_csv_postures, read_schroeder26
from synergy.tasks import TaskMap, label_for

__all__ = ["FORMATS", "Trial", "bundle_from_trials", "check_inputs", "fit_trials", "group_by_task", "poor_reasons",
           "quality_problems", "read_trial", "task_labels"]

#: Input formats of :func:`read_trial` (``auto`` picks by suffix).
FORMATS = ("auto", "csv", "schroeder26", "c3d")


@dataclass(frozen=True, eq=False)
class Trial:
    """Posture frames of one source file (radians, F × D) with provenance."""

    path: str
    postures: np.ndarray
    dof_names: tuple[str, ...] = POSTURE_DOF_NAMES
    task: str | None = None
    sha256: str | None = None
    #: C3D input only: how the markers became angles (marker set, hand, how they were chosen, the
    #: conversion's residuals, verdict, warnings and the reasons for a poor verdict).
    conversion: dict | None = None

    @property
    def frames(self) -> int:
        return int(self.postures.shape[0])

    def source(self) -> dict:
        """The manifest's record of this trial: ``{path, sha256, task, frames}`` and, for a C3D trial,
        its ``conversion`` (marker set, hand, residuals, verdict)."""
        out = {"path": self.path, "sha256": self.sha256, "task": self.task, "frames": self.frames}
        c = self.conversion
        if c:
            out["conversion"] = {"markerset": c["markerset"], "hand": c["hand"],
                                 "residual_median_mm": c["residual_median_mm"],
                                 "residual_p95_mm": c["residual_p95_mm"], "ok_share": c["ok_share"],
                                 "verdict": c["verdict"], "dip_prior": c.get("dip_prior")}
            if c.get("posture_prior"):  # recorded only when used: manifests without it read as before
                out["conversion"]["posture_prior"] = c["posture_prior"]
        return out


def read_trial(path: str | os.PathLike, fmt: str = "auto", *, task: str | None = None,
               markers: str | MarkerSet | None = None, hand: str | None = None, smooth_hz=None,
               calibration="trial", check_hand: bool = True, markersets: Sequence[MarkerSet] | None = None,
               dip_prior_sd: float | None = IP_COUPLING_SD_DEG, prior="auto") -> Trial:
    """Read the posture frames of one file.

    Formats: ``csv`` (joint-angle table: columns named by DoF, ``#`` metadata lines;
    rows with a missing posture angle are dropped), ``schroeder26`` (whitespace table
    of 26 columns, 7–26 are the posture), ``c3d`` (markers → angles by marker IK).
    ``auto`` picks by suffix: .csv, .txt/.dat, .c3d.

    C3D only: ``markers`` (name, path or :class:`~synergy.markers.MarkerSet`) and ``hand`` ('left'
    or 'right') are chosen from the file's labels when not given (among ``markersets``, default
    the shipped ones and the user's, :func:`~synergy.markers.available_markersets`; a hand the
    labels cannot tell is the one the handedness check prefers);
    ``calibration`` is passed to :func:`~synergy.angles.markers_to_angles` (a subject
    :class:`~synergy.calibrate.Calibration` also names the set and hand to use);
    ``check_hand`` False skips the handedness check; ``dip_prior_sd`` is the SD (degrees) of the IK's
    weak DIP = 2/3 PIP prior (:data:`~synergy.angles.IP_COUPLING_SD_DEG`; 0 or None: off); ``prior``
    the IK's posture prior (:func:`~synergy.angles.markers_to_angles`: 'auto', None or a bundle). A trial
    with a wrong hand is converted and judged poor, not refused: :func:`quality_problems` decides.
    ``Trial.conversion`` records it all, the DIP prior included.
    """
    p = Path(path)
    fmt = _format_of(p, fmt)
    conversion = None
    if fmt == "csv":
        X = read_csv_postures(p)
    elif fmt == "schroeder26":
        X = read_schroeder26(p)
    else:
        X, stored_task, conversion = _read_c3d_postures(p, markers, hand, smooth_hz, calibration, check_hand,
                                                        markersets, dip_prior_sd, prior)
        task = task or stored_task
    return Trial(p.as_posix(), X, POSTURE_DOF_NAMES, task, sha256_file(p), conversion)


def _format_of(p: Path, fmt: str) -> str:
    """The format ``p`` is read in (``auto``: by suffix); a missing file is an error here too."""
    if p.is_dir():
        # a folder has no suffix to go by: "unknown file type" sent a user looking for a format option
        raise SynergyError(p, "is a folder: give its files (e.g. FOLDER/*.c3d)")
    if fmt == "auto":
        fmt = {".csv": "csv", ".txt": "schroeder26", ".dat": "schroeder26", ".c3d": "c3d"}.get(
            p.suffix.lower(), "")
        if not fmt:
            raise SynergyError(p, "unknown file type: give the format (csv, schroeder26, c3d)")
    if fmt not in FORMATS:
        raise SynergyError(p, f"unknown format {fmt!r} (known: {', '.join(FORMATS[1:])})")
    if not p.is_file():
        raise SynergyError(p, "no such file")
    return fmt


def check_inputs(paths: Sequence[str | os.PathLike], fmt: str = "auto", *, labels: dict | None = None) -> None:
    """Fail now, not minutes into the conversion of the others, if one of ``paths`` cannot be read
    or, with ``labels`` (``--per-task``: path → task label or None), one has no task: no label and,
    for a C3D, no ``task:<label>`` event (:func:`group_by_task`'s error, before the conversion).

    Each file must have a known format, exist and open; a C3D file must read as a C3D (header,
    parameters, all the frames it announces: :func:`~synergy.c3d.read_c3d`, a fraction of a second
    against the minutes of its marker IK), and a CSV table must name every posture column in its
    header. The errors are those :func:`read_trial` would raise on the same file, so a user sees the
    same line, only sooner.

    Examples
    --------
    >>> import tempfile, os
    >>> f = os.path.join(tempfile.mkdtemp(), "t.csv")
    >>> _ = open(f, "w").write("frame,thumb1_abd")  # a header without the other posture columns
    >>> check_inputs([f])  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    synergy.errors.SynergyError: ...t.csv: missing posture column(s): thumb1_flex, thumb2_flex, ...
    """
    for path in paths:
        p = Path(path)
        fmt_p = _format_of(p, fmt)
        try:
            with open(p, "rb") as fh:
                fh.read(1)
        except OSError as exc:
            raise SynergyError(p, f"cannot read ({exc.strerror or exc})") from None
        data = None
        if fmt_p == "c3d":
            data = read_c3d(p)  # the data are dropped: holding every trial's markers until its turn costs memory
        elif fmt_p == "csv":
            check_csv_header(p)
        if labels is not None and not labels.get(path) and (data is None or not task_from_events(data)):
            raise _no_task(p)


def _no_task(path) -> SynergyError:
    return SynergyError(path, "--per-task: no task label (give --tasks map.yaml, or files that carry a "
                              "task:<label> event)")


def _choose(data, p: Path, markers, hand, calibration, check_hand, markersets):
    """Marker set, hand and the record of how they were chosen (see :func:`read_trial`)."""
    labels = list(data.labels)
    given = "given" if hand else ""
    if isinstance(calibration, Calibration) and calibration.hand:
        if hand and hand != calibration.hand:
            raise SynergyError(calibration.source or "--subject", f"calibrated for the {calibration.hand} hand, "
                                                                  f"not the {hand}")
        hand, given = calibration.hand, given or "subject"
    if markers is not None:
        pool = [markers if isinstance(markers, MarkerSet) else load_markerset(markers)]
    else:
        pool = list(markersets) if markersets is not None else available_markersets()
        if isinstance(calibration, Calibration) and calibration.markerset:
            # the subject was calibrated with one set: a trial of that subject is read with it
            pool = [m for m in pool if m.name == calibration.markerset] or pool
    try:
        ms, hand, rep = choose_markerset(labels, pool, hand=hand, where=p)
    except MarkerSetError:
        if markers is None:
            raise
        # the set was named: its own error lists every missing marker and the labels present
        pool[0].for_hand(hand or "left").match(labels, where=p)
        raise
    rep = {**rep, "chosen": "given" if markers is not None else "labels",
           "hand_from": given or ("labels" if hand else "")}
    if not hand:
        if check_hand:  # side-less labels: the hand whose fit explains the markers
            hc = check_handedness(data, ms, "left", model=ms.hand_model, where=p)
            hand = "right" if hc["verdict"] == "wrong hand" else "left"
            rep["hand_from"] = "handedness check"
        else:
            hand, rep["hand_from"] = "left", "default"
    rep["hand"] = hand
    return ms, hand, rep


def _read_c3d_postures(p: Path, markers, hand, smooth_hz, calibration, check_hand, markersets, dip_prior_sd,
                       prior="auto"):
    """C3D → marker IK → the frames of good quality; the task label stored in the file, if any; and
    the record of the conversion (:attr:`Trial.conversion`)."""
    data = read_c3d(p)
    ms, hand, rep = _choose(data, p, markers, hand, calibration, check_hand, markersets)
    table = markers_to_angles(data, ms, hand=hand, smooth_hz=smooth_hz, calibration=calibration,
                              check_hand="warn" if check_hand else None, ip_coupling_sd_deg=dip_prior_sd or None,
                              prior=prior)
    d = table.attrs["diagnostics"]
    r = table["residual_mm"].to_numpy()
    with np.errstate(all="ignore"):
        med, p95 = (float(np.nanmedian(r)), float(np.nanpercentile(r, 95))) if np.isfinite(r).any() else (None, None)
    conversion = {
        "markerset": ms.name, "hand": hand, "chosen": rep["chosen"], "hand_from": rep["hand_from"],
        "matched": rep["matched"], "total": rep["total"], "others": rep.get("others", []),
        "residual_median_mm": med, "residual_p95_mm": p95, "ok_share": float((table["quality"] == "ok").mean()),
        "verdict": d["verdict"], "warnings": list(d["warnings"]), "reasons": poor_reasons(d),
        "calibration": table.attrs["calibration"].get("method", ""), "dip_prior": table.attrs["dip_prior"],
        "posture_prior": (table.attrs["posture_prior"] or {}).get("name"),
    }
    table = table[table["quality"] == "ok"]
    if table.empty:
        raise SynergyError(p, f"no frame converted with good quality (marker set {ms.name}, {hand} hand: "
                              "check the marker set and --hand)")
    return postures_from_table(table, p), task_from_events(data), conversion


def poor_reasons(diag: dict) -> list:
    """Why a conversion's diagnostics (``df.attrs["diagnostics"]``) have the verdict 'poor', in words
    (the conditions of :func:`synergy.angles.verdict`); empty for other verdicts."""
    out = []
    h = diag.get("handedness") or {}
    if h.get("verdict") == "wrong hand":
        other = "left" if h["chosen"] == "right" else "right"
        out.append(f"the {other} hand fits these markers better ({h['other_residual_mm']:.1f} mm vs "
                   f"{h['residual_mm']:.1f} mm as {h['chosen']}; give --hand {other})")
    if diag.get("poor_share", 0) > POOR_TRIAL_SHARE:
        out.append(f"{100 * diag['poor_share']:.0f} % of frames poor (residual > {diag['poor_threshold_mm']:.1f} mm)")
    driven = diag.get("prior_driven", {})
    pinned = sorted(((v, k) for k, v in diag.get("limit_share", {}).items() if v > 0.25 and k not in driven),
                    reverse=True)
    if pinned:
        out.append("on a joint limit in > 25 % of frames: " + ", ".join(f"{k} {100 * v:.0f} %" for v, k in pinned[:3])
                   + (f" (+{len(pinned) - 3} more)" if len(pinned) > 3 else ""))
    if diag.get("calibration_overfit"):
        line = diag.get("calibration_held_out")
        out.append("the calibration failed its held-out check" + (f" ({line})" if line else ""))
    return out


def quality_problems(trials: Sequence[Trial]) -> list:
    """One :class:`SynergyError` per trial whose conversion was judged poor (file and reasons), in the
    order of ``trials``; the caller refuses them or fits them anyway."""
    out = []
    for t in trials:
        c = t.conversion
        if c and c["verdict"] == "poor":
            why = "; ".join(c["reasons"]) or "judged poor"
            out.append(SynergyError(t.path, f"poor conversion ({c['markerset']}, {c['hand']} hand): {why} "
                                            "(--accept-poor fits it anyway)"))
    return out


def task_labels(files: Sequence, task: str | None = None, task_map: TaskMap | None = None) -> dict:
    """``file -> task label``: ``task`` for every file, or the first matching rule of ``task_map``
    (a file no rule matches is an error: a silent ``None`` would drop it from ``--per-task``)."""
    if task_map is None:
        return {f: task for f in files}
    labels = {}
    for f in files:
        labels[f] = label_for(f, task_map)
        if labels[f] is None:
            raise TaskMapError(task_map.source or "task map", f"no rule matches {f}")
    return labels


def group_by_task(trials: Sequence[Trial], name: str, *, per_task: bool = False,
                  order: Sequence[str] | None = None) -> dict[str, list[Trial]]:
    """Bundle name → its trials: all under ``name``, or with ``per_task`` one ``NAME-TASK`` group per
    task label (in ``order``, default sorted), empty groups left out."""
    if not per_task:
        return {name: list(trials)}
    unlabelled = [tr.path for tr in trials if not tr.task]
    if unlabelled:
        raise _no_task(unlabelled[0])
    order = list(order) if order is not None else sorted({tr.task for tr in trials})
    groups = {f"{name}-{t}": [tr for tr in trials if tr.task == t] for t in order}
    return {k: v for k, v in groups.items() if v}


def fit_trials(trials: Sequence[Trial], n_components=None, stats=None) -> SynergyModel:
    """Fit a :class:`SynergyModel` (with PC limits) on all trials' postures; ``stats`` are the trials'
    sufficient statistics when already computed elsewhere (e.g. as Dask tasks)."""
    if not trials:
        raise SynergyError(None, "no trials to fit")
    names = trials[0].dof_names
    for t in trials:
        if t.dof_names != names:
            raise SynergyError(t.path, f"DoF names differ from {trials[0].path}")
    if stats is None:
        stats = [SufficientStats.from_array(t.postures) for t in trials]
    model = SufficientStats.merge_all(stats).finalize(n_components)
    for t in trials:
        model.update_limits(t.postures)
    return model


def bundle_from_trials(
    trials: Sequence[Trial], name: str, *, n_components=None, registry=None, version=None,
    tasks: Sequence[str] | None = None, hand_model: str = "default",
    hand_model_sha256: str | None = None, heldout: bool = True, stats=None,
) -> Bundle:
    """Fit, estimate held-out reconstruction error, save and return the new bundle."""
    model = fit_trials(trials, n_components, stats)
    ho = None
    if heldout:
        try:
            rms, method = heldout_curve([t.postures for t in trials])
            ho = {"method": method, "rms_rad": rms.tolist()}
        except SynergyError:
            ho = None  # too little data to hold any out; the bundle is still valid
    if tasks is None:
        tasks = sorted({t.task for t in trials if t.task})
    path = save_bundle(
        model, name, version, registry=registry, dof_names=trials[0].dof_names, tasks=tasks,
        sources=[t.source() for t in trials], n_trials=len(trials), hand_model=hand_model,
        hand_model_sha256=hand_model_sha256, heldout=ho,
    )
    return read_bundle(path)
