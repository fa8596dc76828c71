"""Posture files → ``(F, 20)`` posture arrays (radians, :data:`~handmodel.dofs.POSTURE_DOF_NAMES` order).

Two formats: ``schroeder26`` (the whitespace tables of the paper's data, e.g. ``fingerfist.txt``: 26
columns per row, θ in the paper's order, 7–26 being the posture) and joint-angle CSV tables (columns
named by DoF, ``#`` metadata lines, as ``synergy angles`` writes them). C3D input goes through marker
IK first (:func:`synergy.fit.read_trial`).

Examples
--------
>>> import numpy as np, tempfile, os
>>> path = os.path.join(tempfile.mkdtemp(), "p.txt")
>>> np.savetxt(path, np.arange(52.0).reshape(2, 26))
>>> read_schroeder26(path)[:, :3]
array([[ 6.,  7.,  8.],
       [32., 33., 34.]])
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from handmodel.dofs import DOF_NAMES, POSE_DOF_NAMES, POSTURE_DOF_NAMES
from synergy.errors import SynergyError


def read_schroeder26(path: str | os.PathLike) -> np.ndarray:
    """The 20 posture columns (7–26) of a schroeder26 posture file, ``(F, 20)`` radians.

    Raises :class:`~synergy.errors.SynergyError` naming the file when it is missing, not a numeric
    table of 26 columns, empty, or holds NaN/infinity.
    """
    p = Path(path)
    if not p.is_file():
        raise SynergyError(p, "no such file")
    try:
        with warnings.catch_warnings():  # an empty file is reported below, as an error
            warnings.simplefilter("ignore", UserWarning)
            A = np.loadtxt(p, dtype=float, ndmin=2)
    except (ValueError, OSError, UnicodeDecodeError) as exc:
        raise SynergyError(p, f"cannot read whitespace table ({exc})") from None
    if A.shape[1] != len(DOF_NAMES) or A.shape[0] == 0:
        raise SynergyError(p, f"expected rows of {len(DOF_NAMES)} values (pose + posture), got shape {A.shape}")
    if not np.isfinite(A).all():
        raise SynergyError(p, "holds NaN or infinity")
    return A[:, len(POSE_DOF_NAMES):]


def check_posture_columns(columns, where) -> None:
    """Raise :class:`~synergy.errors.SynergyError` naming ``where`` unless ``columns`` hold every
    posture DoF (a table's header is enough to know)."""
    missing = [c for c in POSTURE_DOF_NAMES if c not in columns]
    if missing:
        raise SynergyError(where, f"missing posture column(s): {', '.join(missing)}")


def postures_from_table(table: pd.DataFrame, where) -> np.ndarray:
    """The complete posture rows of a joint-angle table; rows with a missing angle are dropped
    (frames where marker IK failed carry NaN)."""
    check_posture_columns(table.columns, where)
    try:
        X = table.loc[:, list(POSTURE_DOF_NAMES)].to_numpy(dtype=float)
    except (ValueError, TypeError) as exc:
        raise SynergyError(where, f"non-numeric posture values ({exc})") from None
    X = X[np.isfinite(X).all(axis=1)]
    if X.shape[0] == 0:
        raise SynergyError(where, "no complete posture rows")
    return X


def _read_csv(p: Path, **kw) -> pd.DataFrame:
    try:
        return pd.read_csv(p, comment="#", skipinitialspace=True, **kw)
    except (ValueError, OSError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise SynergyError(p, f"cannot read CSV ({exc})") from None


def read_csv_postures(path: str | os.PathLike) -> np.ndarray:
    """The complete posture rows of a joint-angle CSV table, ``(F, 20)`` radians."""
    p = Path(path)
    return postures_from_table(_read_csv(p), p)


def check_csv_header(path: str | os.PathLike) -> None:
    """Raise :class:`~synergy.errors.SynergyError` as :func:`read_csv_postures` would if the CSV
    table's header lacks a posture column or cannot be read; reads the header only."""
    p = Path(path)
    check_posture_columns(_read_csv(p, nrows=0).columns, p)
