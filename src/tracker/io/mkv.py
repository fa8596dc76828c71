"""Azure Kinect ``.mkv`` recordings (the Azure Kinect recorder's Matroska files), read in place with
PyAV, without the Azure Kinect SDK.

The depth track (title ``DEPTH``, codec ``b16g``: 16-bit big-endian millimetres, 0 = no data) gives
one frame per packet; its timestamps are the file's. The intrinsics come from the calibration
attachment (``calibration.json``): the SDK stores them normalised to the 1024×1024 depth sensor with
the origin at a pixel corner, and converts them per depth mode (binned resolution, crop offset,
output size; the Azure Kinect SDK's ``mode_specific_calibration.c``) — :func:`depth_intrinsics`
does the same. Lens distortion is not modelled (the tracker's cameras are pinholes). The colour
track (MJPG, with its own strongly distorted lens) is not read.

Every problem found in the file is a :class:`~tracker.errors.RecordingError` naming it.
"""
from __future__ import annotations

import json
from pathlib import Path

import av
import numpy as np

from ..errors import RecordingError, TrackerError
from .base import EBML_MAGIC, check_frame_size, looks_like
from .cameras import Camera
from .file_base import FileRecording

#: Depth modes: (binned calibration resolution, crop offset, output size), per the Azure Kinect SDK.
DEPTH_MODES = {
    "NFOV_2X2BINNED": ((512, 512), (96, 90), (320, 288)),
    "NFOV_UNBINNED": ((1024, 1024), (192, 180), (640, 576)),
    "WFOV_2X2BINNED": ((512, 512), (0, 0), (512, 512)),
    "WFOV_UNBINNED": ((1024, 1024), (0, 0), (1024, 1024)),
    "PASSIVE_IR": ((1024, 1024), (0, 0), (1024, 1024)),
}
#: A calibration attachment larger than this is not believed (the real ones are about 4 kB).
_MAX_CALIBRATION_BYTES = 1 << 20
#: Packets read past a seek before the wanted frame must have come.
_MAX_SEEK_PACKETS = 512


def depth_intrinsics(calibration: dict, mode: str, where) -> tuple[int, int, float, float, float, float]:
    """``(width, height, fx, fy, cx, cy)`` of the depth image in ``mode`` from the calibration JSON.

    Examples
    --------
    >>> cal = {"CalibrationInformation": {"Cameras": [{"Purpose": "CALIBRATION_CameraPurposeDepth",
    ...        "SensorWidth": 1024, "SensorHeight": 1024,
    ...        "Intrinsics": {"ModelParameters": [0.5, 0.5, 0.5, 0.5] + [0] * 10}}]}}
    >>> depth_intrinsics(cal, "NFOV_UNBINNED", "x")
    (640, 576, 512.0, 512.0, 319.5, 331.5)
    """
    if mode not in DEPTH_MODES:
        raise RecordingError(where, f"depth mode {mode!r} is not one of {', '.join(DEPTH_MODES)}")
    try:
        cams = calibration["CalibrationInformation"]["Cameras"]
        depth = [c for c in cams if c.get("Purpose") == "CALIBRATION_CameraPurposeDepth"]
        if len(depth) != 1:
            raise RecordingError(where, f"calibration holds {len(depth)} depth cameras, expected 1")
        cam = depth[0]
        p = [float(v) for v in cam["Intrinsics"]["ModelParameters"][:4]]
        sensor = (int(cam.get("SensorWidth", 1024)), int(cam.get("SensorHeight", 1024)))
    except RecordingError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
        raise RecordingError(where, f"calibration has no depth camera intrinsics ({type(exc).__name__}: {exc})") from None
    if len(p) != 4 or not all(np.isfinite(p)):
        raise RecordingError(where, "calibration's depth intrinsics are missing or not finite")
    if sensor != (1024, 1024):
        raise RecordingError(where, f"depth sensor calibrated at {sensor[0]}×{sensor[1]}, expected 1024×1024")
    (bw, bh), (ox, oy), (w, h) = DEPTH_MODES[mode]
    cx_n, cy_n, fx_n, fy_n = p
    # normalised and corner-origin → pixels with the origin at the first pixel's centre
    return w, h, fx_n * bw, fy_n * bh, cx_n * bw - ox - 0.5, cy_n * bh - oy - 0.5


def _vint(data: bytes, i: int, keep_marker: bool = False):
    """An EBML variable-length integer at ``data[i]``: ``(value, length)``, or None past the end."""
    if i >= len(data) or not data[i]:
        return None
    n = 8 - data[i].bit_length() + 1
    if i + n > len(data):
        return None
    v = data[i] if keep_marker else data[i] & ((1 << (8 - n)) - 1)
    for b in data[i + 1:i + n]:
        v = (v << 8) | b
    return v, n


def cut_short(path: Path):
    """``(declared, size)`` when the file's Matroska segment declares more bytes than the file holds
    (a recording copied or downloaded only in part), else None (complete, a segment of unknown size as
    a live recorder writes it, or not Matroska: the reader says so)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(256)
            size = fh.seek(0, 2)
    except OSError:
        return None
    ebml = _vint(head, 0, keep_marker=True)
    if ebml is None or ebml[0] != int.from_bytes(EBML_MAGIC, "big"):
        return None
    hs = _vint(head, ebml[1])
    i = ebml[1] + hs[1] + hs[0] if hs else len(head)
    seg = _vint(head, i, keep_marker=True)
    if seg is None or seg[0] != 0x18538067:
        return None
    ss = _vint(head, i + seg[1])
    if ss is None or ss[0] == (1 << (7 * ss[1])) - 1:  # all ones: size unknown
        return None
    declared = i + seg[1] + ss[1] + ss[0]
    return (declared, size) if declared > size else None


#: The elements a Matroska Segment holds (level 1), and those a Cluster holds: any other ID where an
#: element must start means the size of the element before it is wrong.
_SEGMENT_CHILDREN = {0x114D9B74: "SeekHead", 0x1549A966: "Info", 0x1654AE6B: "Tracks", 0x1C53BB6B: "Cues",
                     0x1941A469: "Attachments", 0x1043A770: "Chapters", 0x1254C367: "Tags",
                     0x1F43B675: "Cluster", 0xEC: "Void", 0xBF: "CRC-32"}
_CLUSTER_CHILDREN = {0xE7: "Timecode", 0xA3: "SimpleBlock", 0xA0: "BlockGroup", 0xA7: "Position",
                     0xAB: "PrevSize", 0x5854: "SilentTracks", 0xAF: "EncryptedBlock", 0xEC: "Void", 0xBF: "CRC-32"}


def check_structure(path: Path) -> None:
    """Walk the Segment's elements and each Cluster's, and refuse the file at the first element whose
    declared size runs past its parent or is followed by no element (a damaged size field): PyAV
    resynchronises past such damage and reads on without a word, losing or misplacing frames. A
    file cut short (:func:`cut_short`) may end inside its last element; that is reported elsewhere.

    Raises
    ------
    RecordingError
        Naming the element, its byte offset and what is wrong.
    """
    try:
        with open(path, "rb") as fh:
            _walk_segment(path, fh, fh.seek(0, 2))
    except OSError as exc:
        raise RecordingError(path, f"cannot read: {exc.strerror or exc}") from None


def _walk_segment(path: Path, fh, size: int) -> None:
    """:func:`check_structure` on an open file of ``size`` bytes: element headers only (a recording
    may be gigabytes; each header is read where the one before it says)."""
    def at(pos):
        fh.seek(pos)
        return fh.read(16)

    head = at(0) + fh.read(240)
    ebml = _vint(head, 0, keep_marker=True)
    hs = _vint(head, ebml[1]) if ebml else None
    if hs is None:
        return  # not Matroska: the container opener says so
    i = ebml[1] + hs[1] + hs[0]
    h = at(i)
    seg, ss = _vint(h, 0, keep_marker=True), None
    if seg is None or seg[0] != 0x18538067 or (ss := _vint(h, seg[1])) is None:
        return
    start = i + seg[1] + ss[1]
    unknown = ss[0] == (1 << (7 * ss[1])) - 1
    end = size if unknown else min(start + ss[0], size)
    cut = not unknown and start + ss[0] > size

    def walk(pos, stop, children, parent):
        while pos < stop:
            h = at(pos)
            eid = _vint(h, 0, keep_marker=True)
            n = _vint(h, eid[1]) if eid else None
            if eid is None or eid[0] not in children or n is None or pos + eid[1] + n[1] > size:
                if cut and (eid is None or n is None or pos + eid[1] + n[1] > size):
                    return  # the copy ends inside this element's header
                raise RecordingError(path, f"damaged: no {parent} element starts at byte {pos} (the size of the "
                                           "element before it is wrong, or the bytes there are)")
            name, body = children[eid[0]], pos + eid[1] + n[1]
            if name == "Cluster" and n[0] == (1 << (7 * n[1])) - 1:
                return  # a live recorder's Cluster of unknown size: its end is where the next one starts
            if body + n[0] > stop and not (cut and body + n[0] > size):
                raise RecordingError(path, f"damaged: the {name} element at byte {pos} declares {n[0]} bytes, "
                                           f"past the end of its {parent} at byte {stop}")
            if name == "Cluster":
                walk(body, min(body + n[0], stop), _CLUSTER_CHILDREN, "Cluster")
            pos = body + n[0]

    walk(start, end, _SEGMENT_CHILDREN, "Segment")


def _cut_text(path: Path) -> str:
    """"cut short: the file has N of its M bytes" for a file cut short (:func:`cut_short`), else ""."""
    cut = cut_short(path)
    return "" if cut is None else f"cut short: the file has {cut[1]} of its {cut[0]} bytes"


def _cut_note(path: Path) -> str:
    cut = _cut_text(path)
    return cut and f"; {cut}"


def _open_container(path: Path):
    try:
        with open(path, "rb") as fh:
            head = fh.read(64)
    except OSError as exc:
        raise RecordingError(path, f"cannot read: {exc.strerror or exc}") from None
    if not head.startswith(EBML_MAGIC):
        # PyAV's own error is an errno ("[Errno 1094995529] Invalid data found when processing input")
        raise RecordingError(path, f"not a Matroska file: it does not start with an EBML header ({looks_like(head)})")
    try:
        return av.open(str(path), "r")
    except Exception as exc:  # PyAV raises many types for damaged files
        raise RecordingError(path, f"not a readable Matroska file ({type(exc).__name__}: {exc})") from None


def _depth_stream(container, path):
    video = [s for s in container.streams if s.type == "video"]
    depth = [s for s in video if s.metadata.get("title") == "DEPTH" or "K4A_DEPTH_MODE" in s.metadata]
    if not depth:
        raise RecordingError(path, "no Azure Kinect depth track (a video track titled DEPTH) in the file")
    return depth[0]


def _calibration(container, path) -> dict:
    att = [s for s in container.streams if s.type == "attachment"
           and (s.metadata.get("K4A_CALIBRATION_FILE") or s.metadata.get("filename", "")) == "calibration.json"]
    if not att:
        raise RecordingError(path, "no calibration.json attachment: the intrinsics are unknown")
    data = att[0].data
    if data is None or len(data) > _MAX_CALIBRATION_BYTES:
        raise RecordingError(path, "calibration attachment is empty or larger than 1 MB")
    try:
        cal = json.loads(bytes(data).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RecordingError(path, f"calibration.json is not valid JSON ({exc})") from None
    if not isinstance(cal, dict):
        raise RecordingError(path, "calibration.json is not a JSON object")
    return cal


class MkvRecording(FileRecording):
    """The depth frames of an Azure Kinect ``.mkv`` (see the module docstring)."""

    def __init__(self, path, camera, stamps_ns, pts, fps, handedness, source, stream_index: int):
        super().__init__(path, camera, stamps_ns, fps, handedness, source, False)
        self._pts = np.asarray(pts, np.int64)
        self._stream_index = stream_index
        self._container = None

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_container"] = None  # an open file cannot be pickled; each process opens it again
        return state

    def _read_raw(self, k: int):
        where = f"{self.path} (depth frame {k})"
        if self._container is None:
            self._container = _open_container(self.path)
        c = self._container
        stream = c.streams[self._stream_index]
        want = int(self._pts[k])
        try:
            c.seek(want, stream=stream, backward=True, any_frame=True)
            for n, pkt in enumerate(c.demux(stream)):
                if pkt.pts is not None and pkt.pts == want and pkt.size:
                    return self._units(bytes(pkt), where), None
                if n > _MAX_SEEK_PACKETS or (pkt.pts is not None and pkt.pts > want):
                    break
        except RecordingError:
            raise
        except Exception as exc:  # PyAV raises many types for damaged files
            self.close()
            raise RecordingError(where, f"damaged file ({type(exc).__name__}: {exc})") from None
        raise RecordingError(where, f"frame at {want} (stream time) listed at opening is not found")

    def _units(self, data: bytes, where) -> np.ndarray:
        w, h = self.camera.width, self.camera.height
        if len(data) != 2 * w * h:
            raise RecordingError(where, f"depth packet of {len(data)} bytes, a {w}×{h} b16g frame has {2 * w * h}")
        return np.frombuffer(data, ">u2").astype(np.uint16).reshape(h, w)

    def close(self):
        """Close the file (it reopens on the next frame read)."""
        if self._container is not None:
            try:
                self._container.close()
            finally:
                self._container = None


def open_mkv(path, *, handedness: str = "left") -> MkvRecording:
    """Open an Azure Kinect ``.mkv`` as an :class:`MkvRecording` (indexing its depth packets once).

    Raises
    ------
    RecordingError
        Naming the file: not a Matroska file, no depth track, no or bad calibration, an unknown depth
        mode, frames of the wrong size, no depth frames.
    """
    path = Path(path)
    c = _open_container(path)
    try:
        check_structure(path)
        s = _depth_stream(c, path)
        mode = s.metadata.get("K4A_DEPTH_MODE", "")
        w, h, fx, fy, cx, cy = depth_intrinsics(_calibration(c, path), mode, path)
        cc = s.codec_context
        if cc is None or s.time_base is None:
            raise RecordingError(path, "the depth track has no codec parameters or time base (a damaged track header)")
        check_frame_size(int(cc.width or 0), int(cc.height or 0), path)
        if (cc.width, cc.height) != (w, h):
            raise RecordingError(path, f"depth track is {cc.width}×{cc.height}, depth mode {mode} gives {w}×{h}")
        tag = (getattr(s, "codec_tag", "") or "").lower()
        if tag and tag != "b16g":
            raise RecordingError(path, f"depth track codec {tag!r}, expected b16g (16-bit big-endian)")
        pts = []
        try:
            for pkt in c.demux(s):
                if pkt.pts is not None and pkt.size:
                    pts.append(int(pkt.pts))
        except Exception as exc:  # PyAV raises many types for damaged files
            raise RecordingError(path, f"damaged file after {len(pts)} depth frames ({type(exc).__name__}: {exc})"
                                       + _cut_note(path)) from None
        if not pts:
            raise RecordingError(path, "the depth track holds no frames" + _cut_note(path))
        pts = np.sort(np.array(pts, np.int64))
        tb = s.time_base
        stamps = np.rint(pts * (1e9 * float(tb))).astype(np.int64)
        rate = s.average_rate or s.guessed_rate
        if rate:
            fps = float(rate)
        else:
            gaps = np.diff(stamps)
            gaps = gaps[gaps > 0]
            fps = 1e9 / float(np.median(gaps)) if gaps.size else 30.0
        try:
            cam = Camera(w, h, fx, fy, cx, cy, 0.001, "uint16", f"azure_kinect_{mode.lower()}")
        except TrackerError as exc:
            raise RecordingError(path, exc.reason) from None
        # a file cut short still reads up to its cut; tracker info shows that frames may be missing,
        # tracker track warns of it
        cut = _cut_text(path)
        rec = MkvRecording(path, cam, stamps, pts, fps, handedness,
                           f"Azure Kinect recording {path.name}, depth mode {mode}{cut and '; ' + cut}", s.index)
        rec.damage = cut
        return rec
    finally:
        c.close()
