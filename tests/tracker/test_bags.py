"""ROS bags as recordings: the real RealSense D435 bag against pyrealsense2, bags written here in every
layout read back exactly (RealSense ROS1 v3 and ROS2 db3, generic ROS1 / ROS2 sqlite / mcap with Image
and compressedDepth PNG and RVL), damaged and wrong bags as one-line errors, the CLI."""
import struct
import sys

from conftest import SHARED_DATA, import_pyrealsense2, played_by_librealsense

import imageio.v3 as iio
import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("rosbags", reason="the [recordings] extra (rosbags) is not installed")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

from tracker.io.bags import BagRecording, _quat_matrix  # noqa: E402
from tracker.errors import RecordingError  # noqa: E402
from tracker.io.images import decode_rvl, inverse_depth_to_metres  # noqa: E402
from tracker.io.recording import Recording, import_recording_file  # noqa: E402

RS_BAG = SHARED_DATA / "sensor_recordings" / "librealsense_single_depth_color_640x480.bag"
W, H = 40, 30
K = (50.0, 0.0, 19.5, 0.0, 52.0, 14.25, 0.0, 0.0, 1.0)
STREAMINFO = "uint32 fps\nstring encoding\nbool is_recommended\n"


def _rs_bag() -> "Path":  # noqa: F821
    if not RS_BAG.is_file():
        pytest.skip(f"real RealSense bag not available: {RS_BAG} (../shared/data is absent)")
    return RS_BAG


def _frames(n=4, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        d = rng.integers(300, 4000, (H, W)).astype(np.uint16)
        d[rng.random((H, W)) < 0.2] = 0
        out.append(d)
    return out


# ----------------------------------------------------------------------------- writing bags (test side)
def _rvl_encode(units: np.ndarray) -> bytes:
    """Wilson's RVL, as compressed_depth_image_transport writes it (the reader's inverse)."""
    words, word, nibbles = [], 0, 0

    def vle(value):
        nonlocal word, nibbles
        while True:
            nib = value & 7
            value >>= 3
            if value:
                nib |= 8
            word = ((word << 4) | nib) & 0xFFFFFFFF
            nibbles += 1
            if nibbles == 8:
                words.append(word)
                word, nibbles = 0, 0
            if not value:
                break

    flat = [int(v) for v in units.ravel()]
    i, prev = 0, 0
    while i < len(flat):
        j = i
        while j < len(flat) and flat[j] == 0:
            j += 1
        vle(j - i)
        k = j
        while k < len(flat) and flat[k] != 0:
            k += 1
        vle(k - j)
        for v in flat[j:k]:
            delta = v - prev
            vle((delta << 1) ^ (delta >> 31))
            prev = v
        i = k
    if nibbles:
        words.append((word << (4 * (8 - nibbles))) & 0xFFFFFFFF)
    return struct.pack(f"<{len(words)}I", *words)


class _Bag:
    """Writes one bag with rosbags in ROS1 or ROS2 (sqlite / mcap) form, messages as plain fields."""

    def __init__(self, path, ros: int, storage=StoragePlugin.SQLITE3, compression=None):
        self.ros = ros
        self.ts = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
        self.ts.register(get_types_from_msg(STREAMINFO, "realsense_msgs/msg/StreamInfo"))
        self.w = Writer1(path) if ros == 1 else Writer2(path, version=9, storage_plugin=storage)
        if compression is not None:
            self.w.set_compression(getattr(Writer1.CompressionFormat, compression))
        self.conns = {}

    def __enter__(self):
        self.w.open()
        return self

    def __exit__(self, *exc):
        self.w.close()

    def put(self, topic, msgtype, t_ns, msg):
        if topic not in self.conns:
            self.conns[topic] = self.w.add_connection(topic, msgtype, typestore=self.ts)
        ser = self.ts.serialize_ros1 if self.ros == 1 else self.ts.serialize_cdr
        self.w.write(self.conns[topic], t_ns, ser(msg, msgtype))

    def header(self, t_ns):
        T = self.ts.types
        stamp = T["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
        if self.ros == 1:
            return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="depth")
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id="depth")

    def image(self, topic, t_ns, a, encoding, bigendian=False, pad=0):
        a = np.asarray(a)
        row = a.reshape(a.shape[0], -1).view(np.uint8).reshape(a.shape[0], -1)
        if bigendian:
            row = a.astype(a.dtype.newbyteorder(">")).reshape(a.shape[0], -1).view(np.uint8).reshape(a.shape[0], -1)
        row = np.concatenate([row, np.zeros((row.shape[0], pad), np.uint8)], 1)
        msg = self.ts.types["sensor_msgs/msg/Image"](
            header=self.header(t_ns), height=a.shape[0], width=a.shape[1], encoding=encoding,
            is_bigendian=int(bigendian), step=row.shape[1], data=np.ascontiguousarray(row).ravel())
        self.put(topic, "sensor_msgs/msg/Image", t_ns, msg)

    def compressed(self, topic, t_ns, data: bytes, fmt: str):
        msg = self.ts.types["sensor_msgs/msg/CompressedImage"](
            header=self.header(t_ns), format=fmt, data=np.frombuffer(data, np.uint8))
        self.put(topic, "sensor_msgs/msg/CompressedImage", t_ns, msg)

    def camera_info(self, topic, t_ns, w=W, h=H, k=K):
        T = self.ts.types
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        arrays = dict(D=np.zeros(5), K=np.array(k), R=np.eye(3).ravel(), P=np.zeros(12))
        if self.ros == 2:
            arrays = {key.lower(): v for key, v in arrays.items()}
        msg = T["sensor_msgs/msg/CameraInfo"](header=self.header(t_ns), height=h, width=w,
                                              distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi,
                                              **arrays)
        self.put(topic, "sensor_msgs/msg/CameraInfo", t_ns, msg)

    def string(self, topic, t_ns, text):
        self.put(topic, "std_msgs/msg/String", t_ns, self.ts.types["std_msgs/msg/String"](data=text))

    def float32(self, topic, t_ns, v):
        self.put(topic, "std_msgs/msg/Float32", t_ns, self.ts.types["std_msgs/msg/Float32"](data=v))


DEV = "/device_0/sensor_0"
STREAM = f"{DEV}/Depth_0"
T0 = 1_000_000_000  # static messages at t ≥ 1 ns, as pyrealsense2's playback needs; frames later
DT = 33_333_333


def _write_realsense_ros1(path, frames, units=0.000125, fps=30):
    with _Bag(path, 1) as b:
        T = b.ts.types
        b.put("/file_version", "std_msgs/msg/UInt32", 1, T["std_msgs/msg/UInt32"](data=3))
        # what pyrealsense2's playback needs besides the stream: device and sensor names, the extrinsics
        kv = T["diagnostic_msgs/msg/KeyValue"]
        b.put("/device_0/info", "diagnostic_msgs/msg/KeyValue", 1, kv(key="Name", value="Intel RealSense D435"))
        b.put(f"{DEV}/info", "diagnostic_msgs/msg/KeyValue", 1, kv(key="Name", value="Stereo Module"))
        b.put(f"{STREAM}/tf/0", "geometry_msgs/msg/Transform", 1, T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
        b.put(f"{STREAM}/info", "realsense_msgs/msg/StreamInfo", 1,
              b.ts.types["realsense_msgs/msg/StreamInfo"](fps=fps, encoding="mono16", is_recommended=True))
        b.camera_info(f"{STREAM}/info/camera_info", 1)
        b.float32(f"{DEV}/option/Depth Units/value", 1, units)
        for i, d in enumerate(frames):
            b.image(f"{STREAM}/image/data", T0 + i * DT, d, "mono16")


def _write_realsense_ros2(path, frames, units=0.000125, fps=30):
    with _Bag(path, 2) as b:
        b.put("/file_version", "std_msgs/msg/UInt32", 1, b.ts.types["std_msgs/msg/UInt32"](data=4))
        b.string(f"{STREAM}/info", 1, f"encoding=Z16;fps={fps}")
        fx, _, cx, _, fy, cy = K[:6]
        b.string(f"{STREAM}/info/camera_info", 1,
                 f"width={W};height={H};fx={fx!r};ppx={cx!r};fy={fy!r};ppy={cy!r};model=Brown Conrady;coeffs=0,0,0,0,0")
        b.string(f"{DEV}/option/Depth_Units/value", 1, f"{units:f}")
        for i, d in enumerate(frames):
            b.image(f"{STREAM}/image/data", T0 + i * DT, d, "mono16")


def _write_realsense_ros2_compressed(path, frames, units=0.000125, fps=30):
    """librealsense's db3 with compression on: compressedDepth PNG (zero config header) per frame."""
    with _Bag(path, 2) as b:
        b.string(f"{STREAM}/info", 1, f"encoding=Z16;fps={fps}")
        fx, _, cx, _, fy, cy = K[:6]
        b.string(f"{STREAM}/info/camera_info", 1, f"width={W};height={H};fx={fx!r};ppx={cx!r};fy={fy!r};ppy={cy!r}")
        b.string(f"{DEV}/option/Depth_Units/value", 1, f"{units:f}")
        for i, d in enumerate(frames):
            b.compressed(f"{STREAM}/image/compressedDepth", T0 + i * DT, bytes(12) + _png(d),
                         "16UC1; compressedDepth png")


def _png(a) -> bytes:
    return iio.imwrite("<bytes>", a, extension=".png", plugin="pillow")


def _quantise(metres, depth_max=10.0, z0=100.0):
    """compressed_depth_image_transport's 32FC1 encoding: q = A / d + B, 0 for no depth."""
    a = z0 * (z0 + 1.0)
    b = 1.0 - a / depth_max
    d = np.asarray(metres, np.float32)
    with np.errstate(divide="ignore"):
        q = np.where(np.isfinite(d) & (d > 0) & (d < depth_max), np.float32(a) / d + np.float32(b), 0)
    return q.astype(np.uint16), a, b


# ----------------------------------------------------------------------------- the real bag
@pytest.mark.isolated  # librealsense (conftest)
def test_real_realsense_bag_matches_pyrealsense2():
    path = _rs_bag()
    rs = import_pyrealsense2()
    rec = Recording.open(path)
    assert isinstance(rec, BagRecording) and len(rec) == 2  # SOURCES.md §10: 2 depth frames
    assert rec.camera.shape == (480, 640) and rec.has_color

    with played_by_librealsense(rs, path) as (frames, scale):
        dp = frames[rs.stream.depth][0].get_profile().as_video_stream_profile()
        intr = dp.get_intrinsics()
        ext = dp.get_extrinsics_to(frames[rs.stream.color][0].get_profile())
        depth = [np.asanyarray(f.get_data()).copy() for f in frames[rs.stream.depth]]
        width, height, fps = dp.width(), dp.height(), dp.fps()
    assert len(depth) == len(rec)
    c = rec.camera
    assert c.depth_scale_m == pytest.approx(scale, rel=1e-7)
    assert (c.width, c.height) == (intr.width, intr.height) == (width, height)
    np.testing.assert_allclose([c.fx, c.fy, c.cx, c.cy], [intr.fx, intr.fy, intr.ppx, intr.ppy], rtol=1e-6)
    assert rec.fps == fps
    for i, f in enumerate(depth):  # the frames pyrealsense2 delivers are ours, unit for unit, in order
        assert np.array_equal(rec.depth_units(i), f)
    # depth→colour extrinsics: the bag's quaternion is pyrealsense2's rotation (column-major)
    np.testing.assert_allclose(rec._color_R, np.array(ext.rotation).reshape(3, 3).T, atol=2e-6)
    np.testing.assert_allclose(rec._color_t, ext.translation, atol=1e-7)


@pytest.mark.isolated  # librealsense (conftest)
def test_written_realsense_bag_reads_the_same_in_pyrealsense2(tmp_path):
    """Our RealSense layout is the one librealsense plays back: same intrinsics, unit and frames."""
    rs = import_pyrealsense2()
    frames = _frames(5, seed=9)
    path = tmp_path / "written.bag"
    _write_realsense_ros1(path, frames)
    with played_by_librealsense(rs, path) as (played, scale):
        intr = played[rs.stream.depth][0].get_profile().as_video_stream_profile().get_intrinsics()
        got = [np.asanyarray(f.get_data()).copy() for f in played[rs.stream.depth]]
    rec = Recording.open(path)
    assert rec.camera.depth_scale_m == pytest.approx(scale, rel=1e-6) == 0.000125
    np.testing.assert_allclose([rec.camera.fx, rec.camera.fy, rec.camera.cx, rec.camera.cy],
                               [intr.fx, intr.fy, intr.ppx, intr.ppy], rtol=1e-6)
    assert len(got) == len(frames) == len(rec)
    for i, a in enumerate(got):  # every frame, in order, ours unit for unit
        assert np.array_equal(a, rec.depth_units(i))


def test_real_realsense_bag_times_and_colour():
    rec = Recording.open(_rs_bag())
    np.testing.assert_allclose(rec.times_s, [0.0, 0.1679332], atol=1e-7)  # bag times, not index / fps
    f = rec[1]
    assert f.time_s == pytest.approx(0.1679332) and f.color.shape == (480, 640, 3)
    # colour only where depth is (registration lifts depth pixels), and most of the middle is covered
    assert not f.color[~np.isfinite(f.depth)].any()
    assert (f.color[200:280, 250:350].sum(-1) > 0).mean() > 0.9


# ----------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("writer,suffix", [(_write_realsense_ros1, ".bag"), (_write_realsense_ros2, ""),
                                           (_write_realsense_ros2_compressed, "")])
def test_realsense_layouts_round_trip(tmp_path, writer, suffix):
    frames = _frames()
    path = tmp_path / f"rs{suffix}"
    writer(path, frames)
    if not suffix:  # a RealSense .db3 is a bare sqlite file: read that, not the folder around it
        path = next(path.glob("*.db3"))
    rec = Recording.open(path, handedness="right")
    assert len(rec) == 4 and rec.handedness == "right" and not rec.has_color
    c = rec.camera
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (W, H, K[0], K[4], K[2], K[5])
    assert c.depth_scale_m == pytest.approx(0.000125, rel=1e-6) and rec.fps == 30
    for i, d in enumerate(frames):
        assert np.array_equal(rec.depth_units(i), d)
        np.testing.assert_allclose(rec[i].depth, np.where(d > 0, d * c.depth_scale_m, np.nan), rtol=1e-6)
    np.testing.assert_allclose(rec.times_s, np.arange(4) * DT / 1e9)


@pytest.mark.parametrize("ros,storage", [(1, None), (2, StoragePlugin.SQLITE3), (2, StoragePlugin.MCAP)])
def test_generic_image_topics_round_trip(tmp_path, ros, storage):
    frames = _frames(3, seed=1)
    metres = [np.where(d > 0, d / 1000.0 + 0.0003, np.nan).astype(np.float32) for d in frames]
    rng = np.random.default_rng(2)
    colors = [rng.integers(0, 256, (H, W, 3)).astype(np.uint8) for _ in frames]
    path = tmp_path / ("g.bag" if ros == 1 else "g2")
    with _Bag(path, ros, storage or StoragePlugin.SQLITE3) as b:
        b.camera_info("/cam/depth/camera_info", 5)
        b.camera_info("/cam/color/camera_info", 5)
        for i in range(3):
            t = T0 + i * DT
            b.image("/cam/depth/image_raw", t, frames[i], "16UC1", bigendian=(i == 1), pad=3)
            b.image("/cam/depth/image_m", t, metres[i], "32FC1")
            b.image("/cam/color/image_raw", t + 1000, colors[i][..., ::-1], "bgr8")
    with pytest.raises(RecordingError, match="several depth image topics"):
        Recording.open(path)
    rec = Recording.open(path, topic="/cam/depth/image_raw", color_topic="/cam/color/image_raw")
    assert len(rec) == 3 and rec.camera.depth_scale_m == 0.001 and rec.fps == pytest.approx(30, rel=1e-6)
    for i in range(3):
        assert np.array_equal(rec.depth_units(i), frames[i])
        assert np.array_equal(rec[i].color, colors[i])  # same intrinsics and size: the colour grid is the depth's
    m = Recording.open(path, topic="/cam/depth/image_m")
    assert m.depth_kind == "metres"
    for i in range(3):
        assert np.array_equal(m[i].depth, metres[i], equal_nan=True)  # float metres exactly as stored


@pytest.mark.parametrize("codec", ["png", "rvl"])
@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_compressed_depth_round_trip(tmp_path, codec, storage):
    frames = _frames(3, seed=3)
    metres = [np.where(d > 0, d / 1000.0, np.nan).astype(np.float32) for d in frames]
    path = tmp_path / "c2"
    quant = []
    with _Bag(path, 2, storage) as b:
        b.camera_info("/cam/depth/camera_info", 5)
        for i in range(3):
            t = T0 + i * DT
            if codec == "png":
                body16, fmt = _png(frames[i]), "16UC1; compressedDepth png"
            else:
                body16, fmt = struct.pack("<II", W, H) + _rvl_encode(frames[i]), "16UC1; compressedDepth rvl"
            b.compressed("/cam/depth/image_raw/compressedDepth", t,
                         struct.pack("<iff", int(codec == "rvl"), 0, 0) + body16, fmt)
            q, qa, qb = _quantise(metres[i])
            quant.append((q, qa, qb))
            body32 = _png(q) if codec == "png" else struct.pack("<II", W, H) + _rvl_encode(q)
            b.compressed("/cam/inv/image_raw/compressedDepth", t,
                         struct.pack("<iff", int(codec == "rvl"), qa, qb) + body32, f"32FC1; compressedDepth {codec}")
    rec = Recording.open(path, topic="/cam/depth/image_raw/compressedDepth")
    assert rec.camera.fx == K[0] and len(rec) == 3
    for i in range(3):
        assert np.array_equal(rec.depth_units(i), frames[i])
    inv = Recording.open(path, topic="/cam/inv/image_raw/compressedDepth")
    for i in range(3):
        q, qa, qb = quant[i]
        d = inv[i].depth
        assert np.array_equal(d, inverse_depth_to_metres(q, qa, qb), equal_nan=True)
        assert np.array_equal(np.isnan(d), np.isnan(metres[i]))
        ok = np.isfinite(d)
        # quantised inverse depth: the step at 4 m is d² / A ≈ 1.6 mm
        assert np.abs(d[ok] - metres[i][ok]).max() < 2e-3


def test_rvl_decoder_refuses_damage():
    units = _frames(1)[0]
    data = _rvl_encode(units)
    assert np.array_equal(decode_rvl(data, W, H, "x"), units)
    with pytest.raises(RecordingError, match="x: damaged RVL depth image \\(the RVL stream ends"):
        decode_rvl(data[: len(data) // 2], W, H, "x")
    with pytest.raises(RecordingError, match="longer than the image"):
        decode_rvl(_rvl_encode(np.ones((H, W + 5), np.uint16)), W, H, "x")
    with pytest.raises(RecordingError, match="more than 32 bits"):
        decode_rvl(b"\xff" * 64, W, H, "x")


def test_select_and_import(tmp_path):
    frames = _frames(10, seed=4)
    src = tmp_path / "rs.bag"
    _write_realsense_ros1(src, frames)
    rec = Recording.open(src).select(start_s=0.05, end_s=0.25, every=2)
    # file times 0, 0.0333, … 0.3: from 0.05 to 0.25 are frames 2…7; every 2nd → 2, 4, 6
    np.testing.assert_allclose(rec.times_s, np.array([2, 4, 6]) * DT / 1e9)
    assert [rec[i].index for i in range(3)] == [0, 1, 2]
    assert np.array_equal(rec.depth_units(1), frames[4])
    out = import_recording_file(src, tmp_path / "rec", start_s=0.05, end_s=0.25, every=2, handedness="right")
    assert len(out) == 3 and out.fps == 15 and out.handedness == "right"
    assert out.camera.depth_scale_m == pytest.approx(0.000125, rel=1e-6)
    for i, k in enumerate([2, 4, 6]):
        assert np.array_equal(out.depth_units(i), frames[k])
    with pytest.raises(RecordingError, match="exists and is not empty"):
        import_recording_file(src, tmp_path / "rec")
    # a negative time is refused, not read as "from the first frame" (it was)
    for kw in ({"start_s": -1.0}, {"end_s": -0.1}):
        with pytest.raises(RecordingError, match="must be ≥ 0 s"):
            Recording.open(src).select(**kw)


def test_recording_pickles_without_its_open_reader(tmp_path):
    import pickle

    src = tmp_path / "rs.bag"
    frames = _frames(2)
    _write_realsense_ros1(src, frames)
    rec = Recording.open(src)
    assert np.array_equal(rec.depth_units(1), frames[1])  # opens the reader
    again = pickle.loads(pickle.dumps(rec))  # as dask ships it to a worker
    assert np.array_equal(again.depth_units(1), frames[1]) and np.array_equal(again.depth_units(0), frames[0])


def test_quaternion_matrix_is_a_rotation():
    class Q:
        x, y, z, w = 0.1, -0.2, 0.3, 0.9

    R = _quat_matrix(Q)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


# ----------------------------------------------------------------------------- damaged and wrong bags
def _cli(*args):
    from tracker.cli import app

    return CliRunner().invoke(app, [str(a) for a in args])


def _one_error_line(r, path):
    assert r.exit_code == 2, r.output
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}"), r.stderr
    assert "Traceback" not in r.output
    return lines[0]


def _bad_bags(tmp_path):
    good = tmp_path / "good.bag"
    _write_realsense_ros1(good, _frames(3))
    data = good.read_bytes()
    out = {}
    out["truncated"] = tmp_path / "truncated.bag"
    out["truncated"].write_bytes(data[: len(data) // 2])
    # a recorder killed before it closed the bag: the header's index_pos is still 0
    k = data.index(b"index_pos=") + len(b"index_pos=")
    out["unfinished"] = tmp_path / "unfinished.bag"
    out["unfinished"].write_bytes(data[:k] + bytes(8) + data[k + 8:])
    out["garbage"] = tmp_path / "garbage.bag"
    out["garbage"].write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    out["garbage_db3"] = tmp_path / "garbage.db3"
    out["garbage_db3"].write_bytes(b"SQLite format 3\0" + bytes(200))
    out["garbage_mcap"] = tmp_path / "garbage.mcap"
    out["garbage_mcap"].write_bytes(b"\x89MCAP0\r\n" + bytes(100))
    out["empty"] = tmp_path / "empty.bag"
    out["empty"].write_bytes(b"")
    nocam = tmp_path / "nocam.bag"
    with _Bag(nocam, 1) as b:
        b.image("/cam/depth/image_raw", T0, _frames(1)[0], "16UC1")
    out["no_camera_info"] = nocam
    wrongsize = tmp_path / "wrongsize.bag"
    with _Bag(wrongsize, 1) as b:
        b.camera_info("/cam/depth/camera_info", 5, w=W + 1)
        b.image("/cam/depth/image_raw", T0, _frames(1)[0], "16UC1")
    out["wrong_size"] = wrongsize
    huge = tmp_path / "huge.bag"
    with _Bag(huge, 1) as b:
        b.camera_info("/cam/depth/camera_info", 5, w=100000, h=100000)
        b.image("/cam/depth/image_raw", T0, _frames(1)[0], "16UC1")
    out["huge"] = huge
    colour_only = tmp_path / "colour.bag"
    with _Bag(colour_only, 1) as b:
        b.camera_info("/cam/rgb/camera_info", 5)
        b.image("/cam/rgb/image_raw", T0, np.zeros((H, W, 3), np.uint8), "rgb8")
    out["no_depth_topic"] = colour_only
    return good, out


def test_damaged_bags_are_one_line_errors(tmp_path):
    good, bad = _bad_bags(tmp_path)
    expect = {"truncated": "cut short: the bag's index starts at byte", "unfinished": "unfinished: the recorder "
              "never wrote the bag's index", "garbage": "not a ROS1 bag: it does not start with '#ROSBAG V2.0' (unknown binary data)",
              "garbage_db3": "not a readable ROS bag", "garbage_mcap": "not a readable ROS bag",
              "empty": "not a ROS1 bag: it does not start with '#ROSBAG V2.0' (empty)",
              "no_camera_info": "missing camera_info", "wrong_size": "camera info says 41×30",
              "huge": "larger than the supported", "no_depth_topic": "no depth image topic found"}
    for name, path in bad.items():
        for cmd in (["info", path], ["import", path, "-o", tmp_path / f"out_{name}"]):
            line = _one_error_line(_cli(*cmd), path)
            assert expect[name] in line, (name, line)
        assert not (tmp_path / f"out_{name}").exists()
    line = _one_error_line(_cli("info", good, "--topic", "/nope"), good)
    assert "no topic '/nope' (image topics: /device_0/sensor_0/Depth_0/image/data)" in line
    line = _one_error_line(_cli("info", good, "--topic", f"{DEV}/option/Depth Units/value"), good)
    assert "carries std_msgs/msg/Float32, not a depth image" in line
    line = _one_error_line(_cli("import", good, "-o", tmp_path / "x", "--camera", "sr305", "--fps", "15"), good)
    assert "--camera, --fps do not apply" in line


def _bag_file(tmp_path, kind, frames):
    if kind == "bag":
        path = tmp_path / "good.bag"
        _write_realsense_ros1(path, frames)
        return path
    folder = tmp_path / f"good_{kind}"
    with _Bag(folder, 2, StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3) as b:
        b.camera_info("/cam/depth/camera_info", 5)
        for i, d in enumerate(frames):
            b.image("/cam/depth/image_raw", T0 + i * DT, d, "16UC1")
    return next(folder.glob(f"*.{kind}"))


def _read_all_or_error(path, frames):
    """Open and read every frame: what reads back is a prefix of what was written, or it is one
    RecordingError naming the file. Returns True when it read."""
    try:
        rec = Recording.open(path)
        for i in range(len(rec)):
            assert np.array_equal(rec.depth_units(i), frames[i])
        return True
    except RecordingError as exc:
        assert str(path) in str(exc)
        return False


@pytest.mark.parametrize("kind", ["bag", "db3", "mcap"])
def test_cut_and_mutated_bags_read_exactly_or_fail_cleanly(tmp_path, kind):
    frames = _frames(3)
    data = _bag_file(tmp_path, kind, frames).read_bytes()
    bad = tmp_path / f"bad.{kind}"
    for n in np.linspace(0, len(data) - 1, 20).astype(int):
        bad.write_bytes(data[:n])
        _read_all_or_error(bad, frames)
    rng = np.random.default_rng(7)
    for _ in range(20):
        b = bytearray(data)
        for pos in rng.integers(0, len(b), 8):
            b[pos] = int(rng.integers(0, 256))
        bad.write_bytes(bytes(b))
        try:
            rec = Recording.open(bad)
            for i in range(len(rec)):
                rec.depth_units(i)  # a flipped pixel byte reads as another depth: fine, as long as nothing crashes
        except RecordingError as exc:
            assert str(bad) in str(exc)


def test_cli_reads_bags_in_place(tmp_path):
    src = tmp_path / "rs.bag"
    frames = _frames(6)
    _write_realsense_ros1(src, frames)
    r = _cli("info", src)
    assert r.exit_code == 0, r.output
    assert "6 (0.17 s first to last in file time, 30 fps nominal)" in r.output and "0.125 mm per unit" in r.output
    assert "6 (all readable)" in r.output
    r = _cli("info", src, "--every", "4")
    assert r.exit_code == 0 and "2 (all readable)" in r.output, r.output
    r = _cli("show", src, "-o", tmp_path / "sheet.png", "--no-mask")
    assert r.exit_code == 0, r.output
    assert iio.imread(tmp_path / "sheet.png").ndim == 3 and "not yet tested to be a hand" not in r.output
    # with the mask drawn, the sheet says the outline is no hand yet (a mug was shown as "segmented hand")
    from tracker.cli import app

    r = CliRunner().invoke(app, ["show", str(src), "-o", str(tmp_path / "masked.png")], env={"COLUMNS": "80"})
    assert r.exit_code == 0 and "not yet tested to be a hand" in " ".join(r.output.split()), r.output
    # the note is a sentence: wrapped at the terminal's width (a new user's 80 columns got a 125-character line)
    note = [ln for ln in r.output.splitlines() if "segmenter" in ln or "a wall" in ln]
    assert note and max(len(ln) for ln in note) <= 80, note
    r = _cli("import", src, "-o", tmp_path / "rec", "--every", "2", "--end", "0.1", "--hand", "right")
    assert r.exit_code == 0, r.output
    rec = Recording.open(tmp_path / "rec")
    assert len(rec) == 2 and rec.fps == 15 and np.array_equal(rec.depth_units(1), frames[2])
    line = _one_error_line(_cli("import", tmp_path / "rec", "-o", tmp_path / "rec2", "--topic", "/x"), tmp_path / "rec")
    assert "apply to recording files" in line


def test_missing_extra_names_the_pip_install(tmp_path, monkeypatch):
    src = tmp_path / "rs.bag"
    _write_realsense_ros1(src, _frames(1))
    monkeypatch.delitem(sys.modules, "tracker.io.bags", raising=False)
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(RecordingError, match=r"rs\.bag: reading \.bag files needs rosbags.highlevel: "
                                             r"pip install 'synergistic-hand-tracking\[recordings\]'"):
        Recording.open(src)


@pytest.mark.parametrize("kind", ["bag", "db3", "mcap"])
def test_iterating_gives_the_indexed_frames(tmp_path, kind):
    frames = _frames(7, seed=5)
    rec = Recording.open(_bag_file(tmp_path, kind, frames))
    for view, picked in ((rec, range(7)), (rec.select(start_s=0.03, every=3), [1, 4])):
        got = list(view)
        assert [f.index for f in got] == list(range(len(picked)))
        np.testing.assert_allclose([f.time_s for f in got], [k * DT / 1e9 for k in picked])
        for f, k in zip(got, picked):
            scale = rec.camera.depth_scale_m
            assert np.array_equal(np.rint(np.nan_to_num(f.depth / scale)).astype(np.uint16), frames[k])
            assert np.array_equal(f.depth, view[f.index].depth, equal_nan=True)


@pytest.mark.parametrize("compression", ["BZ2", "LZ4"])
def test_compressed_ros1_chunks_read_and_are_bounded(tmp_path, compression, monkeypatch):
    import tracker.io.bags

    frames = _frames(3)
    path = tmp_path / "c.bag"
    with _Bag(path, 1, compression=compression) as b:
        b.camera_info("/cam/depth/camera_info", 5)
        for i, d in enumerate(frames):
            b.image("/cam/depth/image_raw", T0 + i * DT, d, "16UC1")
    rec = Recording.open(path)
    assert all(np.array_equal(rec.depth_units(i), frames[i]) for i in range(3))
    # a chunk expanding past the bound is refused, not expanded (as a bz2/lz4 bomb would be)
    monkeypatch.setattr(tracker.io.bags, "MAX_CHUNK_BYTES", 1000)
    with pytest.raises(RecordingError, match=r"c\.bag: damaged bag, cannot read its messages \(ValueError: a "
                                             r"compressed chunk expands beyond"):
        Recording.open(path)


def test_mcap_chunk_bound(tmp_path, monkeypatch):
    import tracker.io.bags

    frames = _frames(2)
    path = _bag_file(tmp_path, "mcap", frames)
    assert np.array_equal(Recording.open(path).depth_units(1), frames[1])
    monkeypatch.setattr(tracker.io.bags, "MAX_CHUNK_BYTES", 1000)
    with pytest.raises(RecordingError, match=r"\.mcap: an MCAP chunk declares \d+ bytes expanded, more than"):
        Recording.open(path)


def test_a_renamed_file_or_a_bag_cut_inside_its_index_says_so(tmp_path):
    """The reader's own errors named its decoder ("'utf-8' codec can't decode byte 0x89") or "Bag index
    looks damaged"; a user needs what the file is, or that the copy stopped inside the index."""
    from PIL import Image

    good, _ = _bad_bags(tmp_path)
    png = tmp_path / "photo.bag"
    Image.fromarray(np.zeros((4, 4), np.uint16)).save(png, format="PNG")
    assert "not a ROS1 bag: it does not start with '#ROSBAG V2.0' (a PNG image)" in _one_error_line(_cli("info", png), png)
    data = good.read_bytes()
    cut = tmp_path / "cut_in_index.bag"
    cut.write_bytes(data[:-60])  # the index (connection and chunk records) is the file's last part
    line = _one_error_line(_cli("info", cut), cut)
    assert "damaged or cut short inside its index" in line and f"file's end at {len(data) - 60}" in line, line


def test_lengths_past_the_end_are_refused_before_anything_is_allocated(tmp_path):
    """An index record or a chunk declaring 0xFFFFFFF0 bytes made the reader ask for 4 GB (a MemoryError
    under a memory cap, the machine's memory without one) before it found the file shorter: now the
    declared sizes are checked against the file first, and the error names the record."""
    from tracker.io.bags import check_ros1_complete

    good, _ = _bad_bags(tmp_path)
    data = good.read_bytes()
    index_pos = check_ros1_complete(good)
    hlen = struct.unpack("<I", data[index_pos:index_pos + 4])[0]
    cases = {"index header": (index_pos, "declares a header of 4294967280 bytes"),
             "index data": (index_pos + 4 + hlen, "declares 4294967280 bytes of data")}
    for name, (at, want) in cases.items():
        bad = tmp_path / f"{name.replace(' ', '_')}.bag"
        bad.write_bytes(data[:at] + struct.pack("<I", 0xFFFFFFF0) + data[at + 4:])
        line = _one_error_line(_cli("info", bad), bad)
        assert "damaged or cut short inside its index" in line and want in line, line
    # a chunk's data length (the chunk info records say where each chunk starts)
    chunk_pos = [struct.unpack("<Q", data[k + 10:k + 18])[0] for k in _find_all(data, b"chunk_pos=")]
    assert chunk_pos
    c = chunk_pos[0]
    chlen = struct.unpack("<I", data[c:c + 4])[0]
    bad = tmp_path / "chunk.bag"
    bad.write_bytes(data[:c + 4 + chlen] + struct.pack("<I", 0xFFFFFFF0) + data[c + 8 + chlen:])
    line = _one_error_line(_cli("info", bad), bad)
    assert f"damaged: the chunk at byte {c} declares 4294967280 bytes of data" in line, line


def _find_all(data: bytes, needle: bytes):
    k = data.find(needle)
    while k >= 0:
        yield k
        k = data.find(needle, k + 1)


def test_an_implausible_frame_rate_is_refused(tmp_path):
    """``fps: 1.0e-300`` in recording.yaml was accepted (every frame time infinite); a rate outside
    one frame a 100 s to 100 kHz is damage, said in one line, for the folder and for the writer."""
    from tracker.io.cameras import preset
    from tracker.io.recording import FPS_RANGE, RecordingWriter

    rec = tmp_path / "rec"
    assert _cli("synth", "--motion", "open-close", "--frames", "2", "-o", rec).exit_code == 0
    yaml_path = rec / "recording.yaml"
    text = yaml_path.read_text()
    for fps in ("1.0e-300", "0.0", "-30", "1.0e+9", ".nan"):
        yaml_path.write_text("\n".join(f"fps: {fps}" if ln.startswith("fps:") else ln for ln in text.splitlines()) + "\n")
        line = _one_error_line(_cli("info", rec), yaml_path)
        assert "fps" in line, (fps, line)
    for fps in (FPS_RANGE[0] / 2, FPS_RANGE[1] * 2, float("nan")):
        with pytest.raises(RecordingError, match="fps must be between"):
            RecordingWriter(tmp_path / f"w{fps}", preset("kinect1"), fps=fps)


def test_a_chunk_size_that_stays_inside_the_file_still_names_the_chunk(tmp_path):
    """A chunk's data length a few bytes short or long stays inside the file, so the bounds check passes;
    rosbags then read past the chunk's real end without a word. A chunk is followed by its index data
    records: the reader checks that one starts where the chunk's size says it ends."""
    good, _ = _bad_bags(tmp_path)
    data = good.read_bytes()
    c = [struct.unpack("<Q", data[k + 10:k + 18])[0] for k in _find_all(data, b"chunk_pos=")][0]
    chlen = struct.unpack("<I", data[c:c + 4])[0]
    dlen = struct.unpack("<I", data[c + 4 + chlen:c + 8 + chlen])[0]
    for delta in (-3, 8):
        bad = tmp_path / f"chunk{delta}.bag"
        bad.write_bytes(data[:c + 4 + chlen] + struct.pack("<I", dlen + delta) + data[c + 8 + chlen:])
        line = _one_error_line(_cli("info", bad), bad)
        assert f"damaged: the chunk at byte {c} declares a size that ends at byte {c + 8 + chlen + dlen + delta}" in line, line
    # a header length inside the file but larger than any record's is not read into memory
    bad = tmp_path / "header.bag"
    bad.write_bytes(data[:c] + struct.pack("<I", (1 << 24) + 1) + data[c + 4:])
    line = _one_error_line(_cli("info", bad), bad)
    assert f"damaged: the chunk at byte {c} declares a header of {(1 << 24) + 1} bytes" in line, line


def test_an_import_that_fails_midway_leaves_no_folder(tmp_path):
    """A frame that cannot be read after others were written (here the third, of the wrong size) ends
    the import with its error and removes what was written: no half recording under the final name."""
    bad = tmp_path / "midway.bag"
    frames = _frames(3)
    with _Bag(bad, 1) as b:
        b.camera_info("/cam/depth/camera_info", 5)
        for k, f in enumerate(frames):
            b.image("/cam/depth/image_raw", T0 + (k + 1) * 33_000_000, f if k < 2 else f[:, :-1], "16UC1")
    dst = tmp_path / "out"
    line = _one_error_line(_cli("import", bad, "-o", dst), bad)
    assert "frame 2): depth image is 39×30, the camera info says 40×30" in line, line
    assert not dst.exists()
