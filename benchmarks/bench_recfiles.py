"""Read speed of a RealSense .bag read in place (tracker.io.bags) against pyrealsense2's playback of the
same file, in one run.

The file: 300 depth frames of 640x480 (mono16, 30 fps) written with rosbags in the RealSense file
format v3, uncompressed, as RealSense Viewer writes it. Ours: every frame in order (``for frame in
rec``, depth in metres) and every frame by index (``rec[i]``); the peer: pyrealsense2 playback with
real-time off, every depth frame as a numpy array (units). Skips the peer when pyrealsense2 is missing.

Run: .venv/bin/python benchmarks/bench_recfiles.py [--frames N]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from tracker.io.recording import Recording

W, H = 640, 480
STREAM = "/device_0/sensor_0/Depth_0"


def write_bag(path: Path, n: int) -> None:
    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg("uint32 fps\nstring encoding\nbool is_recommended\n", "realsense_msgs/msg/StreamInfo"))
    T = ts.types
    rng = np.random.default_rng(0)
    base = rng.integers(400, 2000, (H, W)).astype(np.uint16)

    def header(t):
        return T["std_msgs/msg/Header"](seq=0, stamp=T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9),
                                        frame_id="0")

    with Writer(path) as w:
        def put(topic, typ, t, msg):
            conn = conns.get(topic) or conns.setdefault(topic, w.add_connection(topic, typ, typestore=ts))
            w.write(conn, t, ts.serialize_ros1(msg, typ))

        conns: dict = {}
        put("/file_version", "std_msgs/msg/UInt32", 1, T["std_msgs/msg/UInt32"](data=3))
        kv = T["diagnostic_msgs/msg/KeyValue"]
        put("/device_0/info", "diagnostic_msgs/msg/KeyValue", 1, kv(key="Name", value="Intel RealSense D435"))
        put("/device_0/sensor_0/info", "diagnostic_msgs/msg/KeyValue", 1, kv(key="Name", value="Stereo Module"))
        g = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        put(f"{STREAM}/tf/0", "geometry_msgs/msg/Transform", 1, T["geometry_msgs/msg/Transform"](
            translation=g, rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
        put(f"{STREAM}/info", "realsense_msgs/msg/StreamInfo", 1,
            T["realsense_msgs/msg/StreamInfo"](fps=30, encoding="mono16", is_recommended=True))
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        put(f"{STREAM}/info/camera_info", "sensor_msgs/msg/CameraInfo", 1, T["sensor_msgs/msg/CameraInfo"](
            header=header(1), height=H, width=W, distortion_model="Brown Conrady", D=np.zeros(5),
            K=np.array([385.0, 0, 320.0, 0, 385.0, 240.0, 0, 0, 1]), R=np.zeros(9), P=np.zeros(12),
            binning_x=0, binning_y=0, roi=roi))
        put("/device_0/sensor_0/option/Depth Units/value", "std_msgs/msg/Float32", 1,
            T["std_msgs/msg/Float32"](data=0.001))
        for i in range(n):
            t = 10**9 + i * 33_333_333
            d = np.roll(base, i, axis=1)
            put(f"{STREAM}/image/data", "sensor_msgs/msg/Image", t, T["sensor_msgs/msg/Image"](
                header=header(t), height=H, width=W, encoding="mono16", is_bigendian=0, step=2 * W,
                data=d.view(np.uint8).ravel()))


def ours_in_order(path: Path) -> tuple[float, int]:
    t0 = time.perf_counter()
    rec = Recording.open(path)
    n = sum(1 for f in rec if f.depth.shape == (H, W))
    return time.perf_counter() - t0, n


def ours_by_index(path: Path) -> tuple[float, int]:
    t0 = time.perf_counter()
    rec = Recording.open(path)
    n = sum(1 for i in range(len(rec)) if rec[i].depth.shape == (H, W))
    return time.perf_counter() - t0, n


def pyrealsense2_playback(path: Path, expected: int) -> tuple[float, int] | None:
    try:
        import pyrealsense2 as rs
    except ImportError:
        return None
    t0 = time.perf_counter()
    pipe, cfg = rs.pipeline(), rs.config()
    cfg.enable_device_from_file(str(path), repeat_playback=False)
    prof = pipe.start(cfg)
    prof.get_device().as_playback().set_real_time(False)
    n = 0
    try:
        while True:
            ok, fs = pipe.try_wait_for_frames(2000)
            if not ok:
                break
            d = fs.get_depth_frame()
            if d and np.asanyarray(d.get_data()).shape == (H, W):
                n += 1
                if n == expected:  # timed to the last frame, not to the timeout that ends playback
                    break
    finally:
        dt = time.perf_counter() - t0
        pipe.stop()
    return dt, n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    n = ap.parse_args().frames
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.bag"
        write_bag(path, n)
        mb = path.stat().st_size / 1e6
        print(f"RealSense .bag, {n} frames {W}x{H} mono16, {mb:.0f} MB")
        for name, fn in (("ours, in order (for frame in rec)", ours_in_order),
                         ("ours, by index (rec[i])", ours_by_index),
                         ("pyrealsense2 playback (peer)", lambda p: pyrealsense2_playback(p, n))):
            r = fn(path)
            if r is None:
                print(f"{name}: skipped (pyrealsense2 not installed)")
                continue
            dt, k = r
            print(f"{name}: {k} frames in {dt:.2f} s = {k / dt:.0f} frames/s")


if __name__ == "__main__":
    main()
