"""Pipeline stage ``init``: fit one frame without temporal prior (the start of tracking, and its
re-initialisation after a loss).

The modules, in the order of the search:

- :mod:`.candidates`: the starts (placements from the cloud, synergy postures, finger shapes) and
  the thinned cloud that ranks them;
- :mod:`.scoring`: :class:`FitContext`, the parts of one hand's fits that a tracker builds once
  (everything here works on one), which fits the starts, and :func:`score`, which ranks the fits;
- :mod:`.overlap`: what fingers passing into each other cost the finger-wise restarts (compiled);
- :mod:`.search`: :func:`fit_single_frame`, the search that runs them (successive halving or
  exhaustive), and the finger-wise restarts;
- :mod:`.settings`: :class:`InitSettings` and the threads a batch of fits runs on.

Every name below is importable from ``tracker.init`` itself.
"""
from .candidates import (
    FINGER_SHAPES_DEG,
    PAIR_SHAPES,
    diverse,
    finger_pair_variants,
    finger_shapes,
    finger_variants,
    placements,
    posture_candidates,
    posture_grid,
    thin,
)
from .overlap import (
    FINGER_OVERLAP_SHARE,
    FINGER_OVERLAP_WEIGHT,
    finger_capsules,
    finger_overlap_mm,
    segment_distances,
)
from .scoring import MODEL_TO_DATA_WEIGHT, REJECTED_PAIR_MM, FitContext, data_cost_mm, score
from .search import (
    COUPLED_RESTART_DEG,
    PAIR_SCORE_MM,
    SearchBudget,
    converge,
    finger_search,
    finger_search_batched,
    fit_single_frame,
    restart_fingers,
    seeded_search,
)
from .settings import STRATEGIES, HalvingSettings, InitSettings, SeededSettings, available_cores, search_threads

# not this package's public names, but imported from tracker.init where they were before the split
# (tracker.scale's palm-side samples; the data term's cap, tracker.correspond's, in the tests)
from ..correspond import DATA_CAP_MM  # noqa: F401
from .candidates import _palm_side  # noqa: F401

__all__ = [
    # settings
    "InitSettings", "HalvingSettings", "SeededSettings", "STRATEGIES", "available_cores", "search_threads",
    # candidates
    "placements", "posture_candidates", "posture_grid", "diverse", "FINGER_SHAPES_DEG", "PAIR_SHAPES",
    "finger_shapes", "finger_variants", "finger_pair_variants", "thin",
    # scoring
    "FitContext", "score", "data_cost_mm", "MODEL_TO_DATA_WEIGHT", "REJECTED_PAIR_MM",
    # overlap
    "finger_capsules", "finger_overlap_mm", "segment_distances", "FINGER_OVERLAP_WEIGHT", "FINGER_OVERLAP_SHARE",
    # search
    "fit_single_frame", "seeded_search", "converge", "restart_fingers", "SearchBudget", "finger_search", "finger_search_batched",
    "PAIR_SCORE_MM", "COUPLED_RESTART_DEG",
]
