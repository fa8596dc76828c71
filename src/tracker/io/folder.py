"""Recording folders (DESIGN.md): ``recording.yaml``, ``depth/000000.png`` …, optional ``color/`` and
``truth.csv``. Frames are read lazily; depth comes out in metres as float32 with NaN for no data.

Layout::

    rec/
      recording.yaml      camera intrinsics and image size, depth encoding and scale, fps, handedness,
                          frame count, colour and truth flags (data_schema/recording.schema.json)
      depth/000000.png    one PNG per frame, numbered from 0 without gaps, in the depth encoding
      color/000000.png    optional, 8-bit RGB registered to the depth image
      truth.csv           optional: frame, time_s and the 26 DoF per frame (metres, radians)

The depth encoding says how a PNG stores integer units (``metres = units · scale_m``, 0 = no data):
``uint16`` is a 16-bit greyscale PNG (Kinect, RealSense with ``scale_m`` 0.000125), ``nyu_rgb`` an
8-bit RGB PNG with ``units = G·256 + B`` (the NYU hand dataset).


Writing one: :mod:`tracker.io.writer`; the examples: :mod:`tracker.io.recording`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from handmodel.dofs import DOF_NAMES
from handmodel.fileio import load_yaml, schema_errors

from ..errors import RecordingError, TrackerError
from .base import (_FRAME_RE, Frame, _shortened, check_frame_size, check_recording_path, is_recording_file,
                   natural_sorted)
from .cameras import Camera
from .files import open_recording_file
from .images import read_color, read_depth_units, units_to_metres


def _frame_files(folder: Path, n: int, what: str) -> list[Path]:
    """``folder/000000.png`` … for ``n`` frames; gaps and strays are errors naming the files.

    The count is checked against the files present before any list of ``n`` paths is built:
    ``frames: 1000000000`` in recording.yaml must not cost 10⁹ paths.
    """
    if not folder.is_dir():
        raise RecordingError(folder, f"missing folder (recording.yaml says {n} {what} frames)")
    try:
        present = {p.name for p in folder.iterdir() if _FRAME_RE.match(p.name)}
    except OSError as exc:
        raise RecordingError(folder, f"cannot list: {exc.strerror or exc}") from None
    expected = {f"{i:06d}.png" for i in range(min(n, len(present)))}
    in_range = present & expected
    if n > len(present) or len(in_range) < n:
        # the first gaps lie within the first len(present) + 5 numbers
        missing = [f"{i:06d}.png" for i in range(min(n, len(present) + 5)) if f"{i:06d}.png" not in present][:5]
        count = n - len(in_range)
        more = f" … ({count} missing)" if count > 5 else ""
        raise RecordingError(folder, f"missing frame file(s) {', '.join(missing)}{more} "
                                     f"of {n} in recording.yaml")
    extra = natural_sorted(present - expected)
    if extra:
        raise RecordingError(folder, f"unexpected frame file(s) {', '.join(p.name for p in extra[:5])} "
                                     f"(recording.yaml says {n} frames)")
    return [folder / f"{i:06d}.png" for i in range(n)]


def _read_truth(path: Path, n: int, fps: float) -> np.ndarray:
    """θ of every frame ``(n, 26)`` from ``truth.csv``, checked (columns, rows, frames in order, numbers);
    its table is :func:`_truth_table`, built when asked for (tracking never asks: pandas stays unloaded)."""
    import csv

    names = list(DOF_NAMES)
    try:
        with open(path, newline="") as fh:
            rows = [r for r in csv.reader(fh) if r and not r[0].startswith("#")]
    except FileNotFoundError:
        raise RecordingError(path, "missing (recording.yaml says truth: true)") from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise RecordingError(path, f"cannot read ({exc})") from None
    if not rows:
        raise RecordingError(path, "empty (no header row)")
    head = [h.strip() for h in rows[0]]
    lack = [k for k in ["frame", *names] if k not in head]
    if lack:
        raise RecordingError(path, f"missing column(s) {', '.join(lack[:5])}{' …' if len(lack) > 5 else ''}")
    body = rows[1:]
    if len(body) != n:
        raise RecordingError(path, f"{len(body)} rows for {n} frames")
    cols = {k: j for j, k in enumerate(head)}
    try:
        # float() reads what repr() wrote exactly (pandas' default parser may be off by an ulp)
        theta = np.array([[float(r[cols[k]]) for k in names] for r in body], float).reshape(n, len(names))
        frame = np.array([int(r[cols["frame"]]) for r in body], int)
        if "time_s" in cols:
            [float(r[cols["time_s"]]) for r in body]  # checked only: frame times are index / fps
    except (ValueError, IndexError) as exc:
        raise RecordingError(path, f"bad value ({exc})") from None
    if not np.array_equal(frame, np.arange(n)):
        k = int(np.argmax(frame != np.arange(n)))
        raise RecordingError(path, f"row {k + 1}: frame {frame[k]}, expected {k} (frames 0…{n - 1} in order)")
    return theta


def _truth_table(theta, fps: float):
    """The truth as a DataFrame: ``frame`` (0…n-1, as :func:`_read_truth` checked), ``time_s`` (index /
    ``fps``) and the 26 DoF columns of ``theta``."""
    import pandas as pd

    n = len(theta)
    df = pd.DataFrame(theta, columns=list(DOF_NAMES))
    df.insert(0, "time_s", np.arange(n) / fps)
    df.insert(0, "frame", np.arange(n))
    return df


class Recording:
    """A recording folder opened for reading (:meth:`open`).

    ``len(rec)``, ``rec[i]`` and ``for frame in rec`` give :class:`Frame` objects, read lazily.
    Attributes: ``path``, ``camera``, ``fps``, ``handedness``, ``meta`` (the YAML), ``truth``
    (DataFrame with ``frame``, ``time_s`` and the 26 DoF columns, or None).
    """

    def __init__(self, path: Path, meta: dict, camera: Camera, depth_files: list, color_files: list | None,
                 truth=None, truth_theta=None):
        self.path = path
        self.meta = meta
        self.camera = camera
        self.fps = float(meta["fps"])
        self.handedness = meta["handedness"]
        self._depth = depth_files
        self._color = color_files
        self._truth = truth
        self._theta = truth_theta

    @classmethod
    def open(cls, path, *, topic: str | None = None, color_topic: str | None = None,
             handedness: str | None = None) -> "Recording":
        """Open and check a recording folder (metadata, frame files, truth); frames are read later.

        A recording file — RealSense ``.bag`` / ``.db3``, a ROS1 ``.bag``, a ROS2 bag (``.db3``,
        ``.mcap`` or its folder with ``metadata.yaml``), an Azure Kinect ``.mkv`` — is read in place
        (:class:`FileRecording`, see :func:`open_recording_file`), never copied.

        Parameters
        ----------
        path : recording folder or recording file
        topic, color_topic : depth and colour topics of a ROS bag (default: found in the file)
        handedness : ``left`` or ``right``; overrides the folder's, and names the hand of a file
            (which cannot say; default ``left``)

        Raises
        ------
        RecordingError
            Naming the file and the problem: no folder, missing ``recording.yaml``, invalid YAML or
            schema violation (with the field), missing or stray frame files, a bad ``truth.csv``; for
            a recording file, any damage found in it.
        """
        path = Path(path)
        check_recording_path(path, topic=topic, color_topic=color_topic, handedness=handedness)
        if is_recording_file(path):
            return open_recording_file(path, topic=topic, color_topic=color_topic, handedness=handedness or "left")
        y = path / "recording.yaml"
        meta = load_yaml(y, RecordingError)
        problem = schema_errors(meta if meta is not None else {}, "recording")
        if problem:
            raise RecordingError(y, f"schema violation, {_shortened(problem)}")
        c, dp = meta["camera"], meta["depth"]
        try:
            cam = Camera(c["width"], c["height"], c["fx"], c["fy"], c["cx"], c["cy"], dp["scale_m"], dp["encoding"],
                         c.get("name", "custom"))
        except TrackerError as exc:
            raise RecordingError(y, exc.reason) from None
        check_frame_size(cam.width, cam.height, y)
        n = int(meta["frames"])
        depth = _frame_files(path / "depth", n, "depth")
        color = _frame_files(path / "color", n, "colour") if meta.get("color") else None
        theta = None
        if meta.get("truth"):
            theta = _read_truth(path / "truth.csv", n, float(meta["fps"]))
        rec = cls(path, meta, cam, depth, color, None, theta)
        if handedness is not None:
            rec.handedness = handedness
        return rec

    def __len__(self) -> int:
        return len(self._depth)

    def __repr__(self) -> str:
        return (f"Recording({str(self.path)!r}, {len(self)} frames, {self.camera.name} "
                f"{self.camera.width}×{self.camera.height}, {self.fps:g} fps, {self.handedness})")

    @property
    def has_color(self) -> bool:
        return self._color is not None

    @property
    def has_truth(self) -> bool:
        return self._theta is not None

    @property
    def truth(self):
        """The truth as a DataFrame (``frame``, ``time_s`` and the 26 DoF columns), or None; made at the
        first ask from the θ read at :meth:`open` (pandas loads then, never for tracking)."""
        if self._truth is None and self._theta is not None:
            self._truth = _truth_table(self._theta, self.fps)
        return self._truth

    @truth.setter
    def truth(self, value):
        self._truth = value

    def depth_units(self, i: int) -> np.ndarray:
        """Stored depth units of frame ``i`` (uint16), as in the file."""
        return read_depth_units(self._depth[self._index(i)], self.camera)

    def _index(self, i) -> int:
        n = len(self)
        if isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)):
            raise TypeError(f"frame index must be an integer, got {type(i).__name__}")
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for {n} frames")
        return int(i) % n

    def __getitem__(self, i) -> Frame:
        i = self._index(i)
        depth = units_to_metres(read_depth_units(self._depth[i], self.camera), self.camera)
        color = read_color(self._color[i], self.camera) if self._color is not None else None
        truth = None if self._theta is None else self._theta[i].copy()
        return Frame(i, i / self.fps, depth, color, truth)

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def frames_or_problems(self):
        """The frames as ``for frame in rec`` gives them, except that a frame whose files cannot be read
        (a PNG cut short, garbage bytes) comes as a :class:`Frame` without depth whose ``problem`` says
        why, and the frames after it still come: a long run is not lost to one bad file."""
        for i in range(len(self)):
            try:
                yield self[i]
            except RecordingError as exc:
                yield Frame(i, i / self.fps, None, problem=str(exc))

    def truth_array(self):
        """θ of every frame ``(F, 26)``, or None."""
        return None if self._theta is None else self._theta.copy()



def open_recording(path, *, topic: str | None = None, color_topic: str | None = None,
                   handedness: str | None = None) -> Recording:
    """Open a recording for reading: our folder, a RealSense or ROS bag, an Azure Kinect ``.mkv``.

    The public entry point (``tracker.open_recording``); :meth:`Recording.open` is the reader.

    >>> open_recording("no/such/folder")
    Traceback (most recent call last):
    ...
    tracker.errors.RecordingError: no/such/folder: no such recording folder
    """
    return Recording.open(path, topic=topic, color_topic=color_topic, handedness=handedness)

