"""Synthetic depth rendering throughput on one core: our numba z-buffer vs ray casting, same scene, same run.

Scene: the default hand mesh (8.7k triangles) opening and closing at 0.6–0.9 m in front of a
640×480 Kinect-v1 camera. The peer is trimesh's ray casting when its acceleration structure is
installed (``rtree``, or ``embreex``), otherwise an independent numpy Möller–Trumbore ray caster
with tile binning (tracker.sim.raycast, which tests/tracker/test_synthetic.py checks the renderer against); the table says which.

Run: .venv/bin/python benchmarks/bench_render.py [--frames 300] [--peer-frames 5]
"""
from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from handmodel import HandModel  # noqa: E402
from tracker.sim.motions import GlobalPath, OPEN, FIST, Motion, keyframes, with_path  # noqa: E402
from tracker.sim.noise import NoiseModel  # noqa: E402
from tracker.sim.raycast import raycast  # noqa: E402
from tracker.sim.render import DepthRenderer  # noqa: E402


def camera():
    try:
        from tracker.io.cameras import preset

        return preset("kinect1")
    except ImportError:
        from types import SimpleNamespace

        return SimpleNamespace(width=640, height=480, fx=580.0, fy=580.0, cx=319.5, cy=239.5, name="kinect1")


def trimesh_raycast(V, F, cam):
    """trimesh's ray casting (needs rtree or embreex); ``None`` when unavailable."""
    import trimesh

    mesh = trimesh.Trimesh(V, F, process=False)
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector  # noqa: F401

        intersector = trimesh.ray.ray_pyembree.RayMeshIntersector(mesh)
    except Exception:
        try:
            import rtree  # noqa: F401
        except ImportError:
            return None
        intersector = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    d = np.stack([(u.ravel() - cam.cx) / cam.fx, (v.ravel() - cam.cy) / cam.fy, np.ones(u.size)], 1)
    loc, ray, _ = intersector.intersects_location(np.zeros_like(d), d, multiple_hits=False)
    depth = np.full(u.size, np.nan)
    depth[ray] = loc[:, 2]
    return depth.reshape(cam.height, cam.width)


def per_frame(fn, items, repeat=3):
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        for x in items:
            fn(x)
        best = min(best, (time.perf_counter() - t) / len(items))
    return best


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--peer-frames", type=int, default=5, help="frames for the (slow) ray-casting peer")
    args = ap.parse_args()
    hand = HandModel.load()
    cam = camera()
    fps = 30.0
    path = GlobalPath(centre=(0.0, 0.0, 0.75), amplitude=(0.04, 0.03, 0.15))  # hand centre at 0.60–0.90 m
    motion = Motion("bench", with_path(keyframes([OPEN, FIST], args.frames, fps, 2.0), hand, fps, path), fps)
    thetas = list(motion.theta)
    r = DepthRenderer(hand, cam)
    mesh = r._p.mesh
    posed = [r.pose(th) for th in thetas]
    r.render(thetas[0], color=True, incidence=True)  # compile / load the numba cache
    noise = NoiseModel.preset("kinect1")
    depths = [r.render(th).depth for th in thetas[::max(len(thetas) // 50, 1)]]
    z = np.array([np.nanmedian(d) for d in depths])

    rows = []
    t_lbs = per_frame(r.pose, thetas)
    t_lbs_np = per_frame(mesh.pose, thetas[:50])
    t_ras = per_frame(r.rasterize, posed)
    t_full = per_frame(lambda th: r.render(th, labels=True), thetas)
    t_col = per_frame(lambda th: r.render(th, color=True), thetas[:100], repeat=1)
    rng = np.random.default_rng(0)
    t_noise = per_frame(lambda d: noise.apply(d, cam, rng), depths, repeat=1)
    rows += [("LBS (numba, sparse weights)", t_lbs), ("LBS (numpy SkinnedMesh.pose)", t_lbs_np),
             ("z-buffer raster only", t_ras), ("render = LBS + raster + labels", t_full),
             ("render + colour image", t_col), ("kinect1 noise on a rendered frame", t_noise)]

    P = min(args.peer_frames, len(thetas))
    peer_name = "peer: trimesh ray casting"
    peer = trimesh_raycast(posed[0], mesh.faces, cam)
    if peer is None:
        peer_name = "peer: numpy Möller–Trumbore ray caster (*)"
        cast = lambda i: raycast(posed[i], mesh.faces, cam)[0]  # noqa: E731
    else:
        cast = lambda i: trimesh_raycast(posed[i], mesh.faces, cam)  # noqa: E731
    peer_idx = list(np.linspace(0, len(thetas) - 1, P).astype(int))
    t_peer = per_frame(cast, peer_idx, repeat=1)
    rows.append((peer_name, t_peer))
    diff = 0.0
    for i in peer_idx:
        a, b = r.rasterize(posed[i])[0], cast(i)
        both = np.isfinite(a) & np.isfinite(b)
        diff = max(diff, float(np.abs(a[both] - b[both]).max()))

    print(f"\nSynthetic depth rendering, {cam.width}×{cam.height}, {len(mesh.faces)} triangles, hand at "
          f"{z.min():.2f}–{z.max():.2f} m (median depth per frame), NUMBA_NUM_THREADS="
          f"{os.environ.get('NUMBA_NUM_THREADS')}, {len(thetas)} frames ({P} for the peer)\n")
    w = max(len(n) for n, _ in rows)
    print(f"{'stage':<{w}}  {'ms/frame':>9}  {'frames/s':>9}")
    for n, t in rows:
        print(f"{n:<{w}}  {1e3 * t:9.3f}  {1 / t:9.0f}")
    print(f"\nrenderer vs peer: {t_peer / t_ras:.0f}× faster (raster), {t_peer / t_full:.0f}× (full render); "
          f"max depth difference {1e3 * diff:.4f} mm")
    if peer_name.endswith("(*)"):
        print("(*) trimesh's ray casting needs rtree or embreex, which are not installed; the peer is the "
              "independent numpy ray caster tracker.sim.raycast (the tests' reference)")
    floor = 200.0
    print(f"floor ≥ {floor:.0f} frames/s with LBS: {'met' if 1 / t_full >= floor else 'MISSED'} "
          f"({1 / t_full:.0f} frames/s)")


if __name__ == "__main__":
    main()
