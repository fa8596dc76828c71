"""What every recording reader and writer shares: frame-size and frame-rate bounds, the
:class:`Frame` a reader gives, natural name order, and the first bytes that tell recording files
apart (:func:`looks_like`, :func:`is_recording_file`), and what makes a path no recording before anything
is read (:func:`check_recording_path`). Imports nothing else of :mod:`tracker.io`, so every reader and
writer can import it, and no numpy: a command checks its recording's path with it before its heavy imports.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import RecordingError

if TYPE_CHECKING:  # the annotations only: a path is checked without loading numpy
    import numpy as np

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



#: The first bytes of a ROS1 bag, of a Matroska file (its EBML header's ID: Azure Kinect .mkv) and of an
#: SQLite database (a ROS2 .db3): what the readers test a file for (tracker.io.bags, tracker.io.mkv).
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


def is_recording_file(path) -> bool:
    """True for a path :func:`open_recording_file` reads: a file with one of
    :data:`RECORDING_FILE_SUFFIXES`, or a ROS2 bag folder (``metadata.yaml`` and no ``recording.yaml``)."""
    p = Path(path)
    if p.suffix.lower() in RECORDING_FILE_SUFFIXES and not p.is_dir():
        return True
    return p.is_dir() and (p / "metadata.yaml").is_file() and not (p / "recording.yaml").exists()


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


def check_recording_file(path, topic=None, color_topic=None) -> None:
    """Refuse a recording file (:func:`is_recording_file`) that is not there, or topics for a ``.mkv``:
    what :func:`tracker.io.files.open_recording_file` refuses before it loads a reader."""
    path = Path(path)
    if not path.exists():
        raise RecordingError(path, "no such recording file")
    if path.suffix.lower() == ".mkv" and (topic is not None or color_topic is not None):
        raise RecordingError(path, "--topic and --color-topic apply to ROS bags, not to .mkv files")


def check_recording_path(path, *, topic=None, color_topic=None, handedness=None) -> None:
    """Refuse what :meth:`tracker.io.recording.Recording.open` refuses before it reads anything: a
    handedness other than left or right, a recording file that is not there (:func:`check_recording_file`),
    topics for a folder, a file that is no recording, no such folder, a folder without ``recording.yaml``
    (the PNG files of a camera, or a folder of recordings: what to do instead). Only the file system's
    entries are looked at, so a command says a mistyped path at once, before its heavy imports
    (``tracker track``: ~1 s); the recording's contents are checked when it is opened.

    Raises
    ------
    RecordingError
        Naming the path (or its missing ``recording.yaml``) and the problem.
    """
    path = Path(path)
    if handedness is not None and handedness not in HANDEDNESS:
        raise RecordingError(path, f"handedness must be left or right, got {handedness!r}")
    if is_recording_file(path):
        check_recording_file(path, topic, color_topic)
        return
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
