"""Fuzz :func:`synergy.c3d.read_c3d` with mutated copies of the C3D corpus.

Every mutant must end as a :class:`~synergy.c3d.MarkerData` ("read") or a
:class:`~synergy.errors.C3DError` ("clean error"), within ``--timeout`` seconds, without
taking the calling process down. Mutants are reproducible: mutant ``i`` of seed ``S`` is
always the same bytes (``--keep DIR`` saves the ones that fail).

Usage::

    python tools/fuzz_c3d.py --mutants 100000 --seed 1 --jobs 2 [--corpus ../shared/data] [--keep DIR]

Prints the counts: read, clean error, other exception (a bug in our code), crash (the
calling process died), hang (over the timeout) and the largest resident set of any process
involved (caller or reader worker). Exits 1 if there was any crash, hang or other exception.

Each job runs in its own process and reports one line per mutant, so a crash or a hang of
a job is charged to the mutant it was working on and the job is restarted after it.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import select
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
DEFAULT_CORPUS = HERE.parent.parent / "shared" / "data"

# Values that make counts, offsets and rates extreme when written over a field.
_INT16 = (0, 1, 0x7FFF, 0x8000, 0xFFFF, 0x00FF, 0xFF00)
_FLOAT32 = (0.0, -1.0, 1e9, -1e9, 1e38, float("nan"), float("inf"), 1e-30)


def corpus_files(root) -> list[Path]:
    """The C3D files under ``root`` (any case of the suffix), sorted."""
    return sorted(p for p in Path(root).rglob("*") if p.suffix.lower() == ".c3d" and p.is_file())


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """One to four random edits of ``data``, most of them in the header and parameter section
    (the first 16 KiB), where a single byte changes how everything after it is read."""
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 5))):
        if not b:
            break
        head = min(len(b), 16384)
        at = int(rng.integers(0, head if rng.random() < 0.8 else len(b)))
        kind = int(rng.integers(0, 7))
        if kind == 0:                                    # flip one bit
            b[at] ^= 1 << int(rng.integers(0, 8))
        elif kind == 1:                                  # one random byte
            b[at] = int(rng.integers(0, 256))
        elif kind == 2:                                  # an extreme 16-bit word
            v = _INT16[int(rng.integers(0, len(_INT16)))]
            b[at:at + 2] = v.to_bytes(2, "little" if rng.random() < 0.5 else "big")
        elif kind == 3:                                  # an extreme float32
            v = np.float32(_FLOAT32[int(rng.integers(0, len(_FLOAT32)))])
            b[at:at + 4] = v.tobytes()
        elif kind == 4:                                  # truncate
            del b[int(rng.integers(0, len(b))):]
        elif kind == 5:                                  # drop a 512-byte block
            blk = at // 512 * 512
            del b[blk:blk + 512]
        else:                                            # duplicate a 512-byte block
            blk = at // 512 * 512
            b[blk:blk] = b[blk:blk + 512]
    return bytes(b)


def mutant(files: list[Path], seed: int, i: int, cache: dict) -> tuple[Path, bytes]:
    """Mutant ``i`` of ``seed``: its source file and its bytes."""
    rng = np.random.default_rng([seed, i])
    src = files[int(rng.integers(0, len(files)))]
    if src not in cache:
        cache[src] = src.read_bytes()
    return src, mutate(cache[src], rng)


def _worker_rss_kb() -> int:
    """Peak resident set of the live reader worker (it is reaped only when it dies)."""
    from synergy import c3d_native

    w = c3d_native._worker
    if w is None or w.proc.poll() is not None:
        return 0
    try:
        for line in Path(f"/proc/{w.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def _job(corpus: Path, seed: int, start: int, stop: int, step: int) -> None:
    """Run mutants start, start+step, ... < stop; print one JSON line per mutant."""
    from synergy.c3d import read_c3d
    from synergy.errors import C3DError

    files = corpus_files(corpus)
    cache: dict = {}
    with tempfile.TemporaryDirectory(prefix="fuzz_c3d.") as tmp:
        for i in range(start, stop, step):
            src, data = mutant(files, seed, i, cache)
            path = Path(tmp) / f"m{i}.c3d"
            path.write_bytes(data)
            print(json.dumps({"i": i, "start": True}), flush=True)
            t0 = time.monotonic()
            try:
                read_c3d(path)
                outcome, detail = "read", ""
            except C3DError:
                outcome, detail = "error", ""
            except Exception:  # noqa: BLE001 - exactly what the fuzzer hunts
                outcome, detail = "other", traceback.format_exc(limit=3).splitlines()[-1]
            rss = max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
                      resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, _worker_rss_kb())
            print(json.dumps({"i": i, "outcome": outcome, "s": time.monotonic() - t0, "rss_kb": rss,
                              "src": src.name, "detail": detail}), flush=True)
            path.unlink()


def run(corpus: Path, mutants: int, seed: int, jobs: int, timeout: float, keep: Path | None,
        log=print) -> dict:
    """Run the fuzzer; return the counts."""
    counts = {"read": 0, "error": 0, "other": 0, "crash": 0, "hang": 0}
    max_rss_kb, slowest = 0, 0.0
    files = corpus_files(corpus)
    if not files:
        raise SystemExit(f"error: {corpus}: no C3D files")
    cache: dict = {}

    def save(i: int, what: str) -> None:
        if keep is not None:
            keep.mkdir(parents=True, exist_ok=True)
            src, data = mutant(files, seed, i, cache)
            (keep / f"{what}-seed{seed}-{i}-{src.stem}.c3d").write_bytes(data)

    def spawn(start: int, step: int) -> dict:
        cmd = [sys.executable, __file__, "--_job", str(corpus), str(seed), str(start), str(mutants), str(step)]
        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, bufsize=1)
        return {"proc": p, "step": step, "current": None, "since": time.monotonic()}

    def lost(j: dict, kind: str, detail: str = "") -> int:
        """A job lost inside its current mutant (a crash or a hang): count, log and keep the mutant, and
        carry the job's share of mutants on from the next one. Returns the mutants done (1)."""
        counts[kind] += 1
        log(f"{kind.upper()} mutant {j['current']} {detail}".rstrip())
        save(j["current"], kind)
        nxt = j["current"] + j["step"]
        if nxt < mutants:
            running.append(spawn(nxt, j["step"]))
        return 1

    running = [spawn(j, jobs) for j in range(min(jobs, mutants))]
    done = 0
    t_start = time.monotonic()
    while running:
        fds = {j["proc"].stdout.fileno(): j for j in running}
        ready, _, _ = select.select(list(fds), [], [], 1.0)
        now = time.monotonic()
        for fd in ready:
            j = fds[fd]
            line = j["proc"].stdout.readline()
            if not line:                                  # the job ended or died
                rc = j["proc"].wait()
                running.remove(j)
                if j["current"] is not None:              # died inside a mutant: a crash
                    done += lost(j, "crash", f"(exit {rc})")
                continue
            msg = json.loads(line)
            if msg.get("start"):
                j["current"], j["since"] = msg["i"], now
                continue
            j["current"] = None
            counts[msg["outcome"]] += 1
            done += 1
            max_rss_kb = max(max_rss_kb, msg["rss_kb"])
            slowest = max(slowest, msg["s"])
            if msg["outcome"] == "other":
                log(f"OTHER mutant {msg['i']} of {msg['src']}: {msg['detail']}")
                save(msg["i"], "other")
            if done % 1000 == 0:
                log(f"{done}/{mutants} {counts} max RSS {max_rss_kb / 1024:.0f} MB "
                    f"({time.monotonic() - t_start:.0f} s)")
        for j in list(running):                           # a mutant over the timeout: a hang
            if j["current"] is not None and now - j["since"] > timeout:
                j["proc"].kill()
                j["proc"].wait()
                running.remove(j)
                done += lost(j, "hang")
    return {**counts, "mutants": done, "max_rss_mb": round(max_rss_kb / 1024, 1),
            "slowest_s": round(slowest, 2), "seconds": round(time.monotonic() - t_start, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mutants", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=max(1, (os.cpu_count() or 2) - 0))
    ap.add_argument("--corpus", type=Path, default=DEFAULT_CORPUS, help="Folder searched for *.c3d.")
    ap.add_argument("--timeout", type=float, default=10.0, help="Seconds after which a mutant is a hang.")
    ap.add_argument("--keep", type=Path, default=None, help="Save failing mutants here.")
    ap.add_argument("--_job", nargs=5, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a._job:
        corpus, seed, start, stop, step = a._job
        _job(Path(corpus), int(seed), int(start), int(stop), int(step))
        return 0
    res = run(a.corpus, a.mutants, a.seed, a.jobs, a.timeout, a.keep)
    print(json.dumps(res))
    return 1 if res["crash"] or res["hang"] or res["other"] else 0


if __name__ == "__main__":
    sys.exit(main())
