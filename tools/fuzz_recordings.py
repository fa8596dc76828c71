"""Fuzz the recording readers (:func:`tracker.io.recording.open_recording`) with mutated recordings.

Formats: ``bag`` (ROS1: a depth bag written here and the real RealSense ``.bag`` from
``../shared/data``), ``db3`` and ``mcap`` (ROS2, written here), ``mkv`` (the real Azure Kinect file)
and ``png`` (our recording folder, ``recording.yaml`` and 16-bit PNGs: one written here by
:class:`~tracker.io.recording.RecordingWriter`, one made by ``tracker import`` of the real ``.mkv``). Every mutant is
opened and every frame's depth read; it must end read or as a clean
:class:`~tracker.errors.RecordingError` / :class:`~tracker.errors.TrackerError`, within ``--timeout``
seconds, with no process over ``--max-rss-mb``. Mutant ``i`` of seed ``S`` and format ``F`` is
always the same bytes (``--keep DIR`` saves the ones that fail).

Usage::

    python tools/fuzz_recordings.py --mutants 10000 --formats bag,db3,mcap,mkv,png --jobs 2 [--keep DIR]

Prints per format the counts: read, clean error, other exception (a bug in our code), crash (the
reading process died), hang (over the timeout), memory (a mutant that took the reader past
``--max-rss-mb``) and the largest resident set. Exits 1 if there was any failure.

Each job is a process that reads many mutants and reports one line per mutant, so a crash or a hang
is charged to the mutant it was on and the job restarts after it. Jobs run under an address-space
cap (``--cap-gb``) so that a runaway allocation fails there instead of taking the machine.
"""
from __future__ import annotations

import argparse
import json
import resource
import select
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
DEFAULT_CORPUS = HERE.parent.parent / "shared" / "data"
FORMATS = ("bag", "db3", "mcap", "mkv", "png")
REAL = {"bag": "sensor_recordings/librealsense_single_depth_color_640x480.bag",
        "mkv": "sensor_recordings/azure_kinect_recording.mkv"}

# Values written over length, count and size fields
_U32 = (0, 1, 0x7FFFFFFF, 0x80000000, 0xFFFFFFF0, 0xFFFFFFFF, 0x00010000)
# Values written over recording.yaml's numbers
_YAML_VALUES = ("1.0e-300", "0", "-1", ".nan", ".inf", "1.0e+300", "99999999", "4097", "'x'", "[]", "null")


# ----------------------------------------------------------------------------- seeds
def _write_ros_bag(path: Path, ros: int, storage=None) -> Path:
    """A small depth recording (camera_info + 3 depth frames 40×30, mono16) written with rosbags."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    T = ts.types
    w = Writer1(path) if ros == 1 else Writer2(path, version=9, storage_plugin=storage)
    ser = ts.serialize_ros1 if ros == 1 else ts.serialize_cdr
    rng = np.random.default_rng(0)
    w.open()
    try:
        def header(t):
            stamp = T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9)
            return (T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="depth") if ros == 1
                    else T["std_msgs/msg/Header"](stamp=stamp, frame_id="depth"))

        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        arrays = dict(D=np.zeros(5), K=np.array([50.0, 0, 19.5, 0, 52.0, 14.25, 0, 0, 1]), R=np.eye(3).ravel(),
                      P=np.zeros(12))
        if ros == 2:
            arrays = {k.lower(): v for k, v in arrays.items()}
        info = T["sensor_msgs/msg/CameraInfo"](header=header(10**9), height=30, width=40, distortion_model="plumb_bob",
                                               binning_x=0, binning_y=0, roi=roi, **arrays)
        c_info = w.add_connection("/cam/depth/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        c_img = w.add_connection("/cam/depth/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        w.write(c_info, 10**9, ser(info, "sensor_msgs/msg/CameraInfo"))
        for k in range(3):
            t = 10**9 + (k + 1) * 33_333_333
            d = rng.integers(300, 4000, (30, 40)).astype(np.uint16)
            msg = T["sensor_msgs/msg/Image"](header=header(t), height=30, width=40, encoding="16UC1", is_bigendian=0,
                                             step=80, data=d.view(np.uint8).ravel())
            w.write(c_img, t, ser(msg, "sensor_msgs/msg/Image"))
    finally:
        w.close()
    return path


def seeds(fmt: str, work: Path, corpus: Path) -> list[Path]:
    """The seed recordings of a format: written under ``work``, and the real file in ``corpus``."""
    out = []
    if fmt == "bag":
        out.append(_write_ros_bag(work / "ros1.bag", 1))
    elif fmt in ("db3", "mcap"):
        from rosbags.rosbag2 import StoragePlugin

        folder = _write_ros_bag(work / f"ros2_{fmt}", 2, StoragePlugin.SQLITE3 if fmt == "db3" else StoragePlugin.MCAP)
        out.append(next(folder.glob(f"*.{fmt}")))
    elif fmt == "png":
        from tracker.io.cameras import Camera
        from tracker.io.recording import RecordingWriter

        rng = np.random.default_rng(0)
        with RecordingWriter(work / "folder", Camera(40, 30, 50.0, 52.0, 19.5, 14.25, 0.001, "uint16", "fuzz"),
                             fps=30, handedness="right", source="fuzz seed") as w:
            for _ in range(3):
                w.write_units(rng.integers(300, 4000, (30, 40)).astype(np.uint16))
        out.append(work / "folder")
        if (corpus / REAL["mkv"]).is_file():  # what `tracker import` makes of a real file
            from tracker.io.recording import import_recording_file

            import_recording_file(corpus / REAL["mkv"], work / "imported", handedness="left")
            out.append(work / "imported")
        return out
    if fmt in REAL and (corpus / REAL[fmt]).is_file():
        out.append(corpus / REAL[fmt])
    return out


# ----------------------------------------------------------------------------- mutants
def mutate_bytes(data: bytes, rng: np.random.Generator, head: int = 4096) -> bytes:
    """One to four edits: bit flips, random bytes, an extreme u32 over a length field, truncation, a
    dropped or duplicated block; half of them in the first ``head`` bytes or the last 4 KiB, where
    headers and indexes sit."""
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 5))):
        if not b:
            break
        r = rng.random()
        if r < 0.35:
            at = int(rng.integers(0, min(len(b), head)))
        elif r < 0.6:
            at = int(rng.integers(max(0, len(b) - 4096), len(b)))
        else:
            at = int(rng.integers(0, len(b)))
        kind = int(rng.integers(0, 6))
        if kind == 0:
            b[at] ^= 1 << int(rng.integers(0, 8))
        elif kind == 1:
            b[at] = int(rng.integers(0, 256))
        elif kind == 2:
            v = _U32[int(rng.integers(0, len(_U32)))]
            b[at:at + 4] = v.to_bytes(4, "little" if rng.random() < 0.7 else "big")
        elif kind == 3:
            del b[int(rng.integers(0, len(b))):]
        elif kind == 4:
            del b[at:at + int(rng.integers(1, 512))]
        else:
            n = int(rng.integers(1, 512))
            b[at:at] = b[at:at + n]
    return bytes(b)


def mutate_yaml(text: str, rng: np.random.Generator) -> str:
    """One value of recording.yaml replaced by an implausible one, or a line dropped or cut."""
    lines = text.splitlines()
    k = int(rng.integers(0, len(lines)))
    kind = int(rng.integers(0, 3))
    if kind == 0 and ":" in lines[k]:
        key = lines[k].split(":", 1)[0]
        lines[k] = f"{key}: {_YAML_VALUES[int(rng.integers(0, len(_YAML_VALUES)))]}"
    elif kind == 1:
        del lines[k]
    else:
        lines[k] = lines[k][:int(rng.integers(0, len(lines[k]) + 1))]
    return "\n".join(lines) + "\n"


def make_mutant(fmt: str, sources: list[Path], seed: int, i: int, into: Path) -> tuple[Path, str]:
    """Mutant ``i`` of ``seed`` written under ``into``: its path and its source's name."""
    rng = np.random.default_rng([seed, FORMATS.index(fmt), i])
    src = sources[int(rng.integers(0, len(sources)))]
    if fmt != "png":
        path = into / f"m{i}{src.suffix}"
        path.write_bytes(mutate_bytes(src.read_bytes(), rng))
        return path, src.name
    path = into / f"m{i}"
    shutil.copytree(src, path)
    pngs = sorted((path / "depth").glob("*.png"))
    if rng.random() < 0.5:
        y = path / "recording.yaml"
        y.write_text(mutate_yaml(y.read_text(), rng))
    else:
        p = pngs[int(rng.integers(0, len(pngs)))]
        p.write_bytes(mutate_bytes(p.read_bytes(), rng, head=64))
    return path, src.name


def _rss_kb() -> int:
    return max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)


def _job(fmt: str, corpus: Path, seed: int, start: int, stop: int, step: int, cap_gb: float) -> None:
    """Read mutants start, start+step, ... < stop of ``fmt``; print one JSON line per mutant."""
    cap = int(cap_gb * (1 << 30))
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    from tracker.errors import RecordingError, TrackerError
    from tracker.io.recording import open_recording

    with tempfile.TemporaryDirectory(prefix="fuzz_rec.") as tmp:
        tmp = Path(tmp)
        (tmp / "seeds").mkdir()
        sources = seeds(fmt, tmp / "seeds", corpus)
        for i in range(start, stop, step):
            into = tmp / f"m{i}"
            into.mkdir()
            path, src = make_mutant(fmt, sources, seed, i, into)
            print(json.dumps({"i": i, "start": True}), flush=True)
            t0, before = time.monotonic(), _rss_kb()
            try:
                rec = open_recording(path)
                n = 0
                for frame in rec:
                    n += frame.depth is not None
                outcome, detail = "read", f"{n} frames"
            except (RecordingError, TrackerError):
                outcome, detail = "error", ""
            except Exception:  # noqa: BLE001 - exactly what the fuzzer hunts
                outcome, detail = "other", traceback.format_exc(limit=4).strip().splitlines()[-1]
            rss = _rss_kb()
            print(json.dumps({"i": i, "outcome": outcome, "s": time.monotonic() - t0, "rss_kb": rss,
                              "grew_kb": rss - before, "src": src, "detail": detail}), flush=True)
            shutil.rmtree(into, ignore_errors=True)


def run(fmt: str, corpus: Path, mutants: int, seed: int, jobs: int, timeout: float, max_rss_mb: float,
        cap_gb: float, keep: Path | None, log=print) -> dict:
    """Fuzz one format; return its counts and the largest resident set (MB)."""
    counts = {"read": 0, "error": 0, "other": 0, "crash": 0, "hang": 0, "memory": 0}
    peak_kb, slowest = 0, 0.0

    def save(i: int, what: str) -> None:
        if keep is None:
            return
        with tempfile.TemporaryDirectory() as t:
            t = Path(t)
            (t / "seeds").mkdir()
            path, src = make_mutant(fmt, seeds(fmt, t / "seeds", corpus), seed, i, t)
            keep.mkdir(parents=True, exist_ok=True)
            dst = keep / f"{what}-{fmt}-seed{seed}-{i}-{path.name}"
            (shutil.copytree if path.is_dir() else shutil.copy)(path, dst)

    def spawn(start: int, step: int) -> dict:
        cmd = [sys.executable, __file__, "--_job", fmt, str(corpus), str(seed), str(start), str(mutants), str(step),
               str(cap_gb)]
        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, bufsize=1)
        return {"proc": p, "step": step, "current": None, "since": time.monotonic()}

    def lost(j: dict, kind: str, detail: str = "") -> int:
        counts[kind] += 1
        log(f"{kind.upper()} {fmt} mutant {j['current']} {detail}".rstrip())
        save(j["current"], kind)
        nxt = j["current"] + j["step"]
        if nxt < mutants:
            running.append(spawn(nxt, j["step"]))
        return 1

    running = [spawn(j, jobs) for j in range(min(jobs, mutants))]
    done, t_start = 0, time.monotonic()
    while running:
        fds = {j["proc"].stdout.fileno(): j for j in running}
        ready, _, _ = select.select(list(fds), [], [], 1.0)
        now = time.monotonic()
        for fd in ready:
            j = fds[fd]
            line = j["proc"].stdout.readline()
            if not line:
                rc = j["proc"].wait()
                running.remove(j)
                if j["current"] is not None:
                    done += lost(j, "crash", f"(exit {rc})")
                elif rc != 0:
                    raise SystemExit(f"error: the {fmt} reader job failed before its first mutant (exit {rc}); "
                                     "run it alone to see why")
                continue
            msg = json.loads(line)
            if msg.get("start"):
                j["current"], j["since"] = msg["i"], now
                continue
            j["current"] = None
            done += 1
            peak_kb, slowest = max(peak_kb, msg["rss_kb"]), max(slowest, msg["s"])
            outcome = msg["outcome"]
            if msg["rss_kb"] > max_rss_mb * 1024 and msg["grew_kb"] > 0:
                outcome = "memory"  # this mutant took the reader past the bound
            counts[outcome] += 1
            if outcome in ("other", "memory"):
                log(f"{outcome.upper()} {fmt} mutant {msg['i']} of {msg['src']}: {msg['detail']} "
                    f"({msg['rss_kb'] / 1024:.0f} MB)")
                save(msg["i"], outcome)
            if done % 1000 == 0:
                log(f"{fmt}: {done}/{mutants} {counts} max RSS {peak_kb / 1024:.0f} MB ({time.monotonic() - t_start:.0f} s)")
        for j in list(running):
            if j["current"] is not None and now - j["since"] > timeout:
                j["proc"].kill()
                j["proc"].wait()
                running.remove(j)
                done += lost(j, "hang")
    return {**counts, "max_rss_mb": peak_kb / 1024, "slowest_s": slowest, "seconds": time.monotonic() - t_start}


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    if argv and argv[0] == "--_job":
        fmt, corpus, seed, start, stop, step, cap = argv[1:8]
        _job(fmt, Path(corpus), int(seed), int(start), int(stop), int(step), float(cap))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mutants", type=int, default=1000, help="mutants per format")
    ap.add_argument("--formats", default=",".join(FORMATS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--timeout", type=float, default=30.0, help="seconds one mutant may take")
    ap.add_argument("--max-rss-mb", type=float, default=1024.0)
    ap.add_argument("--cap-gb", type=float, default=1.0, help="address-space cap (RLIMIT_AS) of a reading process")
    ap.add_argument("--corpus", type=Path, default=DEFAULT_CORPUS)
    ap.add_argument("--keep", type=Path, default=None, help="save failing mutants here")
    args = ap.parse_args(argv)
    formats = [f for f in args.formats.split(",") if f]
    bad = [f for f in formats if f not in FORMATS]
    if bad:
        print(f"error: unknown format {bad[0]!r} (one of {', '.join(FORMATS)})", file=sys.stderr)
        return 2
    failed = False
    rows = []
    for fmt in formats:
        if fmt == "mkv" and not (args.corpus / REAL["mkv"]).is_file():
            print(f"{fmt}: skipped (no seed: {args.corpus / REAL['mkv']} is absent)")
            continue
        c = run(fmt, args.corpus, args.mutants, args.seed, args.jobs, args.timeout, args.max_rss_mb, args.cap_gb,
                args.keep)
        rows.append((fmt, c))
        failed |= any(c[k] for k in ("other", "crash", "hang", "memory"))
    print(f"{'format':<7}{'mutants':>9}{'read':>8}{'error':>8}{'other':>7}{'crash':>7}{'hang':>6}{'memory':>8}"
          f"{'max RSS MB':>12}{'slowest s':>11}{'time s':>8}")
    for fmt, c in rows:
        n = sum(c[k] for k in ("read", "error", "other", "crash", "hang", "memory"))
        print(f"{fmt:<7}{n:>9}{c['read']:>8}{c['error']:>8}{c['other']:>7}{c['crash']:>7}{c['hang']:>6}"
              f"{c['memory']:>8}{c['max_rss_mb']:>12.0f}{c['slowest_s']:>11.2f}{c['seconds']:>8.0f}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
