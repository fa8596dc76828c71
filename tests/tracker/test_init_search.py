"""The start search by successive halving: the batched candidate fits are the single fits they stand
for, the search is as accurate as the exhaustive one on the experiments' frames, the finger-wise
restarts ranked all at once still find a finger flexed alone, and bad settings are refused."""
from dataclasses import replace

import numpy as np
import pytest

from handmodel import HandModel
from handmodel.errors import HandModelError
from tracker.io.cameras import preset
from tracker.correspond import Silhouette
from tracker.errors import TrackerError
from tracker.evaluate import posture_error_deg
from tracker.init import (
    InitSettings,
    available_cores,
    finger_search_batched,
    search_threads,
    fit_single_frame,
    score,
    thin,
)
from tracker.observe import observe
from tracker.segment import Segmenter
from tracker.sim import experiments as E
from tracker.sim.render import DepthRenderer
from tracker.track import FrameTracker, TrackerSettings

HAND = HandModel.load()
CAM = preset("kinect1")
# the rendered hand has no forearm: nothing to cut, the tests see the whole hand
SEG = Segmenter(forearm="keep")


@pytest.fixture(scope="module")
def bundle():
    from synergy.bundle import load_bundle

    return load_bundle("fingerfist")


def frame(truth):
    ob = observe(DepthRenderer(HAND, CAM).render(truth, labels=False).depth, CAM, stride=1, target_points=None,
                 smooth=0, segmenter=SEG)
    return ob, Silhouette(ob.mask, ob.depth, CAM)


def protocol_frames(bundle, rows, slots=None):
    """The experiments' single-frame protocol: fingerfist rows at 0.6–0.9 m (frame ``i`` of the experiment
    at 0.6 + 0.1·(i mod 4) m; ``slots``: the experiment's frame indices, default 0, 1, …), every pixel; the
    start is the truth's global pose with the synergy mean."""
    P = E.fingerfist_postures()
    out = []
    for i, row in zip(range(len(rows)) if slots is None else slots, rows):
        truth = E.sequence(P[row:row + 1], bundle.model.mean_, lead=0, distance=0.6 + 0.3 * (i % 4) / 3)[0]
        start = truth.copy()
        start[~HAND.pose_mask] = bundle.model.mean_
        out.append((truth, start, *frame(truth)))
    return out


def test_fit_many_is_one_fit_and_score_per_start(bundle):
    """Every row of the batch is what :meth:`FitContext.fit` and :func:`score` give for that start, in every
    mode, and ``gn`` is the ICP settings' Gauss-Newton count replaced (not ignored)."""
    tr = FrameTracker(HAND, TrackerSettings(), synergies=bundle)
    ctx = tr.context
    (_, start, ob, sil), = protocol_frames(bundle, [2500])
    sub = thin(ob.points, 400)
    pts, nrm = ob.points[sub], ob.normals[sub]
    rng = np.random.default_rng(0)
    starts = [start + np.r_[np.zeros(6), rng.normal(0.0, 0.15, HAND.n_dofs - 6)] for _ in range(3)]
    for mode, through in (("full", False), ("reduced", False), ("hierarchical", True)):
        T, S = ctx.fit_many(starts, pts, mode, 1, 3, silhouette=sil, normals=nrm, through=through)
        for th0, th, s in zip(starts, T, S):
            ref, corr = ctx.fit(th0, pts, mode, 1, 3, silhouette=sil, normals=nrm, through=through)
            np.testing.assert_array_equal(th, ref)
            assert s == score(ctx, ref, corr, sil)
    T1, _ = ctx.fit_many(starts[:1], pts, "full", 0, 2, silhouette=sil, normals=nrm, gn=1)
    ctx1 = replace(ctx, icp=replace(ctx.icp, gn_iterations=1))
    np.testing.assert_array_equal(T1[0], ctx1.fit(starts[0], pts, "full", 0, 2, silhouette=sil, normals=nrm)[0])
    assert not np.array_equal(T1[0], ctx.fit(starts[0], pts, "full", 0, 2, silhouette=sil, normals=nrm)[0])


def test_batched_fits_are_lone_fits_with_a_wrist_cue_without_silhouette_and_off_the_cloud(bundle):
    """The compiled batch (one call for every start, :func:`tracker._fit_kernels.fit_score_many_entry`) is
    each start's lone :meth:`FitContext.fit` and :func:`score` bit for bit: with the frame's wrist cue in the
    score, without a silhouette (no model→data term), with rigid steps, and for starts so far off that
    some of the cloud's points find no model surface (a pair row a lone fit leaves as it found it: the
    batch must not carry the start before's rows over)."""
    from tracker.wrist import WristCue

    tr = FrameTracker(HAND, TrackerSettings(), synergies=bundle)
    ctx = tr.context
    (_, start, ob, sil), = protocol_frames(bundle, [3100])
    sub = thin(ob.points, 350)
    pts, nrm = ob.points[sub], ob.normals[sub]
    sil.wrist = WristCue(point=pts.mean(0) + [0.0, 0.08, 0.0], pixel=np.zeros(2), direction=np.array([0.0, 1.0, 0.0]),
                         width_m=0.06)
    rng = np.random.default_rng(2)
    starts = [start + np.r_[rng.normal(0.0, 0.01, 6), rng.normal(0.0, 0.3, HAND.n_dofs - 6)] for _ in range(4)]
    far = start.copy()
    far[:3] += [0.0, 0.0, 0.4]  # 40 cm behind the cloud, every pair farther than the rejection distance
    starts.insert(2, far)
    for silhouette, n_rigid in ((sil, 0), (None, 1), (sil, 2)):
        T, S = ctx.fit_many(starts, pts, "full", n_rigid, 3, silhouette=silhouette, normals=nrm, gn=2)
        for th0, th, s in zip(starts, T, S):
            one, c1 = replace(ctx, icp=replace(ctx.icp, gn_iterations=2)).fit(th0, pts, "full", n_rigid, 3,
                                                                               silhouette=silhouette, normals=nrm)
            np.testing.assert_array_equal(th, one)
            assert s == score(ctx, one, c1, silhouette)
        assert not np.all(np.isfinite(S)) or len(np.unique(S)) == len(S)
    # the far start's pairs are all rejected at the start: the test above compared that case
    _, c_far = ctx.fit(far, pts, "full", 0, 0, normals=nrm)
    assert not c_far.valid.any()


def test_fits_in_threads_are_the_fits_one_after_another(bundle):
    """A batch fitted on 3 threads gives every start's θ and score bit for bit, in the starts' order (a
    shared buffer or a shuffled result would not), and a whole start search on 2 threads is the one on
    one; a fit that raises raises out of the threaded batch."""
    tr = FrameTracker(HAND, TrackerSettings(), synergies=bundle)
    ctx = tr.context
    (_, start, ob, sil), = protocol_frames(bundle, [1200])
    sub = thin(ob.points, 300)
    pts, nrm = ob.points[sub], ob.normals[sub]
    rng = np.random.default_rng(1)
    starts = [start + np.r_[rng.normal(0.0, 0.01, 6), rng.normal(0.0, 0.3, HAND.n_dofs - 6)] for _ in range(9)]
    T1, S1 = replace(ctx, threads=1).fit_many(starts, pts, "full", 1, 2, silhouette=sil, normals=nrm)
    T3, S3 = replace(ctx, threads=3).fit_many(starts, pts, "full", 1, 2, silhouette=sil, normals=nrm)
    np.testing.assert_array_equal(T3, T1)
    np.testing.assert_array_equal(S3, S1)
    assert len(np.unique(S1)) == len(S1)  # distinct fits: an order mix-up would show
    one = fit_single_frame(replace(ctx, threads=1), ob.points, InitSettings.cheap(), silhouette=sil, normals=ob.normals)
    two = fit_single_frame(replace(ctx, threads=2), ob.points, InitSettings.cheap(), silhouette=sil, normals=ob.normals)
    np.testing.assert_array_equal(two[0], one[0])
    bad = [starts[0], np.full(HAND.n_dofs, np.nan)]
    with pytest.raises(HandModelError, match="NaN"):
        replace(ctx, threads=2).fit_many(bad, pts, "full", 1, 2, silhouette=sil, normals=nrm)
    cores = available_cores()
    assert search_threads(3) == min(3, cores) and search_threads(0) == min(cores, 4)
    assert search_threads(100) == cores and search_threads(1) == 1


def _search_in(q, ctx, points):
    q.put(fit_single_frame(ctx, points, InitSettings.cheap())[0])


def test_a_process_forked_after_a_threaded_search_searches_too(bundle):
    """A worker forked after a search (``-j`` workers) runs its own searches on threads: the parent's
    pool has no threads in the child (reused, the child waited for ever). The child's θ is the parent's."""
    import multiprocessing as mp
    import queue

    tr = FrameTracker(HAND, TrackerSettings().replace(init=dict(threads=2)), synergies=bundle)
    (_, _, ob, _), = protocol_frames(bundle, [300])
    pts = ob.points[thin(ob.points, 400)]
    want = fit_single_frame(tr.context, pts, InitSettings.cheap())[0]
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_search_in, args=(q, tr.context, pts))
    p.start()
    try:
        got = q.get(timeout=120)
    except queue.Empty:
        pytest.fail("the forked process's search never finished")
    finally:
        p.join(5)
        if p.is_alive():
            p.kill()
    np.testing.assert_array_equal(got, want)


@pytest.mark.slow
def test_threaded_search_with_an_empty_numba_cache_is_right(tmp_path):
    """The first threaded search of a process whose kernels are not compiled yet (an empty numba cache,
    as on a fresh install) gives the θ of a warm one: without the batch's first fit running alone, the
    threads called kernels being compiled and got uninitialised memory (θ ~1e-310) or NaN."""
    import os
    import subprocess
    import sys

    # the frame is rendered and observed here (warm): the child compiles what the search needs, not the renderer
    th = np.zeros(HAND.n_dofs)
    th[2] = 0.7
    np.save(tmp_path / "points.npy", observe(DepthRenderer(HAND, CAM).render(th, labels=False).depth, CAM).points)
    code = ("import numpy as np\n"
            "from handmodel import HandModel\n"
            "from tracker.track import FrameTracker, TrackerSettings\n"
            "from tracker.init import InitSettings, fit_single_frame\n"
            f"hand = HandModel.load(); points = np.load({str(tmp_path / 'points.npy')!r})\n"
            # full DoF, no bundle: the child compiles the threaded fits' kernels, not the subspaces' too
            "tr = FrameTracker(hand, TrackerSettings().replace(scale=dict(hand_scale=1.0), init=dict(threads=2)))\n"
            "print(repr(fit_single_frame(tr.context, points, InitSettings.cheap())[0].tolist()))\n")
    outs = []
    for cache in (tmp_path / "cold", None):
        env = dict(os.environ, **({"NUMBA_CACHE_DIR": str(cache)} if cache else {}))
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=900)
        assert r.returncode == 0, r.stderr
        outs.append(np.array(eval(r.stdout.strip().splitlines()[-1])))
    np.testing.assert_array_equal(outs[0], outs[1])
    assert abs(outs[0][2] - 0.7) < 0.01


@pytest.mark.slow
def test_halving_search_is_accurate_from_the_global_pose(bundle):
    """The report's protocol (hierarchical, 30 ICP iterations): the halving search gets every frame
    under 1° (the issue's floor: mean ≤ 0.5°, each ≤ 2°) and never scores much worse than the
    exhaustive search on the same frame (it would when it dropped the right start)."""
    rows = np.random.default_rng(0).choice(len(E.fingerfist_postures()), 24, replace=False)[:4]  # the report's first
    tr = E._tracker(HAND, bundle, mode="full", init=dict(icp_iterations=30))
    assert tr.settings.init.strategy == "halving"
    ex = replace(tr.settings.init, strategy="exhaustive")
    errs = []
    for truth, start, ob, sil in protocol_frames(bundle, rows):
        th, corr = tr.fit_single_frame(ob.points, theta0=start, mode="hierarchical", silhouette=sil, normals=ob.normals)
        tho, co = fit_single_frame(tr.context, ob.points, ex, theta0=start, mode="hierarchical", silhouette=sil,
                                   normals=ob.normals)
        errs.append(float(posture_error_deg(th, truth, HAND.pose_mask)))
        s, so = score(tr.context, th, corr, sil), score(tr.context, tho, co, sil)
        print(f"\nrow: halving {errs[-1]:.2f} deg (score {s:.2f}), exhaustive "
              f"{posture_error_deg(tho, truth, HAND.pose_mask):.2f} deg (score {so:.2f})")
        assert s < so + 0.5
    assert max(errs) <= 1.0 and np.mean(errs) <= 0.5


@pytest.mark.slow
def test_halving_search_from_no_pose_finds_the_hand(bundle):
    """No pose given: the placements from the cloud, fitted longer before the synergy grid, find an open
    hand and a partly closed one within 1° (the frame that the short fits from the placements alone
    left 20° off is the second)."""
    tr = E._tracker(HAND, bundle, mode="full", init=dict(icp_iterations=30))
    rows = np.random.default_rng(0).choice(len(E.fingerfist_postures()), 24, replace=False)  # the report's rows
    for truth, _, ob, sil in protocol_frames(bundle, rows[[0, 6]], slots=[0, 6]):
        th, _ = tr.fit_single_frame(ob.points, mode="hierarchical", silhouette=sil, normals=ob.normals)
        err = float(posture_error_deg(th, truth, HAND.pose_mask))
        print(f"\nno pose: {err:.2f} deg")
        assert err <= 1.0


def test_batched_finger_search_bends_back_a_finger_flexed_alone(bundle):
    """A ring finger curled alone (PIP-led), the fit holding it straight and the rest right: the
    finger shapes ranked in one batch find the curl; without the ring finger's shapes they cannot."""
    names = list(HAND.dof_names)
    truth = E.sequence(bundle.model.mean_[None], bundle.model.mean_, lead=0, distance=0.7)[0]
    for n in names:
        if "flex" in n and not n.startswith("thumb"):
            truth[names.index(n)] = np.radians(-5.0)
    for n, deg in (("ring1_flex", -45.0), ("ring2_flex", -100.0), ("ring3_flex", -15.0)):
        truth[names.index(n)] = np.radians(deg)
    ob, sil = frame(truth)
    tr = FrameTracker(HAND, TrackerSettings(), synergies=bundle)
    ctx = tr.context
    wrong = truth.copy()
    for n in ("ring1_flex", "ring2_flex", "ring3_flex"):
        wrong[names.index(n)] = np.radians(-5.0)
    st = InitSettings()
    th = finger_search_batched(ctx, wrong, ob.points, st, silhouette=sil, normals=ob.normals)
    err = float(posture_error_deg(th, truth, HAND.pose_mask))
    no_ring = replace(ctx, finger_shapes=[(fi, v) for fi, v in ctx.finger_shapes if not names[fi[0]].startswith("ring")])
    th_n = finger_search_batched(no_ring, wrong, ob.points, st, silhouette=sil, normals=ob.normals)
    err_n = float(posture_error_deg(th_n, truth, HAND.pose_mask))
    print(f"\nring finger alone: from straight {posture_error_deg(wrong, truth, HAND.pose_mask):.1f} deg, batched "
          f"finger search {err:.2f} deg, without the ring finger's shapes {err_n:.2f} deg")
    assert err <= 1.5
    assert err_n > 2.0 * err


@pytest.mark.parametrize("change, word", [({"strategy": "quick"}, "strategy"), ({"halving": {"keep": (0, 3)}}, "keep"),
                                          ({"halving": {"keep": (4,)}}, "keep"), ({"threads": -1}, "threads"),
                                          ({"halving": {"restart_icp": 0}}, "restart_icp"),
                                          ({"halving": {"restart_margin_mm": -1.0}}, "restart_margin_mm"),
                                          ({"halving": {"seeded": {"first": "one"}}}, "seeded first"),
                                          ({"halving": {"seeded": {"restart_points": 0}}}, "restart_points")])
def test_bad_search_settings_are_refused(bundle, change, word):
    tr = FrameTracker(HAND, TrackerSettings(), synergies=bundle)
    st = InitSettings().replace(**change)
    with pytest.raises(TrackerError, match=word) as e:
        fit_single_frame(tr.context, np.zeros((50, 3)) + [0.0, 0.0, 0.7], st)
    assert "\n" not in str(e.value)
