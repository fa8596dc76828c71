"""Compile the tracker's numba kernels once, at install time, so that a user's first call does not.

The kernels are compiled on first use and kept in numba's cache (``__pycache__`` beside each
module, or ``$NUMBA_CACHE_DIR``); a first ``tracker track`` on a fresh install otherwise spends
minutes compiling before its first frame. ``tracker compile`` (or ``python -m tracker.compile``;
``make``'s environment step runs it) renders a few frames and tracks them the way ``tracker
track`` does, in each mode, so every kernel a tracking run calls is compiled with the argument types
it is called with, then says how many of the package's kernels are in the cache. The cache is per
machine (numba compiles for the processor it runs on), which is why this is an install step and not
something a wheel could carry.

This module is a tool like the CLI modules: it imports the renderer (``tracker.sim``) inside
:func:`compile_all` only.
"""
from __future__ import annotations

import importlib
import pkgutil
import sys
import tempfile
import time
from pathlib import Path

#: what a first call on a fresh install costs: a first ``tracker track`` of one still with an empty
#: cache took 123 s of CPU, 394 s wall on this project's shared 2-core machine (2026-11-28)
COMPILE_MINUTES = "2–7"
#: the packages whose numba kernels are counted
PACKAGES = ("handmodel", "tracker")
#: a kernel every tracking run calls: no cache entry for it means the kernels were never compiled
PROBE = ("tracker._fit_kernels", "fit_entry")


def _cache_index(dispatcher) -> dict:
    """The compiled signatures numba's cache holds for ``dispatcher`` (empty when none, or stale)."""
    try:
        return dispatcher._cache._cache_file._load_index()
    except Exception:  # numba's cache internals differ between versions: then say nothing
        return {"unknown": None}


def is_cold() -> bool:
    """Whether numba's cache holds no compiled tracking kernel (a fresh install, a changed kernel
    source, another ``$NUMBA_CACHE_DIR``): the next tracking call will compile."""
    module, name = PROBE
    return not _cache_index(getattr(importlib.import_module(module), name))


def cold_message() -> str | None:
    """The one line a command prints before it compiles, or None when the kernels are compiled."""
    if not is_cold():
        return None
    return (f"note: compiling the tracker's kernels for this machine (once; about {COMPILE_MINUTES} min on "
            f"2 cores). `tracker compile` does it ahead, e.g. right after pip install.")


def kernels():
    """``(module name, function name, dispatcher)`` of every numba kernel of :data:`PACKAGES` that
    keeps a cache (``cache=True``), the modules imported to find them (the simulator's too)."""
    from numba.core.registry import CPUDispatcher

    out = []
    for pkg_name in PACKAGES:
        pkg = importlib.import_module(pkg_name)
        names = [pkg_name] + [m.name for m in pkgutil.walk_packages(pkg.__path__, pkg_name + ".")]
        for name in sorted(names):
            if name.endswith((".__main__", ".compile")) or ".cli" in name or name.endswith("_cli"):
                continue
            try:
                module = importlib.import_module(name)
            except Exception:  # an optional extra that is not installed or cannot load (rerun, realsense, ...)
                continue
            for attr, obj in vars(module).items():
                if (isinstance(obj, CPUDispatcher) and obj.__module__ == name
                        and getattr(obj, "_cache", None) is not None and type(obj._cache).__name__ != "NullCache"):
                    out.append((name, attr, obj))
    return out


def compiled_share():
    """``(compiled, total)``: how many of :func:`kernels` have a compiled signature in the cache."""
    ks = kernels()
    return sum(1 for _, _, d in ks if _cache_index(d)), len(ks)


def _workload(folder: Path):
    """The steps of :func:`compile_all`: ``(label, callable)``."""
    from handmodel import HandModel
    from tracker import TRACKING_HAND
    from tracker.run import TrackJob, run_job
    from tracker.sim.synthesize import synthesize

    hand = HandModel.load(TRACKING_HAND)
    recs = {}

    def render(name, camera, noise, motion):
        def step():
            recs[name] = folder / name
            synthesize(motion, camera, noise, recs[name], frames=8, hand=hand, clutter="forearm,torso")
        return step

    def track(name, mode):
        def step():
            run_job(TrackJob(str(recs[name]), str(folder / f"{name}-{mode}.csv"), synergies="fingerfist",
                             overwrite=True, settings=_settings(mode)))
        return step

    return [("rendering a Kinect v1 recording", render("kinect1", "kinect1", "kinect1", "grasp-back")),
            ("tracking it (full: size calibration, start search, safety net)", track("kinect1", "full")),
            ("tracking it (reduced)", track("kinect1", "reduced")),
            ("tracking it (hierarchical)", track("kinect1", "hierarchical")),
            ("rendering an SR305 recording", render("sr305", "sr305", "realsense", "open-close")),
            ("tracking it (full)", track("sr305", "full"))]


def _settings(mode):
    from tracker.settings import TrackerSettings

    return TrackerSettings(mode=mode)


def compile_all(progress=None) -> tuple[int, int, float]:
    """Compile every kernel a tracking run calls (see the module's docstring). ``progress(i, n, label,
    seconds)`` is called before each step (``seconds``: elapsed). Returns ``(compiled, total,
    seconds)`` (:func:`compiled_share`)."""
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="tracker-compile-") as tmp:
        steps = _workload(Path(tmp))
        for i, (label, step) in enumerate(steps):
            if progress is not None:
                progress(i + 1, len(steps), label, time.perf_counter() - t0)
            step()
    done, total = compiled_share()
    return done, total, time.perf_counter() - t0


def main(argv=None) -> int:
    """``python -m tracker.compile``: :func:`compile_all` with a progress line on stderr."""
    def progress(i, n, label, seconds):
        print(f"compiling the tracker's kernels [{i}/{n}] {label} ({seconds:.0f} s)", file=sys.stderr, flush=True)

    done, total, seconds = compile_all(progress)
    print(f"compiled: {done} of {total} kernels in numba's cache ({seconds:.0f} s); the others compile when "
          f"first used (other options: --model mesh, point-to-plane, the simulator's extras)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
