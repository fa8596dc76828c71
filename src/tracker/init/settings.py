"""The single-frame search's settings (:class:`InitSettings` and its successive-halving schedule,
:class:`HalvingSettings`) and the threads its batches of fits run on (:func:`search_threads`)."""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

from ..errors import TrackerError
from ..settings_base import SettingsGroup


@dataclass(frozen=True)
class SeededSettings(SettingsGroup):
    """How :func:`tracker.init.seeded_search` fits a detected hand before it decides whether the full
    search runs, and the finger-wise restarts of a start it accepts.

    ``first``: ``"search"`` (default) fits the synergy postures at the detected hand's global pose with the
    detected θ and the extra θ (:func:`tracker.init.fit_single_frame` from ``theta0``, no synergy grid),
    ``keep`` of them going on to the coarse and the refinement cloud (the search's ``HalvingSettings.keep``
    when None; a full search that follows keeps the search's); ``"fit"`` fits the detected θ and each extra θ
    once (``icp_iterations`` with all DoF on the whole cloud, one rigid step first, as the hand-presence
    test's fit) and falls back to ``"search"``'s fits when none scores within the acceptance.
    ``restart_icp``, ``restart_margin_mm``, ``restart_points`` and ``restart_pairs`` replace the search's own
    (``HalvingSettings.restart_icp``, ``restart_margin_mm``, ``rank_points``, ``InitSettings.finger_pairs``) for an
    accepted start's restarts; None keeps the search's. ``calibration``: the size calibration's first search
    (:meth:`InitSettings.sizing`) uses these settings too; False (default): the search's own (:meth:`full`): with
    cheaper fits there (``keep`` (2, 1), restarts ranked with 2 ICP iterations on 200 points, margin 0), 4 of the
    harder scenes' 24 calibrated sizes moved, all 4 further from the true size (found / true 0.999 → 0.939, 1.120 →
    1.189, 1.174 → 0.790, 0.903 → 0.676).

    ``keep`` (2, 1) with ``restart_margin_mm`` 0 (the best 2 of the detected hand's 7 starts on the coarse cloud,
    the best 1 on the refinement cloud; a restart going on only when it ranks better than the fit itself) cuts an
    accepted start by a third (bench_start's 46: 69 → 46 ms CPU median alternating; mean keypoint error 4.30 →
    4.12 mm) and betters the paper's Fig. 8 (1 + 0 ICP iterations 1.77° → 1.41°), but it is not the default: the
    regenerated experiments report had the paper's mesh-model cell worse (full 1.59° → 1.71°), five other paper
    cells 0.01–0.03° worse and a rotation without the net lost earlier (16.7° → 20.6°); made the default in 4ae2220
    and taken back. Cheaper restarts (``restart_icp=2``: 34-37 ms) missed the thumb after blank frames
    (test_track: 0.44° → 2.1°). ``first="fit"`` with ``restart_icp=2``, ``restart_margin_mm=0`` ("C1", ~30 ms)
    was reverted as the default too: Fig. 8's sequences begin at the synergy mean, one of ``"search"``'s starts,
    and its one fit was left unconverged when no restart went on (Fig. 8 1.77° → 4.48°;
    docs/experiments/start-cost.md).
    """

    first: str = "search"
    keep: tuple | None = None
    restart_icp: int | None = None
    restart_margin_mm: float | None = None
    restart_points: int | None = None
    restart_pairs: bool | None = None
    calibration: bool = False

    @classmethod
    def full(cls) -> SeededSettings:
        """The detected hand fitted by the search's own fits (its synergy starts, the search's ``keep``) and its
        restarts ranked by the search's own settings."""
        return cls(first="search", keep=None, restart_icp=None, restart_margin_mm=None, restart_points=None,
                   restart_pairs=None, calibration=True)

    def check(self):
        if self.first not in SEEDED_FIRST:
            raise TrackerError("settings", f"init seeded first must be one of {', '.join(SEEDED_FIRST)}, "
                                           f"got {self.first!r}")
        k = self.keep
        if k is not None and not (isinstance(k, (tuple, list)) and len(k) == 2
                                  and all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in k)):
            raise TrackerError("settings", f"init seeded keep must be two counts ≥ 1, got {self.keep!r}")
        if self.restart_points is not None and int(self.restart_points) < 1:
            raise TrackerError("settings", f"init seeded restart_points must be ≥ 1, got {self.restart_points!r}")


SEEDED_FIRST = ("search", "fit")


@dataclass(frozen=True)
class HalvingSettings(SettingsGroup):
    """The successive-halving schedule of the single-frame search (:class:`InitSettings` ``strategy``
    "halving"): every start fitted briefly on ``rank_points`` points (``rank_icp`` ICP iterations of
    ``rank_gn`` Gauss-Newton steps), the best ``keep[0]`` longer on the coarse cloud, the best
    ``keep[1]`` of those for ``refine_icp`` iterations on ``refine_points``; at most ``finger_sweeps``
    sweeps of finger-wise restarts; the winner polished with ``polish_icp`` on the full cloud. ``seeded``:
    how a detected hand's start is fitted and its restarts ranked (:class:`SeededSettings`; read as
    ``InitSettings.seeded`` too).
    """

    rank_points: int = 300
    rank_icp: int = 2
    rank_gn: int = 2
    keep: tuple = (12, 3)
    refine_points: int = 1500
    refine_icp: int = 8
    polish_icp: int = 4
    finger_sweeps: int = 3
    restart_icp: int = 4
    restart_margin_mm: float = 2.0
    seeded: SeededSettings = field(default_factory=SeededSettings)

    def check(self):
        if min(self.keep, default=0) < 1 or len(self.keep) != 2:
            raise TrackerError("settings", f"init keep must be two counts ≥ 1, got {self.keep!r}")
        if int(self.restart_icp) < 1 or not self.restart_margin_mm >= 0:
            raise TrackerError("settings", f"init restart_icp must be ≥ 1 and restart_margin_mm ≥ 0, got "
                                           f"{self.restart_icp!r}, {self.restart_margin_mm!r}")




@dataclass(frozen=True)
class InitSettings(SettingsGroup):
    """The single-frame search.

    ``icp_iterations``: ICP iterations refining each start on the full cloud; ``postures``: starts from
    the mean and ±σ along this many PCs; ``search``: the coarse synergy-grid search (our addition; off =
    the paper's fit from the mean); ``finger_search``: finger variants and finger-wise restarts (ours);
    ``finger_search_icp``: ICP iterations of a finger's best restart on the full cloud; ``placements``:
    how many orientation-diverse placements go on; ``coarse_points``: size of the thinned cloud that
    ranks candidates.

    ``threads``: how many fits of a batch (:meth:`FitContext.fit_many`) run at once, in threads (the
    compiled fit releases the GIL; each fit is independent, so the result is the same for any count);
    0 = the cores this process may use, at most 4 (:func:`search_threads`).

    ``strategy``: ``"halving"`` (default, successive halving: ``halving``, :class:`HalvingSettings`,
    whose fields read as this object's too, ``rank_points`` …) ranks every start briefly
    (:meth:`FitContext.fit_many`), the coarse stage on ``coarse_points``; the finger-wise restarts
    rank all fingers' shapes at once (``restart_icp`` ICP iterations on ``rank_points``) and refit only
    the promising ones (ranked within ``restart_margin_mm`` of θ's own score); the winner is converged with
    all DoF (``icp_iterations`` on ``refine_points``, then ``polish_icp`` on the full cloud); ``finger_pairs``: the restarts also set two neighbouring
    fingers at once while the fit scores poorly (:func:`finger_pair_variants`, ``PAIR_SCORE_MM``;
    3× the restarts' starts). ``refit_pose``: a given ``theta0`` may be off (a previous frame's), so
    it is also fitted longer and both go on. ``"exhaustive"``: the earlier search, every
    start refined with ``icp_iterations`` on the full cloud (2–3× the CPU time with the compiled ICP
    loop, ~14× with the Python one; kept as the reference the benchmark compares with).

    ``seeded`` (``halving.seeded``): how the search with a detected hand first (:func:`tracker.init.seeded_search`)
    fits that hand and restarts an accepted start's fingers (:class:`SeededSettings`).
    """

    icp_iterations: int = 12
    postures: int = 2
    search: bool = True
    finger_search: bool = True
    finger_search_icp: int = 10
    placements: int = 3
    coarse_points: int = 800
    strategy: str = "halving"
    halving: HalvingSettings = field(default_factory=HalvingSettings)
    refit_pose: bool = False
    finger_pairs: bool = True
    threads: int = 0

    # the halving schedule's fields, read where the search reads them
    rank_points = property(lambda self: self.halving.rank_points)
    rank_icp = property(lambda self: self.halving.rank_icp)
    rank_gn = property(lambda self: self.halving.rank_gn)
    keep = property(lambda self: self.halving.keep)
    refine_points = property(lambda self: self.halving.refine_points)
    refine_icp = property(lambda self: self.halving.refine_icp)
    polish_icp = property(lambda self: self.halving.polish_icp)
    finger_sweeps = property(lambda self: self.halving.finger_sweeps)
    restart_icp = property(lambda self: self.halving.restart_icp)
    seeded = property(lambda self: self.halving.seeded)
    restart_margin_mm = property(lambda self: self.halving.restart_margin_mm)

    @classmethod
    def cheap(cls, **changes) -> InitSettings:
        """A search about 3× cheaper than the default, for a frame whose global pose is roughly known
        (e.g. from the last tracked frame: ``fit_single_frame(ctx, points, InitSettings.cheap(),
        theta0=last, extra=(last,))``): fewer starts go on after the ranking, shorter refinements on
        fewer points, one sweep of finger-wise restarts and no pair restarts (they would add half
        again to the safety net's searches while tracking, for the few frames whose fingers swapped)."""
        halving = HalvingSettings(rank_points=200, keep=(6, 2), refine_points=800, refine_icp=6, polish_icp=2,
                                  finger_sweeps=1)
        return cls(icp_iterations=10, halving=halving, finger_pairs=False).replace(**changes)

    @classmethod
    def paper(cls):
        """The paper's fit from the synergy mean: no coarse or finger-wise search."""
        return cls(search=False, finger_search=False)

    def sizing(self) -> InitSettings:
        """These settings as the size calibration searches with them (:class:`tracker.sizing.SizeCalibration`):
        its first search from a detected hand by ``seeded`` when ``seeded.calibration``, else by the search's
        own fits and restarts (:meth:`SeededSettings.full`)."""
        return self if self.seeded.calibration else self.replace(halving=dict(seeded=SeededSettings.full()))

    def check(self):
        if self.strategy not in STRATEGIES:
            raise TrackerError("settings", f"init strategy must be one of {', '.join(STRATEGIES)}, got {self.strategy!r}")
        self.halving.check()
        self.halving.seeded.check()
        if int(self.threads) < 0:
            raise TrackerError("settings", f"init threads must be ≥ 0 (0 = the cores available), got {self.threads!r}")


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity; the machine's count where that is unknown)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def search_threads(threads: int = 0) -> int:
    """The threads a start search's batches of fits use: ``threads``, or for 0 the cores this process
    may run on (:func:`available_cores`), at most 4 (the batches hold 10–60 fits of ~1 ms; more threads
    gain little once the Python around each fit, which holds the GIL, is a third of the work). Never
    more than the cores: more threads would only take turns on them (``--threads 100`` on 2 cores
    started 100)."""
    n = available_cores()
    return max(1, min(int(threads), n)) if threads else min(n, 4)


_POOLS: dict = {}


def _pool(n):
    """One lasting thread pool per size and process (a search runs ~20 batches; a pool per batch costs
    more than it gains). A process forked after a search (a worker of ``-j``) gets its own: the
    parent's pool has no threads there and would never run a fit."""
    key = (n, os.getpid())
    if key not in _POOLS:
        _POOLS[key] = ThreadPoolExecutor(n, thread_name_prefix="fit")
    return _POOLS[key]


STRATEGIES = ("halving", "exhaustive")
