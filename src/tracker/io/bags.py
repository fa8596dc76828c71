"""ROS bags as recordings, read in place: RealSense ``.bag`` (ROS1, RealSense file format v3) and
``.db3`` (ROS2, ``key=value;…`` info strings), and any ROS1 / ROS2 (sqlite ``.db3`` or ``.mcap``)
bag with a depth image topic.

Depth topics carry ``sensor_msgs/Image`` (``16UC1`` / ``mono16`` in millimetres, ``32FC1`` in
metres) or ``sensor_msgs/CompressedImage`` in the ``compressedDepth`` format (a 12-byte header, then
a 16-bit PNG or an RVL stream; ``32FC1`` stores quantised inverse depth). Intrinsics come from the
stream's ``sensor_msgs/CameraInfo`` (or the RealSense ``key=value`` string), the depth unit from
RealSense's ``Depth Units`` option (otherwise 1 mm for integer depth), the times from the bag.

The bag is indexed once at :func:`open_bag` (ROS1: from the bag's own index, no frame is read;
ROS2: one pass over the depth topic) and each frame is read on demand, so a 20 GB bag is neither
copied nor loaded. An optional colour topic is resampled onto the depth pixel grid
(:func:`tracker.io.images.register_color`) with the RealSense depth→colour extrinsics where the bag
has them, otherwise as if both cameras sat at the same place.

Every problem found in the file — not a bag, truncated, a topic missing or of the wrong type, no
camera info, frames of the wrong size — is a :class:`~tracker.errors.RecordingError` naming it.
"""
from __future__ import annotations

import bz2
import re
from pathlib import Path

import lz4.frame
import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag1.reader import decompressors as _ROS1_DECOMPRESSORS
from rosbags.typesys import Stores, get_typestore

from ..errors import RecordingError, TrackerError
from .bag_checks import check_ros1_complete, check_sqlite_complete
from .bag_messages import (_kv, _number, _quat_matrix, _wrap, color_from_message, depth_from_compressed,
                           depth_from_image, intrinsics_of)
from .base import Frame
from .cameras import Camera
from .file_base import FileRecording
from .images import register_color

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
#: The fields we read of each message type. A bag that embeds its message definitions (MCAP, newer
#: ROS2 sqlite) decodes by them, so a damaged definition gives messages without these fields.
_FIELDS = {IMAGE: ("height", "width", "encoding", "is_bigendian", "step", "data"),
           COMPRESSED: ("format", "data"), CAMERA_INFO: ("height", "width")}
_IMAGE_TYPES = (IMAGE, COMPRESSED)
#: RealSense streams: ``/device_D/sensor_S/Depth_I/…`` (``image/data`` raw, other leaves compressed)
_RS_STREAM = re.compile(r"^((/device_\d+/sensor_\d+)/(Depth|Color|Infrared)_\d+)/")


def _rs(topic: str, kind: str = "Depth"):
    """The RealSense stream match of ``topic`` for a stream kind, or None."""
    m = _RS_STREAM.match(topic)
    return m if m and m.group(3) == kind else None
#: A static message (info, option, camera info) larger than this is not believed.
_MAX_STATIC_BYTES = 1 << 20


#: What one compressed ROS1 chunk may expand to. Chunks hold about 1 MB of messages, or one larger
#: message (a 4096² float frame is 64 MiB); a bz2 or lz4 bomb would otherwise expand without bound.
MAX_CHUNK_BYTES = 512 << 20


def _bounded_decompressor(make):
    def decompress(data: bytes) -> bytes:
        d = make()
        out = d.decompress(data, max_length=MAX_CHUNK_BYTES)
        if not d.eof and not d.needs_input:
            raise ValueError(f"a compressed chunk expands beyond {MAX_CHUNK_BYTES >> 20} MiB")
        return out
    return decompress


_BOUNDED = {"bz2": _bounded_decompressor(bz2.BZ2Decompressor),
            "lz4": _bounded_decompressor(lz4.frame.LZ4FrameDecompressor)}


def _bound_chunks(reader) -> None:
    """Swap a ROS1 reader's chunk decompressors for ones that stop at :data:`MAX_CHUNK_BYTES`."""
    swap = {id(f): _BOUNDED[k] for k, f in _ROS1_DECOMPRESSORS.items() if k in _BOUNDED}
    chunks = getattr(reader, "chunks", None)
    if isinstance(chunks, dict):
        for pos, c in chunks.items():
            if id(c.decompressor) in swap:
                chunks[pos] = c._replace(decompressor=swap[id(c.decompressor)])


class _Bag:
    """An open bag: the reader and its connections; reopened after unpickling."""

    def __init__(self, path: Path):
        self.path = path
        for db in ([path] if path.suffix.lower() == ".db3" else sorted(path.glob("*.db3")) if path.is_dir() else []):
            check_sqlite_complete(db)
        index_pos = None
        if path.is_file() and path.suffix.lower() == ".bag":
            index_pos = check_ros1_complete(path)
        try:
            # bags without embedded message definitions (older ROS2 sqlite) use the Humble types
            self.reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            self.reader.open()
        except Exception as exc:  # rosbags raises many types for damaged files
            if index_pos is not None and "index" in str(exc).lower():
                # the index is the file's last part: a copy that stopped inside it ("Bag index looks damaged")
                raise RecordingError(path, f"damaged or cut short inside its index (from byte {index_pos} to the "
                                           f"file's end at {path.stat().st_size}): copy it again, or rebuild the "
                                           "index with `rosbag reindex`") from None
            raise _wrap(path, "not a readable ROS bag", exc) from None
        if not self.reader.is2:
            for r in self.reader.readers:
                _bound_chunks(r)
        else:
            # MCAP chunk records declare their expanded size: refuse a bomb before it is expanded
            # (a record that understates it is caught by rosbags only after expanding)
            for r in self.reader.readers:
                for c in getattr(getattr(r, "storage", None), "chunks", None) or []:
                    if getattr(c, "uncompressed_size", 0) > MAX_CHUNK_BYTES:
                        self.close()
                        raise RecordingError(path, f"an MCAP chunk declares {c.uncompressed_size} bytes expanded, "
                                                   f"more than the {MAX_CHUNK_BYTES >> 20} MiB allowed")
        self.connections = list(self.reader.connections)

    def close(self):
        try:
            self.reader.close()
        except Exception:  # closing a damaged bag must not hide the error that closed it
            pass

    def by_topic(self, topic: str):
        return [c for c in self.connections if c.topic == topic]

    def messages(self, conns, start=None, stop=None):
        try:
            yield from self.reader.messages(connections=conns, start=start, stop=stop)
        except RecordingError:
            raise
        except Exception as exc:
            raise _wrap(self.path, "damaged bag, cannot read its messages", exc) from None

    def decode(self, conn, raw):
        try:
            msg = self.reader.deserialize(raw, conn.msgtype)
        except Exception as exc:
            raise _wrap(self.path, f"damaged {conn.msgtype} message on {conn.topic}", exc) from None
        missing = [f for f in _FIELDS.get(conn.msgtype, ()) if not hasattr(msg, f)]
        if missing:
            raise RecordingError(self.path, f"damaged message definition of {conn.msgtype} on {conn.topic}: "
                                            f"its messages have no {missing[0]!r}")
        return msg

    def first(self, conns):
        """The first message of these connections, decoded, or None."""
        for conn, _, raw in self.messages(conns):
            if len(raw) > _MAX_STATIC_BYTES:
                raise RecordingError(self.path, f"{conn.topic}: a {len(raw)}-byte {conn.msgtype} message is not believed")
            return self.decode(conn, raw)
        return None

    def stamps(self, conn) -> np.ndarray:
        """Bag times (ns) of every message of ``conn``, in order; from the ROS1 index without reading data."""
        r = self.reader.readers[0]
        if not self.reader.is2 and hasattr(r, "indexes"):
            return np.array([e.time for e in r.indexes.get(conn.id, [])], np.int64)
        return np.array([t for _, t, _ in self.messages([conn])], np.int64)


class BagRecording(FileRecording):
    """The depth (and optional colour) frames of a ROS bag (see the module docstring)."""

    def __init__(self, path, camera, stamps_ns, fps, handedness, source, *, depth_conn, depth_kind,
                 color_conn=None, color_stamps=None, color_K=None, color_R=None, color_t=None):
        super().__init__(path, camera, stamps_ns, fps, handedness, source, color_conn is not None)
        self.depth_kind = depth_kind
        self.topic = depth_conn.topic
        self.color_topic = None if color_conn is None else color_conn.topic
        self._depth_conn, self._color_conn = depth_conn, color_conn
        self._keys = {"depth": (depth_conn.topic, depth_conn.msgtype),
                      "color": None if color_conn is None else (color_conn.topic, color_conn.msgtype)}
        self._color_stamps = color_stamps
        self._color_K, self._color_R, self._color_t = color_K, color_R, color_t
        self._bag: _Bag | None = None
        self._color_cache: tuple[int, np.ndarray] | None = None

    def __getstate__(self):
        # an open reader cannot be pickled (dask workers); each process opens the bag again
        state = dict(self.__dict__)
        # (the connections hold their reader too)
        state.update(_bag=None, _color_cache=None, _depth_conn=None, _color_conn=None)
        return state

    def _open(self) -> _Bag:
        if self._bag is None:
            bag = _Bag(self.path)
            conns = {(c.topic, c.msgtype): c for c in bag.connections}
            if self._keys["depth"] not in conns or (self._keys["color"] and self._keys["color"] not in conns):
                bag.close()
                raise RecordingError(self.path, "the bag changed since it was opened (a topic is gone)")
            self._depth_conn = conns[self._keys["depth"]]
            self._color_conn = conns[self._keys["color"]] if self._keys["color"] else None
            self._bag = bag
        return self._bag

    def _message_at(self, which: str, stamps, k):
        """The ``k``-th message of the ``depth`` or ``color`` topic (bag time ``stamps[k]``), decoded."""
        bag = self._open()  # first: it replaces the connections by those of the reopened bag
        conn = self._depth_conn if which == "depth" else self._color_conn
        t = int(stamps[k])
        nth = k - int(np.searchsorted(stamps, t, "left"))  # several messages may share a time
        for j, (c, _, raw) in enumerate(bag.messages([conn], start=t, stop=t + 1)):
            if j == nth:
                return bag.decode(c, raw)
        raise RecordingError(self.path, f"{conn.topic}: message {k} at {t} ns listed in the index is missing")

    def __iter__(self):
        """The selected frames in order from one pass over the bag (``rec[i]`` looks each frame up
        by its time instead, which for a ROS1 bag walks the index from the start every time)."""
        if not len(self._sel):
            return
        bag = self._open()
        t0, t1 = int(self._stamps[self._sel[0]]), int(self._stamps[self._sel[-1]]) + 1
        k = int(np.searchsorted(self._stamps, t0, "left"))  # the file's index of the first message read
        wanted = iter(self._sel.tolist())
        nxt, i = next(wanted), 0
        for conn, _, raw in bag.messages([self._depth_conn], start=t0, stop=t1):
            if k == nxt:
                depth, color = self._decode(k, bag.decode(conn, raw))
                yield Frame(i, float(self.times_s[i]), self._depth_metres(depth), color, None)
                i += 1
                nxt = next(wanted, None)
                if nxt is None:
                    return
            k += 1
        raise RecordingError(self.path, f"{self.topic}: frame {nxt} listed in the index is missing")

    def _read_raw(self, k: int):
        return self._decode(k, self._message_at("depth", self._stamps, k))

    def _decode(self, k: int, msg):
        where = f"{self.path} ({self.topic}, frame {k})"
        if self._depth_conn.msgtype == IMAGE:
            kind, depth = depth_from_image(msg, where)
        else:
            kind, depth = depth_from_compressed(msg, where)
        if kind != self.depth_kind:
            raise RecordingError(where, f"depth changes from {self.depth_kind} to {kind} within the topic")
        if depth.shape != self.camera.shape:
            raise RecordingError(where, f"depth image is {depth.shape[1]}×{depth.shape[0]}, the camera info says "
                                        f"{self.camera.width}×{self.camera.height}")
        color = None
        if self._keys["color"] is not None:
            color = self._registered_color(k, depth)
        return depth, color

    def _registered_color(self, k, depth):
        cs = self._color_stamps
        t = self._stamps[k]
        j = int(np.clip(np.searchsorted(cs, t), 1, len(cs) - 1)) if len(cs) > 1 else 0
        if len(cs) > 1 and abs(cs[j - 1] - t) <= abs(cs[j] - t):
            j -= 1
        if self._color_cache is None or self._color_cache[0] != j:
            where = f"{self.path} ({self.color_topic}, frame {j})"
            self._color_cache = (j, color_from_message(self._message_at("color", cs, j), where))
        color = self._color_cache[1]
        depth_m = self._depth_metres(depth)
        same_grid = (color.shape[:2] == self.camera.shape and self._color_R is None
                     and np.allclose(self._color_K, self.camera.K))
        if same_grid:
            return color
        return register_color(depth_m, self.camera, color, self._color_K, self._color_R, self._color_t)

    def close(self):
        """Close the bag (it reopens on the next frame read)."""
        if self._bag is not None:
            self._bag.close()
            self._bag = None


def _pick_depth(bag: _Bag, topic):
    """The depth connection: the given topic, a RealSense depth stream, or the one depth-like image topic."""
    images = [c for c in bag.connections if c.msgtype in _IMAGE_TYPES]
    if topic is not None:
        conns = bag.by_topic(topic)
        if not conns:
            names = ", ".join(sorted({c.topic for c in images})[:8]) or "none"
            raise RecordingError(bag.path, f"no topic {topic!r} (image topics: {names})")
        good = [c for c in conns if c.msgtype in _IMAGE_TYPES]
        if not good:
            raise RecordingError(bag.path, f"topic {topic} carries {conns[0].msgtype}, not a depth image "
                                           "(sensor_msgs/Image or CompressedImage)")
        return good[0]
    rs = [c for c in images if _rs(c.topic)]
    if rs:  # the raw stream before a compressed one, then the first stream
        return min(rs, key=lambda c: (not c.topic.endswith("/image/data"), c.topic))
    depthish = [c for c in images if "depth" in c.topic.lower()]
    if len(depthish) == 1:
        return depthish[0]
    if not depthish:
        names = ", ".join(sorted({c.topic for c in images})[:8]) or "none"
        raise RecordingError(bag.path, f"no depth image topic found (image topics: {names}); name one with --topic")
    names = ", ".join(sorted(c.topic for c in depthish)[:8])
    raise RecordingError(bag.path, f"several depth image topics ({names}); choose one with --topic")


def _stream_prefix(topic: str) -> str:
    """``/device_0/sensor_0/Depth_0`` of a RealSense image topic, else the topic's namespace."""
    m = _RS_STREAM.match(topic)
    if m:
        return m.group(1)
    base = topic
    for tail in ("/compressedDepth", "/compressed"):
        if base.endswith(tail):
            base = base[: -len(tail)]
    return base.rsplit("/", 1)[0]


def _camera_info(bag: _Bag, image_topic: str):
    """``(width, height, K)`` for an image topic: RealSense ``…/info/camera_info`` (message or string),
    else the ``sensor_msgs/CameraInfo`` topic nearest in the topic tree."""
    pre = _stream_prefix(image_topic)
    for t in (f"{pre}/info/camera_info", f"{pre}/camera_info"):
        conns = [c for c in bag.by_topic(t) if c.msgtype in (CAMERA_INFO, "std_msgs/msg/String")]
        if conns:
            msg = bag.first(conns)
            if msg is not None:
                return intrinsics_of(msg, f"{bag.path} ({t})")
    infos = [c for c in bag.connections if c.msgtype == CAMERA_INFO]

    def shared(c):
        a, b = pre.split("/"), c.topic.rsplit("/", 1)[0].split("/")
        n = 0
        while n < min(len(a), len(b)) and a[n] == b[n]:
            n += 1
        return n

    infos = [c for c in infos if shared(c) > 1]
    if infos:
        best = max(shared(c) for c in infos)
        near = [c for c in infos if shared(c) == best]
        if len(near) == 1:
            msg = bag.first(near)
            if msg is not None:
                return intrinsics_of(msg, f"{bag.path} ({near[0].topic})")
        else:
            raise RecordingError(bag.path, f"several camera_info topics fit {image_topic} "
                                           f"({', '.join(c.topic for c in near[:4])})")
    raise RecordingError(bag.path, f"missing camera_info for {image_topic} (no sensor_msgs/CameraInfo in "
                                   f"{pre} or near it): the intrinsics are unknown")


def _realsense_fps_units(bag: _Bag, depth_topic: str):
    """Nominal fps and metres per depth unit of a RealSense depth stream, or None where absent."""
    pre = _stream_prefix(depth_topic)
    fps = units = None
    info = [c for c in bag.by_topic(f"{pre}/info") if c.msgtype != CAMERA_INFO]
    if info:
        msg = bag.first(info)
        if hasattr(msg, "fps"):
            fps = _number(msg.fps, f"{bag.path} ({pre}/info)", "fps")
        elif hasattr(msg, "data"):
            kv = _kv(msg.data)
            if "fps" in kv:
                fps = _number(kv["fps"], f"{bag.path} ({pre}/info)", "fps")
    sensor = pre.rsplit("/", 1)[0]
    for name in ("Depth Units", "Depth_Units"):
        t = f"{sensor}/option/{name}/value"
        conns = bag.by_topic(t)
        if conns:
            msg = bag.first(conns)
            if msg is not None:
                units = _number(msg.data, f"{bag.path} ({t})", "depth units")
                if not 0 < units <= 1:
                    raise RecordingError(f"{bag.path} ({t})", f"depth units of {units:g} m are not believed")
                break
    return (fps if fps and fps > 0 else None), units


def _pick_color(bag: _Bag, color_topic, depth_conn):
    if color_topic is None:
        if not _rs(depth_conn.topic):
            return None
        rs = [c for c in bag.connections if c.msgtype in _IMAGE_TYPES and _rs(c.topic, "Color")]
        return min(rs, key=lambda c: (not c.topic.endswith("/image/data"), c.topic)) if rs else None
    conns = [c for c in bag.by_topic(color_topic) if c.msgtype in _IMAGE_TYPES]
    if not conns:
        have = bag.by_topic(color_topic)
        why = f"carries {have[0].msgtype}, not an image" if have else "is not in the bag"
        raise RecordingError(bag.path, f"colour topic {color_topic} {why}")
    return conns[0]


def _color_extrinsics(bag: _Bag, color_topic: str):
    """Depth→colour rotation and translation of a RealSense ROS1 bag (``…/Color_0/tf/0``), or None."""
    conns = bag.by_topic(f"{_stream_prefix(color_topic)}/tf/0")
    msg = bag.first(conns) if conns else None
    if msg is None or not hasattr(msg, "rotation"):
        return None, None
    t = np.array([msg.translation.x, msg.translation.y, msg.translation.z], float)
    R = _quat_matrix(msg.rotation)
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(R))):
        raise RecordingError(bag.path, f"{_stream_prefix(color_topic)}/tf/0 is not a finite transform")
    return R, t


def open_bag(path, *, topic=None, color_topic=None, handedness: str = "left") -> BagRecording:
    """Open a ROS1 / ROS2 bag (RealSense or generic) as a :class:`BagRecording`.

    Parameters
    ----------
    path : ``.bag``, ``.db3``, ``.mcap`` or a ROS2 bag folder
    topic : depth image topic (default: the RealSense depth stream, or the one image topic whose name
        holds ``depth``)
    color_topic : colour image topic (default: the RealSense colour stream; none for other bags)
    handedness : the recorded hand, ``left`` or ``right``

    Raises
    ------
    RecordingError
        Naming the file: unreadable or damaged bag, no such topic, a topic of the wrong type, no
        camera info, no depth frames.
    """
    path = Path(path)
    bag = _Bag(path)
    try:
        depth_conn = _pick_depth(bag, topic)
        where = f"{path} ({depth_conn.topic})"
        stamps = bag.stamps(depth_conn)
        if not len(stamps):
            raise RecordingError(path, f"topic {depth_conn.topic} holds no depth frames")
        order = np.argsort(stamps, kind="stable")
        stamps = stamps[order]
        w, h, K = _camera_info(bag, depth_conn.topic)
        fps, units = (_realsense_fps_units(bag, depth_conn.topic) if _rs(depth_conn.topic)
                      else (None, None))
        first = next(bag.messages([depth_conn], start=int(stamps[0]), stop=int(stamps[0]) + 1), None)
        if first is None:
            raise RecordingError(path, f"{depth_conn.topic}: the first frame listed in the index is missing")
        msg = bag.decode(depth_conn, first[2])
        kind, depth = (depth_from_image(msg, where) if depth_conn.msgtype == IMAGE
                       else depth_from_compressed(msg, where))
        if depth.shape != (h, w):
            raise RecordingError(where, f"depth image is {depth.shape[1]}×{depth.shape[0]}, "
                                        f"the camera info says {w}×{h}")
        if fps is None:
            gaps = np.diff(stamps)
            gaps = gaps[gaps > 0]
            fps = 1e9 / float(np.median(gaps)) if gaps.size else 30.0
        try:
            cam = Camera(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2],
                         units if (units and kind == "units") else 0.001, "uint16",
                         "realsense" if _rs(depth_conn.topic) else "ros")
        except TrackerError as exc:
            raise RecordingError(where, exc.reason) from None
        color_conn = _pick_color(bag, color_topic, depth_conn)
        extra = {}
        if color_conn is not None:
            cstamps = np.sort(bag.stamps(color_conn))
            if not len(cstamps):
                if color_topic is not None:
                    raise RecordingError(path, f"colour topic {color_conn.topic} holds no frames")
                color_conn = None
            else:
                _, _, cK = _camera_info(bag, color_conn.topic)
                R, t = _color_extrinsics(bag, color_conn.topic)
                extra = dict(color_conn=color_conn, color_stamps=cstamps, color_K=cK, color_R=R, color_t=t)
        kind_name = "RealSense" if _rs(depth_conn.topic) else "ROS"
        source = f"{kind_name} bag {path.name}, topic {depth_conn.topic}" + (
            f", colour {color_conn.topic}" if color_conn is not None else "")
        rec = BagRecording(path, cam, stamps, fps, handedness, source, depth_conn=depth_conn, depth_kind=kind, **extra)
    finally:
        bag.close()
    return rec
