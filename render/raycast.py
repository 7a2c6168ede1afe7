"""The one mesh ray caster of the product: first hits of ray batches or whole cameras, and every
hit along a ray, over Open3D's `RaycastingScene` or embreex (both Embree underneath).

- `MeshRaycaster(mesh, backend)`: built from vertices [V, 3] and triangles [T, 3] (an Open3D
  legacy / tensor mesh, a trimesh or a `(vertices, triangles)` tuple); `update_vertices` rebuilds
  the BVH for moved vertices (same triangles).
- `cast(origins, dirs)` -> `MeshHits`: distance `t` (inf where missed), hit mask, triangle ids,
  barycentrics, unit geometric normals. numpy rays give numpy arrays; torch rays give tensors on
  the rays' device.
- `cast_camera(cam)` / `depth(cam)` / `silhouette(cam)`: one ray per pixel centre of a
  `render.cameras.Camera` (hits, camera-z depth [H, W], silhouette [H, W] bool); only the
  pixels where the mesh's image can lie are cast (`Camera.pixel_window`).
- `cast_all(origins, dirs, max_hits)` -> `MultiHits`: the first `max_hits` hits of each ray in
  order (a band around thin parts, entering and leaving a surface).

Backends: "open3d" (`RaycastingScene`, TBB-parallel; multiple hits from `list_intersections`)
and "embree" (embreex, rays split over threads; multiple hits by re-casting from just past each
hit). "auto" takes `DEFAULT_BACKEND`, chosen by bench/bench_raycast.py (bench/RESULTS.md, Ray
casting), or Open3D when embreex is not installed. Both give the same hits (tests/test_raycast.py).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, fields

import numpy as np
import open3d as o3d
import torch

BACKENDS = ("auto", "open3d", "embree")
# Measured (bench/RESULTS.md, Ray casting): first hits equally fast, Open3D builds the BVH 2.5x
# faster (update_vertices every editing step), embree's cast_all is 1.3-1.4x faster.
DEFAULT_BACKEND = "open3d"
_EMBREE_MIN_CHUNK = 16384  # rays per thread below which splitting the batch does not pay


def mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    """Open3D legacy / tensor mesh, trimesh, or (vertices, triangles) -> float32, uint32 arrays."""
    if isinstance(mesh, tuple):
        v, f = mesh
    elif isinstance(mesh, o3d.geometry.TriangleMesh):
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    elif isinstance(mesh, o3d.t.geometry.TriangleMesh):
        v, f = mesh.vertex.positions.numpy(), mesh.triangle.indices.numpy()
    else:  # trimesh
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    v = np.ascontiguousarray(v, np.float32).reshape(-1, 3)
    return v, np.ascontiguousarray(f, np.uint32).reshape(-1, 3)


def face_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit normals [T, 3] float32 of the triangles by winding, (v1 - v0) x (v2 - v0); 0 if flat."""
    v = vertices.astype(np.float64)
    a, b, c = v[triangles[:, 0]], v[triangles[:, 1]], v[triangles[:, 2]]
    n = np.cross(b - a, c - a)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 0, n / np.maximum(length, 1e-300), 0.0).astype(np.float32)


@dataclass
class MeshHits:
    """First hit per ray (numpy arrays, or torch tensors when the rays were torch)."""

    t: np.ndarray  # [R] float32 distance along the ray (in units of |dir|), inf where missed
    triangle: np.ndarray  # [R] int64 triangle id, -1 where missed
    uv: np.ndarray  # [R, 2] float32 barycentric weights of the triangle's vertices 1 and 2
    normal: np.ndarray  # [R, 3] float32 unit geometric normal (winding order), 0 where missed

    @property
    def hit(self):  # [R] bool
        return self.triangle >= 0

    @property
    def barycentrics(self):  # [R, 3] weights of vertices 0, 1, 2
        w0 = 1.0 - self.uv[:, :1] - self.uv[:, 1:]
        cat = torch.cat if isinstance(self.uv, torch.Tensor) else np.concatenate
        return cat([w0, self.uv], 1)

    def to_torch(self, device) -> MeshHits:
        return MeshHits(*(torch.from_numpy(getattr(self, f.name)).to(device) for f in fields(self)))


@dataclass
class MultiHits:
    """The first K hits per ray, nearest first (numpy, or torch when the rays were torch)."""

    t: np.ndarray  # [R, K] float32, inf after the last hit
    triangle: np.ndarray  # [R, K] int64, -1 after the last hit

    @property
    def count(self):  # [R] number of hits found (<= K)
        return (self.triangle >= 0).sum(1)

    def to_torch(self, device) -> MultiHits:
        return MultiHits(
            torch.from_numpy(self.t).to(device), torch.from_numpy(self.triangle).to(device)
        )


def rays_numpy(origins, dirs) -> tuple[np.ndarray, np.ndarray]:
    """origins, dirs (numpy or torch, [R, 3]) -> contiguous float32 numpy arrays."""
    out = []
    for x in (origins, dirs):
        if isinstance(x, torch.Tensor):
            x = x.detach().to("cpu", torch.float32).numpy()
        out.append(np.ascontiguousarray(np.asarray(x, np.float32).reshape(-1, 3)))
    return out[0], out[1]


def resolve_backend(backend: str) -> str:
    """'auto' -> DEFAULT_BACKEND (Open3D when embreex is missing); checks the name."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown ray-casting backend {backend!r}; use one of {BACKENDS}")
    if backend == "auto":
        backend = DEFAULT_BACKEND
        if backend == "embree":
            try:
                import embreex  # noqa: F401
            except ImportError:
                backend = "open3d"
    return backend


class MeshRaycaster:
    """Ray casting against one triangle mesh; `threads` = 0: every core."""

    def __init__(self, mesh, backend: str = "auto", threads: int = 0):
        self.backend = resolve_backend(backend)
        self.threads = int(threads)  # 0: Open3D's automatic count; every usable core for embree
        vertices, self.triangles = mesh_arrays(mesh)  # [V, 3] float32, [T, 3] uint32
        self.update_vertices(vertices)

    def update_vertices(self, vertices) -> None:
        """Rebuilds the BVH from moved vertices [V, 3] (same triangles)."""
        self.vertices = np.ascontiguousarray(np.asarray(vertices, np.float32).reshape(-1, 3))
        self._normals = face_normals(self.vertices, self.triangles)  # [T, 3]
        self._scene = None
        if len(self.triangles) == 0:
            return
        if self.backend == "open3d":
            self._scene = o3d.t.geometry.RaycastingScene()
            self._scene.add_triangles(
                o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles)
            )
        else:
            from embreex import mesh_construction, rtcore_scene

            self._scene = rtcore_scene.EmbreeScene(robust=True)
            mesh_construction.TriangleMesh(
                self._scene, self.vertices, self.triangles.astype(np.int32)
            )

    # ---- first hit ------------------------------------------------------------------------
    def cast(self, origins, dirs) -> MeshHits:
        """Rays origins [R, 3], dirs [R, 3] (numpy or torch) -> first hits."""
        o, d = rays_numpy(origins, dirs)
        t, tri, uv = self._first(o, d)
        normal = np.zeros((len(t), 3), np.float32)
        if len(self._normals):
            normal = self._normals[np.maximum(tri, 0)]  # [R, 3]
            normal[tri < 0] = 0.0
        hits = MeshHits(t, tri, uv, normal)
        return hits.to_torch(origins.device) if isinstance(origins, torch.Tensor) else hits

    def cast_camera(self, cam) -> MeshHits:
        """One ray per pixel centre of `cam` (row-major, `Camera.rays`) -> hits [H*W]. Only
        the pixels of the mesh's `Camera.pixel_window` are cast; the others miss."""
        window = cam.pixel_window(self.vertices)
        if window is None:
            return self.cast(*cam.rays())
        chosen, centres = cam.window_pixels(window)  # [N], [N, 2]
        part = self.cast(*cam.rays(centres))
        n = cam.height * cam.width
        hits = MeshHits(
            np.full(n, np.inf, np.float32),
            np.full(n, -1, np.int64),
            np.zeros((n, 2), np.float32),
            np.zeros((n, 3), np.float32),
        )
        for f in fields(MeshHits):
            getattr(hits, f.name)[chosen] = getattr(part, f.name)
        return hits

    def silhouette(self, cam) -> np.ndarray:
        """The mesh's silhouette [H, W] bool seen by `cam` (pixel centres that hit it)."""
        return self.cast_camera(cam).hit.reshape(cam.height, cam.width)

    def depth(self, cam) -> np.ndarray:
        """Camera-z depth [H, W] float32 of the mesh seen by `cam` (0 where no hit)."""
        t = self.cast_camera(cam).t  # [H*W]
        z = t * cam.z_per_unit_distance()
        z[~np.isfinite(z)] = 0.0
        return z.reshape(cam.height, cam.width).astype(np.float32)

    def _first(self, o: np.ndarray, d: np.ndarray):
        """-> t [R] float32 (inf = miss), triangle [R] int64 (-1 = miss), uv [R, 2] float32."""
        r = len(o)
        if self._scene is None or r == 0:
            return (np.full(r, np.inf, np.float32), np.full(r, -1, np.int64),
                    np.zeros((r, 2), np.float32))  # fmt: skip
        if self.backend == "open3d":
            rays = o3d.core.Tensor(np.concatenate([o, d], 1))
            out = self._scene.cast_rays(rays, nthreads=self.threads)
            t = out["t_hit"].numpy()
            tri = out["primitive_ids"].numpy().astype(np.int64)
            tri[~np.isfinite(t)] = -1
            return t, tri, out["primitive_uvs"].numpy()
        parts = self._embree_map(o, d)
        keys = ("primID", "tfar", "u", "v")
        out = (
            parts[0]
            if len(parts) == 1
            else {k: np.concatenate([p[k] for p in parts]) for k in keys}
        )
        tri = out["primID"].astype(np.int64)
        miss = tri < 0
        t = out["tfar"]
        t[miss] = np.inf
        uv = np.empty((r, 2), np.float32)
        uv[:, 0], uv[:, 1] = out["u"], out["v"]
        uv[miss] = 0.0
        return t, tri, uv

    def _embree_map(self, o: np.ndarray, d: np.ndarray) -> list[dict]:
        """embreex intersection of the rays, split into contiguous chunks over threads."""
        n = min(self.threads or len(os.sched_getaffinity(0)), max(1, len(o) // _EMBREE_MIN_CHUNK))
        if n == 1:
            return [self._scene.run(o, d, output=1)]
        bounds = np.linspace(0, len(o), n + 1).astype(np.int64)
        chunks = [(o[a:b], d[a:b]) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
        with ThreadPoolExecutor(n) as pool:  # embreex releases the GIL while tracing
            return list(pool.map(lambda c: self._scene.run(c[0], c[1], output=1), chunks))

    # ---- every hit ------------------------------------------------------------------------
    def cast_all(self, origins, dirs, max_hits: int = 8, min_gap: float = 1e-5) -> MultiHits:
        """The first `max_hits` hits of each ray, nearest first.

        Embree re-casts from `min_gap` past each hit (two surfaces closer than that along the
        ray count once); Open3D lists every intersection, and hits closer than `min_gap` to the
        previous one are dropped the same way.
        """
        o, d = rays_numpy(origins, dirs)
        r, k = len(o), int(max_hits)
        t_out = np.full((r, k), np.inf, np.float32)
        tri_out = np.full((r, k), -1, np.int64)
        if self._scene is not None and r and k > 0:
            if self.backend == "open3d":
                self._all_open3d(o, d, min_gap, t_out, tri_out)
            else:
                self._all_embree(o, d, min_gap, t_out, tri_out)
        hits = MultiHits(t_out, tri_out)
        return hits.to_torch(origins.device) if isinstance(origins, torch.Tensor) else hits

    def _all_open3d(self, o, d, min_gap, t_out, tri_out) -> None:
        out = self._scene.list_intersections(
            o3d.core.Tensor(np.concatenate([o, d], 1)), nthreads=self.threads
        )
        ray = out["ray_ids"].numpy().astype(np.int64)
        t = out["t_hit"].numpy().astype(np.float64)
        tri = out["primitive_ids"].numpy().astype(np.int64)
        if len(t) == 0:
            return
        # One sorted key per hit (by ray, then distance); hit j of a ray is the first one at
        # least min_gap past hit j - 1, as the embree re-cast finds it.
        span = float(t.max()) + 2 * min_gap + 1.0
        key = ray * span + t
        order = np.argsort(key, kind="stable")
        key, tri = key[order], tri[order]
        rays = np.arange(len(o))
        end = np.searchsorted(key, (rays + 1) * span - 0.5, side="left")  # segment ends
        last = np.full(len(o), -min_gap - 0.25)  # before any hit (t >= 0)
        for j in range(t_out.shape[1]):
            pos = np.searchsorted(key, rays * span + last + min_gap, side="left")
            found = pos < end
            if not found.any():
                break
            r, p = rays[found], pos[found]
            t_out[r, j] = key[p] - r * span
            tri_out[r, j] = tri[p]
            last[r] = key[p] - r * span
            last[~found] = np.inf

    def _all_embree(self, o, d, min_gap, t_out, tri_out) -> None:
        active = np.arange(len(o))
        offset = np.zeros(len(o), np.float64)  # distance of the current origin along the ray
        for j in range(t_out.shape[1]):
            start = (o[active] + offset[active, None] * d[active]).astype(np.float32)
            t, tri, _ = self._first(start, np.ascontiguousarray(d[active]))
            hit = tri >= 0
            active, t, tri = active[hit], t[hit], tri[hit]
            if len(active) == 0:
                break
            t_out[active, j] = offset[active] + t
            tri_out[active, j] = tri
            offset[active] += t + min_gap
