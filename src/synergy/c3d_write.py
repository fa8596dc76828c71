"""Write marker trajectories to a C3D file (ezc3d), published only when :func:`synergy.c3d.read_c3d`
reads it back whole; the reader and :class:`~synergy.c3d.MarkerData`: :mod:`synergy.c3d`."""
from __future__ import annotations

import errno
import os
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from synergy.c3d import UNIT_SCALE, read_c3d
from synergy.errors import C3DError

__all__ = ["write_c3d"]


def write_c3d(
    path: str | os.PathLike,
    points: np.ndarray,
    labels: Sequence[str],
    rate: float,
    *,
    units: str = "mm",
    prefix: str = "",
    first_frame: int = 1,
    descriptions: Sequence[str] | None = None,
    events: Iterable[tuple[str, float, str]] = (),
    overwrite: bool = False,
) -> Path:
    """Write marker trajectories to a float C3D file with ezc3d.

    The file is written to a temporary name in the same folder and then moved into place,
    so a reader never sees half a file.

    Parameters
    ----------
    path : str or PathLike
        Destination.
    points : array_like, shape (F, M, 3)
        Positions in metres; a NaN (or infinite) coordinate marks the point invalid
        (stored with residual -1).
    labels : sequence of str
        M unique marker names (ASCII, no surrounding spaces).
    rate : float
        Frame rate in Hz (stored as float32).
    units : {"mm", "cm", "m"}
        Length unit of the file.
    prefix : str
        Subject prefix written before each label (``"Sim"`` gives ``"Sim:label"``).
    first_frame : int
        Number of the first frame (1-based).
    descriptions : sequence of str, optional
        POINT:DESCRIPTIONS, one per marker.
    events : iterable of (label, time_s, context)
        Written to the EVENT group.
    overwrite : bool
        Replace an existing file; otherwise ``FileExistsError``.

    Returns
    -------
    Path
        The written file.
    """
    import ezc3d

    path = Path(path)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise C3DError(path, f"points must have shape (F, M, 3), got {pts.shape}")
    n_frames, n_markers = pts.shape[:2]
    if n_frames == 0 or n_markers == 0:
        raise C3DError(path, f"nothing to write: {n_frames} frames x {n_markers} markers")
    labels = [str(lab) for lab in labels]
    if len(labels) != n_markers:
        raise C3DError(path, f"{n_markers} markers but {len(labels)} labels")
    bad = [lab for lab in labels if not lab or lab != lab.strip() or not lab.isascii()]
    if bad:
        raise C3DError(path, f"labels must be non-empty ASCII without surrounding spaces: {bad[:3]}")
    if len(set(labels)) != n_markers:
        raise C3DError(path, "labels are not unique")
    if units not in UNIT_SCALE:
        raise C3DError(path, f"unsupported units {units!r} (expected mm, cm or m)")
    if not np.isfinite(rate) or rate <= 0:
        raise C3DError(path, f"rate must be positive, got {rate}")
    if not 1 <= int(first_frame) <= 65535:
        raise C3DError(path, f"first_frame must be in 1..65535, got {first_frame}")
    if descriptions is not None and len(descriptions) != n_markers:
        raise C3DError(path, f"{n_markers} markers but {len(descriptions)} descriptions")
    prefix = prefix.strip()
    if prefix and not prefix.endswith(":"):
        prefix += ":"
    if not overwrite and path.exists():
        raise FileExistsError(f"{path}: exists and is never overwritten")

    invalid = ~np.isfinite(pts).all(axis=2)                # (F, M)
    data = np.empty((4, n_markers, n_frames))
    data[:3] = (pts / UNIT_SCALE[units]).transpose(2, 1, 0)
    data[3] = 1.0
    data[:3, invalid.T] = 0.0
    residuals = np.where(invalid.T, -1.0, 0.0)[None]

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = np.array([float(rate)])
    c["parameters"]["POINT"]["LABELS"]["value"] = [prefix + lab for lab in labels]
    c.add_parameter("POINT", "UNITS", [units])
    if descriptions is not None:
        c.add_parameter("POINT", "DESCRIPTIONS", [str(d) for d in descriptions])
    c["header"]["points"]["first_frame"] = int(first_frame) - 1   # ezc3d counts from 0
    for label, time_s, context in events:
        c.add_event([0, float(time_s)], context=str(context), label=str(label))
    c["data"]["points"] = data
    c["data"]["meta_points"]["residuals"] = residuals

    from handmodel.fileio import atomic_path

    def reads_back(tmp: Path) -> None:
        # ezc3d reports no failed write (a full disk left a 16 KB file that segfaults readers):
        # the file is published only if it reads back whole.
        try:
            got = read_c3d(tmp)
        except C3DError as exc:
            raise OSError(errno.EIO, f"the written C3D file does not read back ({exc.reason})", str(path)) from None
        if (got.n_frames, got.n_markers) != (n_frames, n_markers):
            raise OSError(errno.EIO, f"the written C3D file reads back as {got.n_frames} frames × {got.n_markers} "
                                     f"markers, not {n_frames} × {n_markers}", str(path))

    with atomic_path(path, overwrite=overwrite, suffix=".tmp.c3d", verify=reads_back) as tmp:
        try:
            c.write(str(tmp))
        except Exception as exc:  # noqa: BLE001
            raise C3DError(path, f"ezc3d could not write the file: {exc}") from None
    return path
