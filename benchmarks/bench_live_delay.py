"""How late a live loop publishes each frame: a rendered recording played at its own rate (30 fps,
``tracker.realtime.paced``) with a start search made slow on purpose (1.5 s on two frames, as a real
clip's searches take), tracked in real time (``run.track_realtime``, budget one frame period) and,
as the peer, in turn (every frame waited for, as ``tracker track`` and a non-real-time playback do).

A frame's delay is the wall time from when the sensor would have delivered it (the first frame's
delivery + its time stamp) to its result's publication. Prints p50 / p95 / max delay, frames over
100 ms late, and the statuses.

Run: .venv/bin/python benchmarks/bench_live_delay.py [--frames 90]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from handmodel import HandModel
from synergy.bundle import load_bundle
from tracker.realtime import paced
from tracker.io.recording import Recording
from tracker.run import track_realtime, track_recording
from tracker.sim.synthesize import synthesize
from tracker.track import FrameTracker, TrackerSettings

SLOW_FRAMES = (20, 50)
SLOW_S = 1.5


def run(rec, realtime: bool):
    hand = HandModel.load("human", right=rec.handedness == "right")
    tr = FrameTracker(hand, TrackerSettings().replace(start=dict(check_hand=False)), synergies=load_bundle("fingerfist"))
    track = tr.track

    def slow(ob, cam, color=None):
        if seen[0] in SLOW_FRAMES:
            time.sleep(SLOW_S)  # a start search that takes long, on purpose
        return track(ob, cam, color=color)

    tr.track = slow
    seen, delays, start = [0], [], [None]
    dropped = []

    class Paced:  # the recording delivered at its rate; track_recording reads frames from it as they come
        camera, fps = rec.camera, rec.fps

        def __iter__(self):
            for f in paced(iter(rec), rec.fps, dropped=dropped):
                if start[0] is None:
                    start[0] = time.monotonic() - f.time_s
                seen[0] = f.index
                yield f

    def on_frame(frame, r, ob):
        delays.append((time.monotonic() - (start[0] + frame.time_s)) * 1000.0)

    if realtime:
        df = track_realtime(Paced(), tr, 1000.0 / rec.fps, on_frame)
    else:
        df = track_recording(Paced(), tr, on_frame)
    return np.array(delays), df, dropped


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=90)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        synthesize("open-close", "kinect1", None, Path(tmp) / "rec", frames=args.frames)
        rec = Recording.open(Path(tmp) / "rec")
        run(rec, True)  # warm-up: kernels loaded
        print(f"bench_live_delay: {len(rec)} rendered Kinect v1 frames at {rec.fps:g} fps, paced; a {SLOW_S} s search "
              f"on frames {', '.join(map(str, SLOW_FRAMES))}; delay = publication - sensor delivery")
        print(f"  {'loop':<40} {'p50 ms':>8} {'p95 ms':>8} {'max ms':>8} {'>100 ms':>8} {'dropped':>8}  statuses")
        for label, rt in (("real time (budget one frame period)", True), ("peer: every frame in turn", False)):
            d, df, dropped = run(rec, rt)
            counts = ", ".join(f"{k} {v}" for k, v in df["status"].value_counts().items())
            print(f"  {label:<40} {np.median(d):>8.1f} {np.percentile(d, 95):>8.1f} {d.max():>8.1f} "
                  f"{int((d > 100).sum()):>8} {len(dropped):>8}  {counts}")


if __name__ == "__main__":
    main()
