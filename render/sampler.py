"""Where to sample along rays: proxy-guided band sampling (embree) and the uniform baseline.

- `ProxyRaycaster`: `render.raycast.MeshRaycaster` over the proxy mesh and over a copy inflated
  by `d` along the vertex normals (so silhouettes are covered); `d` may be one per vertex, each
  ray's band then takes the widths interpolated where it hits. `cast` gives per ray the first
  hit on both, and the ray's interval inside the bounding sphere. `update_vertices` rebuilds both
  scenes from warped vertices (milliseconds), for the edited space.
- `BandSampler`: for rays that hit the inflated proxy, `n_band` bins in `[t_hit - d, t_hit + d]`
  or, when only the inflated copy is hit (rays passing by the silhouette), over the stretch the
  ray spends inside the inflated copy, `[t_inflated, t_exit]`: a ray grazing a part of radius r
  runs ~2 sqrt(2 r d) inside it and comes closest to the proxy in the middle, well past
  `t_inflated + 2d`. Merged with `n_coarse` bins over the ray-in-sphere interval; rays that
  miss get the background and cost nothing.
- `UniformSampler`: the paper's baseline, `n_coarse` stratified samples over the ray-in-sphere
  interval + `n_importance` samples drawn from the coarse weights (`sample_pdf`).

Samples are returned as sorted distances `t` [R, S] with the length `delta` [R, S] each one
stands for (bins), ready for `render.volume`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from render.raycast import MeshRaycaster, mesh_arrays, rays_numpy


@dataclass
class RayHits:
    """Per-ray result of casting against the proxy (torch, on the rays' device)."""

    t_hit: torch.Tensor  # [R] first hit on the proxy (inf where missed)
    t_inflated: torch.Tensor  # [R] first hit on the inflated proxy (inf where missed)
    near: torch.Tensor  # [R] entry into the bounding sphere (0 if the origin is inside)
    far: torch.Tensor  # [R] exit from the bounding sphere (near where missed)
    t_exit: torch.Tensor | None = None  # [R] where a ray that misses the proxy leaves the
    # inflated copy again (inf elsewhere); None: unknown (the band is then 2d long)
    width: torch.Tensor | None = None  # [R] the band half-width d at the ray's hit, where the
    # proxy's widths vary by vertex; None: one width for every ray

    @property
    def hit(self) -> torch.Tensor:  # [R] bool: the ray needs the field
        return torch.isfinite(self.t_inflated) | torch.isfinite(self.t_hit)

    def _fields(self) -> tuple:
        return (self.t_hit, self.t_inflated, self.near, self.far, self.t_exit, self.width)

    def __getitem__(self, idx) -> RayHits:
        return RayHits(*(None if v is None else v[idx] for v in self._fields()))

    def to(self, device) -> RayHits:
        return RayHits(*(None if v is None else v.to(device) for v in self._fields()))

    @staticmethod
    def cat(parts: list[RayHits]) -> RayHits:
        """Concatenates hits of several ray batches."""
        columns = zip(*(p._fields() for p in parts), strict=True)
        return RayHits(*(None if None in c else torch.cat(c) for c in columns))


def sphere_interval(
    origins: torch.Tensor, dirs: torch.Tensor, radius: float = 1.0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Ray / sphere (centre 0) intersection for unit dirs -> near [R], far [R], hit [R] bool."""
    b = (origins * dirs).sum(-1)  # [R]
    c = (origins * origins).sum(-1) - radius * radius
    disc = b * b - c
    hit = disc > 0
    root = torch.sqrt(disc.clamp_min(0))
    near = (-b - root).clamp_min(0)
    far = (-b + root).clamp_min(0)
    far = torch.where(hit, far, near)
    return near, far, hit & (far > near)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals [V, 3], oriented outwards (by the sign of the volume)."""
    v = vertices.astype(np.float64)
    a, b, c = v[triangles[:, 0]], v[triangles[:, 1]], v[triangles[:, 2]]
    fn = np.cross(b - a, c - a)  # [T, 3], length = 2 * area
    if np.einsum("ij,ij->", a, fn) < 0:  # negative signed volume: triangles wound inwards
        fn = -fn
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, triangles[:, k], fn)
    return (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)).astype(np.float32)


class ProxyRaycaster:
    """Ray casting against a proxy mesh and its copy inflated by `inflate` (run units): one
    width, or one per vertex [V] (the band half-width then varies over the proxy, and each
    ray's hit carries its own, interpolated over the hit triangle: `RayHits.width`)."""

    def __init__(self, mesh, inflate: float | np.ndarray = 0.04, radius: float = 1.0):
        self.radius = float(radius)
        vertices, self.triangles = mesh_arrays(mesh)
        self.vertex_widths = None  # [V] float32, or None: `inflate` everywhere
        if np.ndim(inflate):
            self.vertex_widths = np.ascontiguousarray(inflate, np.float32).reshape(-1)
            if len(self.vertex_widths) != len(vertices):
                raise ValueError("one inflation per proxy vertex is needed")
            inflate = float(self.vertex_widths.max(initial=0.0))
        self.inflate = float(inflate)  # the widest
        self.update_vertices(vertices)

    def update_vertices(self, vertices: np.ndarray) -> None:
        """Rebuilds both scenes from (warped) vertices [V, 3] with the same triangles."""
        self.vertices = np.ascontiguousarray(vertices, np.float32)
        self._scene = MeshRaycaster((self.vertices, self.triangles))
        self._inflated = None
        if self.inflate > 0:
            widths = self.inflate if self.vertex_widths is None else self.vertex_widths[:, None]
            inflated = self.vertices + widths * vertex_normals(self.vertices, self.triangles)
            self._inflated = MeshRaycaster((inflated, self.triangles))

    def _widths_at(self, hits) -> torch.Tensor:
        """MeshHits [R] -> the vertex widths interpolated at each hit [R] (0 where missed)."""
        corners = self.vertex_widths[self.triangles[np.maximum(hits.triangle, 0)]]  # [R, 3]
        width = (corners * hits.barycentrics).sum(1)
        return torch.from_numpy(np.where(hits.hit, width, 0.0).astype(np.float32))

    def pixel_window(self, cam) -> tuple[int, int, int, int] | None:
        """The pixels of `cam` whose centre rays can hit the proxy or its inflated copy:
        `Camera.pixel_window` of both's vertices (None: any pixel may)."""
        points = [self._scene.vertices]
        if self._inflated is not None:
            points.append(self._inflated.vertices)
        return cam.pixel_window(np.concatenate(points))

    def cast(self, origins: torch.Tensor, dirs: torch.Tensor) -> RayHits:
        """origins [R, 3], unit dirs [R, 3] -> RayHits (on the rays' device)."""
        o, d = rays_numpy(origins, dirs)
        first = self._scene.cast(o, d)
        t_hit = torch.from_numpy(first.t)
        t_exit = torch.full_like(t_hit, float("inf"))
        width = None if self.vertex_widths is None else self._widths_at(first)
        if self._inflated is not None:
            outer = self._inflated.cast(o, d)
            t_inf = torch.from_numpy(outer.t)
            passing = torch.isfinite(t_inf) & ~torch.isfinite(t_hit)  # by the silhouette
            if width is not None:  # by the silhouette: the width where it enters the copy
                width = torch.where(passing, self._widths_at(outer), width)
            if passing.any():  # leave the inflated copy: its next hit along the ray
                sel = passing.numpy()
                start = t_inf[passing].numpy() + 1e-5
                t_next = self._inflated.cast(o[sel] + d[sel] * start[:, None], d[sel]).t
                t_exit[passing] = torch.from_numpy(start + t_next)
        else:
            t_inf = t_hit.clone()
        device = origins.device
        near, far, _ = sphere_interval(origins, dirs, self.radius)
        width = None if width is None else width.to(device)
        return RayHits(t_hit.to(device), t_inf.to(device), near, far, t_exit.to(device), width)


def _stratified(lo: torch.Tensor, hi: torch.Tensor, n: int) -> torch.Tensor:
    """n equal bins from lo [R] to hi [R]: edges [R, n+1]."""
    u = torch.linspace(0.0, 1.0, n + 1, device=lo.device, dtype=lo.dtype)
    edges = lo[:, None] + (hi - lo)[:, None] * u  # [R, n+1]
    return edges


def samples_in_bins(edges: torch.Tensor, perturb: bool, generator=None):
    """Sorted edges [R, B+1] -> one sample per bin t [R, B] (uniform jitter or midpoint), delta."""
    lo, hi = edges[:, :-1], edges[:, 1:]
    if perturb:
        u = torch.rand(lo.shape, generator=generator, device="cpu", dtype=lo.dtype).to(lo.device)
    else:
        u = torch.full_like(lo, 0.5)
    return lo + (hi - lo) * u, hi - lo


def sampler_window(sampler, cam) -> tuple[int, int, int, int] | None:
    """`sampler.pixel_window(cam)`; None (every pixel) for samplers without one."""
    window = getattr(sampler, "pixel_window", None)
    return None if window is None else window(cam)


@dataclass
class BandSampler:
    """Samples in a band around the proxy hit plus a few coarse ones over the sphere interval."""

    raycaster: ProxyRaycaster
    n_band: int = 16  # bins in [t_hit - d, t_hit + d]
    n_coarse: int = 4  # bins over the whole ray-in-sphere interval
    half_width: float | None = None  # d; None: the raycaster's inflation (per ray where it
    # varies by vertex)
    n_importance: int = 0  # (band sampling needs no importance pass)

    @property
    def d(self) -> float:
        return self.raycaster.inflate if self.half_width is None else float(self.half_width)

    @property
    def samples_per_ray(self) -> int:
        return self.n_band + self.n_coarse + (1 if self.n_coarse else 0)

    def cast(self, origins: torch.Tensor, dirs: torch.Tensor) -> RayHits:
        return self.raycaster.cast(origins, dirs)

    def pixel_window(self, cam) -> tuple[int, int, int, int] | None:
        """The pixels of `cam` whose centre rays can need the field (the others miss the
        proxy and its inflated copy): `ProxyRaycaster.pixel_window`; None: any pixel may."""
        return self.raycaster.pixel_window(cam)

    def band(self, hits: RayHits) -> tuple[torch.Tensor, torch.Tensor]:
        """Band [lo, hi] per ray ([R], [R]) from hits. Not clipped to the sphere interval: a
        warped proxy may reach beyond the sphere (an edit that makes the object taller)."""
        d = self.d if hits.width is None or self.half_width is not None else hits.width
        direct = torch.isfinite(hits.t_hit)
        t0 = torch.where(direct, hits.t_hit - d, hits.t_inflated)
        t0 = torch.where(torch.isfinite(t0), t0, hits.near)
        lo = t0.clamp_min(0.0)
        t1 = t0 + 2 * d
        if hits.t_exit is not None:  # passing by: the whole stretch inside the inflated copy
            passing = ~direct & torch.isfinite(hits.t_exit)
            t1 = torch.where(passing, torch.maximum(hits.t_exit, t1), t1)
        hi = torch.maximum(t1, lo + 1e-4)
        return lo, hi

    def sample(
        self, hits: RayHits, perturb: bool = False, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays that need the field -> sorted t [R, S] and bin lengths delta [R, S]."""
        lo, hi = self.band(hits)
        edges = _stratified(lo, hi, self.n_band)  # [R, n_band+1]
        if self.n_coarse:
            far = torch.maximum(hits.far, hi)
            coarse = _stratified(torch.minimum(hits.near, lo), far, self.n_coarse)
            edges = torch.sort(torch.cat([edges, coarse], dim=-1), dim=-1).values
        return samples_in_bins(edges, perturb, generator)


@dataclass
class UniformSampler:
    """The paper's baseline: stratified coarse samples + importance samples over the sphere."""

    n_coarse: int = 64
    n_importance: int = 128
    radius: float = 1.0

    @property
    def samples_per_ray(self) -> int:
        return self.n_coarse + self.n_importance

    def pixel_window(self, cam) -> None:
        """Any pixel's ray may cross the sphere (no window)."""
        return None

    def cast(self, origins: torch.Tensor, dirs: torch.Tensor) -> RayHits:
        near, far, hit = sphere_interval(origins, dirs, self.radius)
        inf = torch.full_like(near, float("inf"))
        t = torch.where(hit, near, inf)
        return RayHits(t, t, near, far)

    def sample(
        self, hits: RayHits, perturb: bool = False, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Coarse stage: sorted t [R, n_coarse], delta [R, n_coarse]."""
        edges = _stratified(hits.near, hits.far, self.n_coarse)
        return samples_in_bins(edges, perturb, generator)

    def importance(
        self,
        hits: RayHits,
        t_coarse: torch.Tensor,
        weights: torch.Tensor,
        perturb: bool = False,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Fine stage: coarse t [R, Nc] + their weights [R, Nc] -> all samples, sorted, + delta."""
        edges = _stratified(hits.near, hits.far, self.n_coarse)  # [R, Nc+1]
        fine = sample_pdf(edges, weights, self.n_importance, perturb, generator)
        t = torch.sort(torch.cat([t_coarse, fine], dim=-1), dim=-1).values  # [R, Nc+Ni]
        # bins: between midpoints of neighbours, closed by the sphere interval
        mids = 0.5 * (t[:, 1:] + t[:, :-1])
        bin_edges = torch.cat([hits.near[:, None], mids, hits.far[:, None]], dim=-1)
        return t, bin_edges[:, 1:] - bin_edges[:, :-1]


def sample_pdf(
    bins: torch.Tensor,
    weights: torch.Tensor,
    n: int,
    perturb: bool = False,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Inverse-CDF sampling: bin edges [R, B+1], weights [R, B] -> n samples [R, n], sorted.

    The pdf is piecewise constant (weights / sum) over the bins; deterministic samples are at the
    CDF levels (i + 0.5) / n.
    """
    weights = weights.detach() + 1e-5
    pdf = weights / weights.sum(-1, keepdim=True)
    cdf = torch.cumsum(pdf, -1)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf], dim=-1)  # [R, B+1]
    if perturb:
        u = torch.rand(cdf.shape[0], n, generator=generator, dtype=cdf.dtype).to(cdf.device)
        u = torch.sort(u, dim=-1).values
    else:
        u = ((torch.arange(n, dtype=cdf.dtype, device=cdf.device) + 0.5) / n).expand(
            cdf.shape[0], n
        )
    u = u.contiguous()
    idx = torch.searchsorted(cdf, u, right=True)  # [R, n]
    below = (idx - 1).clamp(0, cdf.shape[-1] - 1)
    above = idx.clamp(0, cdf.shape[-1] - 1)
    cdf_b, cdf_a = cdf.gather(-1, below), cdf.gather(-1, above)
    bin_b, bin_a = bins.gather(-1, below), bins.gather(-1, above)
    denom = cdf_a - cdf_b
    frac = torch.where(denom < 1e-8, torch.zeros_like(denom), (u - cdf_b) / denom.clamp_min(1e-8))
    return bin_b + frac * (bin_a - bin_b)
