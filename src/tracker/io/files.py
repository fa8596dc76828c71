"""Which reader opens a recording file (:func:`open_recording_file`): a ROS or RealSense bag
(:mod:`tracker.io.bags`) or an Azure Kinect ``.mkv`` (:mod:`tracker.io.mkv`). The readers are imported
when a file is opened: they need the ``[recordings]`` extra, and they import only
:mod:`tracker.io.file_base`, never this module.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import RecordingError
from .base import RECORDINGS_EXTRA, check_recording_file

if TYPE_CHECKING:  # the readers' base imports the folder reader, which imports this module
    from .file_base import FileRecording


def open_recording_file(path, *, topic=None, color_topic=None, handedness: str = "left") -> "FileRecording":
    """Open a camera or ROS recording file in place (see :meth:`Recording.open`).

    The readers need the ``[recordings]`` extra (``rosbags``, ``av``); without it this is a
    RecordingError naming the ``pip install`` to run.
    """
    path = Path(path)
    check_recording_file(path, topic, color_topic)
    mkv = path.suffix.lower() == ".mkv"
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
