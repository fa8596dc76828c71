"""Geometry: capsule closest points vs a brute-force reference, skinned mesh, export."""
import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull

from handmodel import HandModel, HandModelError
from handmodel.geometry import closest_points, fibonacci_sphere, surface_samples

HAND = HandModel.load()


def _closest_on_triangles(p, tri):
    """Brute force: the closest point to ``p`` on any of the triangles ``tri (T,3,3)`` (Ericson's
    region test, vectorised over triangles)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp_ = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp_), np.einsum("ij,ij->i", ac, cp_)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v, w = vb * denom, vc * denom
        res = a + ab * v[:, None] + ac * w[:, None]
        # edges and vertices
        m = (d1 <= 0) & (d2 <= 0)
        res[m] = a[m]
        m = (d3 >= 0) & (d4 <= d3)
        res[m] = b[m]
        m = (d6 >= 0) & (d5 <= d6)
        res[m] = c[m]
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        t = d1 / (d1 - d3)
        res[m] = a[m] + t[m, None] * ab[m]
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        t = d2 / (d2 - d6)
        res[m] = a[m] + t[m, None] * ac[m]
        m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        res[m] = b[m] + t[m, None] * (c[m] - b[m])
    d = np.linalg.norm(res - p, axis=1)
    k = np.nanargmin(d)
    return res[k], d[k]


def _reference_hulls(hand, theta, n=8000):
    """Each primitive as the convex hull of dense samples on its defining spheres (independent of
    the closed-form kernel): a capsule is conv(two spheres), a slab conv(four corner spheres)."""
    G = hand.node_frames(theta)
    dirs = fibonacci_sphere(n)
    hulls = []
    for seg in hand.segments:
        if seg.shape == "capsule":
            centres = np.array([[0, 0, 0], [0, seg.length, 0]], float)
            radii = np.array(seg.radius)
        else:
            w0, w1, t = seg.radius[0] - seg.half_thickness, seg.radius[1] - seg.half_thickness, seg.half_thickness
            centres = np.array([[-w0, 0, 0], [w0, 0, 0], [w1, seg.length, 0], [-w1, seg.length, 0]])
            radii = np.full(4, t)
        pts = (centres[:, None, :] + radii[:, None, None] * dirs[None]).reshape(-1, 3)
        hull = ConvexHull(pts)
        Gj = G[seg.joint]
        tri = pts[hull.simplices] @ Gj[:3, :3].T + Gj[:3, 3]
        hulls.append((tri, hull.equations[:, :3] @ Gj[:3, :3].T, hull.equations[:, 3] - hull.equations[:, :3] @ Gj[:3, :3].T @ Gj[:3, 3]))
    return hulls


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_closest_points_match_brute_force(seed):
    rng = np.random.default_rng(seed)
    th = HAND.zero()
    th[6:] = rng.uniform(HAND.limits[6:, 0], HAND.limits[6:, 1])
    th[2] = 0.5
    pts, _, _ = surface_samples(HAND, th, spacing=0.004, seed=seed)
    q = pts[rng.choice(len(pts), 150)] + rng.normal(0, 0.006, (150, 3))
    cp, seg, nrm, dist = closest_points(HAND, th, q)
    hulls = _reference_hulls(HAND, th)
    best_d = np.full(len(q), np.inf)
    best_p = np.zeros((len(q), 3))
    inside_any = np.zeros(len(q), bool)
    for tri, nrm_h, off_h in hulls:
        inside_any |= np.all(q @ nrm_h.T + off_h <= 0, axis=1)
    # each point visits the hulls nearest its bounding box first and stops at a box farther than the best
    # triangle found: a box is never nearer than what it holds, so the result is the exhaustive one's
    lo = np.array([tri.reshape(-1, 3).min(0) for tri, _, _ in hulls])
    hi = np.array([tri.reshape(-1, 3).max(0) for tri, _, _ in hulls])
    for i, p in enumerate(q):
        box_d = np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0), axis=1)
        for h in np.argsort(box_d):
            if box_d[h] >= best_d[i]:
                break
            cp_i, d_i = _closest_on_triangles(p, hulls[h][0])
            if d_i < best_d[i]:
                best_d[i], best_p[i] = d_i, cp_i
    out = ~inside_any  # outside every primitive: the closest point of the union is unique
    assert out.sum() > 60
    np.testing.assert_allclose(dist[out], best_d[out], atol=1e-4)         # 0.1 mm
    assert np.linalg.norm(cp[out] - best_p[out], axis=1).max() < 1e-4
    # the normal points from the surface towards the query point
    v = q[out] - cp[out]
    cos = np.einsum("ij,ij->i", v / np.linalg.norm(v, axis=1, keepdims=True), nrm[out])
    assert np.all(cos > 0.999)
    assert np.all(dist[inside_any] < 1e-6)


def test_surface_samples_lie_on_surface():
    from handmodel._geometry_kernels import closest_local

    th = HAND.zero()
    th[12] = -1.0
    pts, seg, nrm = surface_samples(HAND, th, spacing=0.003)
    _, _, _, d = closest_points(HAND, th, pts)
    assert np.all(d < 1e-7)  # never outside the model
    G = HAND.node_frames(th)
    loc = np.empty(7)
    agree = []
    for p, s_i, n in zip(pts[::7], seg[::7], nrm[::7]):
        sg = HAND.segments[s_i]
        Gj = G[sg.joint]
        q = (p - Gj[:3, 3]) @ Gj[:3, :3]
        closest_local(0 if sg.shape == "capsule" else 1, sg.length, sg.radius[0], sg.radius[1], sg.half_thickness, q, loc)
        assert abs(loc[6]) < 1e-7  # on its own primitive (0.1 µm)
        agree.append(np.dot(Gj[:3, :3] @ loc[3:6], n) > 0.999)
    assert np.mean(agree) > 0.99  # normals agree except on creases (slab rim, capsule poles)


def test_mesh_rest_pose_and_normals(tmp_path):
    mesh = HAND.mesh()
    assert 8_000 <= len(mesh.faces) <= 14_000
    np.testing.assert_allclose(mesh.weights.sum(1), 1.0)
    np.testing.assert_allclose(mesh.pose(HAND.zero()), mesh.vertices, atol=1e-12)
    # outward normals: each face's normal points away from the axis of the segment it was built on
    fn = mesh.face_normals()
    tri = mesh.vertices[mesh.faces]
    centre = tri.mean(1)
    seg = mesh.segment[mesh.faces[:, 0]]
    G0 = HAND.node_frames(HAND.zero())
    ok = []
    for s_i, s in enumerate(HAND.segments):
        sel = seg == s_i
        Gj = G0[s.joint]
        loc = (centre[sel] - Gj[:3, 3]) @ Gj[:3, :3]
        axis_pt = np.zeros_like(loc)
        axis_pt[:, 1] = np.clip(loc[:, 1], 0, s.length)
        if s.shape == "slab":
            w = np.interp(axis_pt[:, 1], [0, s.length], [s.radius[0] - s.half_thickness, s.radius[1] - s.half_thickness])
            axis_pt[:, 0] = np.clip(loc[:, 0], -w, w)
        out = (loc - axis_pt) @ Gj[:3, :3].T
        ok.append(np.einsum("ij,ij->i", out, fn[sel]) > 0)
    ok = np.concatenate(ok)
    assert ok.mean() > 0.999
    assert mesh.to_trimesh().volume > 0


def test_lbs_follows_the_skeleton():
    mesh = HAND.mesh()
    th = HAND.zero()
    th[:3] = [0.1, 0.0, 0.6]
    th[3:6] = [0.2, -0.3, 0.4]
    th[12] = -1.2  # index PIP
    V = mesh.pose(th)
    # vertices skinned fully to one joint move rigidly with it
    G, G0 = HAND.node_frames(th), HAND.node_frames(HAND.zero())
    for j in [HAND.node_index("index2"), HAND.node_index("wrist"), HAND.node_index("thumb3")]:
        rigid = mesh.weights[:, j] == 1.0
        assert rigid.sum() > 50
        B = G[j] @ np.linalg.inv(G0[j])
        np.testing.assert_allclose(V[rigid], mesh.vertices[rigid] @ B[:3, :3].T + B[:3, 3], atol=1e-12)
    # batched posing
    assert mesh.pose(np.stack([th, th])).shape == (2,) + V.shape


@pytest.mark.parametrize("fmt", ["glb", "ply", "obj"])
def test_export_loads_back(tmp_path, fmt):
    mesh = HAND.mesh()
    th = HAND.zero()
    th[16] = -1.0
    p = mesh.export(tmp_path / f"hand.{fmt}", th)
    m = trimesh.load(p, force="mesh", process=False)
    assert len(m.faces) == len(mesh.faces)
    np.testing.assert_allclose(np.sort(m.vertices, 0), np.sort(mesh.pose(th), 0), atol=1e-6)
    with pytest.raises(HandModelError, match="unsupported mesh format"):
        mesh.export(tmp_path / "hand.xyz")


@pytest.mark.parametrize("right,scale", [(False, 1.0), (True, 1.3)])
def test_wrist_crease_is_the_palms_end_towards_the_forearm(right, scale):
    """The crease point lies on the model's surface (closest-point distance 0) and no palm surface
    sample reaches further back along the hand's axis; it sits on that axis (the palm's mid-plane,
    centred across), whatever the pose, handedness and size."""
    hand = HandModel.load(right=right).scaled(scale)
    rng = np.random.default_rng(3)
    th = hand.zero()
    th[:3] = rng.normal(0, 0.1, 3)
    th[3:6] = rng.uniform(-np.pi, np.pi, 3)
    crease = hand.wrist_crease(th)
    _, _, _, d = closest_points(hand, th, crease[None])
    assert abs(d[0]) < 1e-7
    pts, seg, _ = surface_samples(hand, th, spacing=0.002)
    G = hand.node_frames(th)[0]
    local = (pts[seg == 0] - G[:3, 3]) @ G[:3, :3]
    c = (crease - G[:3, 3]) @ G[:3, :3]
    assert c[1] <= local[:, 1].min() + 1e-9 and c[1] >= local[:, 1].min() - 3e-4  # 0.3 mm: the samples' spacing
    assert abs(c[0]) < 1e-12 and abs(c[2]) < 1e-12
    assert np.isclose(-c[1], hand.segments[0].half_thickness)


def test_surface_samples_drawn_once_per_hand_shape_are_the_draw_itself():
    """The samples in each segment's frame are kept per hand shape, spacing and seed and posed per call:
    a second call, calls for other hands in between, and a fresh draw (the cache bypassed) give the same
    arrays to the bit, each hand its own; posing leaves the kept samples untouched."""
    from handmodel.geometry import _local_samples, _segments_key
    from tracker.sim.hands import HandShape

    base = HandModel.load()
    small, large = HandShape(0.8).apply(base), HandShape(1.3).apply(base)
    rng = np.random.default_rng(4)
    th = np.zeros(base.n_dofs)
    th[~base.pose_mask] = rng.uniform(-0.3, 1.0, int((~base.pose_mask).sum()))
    th[3:6] = rng.uniform(-1.0, 1.0, 3)
    first = surface_samples(small, th, spacing=0.004)
    other = surface_samples(large, th, spacing=0.004)
    again = surface_samples(small, th, spacing=0.004)
    fresh = _local_samples.__wrapped__(_segments_key(small), 0.004, 0)
    G = small.node_frames(th)
    P = np.concatenate([pts @ G[j][:3, :3].T + G[j][:3, 3] for j, pts, _ in fresh])
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(first[0], P)
    assert len(other[0]) != len(first[0])  # a larger hand has more samples at one spacing, not the small one's
    first[0][:] = 0.0  # the caller's arrays are its own
    np.testing.assert_array_equal(surface_samples(small, th, spacing=0.004)[0], P)
    assert not _local_samples(_segments_key(small), 0.004, 0)[0][1].flags.writeable
