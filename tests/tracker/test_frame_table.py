"""The tracking table without pandas (:class:`tracker.io.tracking_file.FrameTable`): the bytes pandas writes.

``tracker track`` writes its outputs from a FrameTable (pandas not loaded); any table of rows must come
out as ``pandas.DataFrame(rows, columns=...).to_csv(index=False, float_format=...)`` writes it, so a
tracking output or keypoints CSV is the same file whichever of the two wrote it.
"""
import io

import numpy as np
import pandas as pd
from hypothesis import given, settings, strategies as st

from handmodel.dofs import DOF_NAMES
from handmodel.model import HandModel
from tracker.io.tracking_file import (FRAME_COLUMNS, FrameTable, parse_tracking, tracking_csv, write_keypoints,
                                      write_tracking)

# a value of each kind pandas tells apart when it types a column of rows (ints within int64: beyond it
# pandas keeps Python objects, which no tracker row holds)
_INTS = st.integers(-2**63, 2**63 - 1) | st.integers(-5, 5).map(np.int64)
_FLOATS = (st.floats(allow_nan=True, allow_infinity=True, allow_subnormal=True)
           | st.floats(width=32).map(np.float32) | st.sampled_from([0.0, -0.0, 1e-300, 123456789.5, float("nan")]))
_MISSING = st.sampled_from([None, float("nan"), np.nan, np.float32("nan")])
_TEXT = st.text(max_size=6) | st.sampled_from(["tracked", "lost", "a,b", 'say "x"', "two\nlines", "", "nan", " "])
_BOOLS = st.booleans() | st.booleans().map(np.bool_)
_KINDS = [_INTS, _FLOATS, _MISSING, _TEXT, _BOOLS]


@st.composite
def _column(draw, n):
    """``n`` values of one column: mostly of one kind (as the tracker's columns are), with missing values
    or another kind mixed in."""
    main = draw(st.sampled_from(_KINDS))
    other = draw(st.sampled_from(_KINDS))
    share = draw(st.sampled_from([0.0, 0.0, 0.3, 1.0]))
    return [draw(other) if draw(st.floats(0, 1)) < share else draw(main) for _ in range(n)]


@st.composite
def _table(draw):
    n_rows, n_cols = draw(st.integers(0, 6)), draw(st.integers(1, 4))
    columns = [draw(_column(n_rows)) for _ in range(n_cols)]
    names = [f"c{k}" for k in range(n_cols)]
    return names, list(zip(*columns)) if n_rows else []


@settings(max_examples=400, deadline=None)
@given(_table(), st.sampled_from(["%.9g", "%.4f"]))
def test_a_frame_table_is_written_as_pandas_writes_its_dataframe(table, float_format):
    names, rows = table
    t = FrameTable(names, rows)
    assert t.csv(float_format) == pd.DataFrame(rows, columns=names).to_csv(index=False, float_format=float_format)
    assert t.to_frame().equals(pd.DataFrame(rows, columns=names))


def _tracked_rows(n=4):
    """Rows as tracker.run makes them: numpy scalars from θ, a lost frame without θ or fit."""
    rng = np.random.default_rng(3)
    rows = []
    for k in range(n):
        lost = k == 2
        theta = np.full(len(DOF_NAMES), np.nan) if lost else rng.normal(size=len(DOF_NAMES))
        rows.append((k, k / 30, "lost" if lost else "tracked", float("nan") if lost else 1.5 + k, 0 if lost else 300 + k,
                     0 if lost else 320, 12.25 + k, *theta))
    return FrameTable([*FRAME_COLUMNS, *DOF_NAMES], rows)


def test_tracking_and_keypoints_files_are_the_same_from_either_table(tmp_path):
    table, meta = _tracked_rows(), {"recording": "r", "handedness": "left", "mode": "full"}
    df = table.to_frame()
    assert tracking_csv(table, meta) == tracking_csv(df, meta)
    write_tracking(tmp_path / "a.csv", table, meta)
    write_tracking(tmp_path / "b.csv", df, meta)
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()
    back, _ = parse_tracking(io.StringIO(tracking_csv(table, meta)), "a.csv")
    assert back["status"].tolist() == ["tracked", "tracked", "lost", "tracked"] and back.loc[2, DOF_NAMES].isna().all()
    hand = HandModel.load("human")
    write_keypoints(tmp_path / "a.kp.csv", hand, table, meta)
    write_keypoints(tmp_path / "b.kp.csv", hand, df, meta)
    text = (tmp_path / "a.kp.csv").read_text()
    assert text == (tmp_path / "b.kp.csv").read_text()
    assert text.splitlines()[2 + 3].startswith("2,,")  # the lost frame's keypoints are empty


def test_a_frame_table_with_an_unknown_status_or_a_missing_column_is_refused(tmp_path):
    import pytest

    from tracker.errors import TrackerError

    table = _tracked_rows()
    bad = FrameTable(table.columns, [table.rows[0][:2] + ("ok",) + table.rows[0][3:]])
    with pytest.raises(TrackerError, match="unknown status ok"):
        write_tracking(tmp_path / "a.csv", bad, {})
    short = FrameTable(table.columns[:-1], [r[:-1] for r in table.rows])
    with pytest.raises(TrackerError, match=f"missing columns {DOF_NAMES[-1]}"):
        write_tracking(tmp_path / "b.csv", short, {})
    assert not list(tmp_path.iterdir())
