"""The experiments report's parts run side by side in worker processes give what they give in one."""
import numpy as np

from tracker.sim.report import STEPS, run_steps


def test_parts_in_two_workers_equal_one_by_one():
    names = ["occlusion", "density"]
    assert set(names) <= set(STEPS)
    seen = []
    alone = run_steps(names, quick=True, jobs=1)
    both = run_steps(names, quick=True, jobs=2, progress=lambda k, n, name: seen.append((k, n, name)))
    assert sorted(seen) == [(1, 2, seen[0][2]), (2, 2, seen[1][2])] and {s[2] for s in seen} == set(names)
    assert alone["occlusion"].keys() == both["occlusion"].keys()
    for k in alone["occlusion"]:
        assert np.isclose(alone["occlusion"][k], both["occlusion"][k]), k
    # the density rows: (stride, share, error, ms) — errors equal, times are the machine's
    assert [(k, round(e, 9)) for k, _, e, _ in alone["density"]] == [(k, round(e, 9)) for k, _, e, _ in both["density"]]
