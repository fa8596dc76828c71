"""Hand model: FK against the original code's regression values and an independent FK, mirroring,
validation of model files and parameter vectors."""

import numpy as np
import pytest
import yaml
from hypothesis import given, settings, strategies as st

from conftest import ROOT, shared
from handmodel import HandModel, HandModelError

# FORMAT.md §2.7 (mm), rounded to the digits shown
ROW1 = {"wrist": (-5.574, -4.874, 18.197), "thumb_tip": (-67.614, 46.593, -2.662),
        "index_tip": (-133.640, 7.391, 1.971), "middle_tip": (-133.303, -15.773, -0.349),
        "ring_tip": (-127.806, -34.309, 2.270), "pinky_tip": (-111.374, -53.266, 1.727)}
ROW4724 = {"thumb_tip": (-14.063, 47.170, -58.655), "index_tip": (-14.369, 41.194, -44.245),
           "middle_tip": (-20.691, 36.094, -32.948), "pinky_tip": (-31.241, 52.906, -17.292)}
ROW4724_HAND = {"thumb_tip": (24.46, 64.90, -32.46), "index_tip": (14.74, 54.20, -26.57),
                "middle_tip": (3.96, 45.42, -27.16), "ring_tip": (-6.34, 43.92, -26.53),
                "pinky_tip": (-19.08, 55.59, -24.91)}


def _mm_theta(row):
    th = np.array(row, float)
    th[:3] /= 1000.0  # the file's translations are model millimetres
    return th


def _check(hand, theta, expected, tol):
    kp = hand.keypoints(theta) * 1000.0
    for name, xyz in expected.items():
        got = kp[hand.keypoint_names.index(name)]
        assert np.all(np.abs(got - np.array(xyz)) <= tol), (name, got, xyz)


def test_fk_regression_values(hand, fingerfist):
    _check(hand, _mm_theta(fingerfist[0]), ROW1, 0.0005 + 1e-6)
    _check(hand, _mm_theta(fingerfist[4723]), ROW4724, 0.0005 + 1e-6)
    th = _mm_theta(fingerfist[4723])
    th[:6] = 0
    _check(hand, th, ROW4724_HAND, 0.005 + 1e-6)


def _reference_fk(calib_path, q):
    """FORMAT.md §6 recipe, written independently from default.calib (mm, unscaled file)."""
    lines = calib_path.read_text().splitlines()
    end = lines.index("end_of_skeleton")
    L, par = {}, {}
    order = []
    for ln in lines[:end]:
        f = ln.split()
        L[f[0]] = np.array([float(x) for x in f[2:18]]).reshape(4, 4).T
        par[f[0]] = f[1]
        order.append(f[0])

    def R(axis, a):
        c, s = np.cos(a), np.sin(a)
        m = np.eye(4)
        i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
        m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
        return m

    loc = {k: v.copy() for k, v in L.items()}
    T = np.eye(4)
    T[:3, 3] = q[:3]
    loc["pose"] = T @ R("x", q[3]) @ R("y", q[4]) @ R("z", q[5])
    for f, k in zip(["Thumb", "Index", "Middle", "Ring", "Pinky"], [6, 10, 14, 18, 22]):
        loc[f"Hand{f}1"] = L[f"Hand{f}1"] @ R("x", q[k + 1]) @ R("z", q[k])
        loc[f"Hand{f}2"] = L[f"Hand{f}2"] @ R("x", q[k + 2])
        loc[f"Hand{f}3"] = L[f"Hand{f}3"] @ R("x", q[k + 3])
    G = {}
    for n in order:
        G[n] = loc[n] if par[n] == n else G[par[n]] @ loc[n]
    return {n: G[n][:3, 3] for n in order}


def test_fk_equals_independent_recipe_on_fingerfist(hand, fingerfist):
    calib = shared("htrack_schroeder", "default.calib")
    rows = fingerfist[::97]
    kp = hand.keypoints(np.array([_mm_theta(r) for r in rows])) * 1000.0
    names = {"wrist": "Hand"}
    for f in ["thumb", "index", "middle", "ring", "pinky"]:
        for k in range(1, 5):
            names[f"{f}{k}" if k < 4 else f"{f}_tip"] = f"Hand{f.capitalize()}{k}"
    worst = 0.0
    for r, row in enumerate(rows):
        ref = _reference_fk(calib, row)
        for i, n in enumerate(hand.keypoint_names):
            worst = max(worst, np.abs(kp[r, i] - ref[names[n]]).max())
    assert worst < 1e-6  # mm


def test_api_shapes_and_names(hand):
    assert len(hand.dof_names) == 26 and hand.dof_names[:6] == ["tx", "ty", "tz", "rx", "ry", "rz"]
    assert hand.dof_names[6:10] == ["thumb1_abd", "thumb1_flex", "thumb2_flex", "thumb3_flex"]
    assert hand.dof_names[-4:] == ["pinky1_abd", "pinky1_flex", "pinky2_flex", "pinky3_flex"]
    assert hand.keypoint_names[0] == "wrist" and hand.keypoint_names[4] == "thumb_tip"
    assert hand.keypoint_names[5::4] == ["index1", "middle1", "ring1", "pinky1"]
    assert len(hand.keypoint_names) == 21 and len(hand.joint_names) == 16
    assert hand.limits.shape == (26, 2) and np.all(np.isinf(hand.limits[:6]))
    np.testing.assert_allclose(hand.limits[7], [-1.5, 0.1])   # thumb1_flex, original active set
    np.testing.assert_allclose(hand.limits[10], [-0.5, 0.4])  # index1_abd
    th = np.zeros((2, 3, 26))
    assert hand.keypoints(th).shape == (2, 3, 21, 3)
    assert hand.joint_frames(th).shape == (2, 3, 16, 4, 4)
    # the scale is folded in: index MCP 65 mm distal of the wrist, metres
    np.testing.assert_allclose(hand.keypoints(np.zeros(26))[5] * 1000, [24.35, 64.93, 0], atol=0.01)


def test_translation_in_metres_and_pose_order(hand):
    th = np.zeros(26)
    th[:3] = [0.1, -0.2, 0.7]
    np.testing.assert_allclose(hand.keypoints(th)[0], [0.1, -0.2, 0.7])
    th[3:6] = [0.3, -0.4, 0.5]
    from handmodel.rigid import euler_to_matrix

    R = euler_to_matrix(th[3:6])
    kp0 = hand.keypoints(np.zeros(26))
    np.testing.assert_allclose(hand.keypoints(th), kp0 @ R.T + th[:3], atol=1e-12)


@given(st.integers(0, 5999))
@settings(max_examples=25, deadline=None)
def test_right_hand_is_mirror_image(i):
    ff = np.loadtxt(shared("htrack_schroeder", "fingerfist.txt"), ndmin=2, max_rows=i + 1)[i]
    left, right = HandModel.load(), HandModel.load(right=True)
    assert right.handedness == "right"
    th = _mm_theta(ff)
    th[:6] = 0
    np.testing.assert_allclose(right.keypoints(th), left.keypoints(th) * [-1, 1, 1], atol=1e-12)
    # the global pose is applied unmirrored
    th2 = _mm_theta(ff)
    from handmodel.rigid import euler_to_matrix

    R = euler_to_matrix(th2[3:6])
    np.testing.assert_allclose(right.keypoints(th2), (left.keypoints(th) * [-1, 1, 1]) @ R.T + th2[:3], atol=1e-12)


# ------------------------------------------------------------------ bad input
def _doc():
    return yaml.safe_load((ROOT / "models" / "hands" / "default.yaml").read_text())


def _load_doc(tmp_path, doc, name="bad.yaml"):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(doc))
    return HandModel.load(p)


def test_missing_joint(tmp_path):
    doc = _doc()
    doc["joints"] = [j for j in doc["joints"] if j["name"] != "index2"]
    with pytest.raises(HandModelError, match=r"bad\.yaml.*joints/\d+/parent: unknown joint 'index2'"):
        _load_doc(tmp_path, doc)


def test_cyclic_parents(tmp_path):
    doc = _doc()
    for j in doc["joints"]:
        if j["name"] == "index1":
            j["parent"] = "index3"
    with pytest.raises(HandModelError, match=r"bad\.yaml.*cyclic parents"):
        _load_doc(tmp_path, doc)


def test_unknown_axis(tmp_path):
    doc = _doc()
    doc["dofs"][8]["axis"] = "w"
    with pytest.raises(HandModelError, match=r"bad\.yaml: field dofs/8/axis"):
        _load_doc(tmp_path, doc)


def test_wrong_dof_count(tmp_path):
    doc = _doc()
    doc["n_dofs"] = 25
    with pytest.raises(HandModelError, match=r"bad\.yaml: field dofs: 26 DoFs, expected 25"):
        _load_doc(tmp_path, doc)
    doc = _doc()
    doc["dofs"] = doc["dofs"][:-1]
    with pytest.raises(HandModelError, match=r"unknown DoF 'pinky3_flex'"):
        _load_doc(tmp_path, doc)


def test_other_bad_files(tmp_path):
    with pytest.raises(HandModelError, match="no such hand model"):
        HandModel.load("nonexistent")
    p = tmp_path / "x.yaml"
    p.write_text("joints: [unclosed")
    with pytest.raises(HandModelError, match="x.yaml: not valid YAML"):
        HandModel.load(p)
    doc = _doc()
    del doc["segments"]
    with pytest.raises(HandModelError, match="'segments' is a required property"):
        _load_doc(tmp_path, doc)
    doc = _doc()
    doc["joints"][3]["rest"]["rotation"][0] = [2.0, 0.0, 0.0]
    with pytest.raises(HandModelError, match="joints/3/rest/rotation: not a proper rotation"):
        _load_doc(tmp_path, doc)


def test_reordered_file_gives_same_model(tmp_path, hand):
    doc = _doc()
    j = doc["joints"]
    doc["joints"] = [j[0]] + list(reversed(j[1:]))  # children before parents
    other = _load_doc(tmp_path, doc, "rev.yaml")
    th = np.random.default_rng(3).uniform(-0.5, 0.1, size=26)
    a = dict(zip(other.keypoint_names, other.keypoints(th)))
    b = dict(zip(hand.keypoint_names, hand.keypoints(th)))
    for k in a:
        np.testing.assert_allclose(a[k], b[k], atol=1e-15)


@pytest.mark.parametrize("bad", [np.full(26, np.nan), np.zeros(25), np.zeros((3, 20)), "abc", 3.0])
def test_bad_theta(hand, bad):
    with pytest.raises(HandModelError, match="theta"):
        hand.keypoints(bad)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3), st.floats(0.7, 1.6), st.sampled_from([0, 1]))
def test_fingertip_ends_are_where_the_model_surface_ends(rot, scale, right):
    """Each finger's end lies on the model's surface (the capsule closest points, an independent
    kernel), and 1 mm further along the last bone is 1 mm off the surface at that finger's last
    segment: the outermost point of the finger on its axis, in any global pose and at any size."""
    from tracker.correspond import CapsuleModel

    hand = HandModel.load(right=bool(right)).scaled(scale)
    theta = np.zeros(hand.n_dofs)
    theta[3:6] = rot
    theta[:3] = [0.02, -0.01, 0.5]
    k, ends = hand.keypoints(theta), hand.fingertip_ends(theta)
    tips = hand.tip_indices
    axis = k[tips] - k[hand.parents[tips]]
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    model = CapsuleModel(hand)
    on = model(theta, ends, facing_only=False, reject=1.0)
    assert np.allclose(on.distance, 0.0, atol=1e-6)  # a micrometre: the kernel works in float64 steps
    past = model(theta, ends + 0.001 * axis, facing_only=False, reject=1.0)
    np.testing.assert_allclose(past.distance, 0.001, atol=1e-6)
    assert np.array_equal(past.nodes, hand.parents[tips])


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(-20.0, 20.0, allow_nan=False), min_size=3, max_size=3))
def test_one_rotation_is_the_batched_rotation_to_the_last_bit(angles):
    """euler_to_matrix's path for one rotation (Python floats, the tracker's per-frame tests) gives the
    batched path's matrix bit for bit, and it is a rotation: a sign or a factor swapped in either path
    fails (the safety net's jump test compares their turns with a threshold)."""
    from handmodel.rigid import euler_to_matrix

    a = np.array(angles)
    R = euler_to_matrix(a)
    np.testing.assert_array_equal(R, euler_to_matrix(a[None])[0])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
