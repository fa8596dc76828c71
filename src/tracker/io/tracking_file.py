"""The tracking output and the keypoints CSV: their one writer and reader.

The tracking output is a CSV with ``# key: value`` header lines (recording, mode, synergies, PCs,
settings, hand model and its hash, units), then one row per frame: ``frame, time_s, status, fit_mm,
points_used, points, ms`` and the 26 DoF columns (metres, radians). :func:`write_tracking` and
:func:`read_tracking` are its one writer and reader (``tracker track`` writes it through
:func:`tracker.run.run_job`; ``tracker eval``, the experiments and users read it);
:func:`write_keypoints` and :func:`read_keypoints` those of the keypoints CSV (``tracker track
--keypoints``, read by ``tracker show --keypoints``).

>>> import io, numpy as np, pandas as pd
>>> df = pd.DataFrame([[0, 0.0, "reinit", 1.5, 300, 310, 20.0] + [0.0] * 26],
...                   columns=list(FRAME_COLUMNS) + list(DOF_NAMES))
>>> text = tracking_csv(df, {"mode": "full", "units": "metres, radians"})
>>> back, meta = parse_tracking(io.StringIO(text), "example.csv")
>>> meta["mode"], back["status"].tolist()
('full', ['reinit'])
"""
from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from handmodel.cliutil import error_line
from handmodel.dofs import DOF_NAMES
from handmodel.errors import ToolkitError
from handmodel.fileio import atomic_write_text
from handmodel.model import HandModel

from ..errors import TrackerError

if TYPE_CHECKING:  # the annotations only: writing never loads pandas, reading does (in the readers)
    import pandas as pd

#: The columns of a tracking output before the DoF names, one row per frame.
FRAME_COLUMNS = ("frame", "time_s", "status", "fit_mm", "points_used", "points", "ms")
#: A frame's status: followed from the last frame, lost (no hand), found by a fresh search, or — in
#: real time only (:func:`tracker.run.track_realtime`) — predicted (its fit was pending: the last fit moved on)
STATUSES = ("tracked", "lost", "reinit", "predicted")


def tracking_metadata(recording_path, tracker, synergies_spec="", synergies_file="") -> dict:
    """The header of a tracking output: what was tracked, how, with which hand model and which synergy
    bundle (``synergies_file``: the bundle file read, since one name@version may be in two registries)."""
    # the model file's identity (a resized hand is that file plus hand_scale)
    st, hand = tracker.settings, getattr(tracker, "base_hand", tracker.hand)
    return {"recording": str(recording_path), "mode": st.mode, "synergies": synergies_spec or "",
            "synergies_file": str(synergies_file or ""),
            "pcs": "" if tracker.n_pcs is None else str(tracker.n_pcs), "stride": str(st.observe.stride),
            "icp": str(st.icp.icp_iterations), "gn": str(st.icp.gn_iterations), "model": st.correspond.model,
            "hand_model": f"{hand.name} {hand.sha256}", "handedness": hand.handedness,
            "hand_model_file": str(hand.path), "hand_calibration": _calibration_text(hand),
            "hand_scale": _scale_text(tracker), "hand_shape": _shape_text(tracker),
            "hand_check": str(getattr(tracker, "hand_check_", None) or ""),
            "detector": _learned_text(getattr(getattr(tracker, "search", None), "keypoints", None)),
            "presence": _learned_text(getattr(tracker, "presence", None)), "units": "metres, radians"}


def _learned_text(part) -> str:
    """A learned part's identity (:class:`tracker.parts.KeypointSeed`, :class:`tracker.parts.HandPresence`):
    its model's name, version and manifest seal, so that a result says which network made it; "" without the
    part, "given in code" for a detector passed as a function."""
    if part is None:
        return ""
    m = getattr(getattr(part, "model", None), "manifest", None)
    if not isinstance(m, dict):
        return "given in code"
    return f"{m.get('name', '')} {m.get('version', '')} (manifest_sha256 {m.get('manifest_sha256', '')})"


def _calibration_text(hand) -> str:
    """For a calibrated hand file (:meth:`handmodel.HandModel.save` of :func:`tracker.scale.calibrated_hand`):
    where its hand came from, so the header says the size is in the file, not in ``hand_scale``."""
    cal = getattr(hand, "calibration", None)
    if not cal:
        return ""
    base = hand.provenance.get("base_model") or {}
    fingers = cal.get("finger_lengths")
    tail = f", finger lengths {', '.join(f'{k} {v:.3f}' for k, v in fingers.items())}" if fingers else ""
    return (f"this file's hand: size {cal.get('hand_scale')} × {base.get('name')} {base.get('sha256')}{tail}, "
            f"calibrated on {cal.get('recording')}")


def _scale_text(tracker) -> str:
    """The hand size tracked with (a factor on the hand model), how it was set, and an automatic
    calibration's per-frame estimates: ``--hand-scale`` takes the number back."""
    scale = getattr(tracker, "scale_", None)
    if scale is None:
        return ""
    est = getattr(tracker, "scale_estimates_", [])
    fingers = getattr(tracker, "finger_scales_", None)
    # per-finger length factors (finger_lengths) follow the size, in the hand model's finger order
    tail = f"; finger lengths {', '.join(f'{k} {v:.3f}' for k, v in fingers.items())}" if fingers else ""
    if tracker.settings.scale.hand_scale != "auto":
        given = "the hand file's calibrated hand as it is" if getattr(tracker.base_hand, "calibration", None) else "given"
        return f"{scale:.4f} ({given}){tail}"
    return f"{scale:.4f} (auto, median of {', '.join(f'{e:.4f}' for e in est)}){tail}"


def _shape_text(tracker) -> str:
    """The tracked hand's shape on the header's model as JSON (``{"scale": s, "fingers": {name: factor}}``),
    for :func:`tracked_hand` to rebuild it; empty when the model was tracked as it is."""
    scale = getattr(tracker, "scale_", None)
    if scale is None:
        return ""
    fingers = getattr(tracker, "finger_scales_", None) or {}
    return json.dumps({"scale": float(scale), "fingers": {k: float(v) for k, v in fingers.items()}})


def tracked_hand(meta, where="tracking output") -> HandModel:
    """The hand a tracking output was tracked with, rebuilt from its header (``meta``): the model file
    it names (its SHA-256 checked), in the handedness tracked, resized by ``hand_shape`` — so its
    keypoints are the ones the tracker fitted (the default model for an output without these keys).

    Raises
    ------
    TrackerError
        Naming ``where``: the model file is gone or changed, or ``hand_shape`` is not readable.
    """
    name, _, sha = str(meta.get("hand_model", "default")).partition(" ")
    source = meta.get("hand_model_file") or name or "default"
    try:
        hand = HandModel.load(source, right=meta.get("handedness") == "right")
    except ToolkitError as exc:
        raise TrackerError(where, f"its hand model {source} cannot be loaded ({error_line(exc).removeprefix('error: ')})") from None
    if sha and hand.sha256 != sha:
        raise TrackerError(where, f"was tracked with hand model {name} {sha[:12]}…, but {source} is now "
                                  f"{hand.sha256[:12]}… (changed since)")
    text = meta.get("hand_shape") or ""
    if not text:
        return hand
    # here, not at the top: reading a tracking output (tracker show --keypoints, a user's script) need not
    # load the fitting modules tracker.resize imports (correspond and its compiled kernels)
    from ..resize import shaped_hand

    try:
        shape = json.loads(text)
        return shaped_hand(hand, float(shape["scale"]), {str(k): float(v) for k, v in shape.get("fingers", {}).items()})
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise TrackerError(where, f"hand_shape in its header is not readable ({exc})") from None


class FrameTable:
    """A table as rows of values, without pandas: what :func:`tracker.run.track_recording` makes for
    :func:`tracker.run.run_job` (``tracker track`` of one recording never loads pandas).

    Parameters
    ----------
    columns : the column names
    rows : one tuple of values a row, in ``columns``' order

    :meth:`csv` is the text of ``pandas.DataFrame(rows, columns=columns).to_csv(index=False,
    float_format=...)`` (:meth:`to_frame`), byte for byte: each column typed as pandas infers it from
    its values (:func:`_column_text`), the rows written by the same :mod:`csv` writer.

    >>> t = FrameTable(("frame", "status", "fit_mm"), [(0, "reinit", 1.25), (1, "lost", float("nan"))])
    >>> len(t), t.column("status"), t.csv("%.9g")
    (2, ['reinit', 'lost'], 'frame,status,fit_mm\\n0,reinit,1.25\\n1,lost,\\n')
    """

    def __init__(self, columns, rows):
        self.columns = tuple(columns)
        self.rows = list(rows)

    def __len__(self) -> int:
        return len(self.rows)

    def column(self, name) -> list:
        """The values of column ``name``, one a row."""
        k = self.columns.index(name)
        return [row[k] for row in self.rows]

    def to_frame(self):
        """The table as a pandas DataFrame (pandas is loaded here)."""
        import pandas as pd

        return pd.DataFrame(self.rows, columns=list(self.columns))

    def csv(self, float_format: str) -> str:
        """The table as pandas' ``to_csv(index=False, float_format=float_format)`` writes :meth:`to_frame`."""
        out = io.StringIO()
        # pandas' writer: csv's minimal quoting and the platform's line ends
        writer = csv.writer(out, lineterminator=os.linesep)
        writer.writerow(self.columns)
        writer.writerows(zip(*(_column_text(values, float_format) for values in zip(*self.rows))))
        return out.getvalue()


def _value_kind(v) -> str:
    """How pandas' type inference of an object column sees one value: ``"na"`` (None, NaN), ``"bool"``,
    ``"int"``, ``"float"`` or ``"other"``."""
    if v is None:
        return "na"
    if isinstance(v, (bool, np.bool_)):
        return "bool"
    if isinstance(v, (int, np.integer)):
        return "int"
    if isinstance(v, (float, np.floating)):
        return "na" if v != v else "float"
    return "other"


def _column_text(values, float_format) -> list[str]:
    """One column's values as ``DataFrame.to_csv`` writes them, the column typed as ``pandas.DataFrame``
    types a column of rows: integers alone an integer column (``str``); integers and floats, with or
    without missing values, a float column (``float_format``, missing empty); booleans alone a boolean
    column; anything else an object column (``str``, missing empty)."""
    kinds = {_value_kind(v) for v in values}
    if kinds == {"int"}:
        return [str(int(v)) for v in values]
    if kinds == {"bool"}:
        return [str(bool(v)) for v in values]
    if kinds <= {"int", "float", "na"} and kinds != {"na"}:
        return ["" if k == "na" else float_format % float(v) for v, k in zip(values, map(_value_kind, values))]
    return ["" if _value_kind(v) == "na" else str(v) for v in values]


def _csv_text(table, float_format) -> str:
    """``table``'s CSV text: a :class:`FrameTable` by its own writer, a DataFrame by pandas'."""
    if isinstance(table, FrameTable):
        return table.csv(float_format)
    return table.to_csv(index=False, float_format=float_format)


def tracking_csv(df, meta) -> str:
    """The tracking output's text: ``# key: value`` lines, then the table (a DataFrame or a
    :class:`FrameTable`)."""
    head = "".join(f"# {k}: {v}\n" for k, v in meta.items())
    return head + _csv_text(df, "%.9g")


def write_tracking(path, df, meta, *, overwrite=False) -> Path:
    """Write a tracking output atomically (never over an existing file unless ``overwrite``); ``df``: a
    DataFrame or a :class:`FrameTable`."""
    _check_table(df, path)
    return atomic_write_text(path, tracking_csv(df, meta), overwrite=overwrite)


def _split_header(stream):
    """``(metadata, table lines)`` of a text stream whose ``# key: value`` lines are its header."""
    meta = {}
    lines = []
    for line in stream:
        if line.startswith("#"):
            k, sep, v = line[1:].partition(":")
            if sep:
                meta[k.strip()] = v.strip()
        else:
            lines.append(line)
    return meta, lines


def parse_tracking(stream, where):
    """``(table, metadata)`` of a tracking output read from a text stream; ``where`` names it in errors."""
    import pandas as pd

    meta, lines = _split_header(stream)
    try:
        df = pd.read_csv(io.StringIO("".join(lines)))
    except (ValueError, pd.errors.ParserError) as exc:
        raise TrackerError(where, f"cannot read tracking output ({exc})") from None
    _check_table(df, where)
    return df, meta


def read_tracking(path):
    """``(table, metadata)`` of a tracking output file (see :func:`write_tracking`)."""
    try:
        with open(path, encoding="utf-8") as f:
            return parse_tracking(f, path)
    except UnicodeDecodeError:
        raise TrackerError(path, "not a tracking output (not UTF-8 text)") from None


def _check_table(df, where):
    missing = [c for c in (*FRAME_COLUMNS, *DOF_NAMES) if c not in df.columns]
    if missing:
        raise TrackerError(where, f"not a tracking output: missing columns {', '.join(missing)}")
    status = df.column("status") if isinstance(df, FrameTable) else df["status"].astype(str)
    bad = sorted(set(map(str, status)) - set(STATUSES))
    if bad:
        raise TrackerError(where, f"unknown status {', '.join(bad)} (expected {', '.join(STATUSES)})")


def keypoints_table(hand, df) -> pd.DataFrame:
    """The 21 keypoints of every tracked frame in mm (NaN where θ is not finite), one row per frame."""
    import pandas as pd

    kd = pd.DataFrame(_keypoints_mm(hand, df[list(hand.dof_names)].to_numpy(float)), columns=_keypoint_columns(hand))
    kd.insert(0, "frame", df["frame"].to_numpy())
    return kd


def _keypoints_mm(hand, th) -> np.ndarray:
    """``(frames, 63)``: the keypoints of each row of ``th`` in mm, NaN where θ is not finite."""
    kps = np.full((len(th), hand.n_nodes * 3), np.nan)
    ok = np.isfinite(th).all(1)
    if ok.any():
        kps[ok] = hand.keypoints(th[ok]).reshape(int(ok.sum()), -1) * 1000.0
    return kps


def _keypoint_columns(hand) -> list[str]:
    return [f"{n}_{a}_mm" for n in hand.keypoint_names for a in "xyz"]


def _keypoints_frame_table(hand, table: FrameTable) -> FrameTable:
    """:func:`keypoints_table` of a :class:`FrameTable`, as a FrameTable (the same CSV, without pandas)."""
    dofs = [table.columns.index(n) for n in hand.dof_names]
    th = np.array([[row[k] for k in dofs] for row in table.rows], float).reshape(len(table), len(dofs))
    return FrameTable(["frame", *_keypoint_columns(hand)],
                      [(f, *k) for f, k in zip(table.column("frame"), _keypoints_mm(hand, th).tolist())])


#: Header keys of a keypoints CSV: the tracking output's, so ``tracker show`` can tell keypoints of
#: another recording (a file without them, written before they were, is read as it is).
KEYPOINTS_HEADER = ("recording", "handedness")


def write_keypoints(path, hand, df, meta, *, overwrite=False) -> Path:
    """Write the keypoints CSV of a tracking (:func:`keypoints_table` of ``df`` on ``hand``) atomically,
    after ``# recording:`` and ``# handedness:`` lines taken from its header ``meta``; it is never written
    over an existing file unless ``overwrite`` (``df``: a DataFrame or a :class:`FrameTable`).
    :func:`read_keypoints` reads it."""
    head = "".join(f"# {k}: {meta[k]}\n" for k in KEYPOINTS_HEADER if k in meta)
    table = _keypoints_frame_table(hand, df) if isinstance(df, FrameTable) else keypoints_table(hand, df)
    return atomic_write_text(path, head + _csv_text(table, "%.4f"), overwrite=overwrite)


def read_keypoints(path, names):
    """``(table, metadata)`` of a keypoints CSV of :func:`write_keypoints` (its header may be absent),
    whose keypoints must include ``names``.

    Raises
    ------
    TrackerError
        Naming ``path``: not readable, or not a keypoints CSV (the first missing columns).
    """
    import pandas as pd

    try:
        with open(path, encoding="utf-8") as f:
            meta, lines = _split_header(f)
        df = pd.read_csv(io.StringIO("".join(lines)))
    except (OSError, ValueError, pd.errors.ParserError) as exc:  # UnicodeDecodeError is a ValueError
        raise TrackerError(path, f"cannot read a keypoints CSV ({type(exc).__name__}: {exc})") from None
    cols = [f"{k}_{a}_mm" for k in names for a in "xyz"]
    missing = [c for c in ["frame", *cols] if c not in df.columns]
    if missing:
        raise TrackerError(path, f"not a keypoints CSV of tracker track (missing {', '.join(missing[:3])}"
                                 f"{' …' if len(missing) > 3 else ''})")
    return df, meta
