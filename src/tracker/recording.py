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

Examples
--------
>>> import numpy as np, tempfile, pathlib
>>> from tracker.cameras import preset
>>> d = pathlib.Path(tempfile.mkdtemp()) / "rec"
>>> with RecordingWriter(d, preset("kinect1"), fps=30, handedness="right") as w:
...     _ = w.write(np.full((480, 640), 0.75, np.float32))
>>> rec = Recording.open(d); len(rec), float(rec[0].depth[0, 0]), rec.handedness
(1, 0.75, 'right')
"""
from __future__ import annotations

import copy
import re
import shutil
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from handmodel.dofs import DOF_NAMES
from handmodel.fileio import atomic_write_bytes, atomic_write_text, load_yaml, schema_errors

from .cameras import MAX_UNITS, Camera, as_camera
from .errors import RecordingError, TrackerError
from .images import encode_units, metres_to_units, png_bytes, read_bytes, read_color, read_depth_units, units_to_metres

SCHEMA_VERSION = 1
HANDEDNESS = ("left", "right")
_FRAME_RE = re.compile(r"^(\d+)\.png$")
# what a recording folder may hold; anything else makes overwrite=True refuse
_OWN = {"recording.yaml", "truth.csv", "depth", "color", "truth_hand.yaml"}  # truth_hand.yaml: tracker.sim.hands

#: Largest frame side (pixels). Depth sensors top out at 1024 (Azure Kinect WFOV) or 1280×720;
#: 4096² float32 is 64 MiB a frame, and tracking keeps about ten such arrays, so a frame this
#: size still fits in a few hundred MB, while an 8000×8000 frame drove ``track`` to ~10 GB.
MAX_FRAME_SIDE = 4096
#: The frame rates (Hz) a recording may declare: one frame a 100 s to 100 kHz (recording.schema.json
#: says the same). A rate outside them is damage (``fps: 1.0e-300`` read as a rate made every frame
#: time infinite), not a camera.
FPS_RANGE = (0.01, 100000.0)


def check_frame_size(width: int, height: int, where) -> None:
    """Refuse a frame size over :data:`MAX_FRAME_SIDE` before anything of that size is built."""
    if width > MAX_FRAME_SIDE or height > MAX_FRAME_SIDE:
        raise RecordingError(where, f"frames of {width}×{height} pixels are larger than the supported "
                                    f"{MAX_FRAME_SIDE}×{MAX_FRAME_SIDE}")


#: Longest quoted value an error message shows (a CSV written over recording.yaml is one 4 kB value).
MAX_SHOWN_VALUE = 80


def _shortened(message: str) -> str:
    """``message`` with every quoted value longer than :data:`MAX_SHOWN_VALUE` characters cut with …,
    so an error stays a line that can be read.

    >>> _shortened("field (top level): '" + "0123456789" * 20 + "' is not of type 'object'")
    "field (top level): '0123456789012345678901234567890123456789012345678901234567890123456789012345678…' is not of type 'object'"
    """
    return re.sub(r"'([^']{%d,})'" % (MAX_SHOWN_VALUE + 1),
                  lambda m: f"'{m.group(1)[:MAX_SHOWN_VALUE - 1]}…'", message)


def _natural_key(p: Path):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.name)]


def natural_sorted(paths) -> list[Path]:
    """Paths sorted by name in natural order (``frame2.png`` before ``frame10.png``)."""
    return sorted((Path(p) for p in paths), key=_natural_key)


@dataclass
class Frame:
    """One frame: ``depth (H, W)`` float32 metres (NaN = no data), ``color (H, W, 3)`` uint8 or None,
    ``truth (26,)`` θ or None; ``problem``: why its files could not be read (then ``depth`` is None)."""

    index: int
    time_s: float
    depth: np.ndarray
    color: np.ndarray | None = None
    truth: np.ndarray | None = None
    problem: str = ""


# ----------------------------------------------------------------------------- reading
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


def _read_truth(path: Path, n: int, fps: float):
    import csv

    import pandas as pd

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
    df = pd.DataFrame(theta, columns=names)
    df.insert(0, "time_s", np.arange(n) / fps)
    df.insert(0, "frame", frame)
    return df, theta


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
        self.truth = truth
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
        if handedness is not None and handedness not in HANDEDNESS:
            raise RecordingError(path, f"handedness must be left or right, got {handedness!r}")
        if is_recording_file(path):
            return open_recording_file(path, topic=topic, color_topic=color_topic, handedness=handedness or "left")
        if topic is not None or color_topic is not None:
            raise RecordingError(path, "--topic and --color-topic apply to ROS bags, not to recording folders")
        y = path / "recording.yaml"
        if path.is_file():
            hint = (": a Rerun recording of a tracking, drawn by tracker show" if path.suffix.lower() == ".rrd"
                    else f" (a recording folder, or a {', '.join(RECORDING_FILE_SUFFIXES)} file)")
            raise RecordingError(path, f"is not a recording{hint}")
        if not path.is_dir():
            raise RecordingError(path, "no such recording folder")
        if not y.is_file():
            pngs = [] if (path / "depth").is_dir() else list_pngs(path)
            if pngs:  # the commonest first step: tracking the camera's own folder of frames
                raise RecordingError(y, f"missing: {path} holds {len(pngs)} PNG files, not a recording; import "
                                        f"them first: tracker import {path} --camera PRESET --hand left|right "
                                        f"-o RECORDING")
            inner = [d for d in path.iterdir() if (d / "recording.yaml").is_file()]
            if inner:  # a folder of recordings (tracker import --each): a command takes them one by one
                raise RecordingError(y, f"missing: {path} holds {len(inner)} recordings, not one; give one of them, "
                                        f"or all of them to tracker track ({path / '*'} -s fingerfist -o RESULTS/); tracker "
                                        "calibrate --each takes stills imported as one recording (tracker import "
                                        "without --each)")
            raise RecordingError(y, "missing (not a recording folder)")
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
        truth = theta = None
        if meta.get("truth"):
            truth, theta = _read_truth(path / "truth.csv", n, float(meta["fps"]))
        rec = cls(path, meta, cam, depth, color, truth, theta)
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


# ----------------------------------------------------------------------------- recording files
#: The first bytes of a ROS1 bag, of a Matroska file (its EBML header's ID: Azure Kinect .mkv) and of an
#: SQLite database (a ROS2 .db3): what the readers test a file for (tracker.bags, tracker.mkv).
ROS1_MAGIC = b"#ROSBAG V2.0\n"
EBML_MAGIC = b"\x1a\x45\xdf\xa3"
SQLITE_MAGIC = b"SQLite format 3\0"
#: The first bytes of formats a recording file is confused with (a file renamed, a download saved as
#: an HTML page): what an error names instead of a reader's decoding error (:func:`looks_like`).
FILE_SIGNATURES = ((ROS1_MAGIC.rstrip(b"\n"), "a ROS1 bag"), (EBML_MAGIC, "a Matroska/WebM file"),
                   (SQLITE_MAGIC, "an SQLite database (a ROS2 .db3)"), (b"\x89MCAP", "an MCAP file"),
                   (b"\x89PNG", "a PNG image"), (b"\xff\xd8\xff", "a JPEG image"), (b"PK\x03\x04", "a zip archive"),
                   (b"\x1f\x8b", "a gzip file"), (b"BZh", "a bzip2 file"), (b"%PDF", "a PDF"),
                   (b"RIFF", "a RIFF file (AVI/WAV)"), (b"<!DOCTYPE", "an HTML page"), (b"<html", "an HTML page"))


def looks_like(head: bytes) -> str:
    """What a file whose first bytes are ``head`` looks like, for an error line: a known format's name,
    "empty", "text" or "unknown binary data".

    >>> looks_like(bytes.fromhex("89504e470d0a1a0a")), looks_like(b"frame,x 1,2"), looks_like(b"")
    ('a PNG image', 'text', 'empty')
    """
    for magic, name in FILE_SIGNATURES:
        if head[:len(magic)].lower() == magic.lower():
            return name
    if not head:
        return "empty"
    try:
        head[:512].decode("utf-8")
        return "text"
    except UnicodeDecodeError:
        return "unknown binary data"


#: Suffixes of the recording files read in place (a ROS2 bag may also be its folder with metadata.yaml).
RECORDING_FILE_SUFFIXES = (".bag", ".db3", ".mcap", ".mkv")
RECORDINGS_EXTRA = "pip install 'synergistic-hand-tracking[recordings]'"


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


def is_recording_file(path) -> bool:
    """True for a path :func:`open_recording_file` reads: a file with one of
    :data:`RECORDING_FILE_SUFFIXES`, or a ROS2 bag folder (``metadata.yaml`` and no ``recording.yaml``)."""
    p = Path(path)
    if p.suffix.lower() in RECORDING_FILE_SUFFIXES and not p.is_dir():
        return True
    return p.is_dir() and (p / "metadata.yaml").is_file() and not (p / "recording.yaml").exists()


def open_recording_file(path, *, topic=None, color_topic=None, handedness: str = "left") -> "FileRecording":
    """Open a camera or ROS recording file in place (see :meth:`Recording.open`).

    The readers need the ``[recordings]`` extra (``rosbags``, ``av``); without it this is a
    RecordingError naming the ``pip install`` to run.
    """
    path = Path(path)
    if not path.exists():
        raise RecordingError(path, "no such recording file")
    mkv = path.suffix.lower() == ".mkv"
    if mkv and (topic is not None or color_topic is not None):
        raise RecordingError(path, "--topic and --color-topic apply to ROS bags, not to .mkv files")
    # the readers import their optional libraries at the top, so a missing extra shows up here;
    # importing them here (not at the top) also keeps this module free of an import cycle
    try:
        if mkv:
            from .mkv import open_mkv as opener
        else:
            from .bags import open_bag as opener
    except ImportError as exc:
        raise RecordingError(path, f"reading {path.suffix or 'ROS2 bag'} files needs {exc.name}: "
                                   f"{RECORDINGS_EXTRA}") from None
    kw = {} if mkv else {"topic": topic, "color_topic": color_topic}
    return opener(path, handedness=handedness, **kw)


class FileRecording(Recording):
    """A recording file read in place, behind the :class:`Recording` interface.

    Subclasses (:class:`tracker.bags.BagRecording`, :class:`tracker.mkv.MkvRecording`) index the
    depth frames of the file once (``stamps_ns``, the file's own timestamps) and decode a frame on
    demand in :meth:`_read_raw`. ``Frame.time_s`` is the file's time of the frame, counted from the
    file's first depth frame; ``fps`` is the stream's nominal rate (or, without one, the median
    frame interval). :meth:`select` cuts a time span or thins the frames without reading them.
    """

    #: what :meth:`_read_raw` gives: integer ``units`` (× camera.depth_scale_m) or float ``metres``
    depth_kind = "units"
    #: what is wrong with a file whose frames still read up to the damage (say "cut short: …"), or ""
    #: for a sound one: the commands warn of it, as the frames past it are missing
    damage = ""

    def __init__(self, path, camera: Camera, stamps_ns, fps: float, handedness: str, source: str,
                 has_color: bool):
        self.path = Path(path)
        self.camera = camera
        self.fps = float(fps)
        if not (np.isfinite(self.fps) and FPS_RANGE[0] <= self.fps <= FPS_RANGE[1]):
            raise RecordingError(self.path, f"a frame rate of {self.fps:g} Hz is not a camera's (damaged frame rate "
                                            "or time stamps?)")
        self.handedness = handedness
        self.truth = None
        self._theta = None
        self._color = True if has_color else None
        self._stamps = np.asarray(stamps_ns, np.int64)
        self._sel = np.arange(len(self._stamps))
        self.source = source
        self.meta = {"camera": {"name": camera.name, "width": camera.width, "height": camera.height,
                                "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy},
                     "depth": {"encoding": camera.depth_encoding, "scale_m": camera.depth_scale_m},
                     "fps": self.fps, "handedness": handedness, "frames": len(self._stamps),
                     "color": bool(has_color), "truth": False, "source": source}

    def __len__(self) -> int:
        return len(self._sel)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({str(self.path)!r}, {len(self)} frames, {self.camera.width}×"
                f"{self.camera.height}, {self.fps:g} fps, {self.handedness})")

    @property
    def times_s(self) -> np.ndarray:
        """The file's time of each selected frame (s from the file's first depth frame)."""
        return (self._stamps[self._sel] - (self._stamps[0] if len(self._stamps) else 0)) / 1e9

    def select(self, start_s: float | None = None, end_s: float | None = None, every: int = 1) -> "FileRecording":
        """The frames from ``start_s`` up to and including ``end_s`` (seconds of the file's time, as
        :attr:`times_s` counts), every ``every``-th of them; a new view, nothing is read."""
        if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
            raise RecordingError(self.path, f"--every must be a positive integer, got {every!r}")
        for name, v in (("--start", start_s), ("--end", end_s)):
            if v is not None and not np.isfinite(v):
                raise RecordingError(self.path, f"{name} must be a finite number of seconds, got {v!r}")
            if v is not None and v < 0:
                # the file's time starts at 0 (its first depth frame): a negative time is a typo, not "from the start"
                raise RecordingError(self.path, f"{name} must be ≥ 0 s (seconds from the first depth frame), got {v:g}")
        t = self.times_s
        keep = np.ones(len(t), bool)
        if start_s is not None:
            keep &= t >= start_s - 1e-9
        if end_s is not None:
            keep &= t <= end_s + 1e-9
        view = copy.copy(self)
        view._sel = self._sel[keep][::int(every)]
        if not len(view._sel) and len(self._sel):
            span = (f"from {start_s:g} s" if end_s is None else f"up to {end_s:g} s" if start_s is None
                    else f"between {start_s:g} s and {end_s:g} s")
            raise RecordingError(self.path, f"no frames {span} (the file's frames span {t[0]:g}–{t[-1]:g} s)")
        return view

    def _read_raw(self, k: int):
        """Depth of the file's ``k``-th depth frame (``units`` uint16 or ``metres`` float32, as
        :attr:`depth_kind` says) and its registered colour ``(H, W, 3)`` uint8 or None."""
        raise NotImplementedError(f"{type(self).__name__} must read its frames")

    def _depth_metres(self, raw) -> np.ndarray:
        if self.depth_kind == "units":
            return units_to_metres(raw, self.camera)
        d = np.asarray(raw, np.float32).copy()
        d[~(np.isfinite(d) & (d > 0))] = np.nan
        return d

    def __getitem__(self, i) -> Frame:
        i = self._index(i)
        raw, color = self._read_raw(int(self._sel[i]))
        return Frame(i, float(self.times_s[i]), self._depth_metres(raw), color, None)

    def depth_units(self, i: int) -> np.ndarray:
        """Depth units of frame ``i`` (uint16) in the camera's scale: as stored for integer depth,
        rounded to the nearest unit for float (metre) depth."""
        i = self._index(i)
        raw, _ = self._read_raw(int(self._sel[i]))
        if self.depth_kind == "units":
            return raw
        return metres_to_units(self._depth_metres(raw), self.camera, self.path)

    def frame_with_units(self, i: int):
        """``(Frame, units)`` of frame ``i`` from one decode (for conversion to a folder)."""
        i = self._index(i)
        raw, color = self._read_raw(int(self._sel[i]))
        depth = self._depth_metres(raw)
        units = raw if self.depth_kind == "units" else metres_to_units(depth, self.camera, self.path)
        return Frame(i, float(self.times_s[i]), depth, color, None), units


def import_recording_file(src, dst, *, topic=None, color_topic=None, start_s=None, end_s=None, every: int = 1,
                          handedness: str = "left", overwrite: bool = False, progress=None) -> Recording:
    """Convert a recording file (see :func:`open_recording_file`) into a recording folder.

    Integer depth is copied unit for unit; float depth (ROS ``32FC1``, metres) is rounded to the
    camera's unit (1 mm). The folder's fps is the file's divided by ``every``; its frame times are
    ``i / fps`` (a folder stores no per-frame times), the file's own times stay in the file.

    Parameters
    ----------
    src : recording file
    dst : recording folder to create
    topic, color_topic : ROS depth and colour topics (default: found in the file)
    start_s, end_s : time span to keep (seconds from the file's first depth frame, both included)
    every : keep every N-th frame of the span
    handedness, overwrite : as for :class:`RecordingWriter`
    progress : callable ``progress(done, total)``, called after each frame

    Returns
    -------
    Recording
        The new recording folder, opened.
    """
    src = Path(src)
    rec = open_recording_file(src, topic=topic, color_topic=color_topic, handedness=handedness)
    rec = rec.select(start_s, end_s, every)
    if not len(rec):
        raise RecordingError(src, "holds no depth frames to import")
    with RecordingWriter(dst, rec.camera, rec.fps / every, handedness, overwrite=overwrite,
                         source=f"import of {src} ({rec.source})") as w:
        for i in range(len(rec)):
            frame, units = rec.frame_with_units(i)
            w.write_units(units, frame.color)
            if progress is not None:
                progress(i + 1, len(rec))
    return Recording.open(dst)


# ----------------------------------------------------------------------------- writing
class RecordingWriter:
    """Write a recording folder frame by frame; use as a context manager.

    Each PNG is written atomically (temporary file + rename); ``truth.csv`` and then
    ``recording.yaml`` are written at :meth:`close`, so a folder without ``recording.yaml`` is an
    unfinished recording. An existing non-empty folder is refused unless ``overwrite=True``, which
    replaces a previous recording (and refuses a folder holding anything else). An error inside the
    ``with`` block (a damaged input frame) removes what was written (:meth:`abort`): a failed import
    leaves no half recording that the next attempt would have to ``--overwrite``.

    Parameters
    ----------
    path : folder to create
    camera : Camera (intrinsics, size, depth encoding and scale)
    fps : frame rate (Hz)
    handedness : ``left`` or ``right``
    overwrite : replace an existing recording in ``path``
    source : free text stored in ``recording.yaml`` (where the frames came from)
    """

    def __init__(self, path, camera, fps: float = 30.0, handedness: str = "left", *, overwrite: bool = False,
                 source: str = ""):
        self.path = Path(path)
        if handedness not in HANDEDNESS:
            raise RecordingError(self.path, f"handedness must be left or right, got {handedness!r}")
        try:
            fps = float(fps)
        except (TypeError, ValueError):
            raise RecordingError(self.path, f"fps must be a number, got {fps!r}") from None
        if not (np.isfinite(fps) and FPS_RANGE[0] <= fps <= FPS_RANGE[1]):
            raise RecordingError(self.path, f"fps must be between {FPS_RANGE[0]:g} and {FPS_RANGE[1]:g} Hz, got {fps}")
        self.camera = as_camera(camera)
        check_frame_size(self.camera.width, self.camera.height, self.path)
        self.fps = fps
        self.handedness = handedness
        self.source = str(source)
        self.n = 0
        self.truth: list[np.ndarray] = []
        self.color: bool | None = None
        self._closed = False
        self._created = not self.path.exists()
        self._written: list[Path] = []
        self._prepare(overwrite)

    def _prepare(self, overwrite: bool):
        p = self.path
        if p.exists() and not p.is_dir():
            raise RecordingError(p, "exists and is not a folder")
        entries = list(p.iterdir()) if p.exists() else []
        if not entries:
            return
        if not overwrite:
            raise RecordingError(p, "exists and is not empty (never overwritten; use another folder, or --overwrite)")
        leftover = {e.name for e in entries if e.name.startswith(".") and e.name.endswith(".tmp")}  # a crashed write
        alien = sorted(e.name for e in entries if e.name not in _OWN | leftover)
        if alien:
            raise RecordingError(p, f"holds {', '.join(alien[:3])}, not part of a recording; refusing to overwrite")
        # recording.yaml goes first: a half-cleared folder must not look like a recording
        for e in sorted(entries, key=lambda e: e.name != "recording.yaml"):
            shutil.rmtree(e) if e.is_dir() and not e.is_symlink() else e.unlink()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def abort(self) -> None:
        """Remove the frames written so far (and the folder, when this writer made it); the writer is
        closed. Nothing else in the folder is touched."""
        if self._closed:
            return
        self._closed = True
        for f in self._written:
            f.unlink(missing_ok=True)
        for d in (self.path / "depth", self.path / "color", *((self.path,) if self._created else ())):
            try:
                d.rmdir()  # only when empty
            except OSError:
                pass

    def __len__(self) -> int:
        return self.n

    def write(self, depth_m, color=None, truth=None) -> int:
        """Append a frame: depth ``(H, W)`` in metres (NaN/0 = no data), optional colour ``(H, W, 3)``
        uint8 and θ ``(26,)``. Returns the frame index."""
        where = self.path / "depth" / f"{self.n:06d}.png"
        return self._write(metres_to_units(depth_m, self.camera, where), color, truth)

    def write_units(self, units, color=None, truth=None) -> int:
        """Append a frame given as stored depth units ``(H, W)`` (integers 0…65535, 0 = no data)."""
        where = self.path / "depth" / f"{self.n:06d}.png"
        u = np.asarray(units)
        if u.shape != self.camera.shape:
            raise RecordingError(where, f"depth frame is {u.shape}, the camera says {self.camera.shape}")
        if not np.issubdtype(u.dtype, np.integer) or (u.size and (u.min() < 0 or u.max() > MAX_UNITS)):
            raise RecordingError(where, f"depth units must be integers in 0…{MAX_UNITS}")
        return self._write(u.astype(np.uint16), color, truth)

    def _write(self, units, color, truth) -> int:
        if self._closed:
            raise RecordingError(self.path, "writer is closed")
        name = f"{self.n:06d}.png"
        has_color = color is not None
        if self.color is not None and has_color != self.color:
            raise RecordingError(self.path / "color" / name, "colour must be given for all frames or none")
        if has_color:
            c = np.asarray(color)
            if c.shape != self.camera.shape + (3,) or c.dtype != np.uint8:
                raise RecordingError(self.path / "color" / name,
                                     f"colour frame must be {self.camera.height}×{self.camera.width}×3 uint8, "
                                     f"got {c.dtype} {c.shape}")
        if (truth is not None) != bool(self.truth) and self.n > 0:
            raise RecordingError(self.path / "truth.csv", f"frame {self.n}: truth must be given for all frames or none")
        if truth is not None:
            t = np.asarray(truth, float)
            if t.shape != (len(list(DOF_NAMES)),):
                raise RecordingError(self.path / "truth.csv", f"frame {self.n}: truth must have shape "
                                                              f"({len(list(DOF_NAMES))},), got {t.shape}")
        self._written.append(atomic_write_bytes(self.path / "depth" / name, png_bytes(encode_units(units, self.camera))))
        if has_color:
            self._written.append(atomic_write_bytes(self.path / "color" / name, png_bytes(c)))
        if truth is not None:
            self.truth.append(t.copy())
        self.color = has_color
        self.n += 1
        return self.n - 1

    def close(self):
        """Write ``truth.csv`` (if any) and ``recording.yaml``."""
        import yaml

        if self._closed:
            return
        self.path.mkdir(parents=True, exist_ok=True)
        if self.truth:
            names = list(DOF_NAMES)
            # repr() is the shortest text that reads back to the same float
            lines = [",".join(["frame", "time_s", *names])]
            lines += [",".join([str(i), repr(i / self.fps), *map(repr, map(float, t))])
                      for i, t in enumerate(self.truth)]
            atomic_write_text(self.path / "truth.csv", "\n".join(lines) + "\n", overwrite=True)
        cam = self.camera
        meta = {
            "schema_version": SCHEMA_VERSION,
            "camera": {"name": cam.name, "width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy,
                       "cx": cam.cx, "cy": cam.cy},
            "depth": {"encoding": cam.depth_encoding, "scale_m": cam.depth_scale_m},
            "fps": self.fps, "handedness": self.handedness, "frames": self.n,
            "color": bool(self.color), "truth": bool(self.truth),
            "created": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "generator": "synergistic-hand-tracking", "source": self.source,
        }
        atomic_write_text(self.path / "recording.yaml", yaml.safe_dump(meta, sort_keys=False), overwrite=True)
        self._closed = True


def list_pngs(folder) -> list[Path]:
    """The PNG files directly in ``folder`` (any case of ``.png``, hidden files skipped), natural order."""
    folder = Path(folder)
    if not folder.is_dir():
        if folder.is_file():
            raise RecordingError(folder, "is a file, not a folder of depth PNGs (give the folder that holds it, or a "
                                         "recording file: .bag, .db3, .mcap, .mkv)")
        raise RecordingError(folder, "no such folder")
    return natural_sorted(p for p in folder.iterdir()
                          if p.suffix.lower() == ".png" and not p.name.startswith(".") and p.is_file())


COLOR_SUFFIXES = (".png", ".jpg", ".jpeg")


def import_color(path, camera: Camera) -> np.ndarray:
    """One colour frame to import: 8-bit RGB(A) PNG or JPEG of the camera's size, registered to the
    depth image (the same pixel grid), as ``(H, W, 3)`` uint8."""
    path = Path(path)
    if path.suffix.lower() == ".png":
        return read_color(path, camera)
    import imageio.v3 as iio

    data = read_bytes(path)
    try:
        a = np.asarray(iio.imread(data, extension=".jpg", plugin="pillow"))
    except Exception as exc:  # Pillow raises many types for damaged files
        raise RecordingError(path, f"unreadable JPEG ({type(exc).__name__}: {exc})") from None
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] < 3:
        raise RecordingError(path, f"colour frames need 8-bit RGB, got {a.dtype} {a.shape}")
    if a.shape[:2] != (camera.height, camera.width):
        raise RecordingError(path, f"image is {a.shape[1]}×{a.shape[0]}, the camera says {camera.width}×{camera.height}")
    return np.ascontiguousarray(a[..., :3])


def _png_sources(src: Path, dst, color):
    """The depth PNGs of ``src`` and their colour frames (or None), in natural name order."""
    files = list_pngs(src)
    if not files:
        raise RecordingError(src, "no PNG files to import")
    if Path(dst).resolve() == src.resolve():
        raise RecordingError(dst, "the recording folder must differ from the source folder")
    colors = None
    if color is not None:
        cdir = Path(color)
        if not cdir.is_dir():
            raise RecordingError(cdir, "no such folder")
        colors = natural_sorted(p for p in cdir.iterdir() if p.suffix.lower() in COLOR_SUFFIXES
                                and not p.name.startswith(".") and p.is_file())
        if len(colors) != len(files):
            raise RecordingError(cdir, f"{len(colors)} colour frames for {len(files)} depth frames in {src}")
    return files, colors


def import_stills(src, dst, camera, fps: float = 30.0, handedness: str = "left", *, overwrite: bool = False,
                  progress=None, color=None) -> list[Recording]:
    """Turn a folder of still depth PNGs — single frames, not a video — into one recording per PNG,
    ``dst/<file stem>/``, so that ``tracker track dst/*`` fits each from its own first frame
    (tracked as one recording, each frame would start from the fit of the one before).

    Parameters and checks as :func:`import_pngs`; ``dst`` must be empty or new, or with ``overwrite``
    hold only recordings (they are replaced). A failure removes every recording this call wrote.

    Returns
    -------
    list of Recording
        The new recordings, opened, in natural name order.
    """
    src, dst = Path(src), Path(dst)
    files, colors = _png_sources(src, dst, color)
    camera = as_camera(camera)
    stems = [f.stem for f in files]
    twins = sorted({s for s in stems if stems.count(s) > 1})
    if twins:
        raise RecordingError(src, f"two PNGs are named {twins[0]} (e.g. .png and .PNG): one recording each needs "
                                  "distinct names")
    if dst.exists() and not dst.is_dir():
        raise RecordingError(dst, "exists and is not a folder")
    old = sorted(dst.iterdir()) if dst.exists() else []
    if old and not overwrite:
        raise RecordingError(dst, "exists and is not empty (never overwritten; use another folder, or --overwrite)")
    alien = [e.name for e in old if not (e.is_dir() and (e / "recording.yaml").is_file())]
    if alien:
        raise RecordingError(dst, f"holds {', '.join(alien[:3])}, not recordings; refusing to overwrite")
    for e in old:
        RecordingWriter(e, camera, fps, handedness, overwrite=True).abort()  # clears a recording, nothing else
        shutil.rmtree(e, ignore_errors=True)
    created = not dst.exists()
    done = []
    try:
        for k, f in enumerate(files):
            with RecordingWriter(dst / f.stem, camera, fps, handedness, source=f"import of {f} (a still frame)") as w:
                w.write_units(read_depth_units(f, camera), None if colors is None else import_color(colors[k], camera))
            done.append(dst / f.stem)
            if progress is not None:
                progress(k + 1, len(files))
    except BaseException:
        for d in done:
            shutil.rmtree(d, ignore_errors=True)
        if created:
            shutil.rmtree(dst, ignore_errors=True)
        raise
    return [Recording.open(d) for d in done]


def import_pngs(src, dst, camera, fps: float = 30.0, handedness: str = "left", *, overwrite: bool = False,
                progress=None, color=None) -> Recording:
    """Turn a plain folder of depth PNGs (natural name order) into a recording.

    Every PNG must match the camera: its size and the depth encoding's PNG type (16-bit greyscale
    for ``uint16``, 8-bit RGB for ``nyu_rgb``). The stored units are copied exactly.

    Parameters
    ----------
    src : folder of PNGs
    dst : recording folder to create
    camera : Camera (e.g. ``preset("sr305")``)
    fps, handedness, overwrite : as for :class:`RecordingWriter`
    progress : callable ``progress(done, total)``, called after each frame
    color : optional folder of colour frames registered to the depth (PNG or JPEG, natural name
        order, one per depth frame), for skin segmentation

    Returns
    -------
    Recording
        The new recording, opened.
    """
    src = Path(src)
    files, colors = _png_sources(src, dst, color)
    camera = as_camera(camera)
    # the frames are renumbered: the source line keeps which files, in which order, they came from
    names = files[0].name if len(files) == 1 else f"{files[0].name} … {files[-1].name}"
    source = f"import of {src} ({len(files)} PNG{'s' if len(files) > 1 else ''}, {names}, in natural name order)"
    with RecordingWriter(dst, camera, fps, handedness, overwrite=overwrite, source=source) as w:
        for k, f in enumerate(files):
            w.write_units(read_depth_units(f, camera), None if colors is None else import_color(colors[k], camera))
            if progress is not None:
                progress(k + 1, len(files))
    return Recording.open(dst)
