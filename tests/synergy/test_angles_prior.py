"""The weak DIP–PIP coupling prior of the marker IK (synergy.angles.refine_with_coupling): it
decides a DIP the markers do not see, and leaves one they do see where the markers put it."""
import numpy as np

from handmodel import HandModel
from synergy.angles import IP_COUPLING, ip_coupling_pairs, refine_with_coupling

HAND = HandModel.load()
PAIRS = ip_coupling_pairs(HAND)


def posture(pip, dip):
    th = np.zeros((1, HAND.n_dofs))
    th[0, :6] = [0.01, 0.02, 0.3, 0.2, -0.1, 0.3]
    th[0, PAIRS[:, 0]] = pip
    th[0, PAIRS[:, 1]] = dip
    return th


def test_observed_dip_stays_where_the_markers_put_it():
    # a marker at every node and one above it: each DIP is measured; truth far from the coupling
    nodes = np.r_[np.arange(HAND.n_nodes), np.arange(HAND.n_nodes)]
    local = np.r_[np.zeros((HAND.n_nodes, 3)), np.tile([0.0, 0.0, 0.01], (HAND.n_nodes, 1))]
    truth = posture(-1.0, 0.0)
    tg = HAND.points(truth, nodes, local)
    out = refine_with_coupling(HAND, nodes, local, tg, truth, None, noise_mm=0.3)
    # the coupling says DIP −38°; two markers see each DIP at 0.25–0.29 mm/° against 0.3 mm noise,
    # so the posterior gives way by ~1° (a prior in the wrong units or 10× too strong: tens of degrees)
    assert np.degrees(np.abs(out - truth)[0, 6:]).max() < 1.5


def test_unseen_dip_follows_its_pip():
    # no marker on a distal phalanx or beyond: the data leave every DIP free
    seen = [k for k in range(HAND.n_nodes) if not HAND.node_names[k].endswith(("3", "_tip"))
            or HAND.node_names[k].startswith("thumb")]
    nodes, local = np.array(seen), np.tile([0.0, 0.0, 0.01], (len(seen), 1))
    truth = posture(-1.2, -0.2)
    tg = HAND.points(truth, nodes, local)
    out = refine_with_coupling(HAND, nodes, local, tg, truth, None, noise_mm=0.3)
    np.testing.assert_allclose(out[0, PAIRS[:, 1]], IP_COUPLING * out[0, PAIRS[:, 0]], atol=1e-3)
    np.testing.assert_allclose(out[0, PAIRS[:, 0]], -1.2, atol=1e-3)  # the PIPs the markers see stay
    # frames without a posture (unsolved) pass through untouched
    both = refine_with_coupling(HAND, nodes, local, np.r_[tg, tg], np.r_[truth, np.full_like(truth, np.nan)],
                                None, noise_mm=0.3)
    assert np.isnan(both[1]).all()
