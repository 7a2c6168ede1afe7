"""Mesh ray casting speed: Open3D's RaycastingScene vs embreex, side by side (render/raycast.py).

Per backend and thread count: BVH build time (scene + first query, which commits it), first-hit
throughput (rays/s) and multiple-hit throughput (`cast_all`, up to `--max-hits` per ray). The
mesh is spot subdivided to ~94k triangles (an icosphere of 82k where the data is missing), in run
units (radius 0.8). Two ray sets of `--rays` each: "camera", the pixels of 4 square views on a
ring at distance ~3.2 (coherent rays, as rendering casts them), and "random", rays from a sphere
of radius 3 towards random points of the mesh's bounding box (incoherent, the worst case).

    .venv/bin/python bench/bench_raycast.py [--rays 1000000] [--max-hits 4] [--repeats 4]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see sine_cli.py

import argparse
import time
from pathlib import Path

import numpy as np
import trimesh

from render.cameras import Camera, look_at
from render.raycast import DEFAULT_BACKEND, MeshRaycaster, mesh_arrays

SPOT = Path(__file__).resolve().parents[1].parent / "shared/data/meshes/spot/spot_triangulated.obj"


def bench_mesh() -> tuple[str, np.ndarray, np.ndarray]:
    if SPOT.is_file():
        mesh = trimesh.load(str(SPOT), process=False, force="mesh")
        mesh = mesh.subdivide().subdivide()
        name = "spot x2 subdivided"
    else:
        mesh, name = trimesh.creation.icosphere(subdivisions=6), "icosphere(6)"
    v, f = mesh_arrays(mesh)
    v = 0.8 * (v - v.mean(0)) / np.linalg.norm(v - v.mean(0), axis=1).max()  # run units
    return name, v, f


def random_rays(vertices: np.ndarray, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o = 3.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
    target = rng.uniform(vertices.min(0), vertices.max(0), (n, 3))
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o.astype(np.float32), d.astype(np.float32)


def camera_rays(n: int, views: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The pixel rays of `views` square cameras on a ring (about n rays in all)."""
    side = max(1, round(np.sqrt(n / views)))
    rays = []
    for a in np.linspace(0, 2 * np.pi, views, endpoint=False):
        eye = [3 * np.cos(a), 3 * np.sin(a), 1.0]
        c2w = look_at(eye, [0.0, 0.0, 0.0])
        rays.append(Camera(side, side, 2.2 * side, 2.2 * side, side / 2, side / 2, c2w).rays())
    return tuple(np.ascontiguousarray(np.concatenate(r)) for r in zip(*rays, strict=True))


def timed(fn) -> tuple[float, object]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rays", type=int, default=1_000_000, help="rays per first-hit batch")
    parser.add_argument("--max-hits", type=int, default=4, help="hits per ray for cast_all")
    parser.add_argument(
        "--repeats", type=int, default=4, help="timed repeats, backends interleaved (fastest kept)"
    )
    args = parser.parse_args()

    name, v, f = bench_mesh()
    ray_sets = {"camera": camera_rays(args.rays), "random": random_rays(v, args.rays)}
    o1, d1 = ray_sets["camera"][0][:1], ray_sets["camera"][1][:1]
    cores = len(os.sched_getaffinity(0))
    print(f"mesh: {name}, {len(v)} vertices, {len(f)} triangles; {cores} cores")
    print(f"rays: {', '.join(f'{k} {len(r[0])}' for k, r in ray_sets.items())}")
    print(f"load average before: {os.getloadavg()[0]:.1f}; default backend: {DEFAULT_BACKEND}")
    print()
    print("| backend | threads | BVH build ms | first hit, camera Mrays/s |"
          " first hit, random Mrays/s |"
          f" cast_all (<= {args.max_hits}), camera Mrays/s | cast_all, random Mrays/s |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|")
    results = {}
    for threads in (1, 0):  # 0: every core
        casters = {
            b: MeshRaycaster((v, f), backend=b, threads=threads) for b in ("open3d", "embree")
        }
        best: dict[tuple[str, str], float] = {}
        for _ in range(args.repeats):  # backends interleaved: both see the same background load
            for backend, caster in casters.items():

                def build(caster=caster):
                    caster.update_vertices(v)
                    caster.cast(o1, d1)  # the first query commits the scene

                runs = {"build": build}
                for kind, (o, d) in ray_sets.items():
                    runs["first", kind] = lambda c=caster, o=o, d=d: c.cast(o, d)
                    runs["all", kind] = lambda c=caster, o=o, d=d: c.cast_all(o, d, args.max_hits)
                for key, fn in runs.items():
                    seconds, results[backend, key] = timed(fn)
                    best[backend, key] = min(best.get((backend, key), np.inf), seconds)
        for backend in casters:
            rate = {
                key: len(ray_sets[key[1]][0]) / best[backend, key] / 1e6
                for key in runs
                if key != "build"
            }
            print(
                f"| {backend} | {threads or f'all ({cores})'} | {1e3 * best[backend, 'build']:.1f}"
                f" | {rate['first', 'camera']:.2f} | {rate['first', 'random']:.2f}"
                f" | {rate['all', 'camera']:.2f} | {rate['all', 'random']:.2f} |"
            )
    print()
    for kind in ray_sets:  # the same answers from both backends
        a, b = results["open3d", ("first", kind)], results["embree", ("first", kind)]
        ma, mb = results["open3d", ("all", kind)], results["embree", ("all", kind)]
        print(
            f"{kind}: hit rate {a.hit.mean():.3f}, hits/ray {ma.count.mean():.2f};"
            f" backends agree on {100 * (a.triangle == b.triangle).mean():.3f} % of first"
            f" triangles, {100 * (ma.count == mb.count).mean():.3f} % of hit counts"
        )
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
