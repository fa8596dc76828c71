"""The recording API in one import: reading a recording folder or file (:func:`open_recording`,
:class:`Recording`), writing one (:class:`RecordingWriter`) and importing one (``import_*``).

The parts live in their own modules, imported in this order (none imports one after it):
:mod:`~tracker.io.base` (bounds, :class:`Frame`, file signatures), :mod:`~tracker.io.files` (which
reader opens a file; it imports the readers when a file is opened), :mod:`~tracker.io.folder` (the
folder reader, :class:`Recording`), :mod:`~tracker.io.file_base` (:class:`FileRecording`, the base
the readers :mod:`~tracker.io.bags` and :mod:`~tracker.io.mkv` import), :mod:`~tracker.io.writer`,
:mod:`~tracker.io.importers`.

Examples
--------
>>> import numpy as np, tempfile, pathlib
>>> from tracker.io.cameras import preset
>>> d = pathlib.Path(tempfile.mkdtemp()) / "rec"
>>> with RecordingWriter(d, preset("kinect1"), fps=30, handedness="right") as w:
...     _ = w.write(np.full((480, 640), 0.75, np.float32))
>>> rec = Recording.open(d); len(rec), float(rec[0].depth[0, 0]), rec.handedness
(1, 0.75, 'right')
"""
from .base import (EBML_MAGIC, FILE_SIGNATURES, FPS_RANGE, HANDEDNESS, MAX_FRAME_SIDE, MAX_SHOWN_VALUE,
                   RECORDING_FILE_SUFFIXES, RECORDINGS_EXTRA, ROS1_MAGIC, SCHEMA_VERSION, SQLITE_MAGIC, Frame,
                   check_frame_size, is_recording_file, looks_like, natural_sorted)
from .file_base import FileRecording
from .files import open_recording_file
from .folder import Recording, open_recording
from .importers import COLOR_SUFFIXES, import_color, import_pngs, import_recording_file, import_stills, list_pngs
from .writer import RecordingWriter

__all__ = ["COLOR_SUFFIXES", "EBML_MAGIC", "FILE_SIGNATURES", "FPS_RANGE", "HANDEDNESS", "MAX_FRAME_SIDE",
           "MAX_SHOWN_VALUE", "RECORDING_FILE_SUFFIXES", "RECORDINGS_EXTRA", "ROS1_MAGIC", "SCHEMA_VERSION",
           "SQLITE_MAGIC", "FileRecording", "Frame", "Recording", "RecordingWriter", "check_frame_size",
           "import_color", "import_pngs", "import_recording_file", "import_stills", "is_recording_file", "list_pngs",
           "looks_like", "natural_sorted", "open_recording", "open_recording_file"]
