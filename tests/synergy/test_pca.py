"""Tests of synergy.pca: exactness, split invariance, published synergies, limits."""
from __future__ import annotations

import pickle
from concurrent.futures import ProcessPoolExecutor

from conftest import SHARED_DATA

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sklearn.decomposition import PCA
from sklearn.utils.estimator_checks import parametrize_with_checks

from handmodel.dofs import POSTURE_DOF_NAMES
from synergy.errors import SynergyError
from synergy.pca import SufficientStats, SynergyModel
from synergy.pca_analysis import heldout_curve, principal_angles

DATA = SHARED_DATA
WEST_HOGAN = DATA / "west_hogan_cyberglove"
FINGERFIST = DATA / "htrack_schroeder" / "fingerfist.txt"


def spectrum_data(n=3000, d=20, seed=0, offset=0.0):
    """Rows with well-separated variances along a random rotation."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(d, d)))
    scales = np.geomspace(1.0, 0.01, d)
    return offset + rng.normal(size=(n, d)) * scales @ Q.T + rng.normal(size=d)


def uneven_chunks(X, cuts=(1, 17, 400, 401, 1500, 2999)):
    bounds = [0, *cuts, len(X)]
    return [X[a:b] for a, b in zip(bounds[:-1], bounds[1:])]


# ----------------------------------------------------------------------------- scikit-learn
@parametrize_with_checks([SynergyModel(), SynergyModel(n_components=2), SynergyModel(n_components=0.9)])
def test_sklearn_estimator_checks(estimator, check):
    check(estimator)


def test_same_as_sklearn_pca():
    X = spectrum_data()
    ours = SynergyModel().fit(X)
    ref = PCA(svd_solver="full").fit(X)
    np.testing.assert_allclose(ours.explained_variance_, ref.explained_variance_, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(ours.explained_variance_ratio_, ref.explained_variance_ratio_, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(ours.mean_, ref.mean_, rtol=0, atol=1e-13)
    cos = np.abs(np.sum(ours.components_ * ref.components_, axis=1))
    np.testing.assert_allclose(cos, 1.0, atol=1e-9)
    signs = np.sign(np.sum(ours.components_ * ref.components_, axis=1))
    np.testing.assert_allclose(ours.transform(X), ref.transform(X) * signs, atol=1e-9)
    np.testing.assert_allclose(ours.inverse_transform(ours.transform(X)), X, atol=1e-9)


def test_n_components_int_float_and_change_without_refit():
    X = spectrum_data()
    m = SynergyModel(n_components=0.9).fit(X)
    cum = np.cumsum(m.all_explained_variance_ratio_)
    k = m.n_components_
    assert cum[k - 1] >= 0.9 > cum[k - 2]
    assert m.components_.shape == (k, 20) and m.transform(X).shape == (len(X), k)
    m3 = m.with_n_components(3)
    assert m3.n_components_ == 3 and m.n_components_ == k
    np.testing.assert_array_equal(m3.components_, m.all_components_[:3])
    assert SynergyModel().fit(X[:5]).n_components_ == 5  # min(n_samples, D), as sklearn
    for bad in (0, 21, 1.0, 1.5, -0.1, True, "3"):
        with pytest.raises(SynergyError):
            SynergyModel(n_components=bad).fit(X)


def test_sign_convention_largest_entry_positive():
    m = SynergyModel().fit(spectrum_data(seed=3))
    C = m.all_components_
    assert np.all(C[np.arange(len(C)), np.argmax(np.abs(C), axis=1)] > 0)
    np.testing.assert_allclose(C @ C.T, np.eye(20), atol=1e-12)


def test_any_dimension():
    for d in (1, 3, 23, 45):
        m = SynergyModel().fit(spectrum_data(n=200, d=d, seed=d))
        assert m.all_components_.shape == (d, d) and m.pc_min_.shape == (d,)


# ----------------------------------------------------------------------------- split invariance
def test_seven_uneven_chunks_equal_one_array():
    X = spectrum_data(offset=0.3)
    whole = SynergyModel().fit(X)
    chunks = uneven_chunks(X)
    assert len(chunks) == 7

    streamed = SynergyModel()
    for c in chunks:
        streamed.partial_fit(c)
    for c in chunks:
        streamed.update_limits(c)

    merged = SufficientStats.merge_all(SufficientStats.from_array(c) for c in chunks[::-1]).finalize()
    for c in chunks:
        merged.update_limits(c)

    for other in (streamed, merged):
        assert other.n_samples_ == whole.n_samples_ == len(X)
        for attr in ("mean_", "components_", "explained_variance_", "explained_variance_ratio_",
                     "pc_min_", "pc_max_", "joint_min_", "joint_max_"):
            np.testing.assert_allclose(getattr(other, attr), getattr(whole, attr), rtol=0, atol=1e-10,
                                       err_msg=attr)
        np.testing.assert_array_equal(other.joint_min_, whole.joint_min_)


def test_partial_fit_resets_limits_until_update():
    X = spectrum_data(n=100, d=4)
    m = SynergyModel().partial_fit(X[:1])
    assert not hasattr(m, "components_")  # one row: nothing to decompose yet
    m.partial_fit(X[1:])
    assert np.all(np.isinf(m.pc_min_))
    m.update_limits(X)
    np.testing.assert_allclose(m.pc_min_, SynergyModel().fit(X).pc_min_, atol=1e-12)


@st.composite
def data_and_split(draw):
    n = draw(st.integers(2, 80))
    d = draw(st.integers(1, 6))
    seed = draw(st.integers(0, 2**32 - 1))
    offset = draw(st.sampled_from([0.0, 1.0, -50.0, 1e4]))
    cuts = sorted(draw(st.lists(st.integers(0, n), max_size=8)))
    rng = np.random.default_rng(seed)
    X = offset + rng.normal(size=(n, d)) * rng.uniform(0.01, 2.0, size=d)
    return X, cuts


@given(data_and_split())
@settings(max_examples=150, deadline=None)
def test_any_split_gives_the_same_statistics(case):
    X, cuts = case
    bounds = [0, *cuts, len(X)]
    parts = [SufficientStats.from_array(X[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]
    merged = SufficientStats.merge_all(parts)
    whole = SufficientStats.from_array(X)
    scale = 1.0 + np.abs(whole.scatter).max()
    assert merged.n == whole.n
    np.testing.assert_allclose(merged.mean, whole.mean, rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(merged.scatter, whole.scatter, rtol=0, atol=1e-10 * scale)
    np.testing.assert_array_equal(merged.min, X.min(axis=0))
    np.testing.assert_array_equal(merged.max, X.max(axis=0))
    ev_m = merged.finalize().all_explained_variance_
    ev_w = SynergyModel().fit(X).all_explained_variance_
    np.testing.assert_allclose(ev_m, ev_w, rtol=0, atol=1e-10 * scale)


@given(st.integers(0, 2**32 - 1), st.integers(2, 40), st.integers(2, 40), st.integers(2, 40))
@settings(max_examples=50, deadline=None)
def test_merge_is_associative_and_commutative(seed, na, nb, nc):
    rng = np.random.default_rng(seed)
    a, b, c = (SufficientStats.from_array(rng.normal(size=(n, 3)) + 7) for n in (na, nb, nc))
    left, right, swapped = a.merge(b).merge(c), a.merge(b.merge(c)), c.merge(a).merge(b)
    for s in (right, swapped):
        np.testing.assert_allclose(s.scatter, left.scatter, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(s.mean, left.mean, rtol=1e-13, atol=1e-13)


def test_large_offset_keeps_precision():
    """A raw Σxxᵀ accumulator loses the spread under a large mean; ours must not."""
    rng = np.random.default_rng(7)
    X = 1e6 + rng.normal(size=(10_000, 3)) * np.array([1e-2, 1e-3, 1e-4])
    XL = X.astype(np.longdouble)
    ref = np.cov(XL - XL.mean(axis=0), rowvar=False)
    sd = np.sqrt(np.diag(ref))

    def rel_err(C):  # error relative to the scale of each entry, sqrt(C_ii C_jj)
        return float(np.max(np.abs(C - ref) / np.outer(sd, sd)))

    for parts in (1, 7, 100):
        stats = SufficientStats.merge_all(SufficientStats.from_array(c) for c in np.array_split(X, parts))
        assert rel_err(stats.covariance()) < 1e-12, parts
    n, s = len(X), X.sum(axis=0)
    naive = (X.T @ X - np.outer(s, s) / n) / (n - 1)
    assert rel_err(naive) > 1e-3  # the test can tell the difference


def test_stats_are_plain_arrays_and_merge_across_processes():
    X = spectrum_data(n=2000, d=5)
    chunks = np.array_split(X, 4)
    with ProcessPoolExecutor(max_workers=2) as pool:
        parts = list(pool.map(SufficientStats.from_array, chunks))
    merged = SufficientStats.merge_all(parts)
    arrays = merged.as_arrays()
    assert all(isinstance(v, np.ndarray) and v.dtype != object for v in arrays.values())
    again = SufficientStats.from_arrays(pickle.loads(pickle.dumps(arrays)))
    np.testing.assert_allclose(again.finalize().all_components_, SynergyModel().fit(X).all_components_,
                               atol=1e-10)


# ----------------------------------------------------------------------------- published synergies
def _west_hogan():
    if not WEST_HOGAN.is_dir():
        pytest.skip(f"West & Hogan CyberGlove data not found at {WEST_HOGAN}")
    from scipy.io import loadmat

    X = loadmat(WEST_HOGAN / "X_R2G_bySubject.mat")["X_R2G_bySubject"]
    V = loadmat(WEST_HOGAN / "V_R2G_bySubject.mat")["V_R2G_bySubject"]
    VAF = loadmat(WEST_HOGAN / "VAF_R2G_bySubject.mat")["VAF_R2G_bySubject"]
    return X, V, VAF


@pytest.mark.parametrize("subject", range(7))
def test_matches_west_hogan_synergies(subject):
    X, V, VAF = _west_hogan()
    m = SynergyModel().fit(X[:, :, subject])
    cos = np.abs(np.sum(m.components_[:3] * V[:, :3, subject].T, axis=1))
    assert np.all(cos >= 0.999), cos
    np.testing.assert_allclose(m.explained_variance_ratio_, VAF[:, subject], rtol=0, atol=1e-3)


# ----------------------------------------------------------------------------- fingerfist
@pytest.fixture(scope="module")
def fingerfist_postures():
    if not FINGERFIST.is_file():
        pytest.skip(f"fingerfist posture data not found at {FINGERFIST}")
    return np.loadtxt(FINGERFIST)[:, 6:]


def test_fingerfist_variance_and_limits(fingerfist_postures):
    X = fingerfist_postures
    assert X.shape == (6000, len(POSTURE_DOF_NAMES))
    m = SynergyModel().fit(X)
    cum = np.cumsum(m.explained_variance_ratio_)
    np.testing.assert_allclose(cum[[0, 2, 5]], [0.713, 0.854, 0.968], atol=1e-3)
    Z = (X - m.mean_) @ m.all_components_.T
    assert np.all(Z >= m.pc_min_) and np.all(Z <= m.pc_max_)
    np.testing.assert_allclose(Z.min(axis=0), m.pc_min_, atol=1e-12)
    np.testing.assert_allclose(Z.max(axis=0), m.pc_max_, atol=1e-12)
    np.testing.assert_array_equal(m.joint_min_, X.min(axis=0))
    np.testing.assert_array_equal(m.joint_max_, X.max(axis=0))


# ----------------------------------------------------------------------------- analysis
def test_reconstruction_error_and_curve():
    X = spectrum_data(n=500, d=6, seed=2)
    m = SynergyModel().fit(X)
    np.testing.assert_allclose(m.reconstruction_error(X, 0), X.std(axis=0), rtol=1e-12)
    np.testing.assert_allclose(m.reconstruction_error(X, 6), 0.0, atol=1e-12)
    curve = m.reconstruction_curve(X)
    assert curve.shape == (7, 6)
    for k in range(7):
        np.testing.assert_allclose(curve[k], m.reconstruction_error(X, k), rtol=1e-10, atol=1e-14)
    ev = m.all_explained_variance_ * (len(X) - 1) / len(X)
    overall = np.sqrt((curve**2).mean(axis=1))
    np.testing.assert_allclose(overall, np.sqrt([ev[k:].sum() / 6 for k in range(7)]), rtol=1e-9, atol=1e-14)
    assert np.all(np.diff(overall) <= 1e-15)


def test_heldout_curve_leave_one_trial_out():
    X = spectrum_data(n=600, d=4, seed=4)
    groups = np.array_split(X, 3)
    rms, method = heldout_curve(groups)
    assert method == "leave-one-trial-out"
    sq = sum(
        (SynergyModel().fit(np.vstack([g for j, g in enumerate(groups) if j != i]))
         .reconstruction_curve(groups[i]) ** 2).sum(axis=1) * len(groups[i])
        for i in range(3)
    )
    np.testing.assert_allclose(rms, np.sqrt(sq / X.size), rtol=1e-9, atol=1e-13)
    rms1, method1 = heldout_curve([X])
    assert method1 == "blocked-5-fold" and rms1.shape == (5,) and rms1[-1] < 1e-12


def test_principal_angles():
    t = 0.3
    a = np.array([[1.0, 0, 0], [0, 1.0, 0]])
    b = np.array([[np.cos(t), 0, np.sin(t)], [0, 1.0, 0]])
    np.testing.assert_allclose(principal_angles(a, b, 1), [t], atol=1e-12)
    np.testing.assert_allclose(principal_angles(a, b, 2), [0.0, t], atol=1e-12)
    m = SynergyModel().fit(spectrum_data(n=300, d=5))
    np.testing.assert_allclose(principal_angles(m, m.all_components_[::-1][::-1], 4), 0.0, atol=1e-7)
    with pytest.raises(SynergyError):
        principal_angles(a, np.eye(4), 1)


def test_bad_input_raises_synergy_error():
    with pytest.raises(SynergyError, match="NaN"):
        SynergyModel().fit(np.array([[0.0, np.nan], [1.0, 2.0]]))
    with pytest.raises(SynergyError, match="1 sample"):
        SynergyModel().fit(np.zeros((1, 3)))
    m = SynergyModel().fit(spectrum_data(n=50, d=3))
    with pytest.raises(SynergyError):
        m.transform(np.zeros((2, 4)))
    with pytest.raises(SynergyError):
        SufficientStats.empty(2).merge(SufficientStats.empty(3))


def test_posture_is_mean_plus_scaled_components():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(300, 6)) @ np.diag([3.0, 2.0, 1.0, 0.5, 0.2, 0.1]) + 0.4
    m = SynergyModel(n_components=2).fit(X)
    sd = np.sqrt(m.all_explained_variance_)
    a = np.array([1.5, -0.5, 2.0])
    want = m.mean_ + (a * sd[:3]) @ m.all_components_[:3]  # beyond n_components_: any PC counts
    np.testing.assert_allclose(m.posture(a), want, atol=1e-12)
    grid = rng.normal(size=(4, 5, 2))
    assert m.posture(grid).shape == (4, 5, 6)
    np.testing.assert_allclose(m.posture(grid)[2, 3], m.posture(grid[2, 3]), atol=1e-12)
    np.testing.assert_array_equal(m.posture(np.zeros(0)), m.mean_)
    # clipping keeps each aᵢσᵢ within the PC limits, and leaves values inside them alone
    z = (m.posture([[40.0, -40.0, 0.3]], clip=True) - m.mean_) @ m.all_components_[:3].T
    np.testing.assert_allclose(z[0], [m.pc_max_[0], m.pc_min_[1], 0.3 * sd[2]], atol=1e-12)
    with pytest.raises(SynergyError, match="posture"):
        m.posture(np.zeros(7))
