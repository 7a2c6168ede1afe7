"""Views of the frozen template kept for texture editing: what F_dT's image depends on.

A texture edit leaves the geometry alone (F_dG is the identity, the template is frozen), so in any
view the template image I_o, the opacity and every sample's volume-rendering weight are constants.
`sample_view` renders them once (no graph) and keeps the samples that matter (weight above
`min_weight`) in a compressed-row layout: the samples of pixel p are `offsets[p]:offsets[p+1]`.
Then the modification image of any range of pixels is

    I_m(p) = sum over its samples s of w_s * m'(x_s)          (`render_modification`)

one F_dT query per kept sample and no template query at all, `chunk` samples at a time in both
the forward and the backward pass (so its memory does not grow with the image).
`jittered_camera` perturbs a pose for L_tex's augmentation, and `LiftedRegion` gives the editable
pixels of any view from the painted region lifted onto the surface (when the run has no feature
field for semantic masks).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch

from render import volume
from render.renderer import _background, sample_hits


@dataclass
class ViewSamples:
    """One view through the frozen template; P pixels (row-major), S kept samples."""

    camera: object  # render.cameras.Camera
    template_rgb: torch.Tensor  # [P, 3] I_o over the background
    opacity: torch.Tensor  # [P]
    depth: torch.Tensor  # [P] expected ray distance (0 where nothing is hit)
    surface: torch.Tensor  # [P, 3] the expected surface point o + depth * d
    points: torch.Tensor  # [S, 3]
    weights: torch.Tensor  # [S]
    pixel: torch.Tensor  # [S] int64, the pixel of each sample (sorted)
    offsets: torch.Tensor  # [P + 1] int64
    editable: torch.Tensor | None = None  # [P] bool: where L_reg does not apply
    template_sim: torch.Tensor | None = None  # [1, T, T] DINO self-similarity of I_o
    shape: tuple[int, int] | None = None  # (h, w) of a crop; None: the camera's image
    goal: torch.Tensor | None = None  # [P, 3] target colours (the edited view)
    region: torch.Tensor | None = None  # [P] the edit's 3D gate rendered (compositor's g)
    features: torch.Tensor | None = None  # [S, F] the template's geometry feature per sample
    colours: torch.Tensor | None = None  # [S, 3] the template's colour c_s per sample
    part_rgb: torch.Tensor | None = None  # [P, 3] the gated part's share of I_o (render_gate)

    def modification(self, texture, s0: int = 0, s1: int | None = None) -> torch.Tensor:
        """F_dT at samples s0..s1-1 [s, 3] (given the samples' template feature when F_dT
        reads one)."""
        cond = None
        if texture.cond_dim:
            if self.features is None:
                raise ValueError("F_dT reads the template's feature: sample_view(features=True)")
            cond = self.features[s0:s1]
        return texture(self.points[s0:s1], cond)

    @property
    def size(self) -> tuple[int, int]:
        """(H, W) of the pixels as an image (the camera's, or the crop's)."""
        return self.shape or (self.camera.height, self.camera.width)

    @property
    def n_pixels(self) -> int:
        return int(self.template_rgb.shape[0])

    def subset(self, pixels: torch.Tensor, shape: tuple[int, int] | None = None) -> ViewSamples:
        """The view restricted to `pixels` [Q] (int64 indices, in the order given; `shape`: the
        (h, w) they form, h * w = Q)."""
        starts, stops = self.offsets[pixels], self.offsets[pixels + 1]
        counts = stops - starts  # [Q]
        offsets = torch.zeros(len(pixels) + 1, dtype=torch.int64, device=counts.device)
        offsets[1:] = torch.cumsum(counts, 0)
        local = torch.arange(int(offsets[-1]), device=counts.device)
        first = torch.repeat_interleave(offsets[:-1], counts)
        ids = torch.repeat_interleave(starts, counts) + (local - first)
        return ViewSamples(
            camera=self.camera,
            template_rgb=self.template_rgb[pixels],
            opacity=self.opacity[pixels],
            depth=self.depth[pixels],
            surface=self.surface[pixels],
            points=self.points[ids],
            weights=self.weights[ids],
            pixel=torch.repeat_interleave(torch.arange(len(pixels), device=counts.device), counts),
            offsets=offsets,
            editable=None if self.editable is None else self.editable[pixels],
            shape=shape,
            goal=None if self.goal is None else self.goal[pixels],
            region=None if self.region is None else self.region[pixels],
            features=None if self.features is None else self.features[ids],
            colours=None if self.colours is None else self.colours[ids],
            part_rgb=None if self.part_rgb is None else self.part_rgb[pixels],
        )

    def crop(self, y0: int, y1: int, x0: int, x1: int) -> ViewSamples:
        """The pixels of rows y0..y1-1 and columns x0..x1-1 of the view's image."""
        pixels = box_pixels(self.size[1], y0, y1, x0, x1, self.offsets.device)
        return self.subset(pixels, (y1 - y0, x1 - x0))


@torch.no_grad()
def sample_view(
    camera,
    template,
    sampler,
    background,
    min_weight: float = 1e-3,
    chunk: int = 8192,
    device=None,
    features: bool = False,
) -> ViewSamples:
    """Renders `camera` through the frozen `template` (as `render.renderer.render_rays`, without
    perturbation) and keeps its samples of weight > min_weight (0 keeps every sample) with
    their colour c_s; features: also keeps each sample's geometry feature (the template's
    "geo_feat")."""
    device = device or torch.device("cpu")
    o_all, d_all = (torch.from_numpy(a).to(device) for a in camera.rays())
    n = len(o_all)
    rgb = _background(background, n, o_all).clone()
    opacity = torch.zeros(n, device=device)
    depth = torch.zeros(n, device=device)
    counts = torch.zeros(n, dtype=torch.int64, device=device)
    points, weights, feats, cols = [], [], [], []
    for start in range(0, n, chunk):
        o, d = o_all[start : start + chunk], d_all[start : start + chunk]
        hits = sampler.cast(o, d)
        idx = torch.nonzero(hits.hit)[:, 0]
        if idx.numel() == 0:
            continue
        sub, o, d = hits[idx], o[idx], d[idx]
        t, delta, _ = sample_hits(sampler, sub, o, d, lambda x, v: template(x, v)["sigma"])
        pts = o[:, None, :] + d[:, None, :] * t[..., None]  # [r, S, 3]
        res = template(pts.reshape(-1, 3), d.repeat_interleave(t.shape[1], 0))
        w = volume.render_weights(res["sigma"].view(t.shape), t, delta=delta)  # [r, S]
        acc = volume.opacity(w)
        colour = volume.composite(w, {"rgb": res["rgb"].view(*t.shape, 3)})["rgb"]
        gidx = start + idx
        rgb[gidx] = volume.over_background(colour, acc, rgb[gidx])
        opacity[gidx] = acc
        depth[gidx] = volume.expected_depth(w, t) / acc.clamp_min(1e-6)
        keep = w > min_weight  # [r, S]
        counts[gidx] = keep.sum(dim=1)
        points.append(pts[keep])
        weights.append(w[keep])
        cols.append(res["rgb"].view(*t.shape, 3)[keep])
        if features:
            feats.append(res["geo_feat"].view(*t.shape, -1)[keep])
    offsets = torch.zeros(n + 1, dtype=torch.int64, device=device)
    offsets[1:] = torch.cumsum(counts, 0)
    empty = torch.zeros(0, 3, device=device)
    kept_features = None
    if features:
        kept_features = torch.cat(feats) if feats else torch.zeros(0, 0, device=device)
    return ViewSamples(
        camera=camera,
        template_rgb=rgb,
        opacity=opacity,
        depth=depth,
        surface=o_all + d_all * depth[:, None],
        points=torch.cat(points) if points else empty,
        weights=torch.cat(weights) if weights else empty[:, 0],
        pixel=torch.repeat_interleave(torch.arange(n, device=device), counts),
        offsets=offsets,
        features=kept_features,
        colours=torch.cat(cols) if cols else empty,
    )


class _ChunkedModification(torch.autograd.Function):
    """I_m of a whole view with the memory of `chunk` samples, in both directions: the forward
    pass queries F_dT chunk by chunk without a graph (or returns `known`, the same values
    computed before); the backward pass re-queries each chunk with a graph and back-propagates
    d loss / d m'(x_s) = w_s * d loss / d I_m(pixel of s) into F_dT's parameters (a chunked
    recomputation, as in gradient checkpointing). `anchor` is one of F_dT's parameters: it only
    makes autograd call `backward` (its gradient here is zero)."""

    @staticmethod
    def forward(ctx, anchor, view, texture, chunk, known):
        ctx.view, ctx.texture, ctx.chunk = view, texture, chunk
        if known is not None:
            return known.clone()
        out = view.template_rgb.new_zeros(view.n_pixels, 3)
        for s0 in range(0, view.points.shape[0], chunk):
            s1 = s0 + chunk
            m = view.modification(texture, s0, s1) * view.weights[s0:s1, None]
            out.index_add_(0, view.pixel[s0:s1], m)
        return out

    @staticmethod
    def backward(ctx, grad):  # [P, 3]
        view, texture, chunk = ctx.view, ctx.texture, ctx.chunk
        with torch.enable_grad():
            for s0 in range(0, view.points.shape[0], chunk):
                s1 = s0 + chunk
                m = view.modification(texture, s0, s1)
                torch.autograd.backward(m, grad[view.pixel[s0:s1]] * view.weights[s0:s1, None])
        anchor_grad = texture.mlp[-1].bias.new_zeros(texture.mlp[-1].bias.shape)
        return anchor_grad, None, None, None, None


def render_modification(
    view: ViewSamples, texture, chunk: int | None = 32768, known: torch.Tensor | None = None
) -> torch.Tensor:
    """I_m of every pixel of the view [P, 3] = per pixel sum of w_s F_dT(x_s).

    With `chunk`, at most that many samples are queried at once, with or without a graph
    (`_ChunkedModification`; `known` [P, 3]: I_m already computed with the same F_dT, so the
    forward pass costs nothing and only the backward pass queries F_dT). None: one plain
    autograd graph over every sample (the reference)."""
    if chunk is not None:
        return _ChunkedModification.apply(texture.mlp[-1].bias, view, texture, chunk, known)
    out = view.template_rgb.new_zeros(view.n_pixels, 3)
    if view.points.shape[0] == 0:
        return out
    m = view.modification(texture) * view.weights[:, None]  # [S, 3]
    return out.index_add(0, view.pixel, m)


@torch.no_grad()
def render_gate(view: ViewSamples, gate) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The 3D gate g(x) rendered with the view's kept samples: [P] = sum_s w_s g(x_s), and the
    part's share of the template colour, [P, 3] = sum_s w_s g(x_s) c_s (None when the view
    kept no colours)."""
    region = view.opacity.new_zeros(view.n_pixels)
    part = None if view.colours is None else view.template_rgb.new_zeros(view.n_pixels, 3)
    if view.points.shape[0] == 0:
        return region, part
    g = view.weights * gate(view.points)  # [S]
    if part is not None:
        part = part.index_add(0, view.pixel, g[:, None] * view.colours)
    return region.index_add(0, view.pixel, g), part


def box_pixels(width: int, y0: int, y1: int, x0: int, x1: int, device=None) -> torch.Tensor:
    """Row-major pixel indices [(y1 - y0) * (x1 - x0)] of a box of an image `width` wide."""
    rows = torch.arange(y0, y1, device=device)[:, None] * width
    return (rows + torch.arange(x0, x1, device=device)[None, :]).reshape(-1)


def jittered_camera(camera, degrees: float, rng: np.random.Generator):
    """The camera turned about the object's centre (the origin) by a random rotation: a uniform
    random axis, an angle drawn from N(0, degrees). degrees 0: the camera itself."""
    if degrees <= 0:
        return camera
    axis = rng.normal(size=3)
    axis /= max(np.linalg.norm(axis), 1e-12)
    angle = np.deg2rad(rng.normal(0.0, degrees))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)  # Rodrigues
    pose = camera.camera_to_world.copy()
    pose[:3, :3] = rot @ pose[:3, :3]
    pose[:3, 3] = rot @ pose[:3, 3]
    return camera.replace(camera_to_world=pose)


def scaled_camera(camera, longer_side: int):
    """The camera resized so its longer side is `longer_side` pixels (aspect kept)."""
    scale = longer_side / max(camera.width, camera.height)
    w, h = max(1, round(camera.width * scale)), max(1, round(camera.height * scale))
    return camera if (w, h) == (camera.width, camera.height) else camera.resized(w, h)


# ---- the region lifted onto the surface (without a feature field) ----------------------------
def surface_points(view: ViewSamples, min_opacity: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(points [M, 3], pixel indices [M]) of the view's object pixels (opacity >= min_opacity):
    each ray's expected surface point."""
    obj = np.nonzero((view.opacity >= min_opacity).cpu().numpy())[0]
    return view.surface.cpu().numpy()[obj], obj


@dataclass
class LiftedRegion:
    """The painted region of the editing view lifted onto the surface: its object pixels' surface
    points, each inside or outside the region. Another view's pixel may change when its surface
    point lies within `tol` of a lifted point inside the region; surface the editing view did not
    see keeps the template, as does the background (conservative: semantic masks from a feature
    field are what carry an edit to the part's unseen sides)."""

    points: np.ndarray  # [M, 3]
    inside: np.ndarray  # [M] bool
    tol: float

    @classmethod
    def from_view(cls, view: ViewSamples, region: np.ndarray, tol: float) -> LiftedRegion:
        """`region` [H, W] bool of the view; `tol` grows to 2 pixel footprints at the median
        depth when those are larger (sparse samples of a small image must still touch)."""
        points, pixels = surface_points(view)
        inside = np.asarray(region).reshape(-1)[pixels]
        if len(pixels):
            footprint = float(np.median(view.depth.cpu().numpy()[pixels])) / view.camera.fx
            tol = max(tol, 2.0 * footprint)
        return cls(points, inside, tol)

    def mirrored(self, plane: np.ndarray) -> LiftedRegion:
        """The region with its points' mirror images in `plane` (n, D; n.x = D) added: on a
        mirror-symmetric object, the side the editing view did not see painted as its mirror."""
        from edit.shape_prior import reflect

        points = np.concatenate([self.points, reflect(self.points, plane)])
        return LiftedRegion(points, np.concatenate([self.inside, self.inside]), self.tol)

    @cached_property
    def _tree(self):
        """KD-tree of the lifted points (built once, on first use)."""
        from scipy.spatial import cKDTree

        return cKDTree(self.points)

    def near(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For points [N, 3] (the region has points): whether the nearest lifted point lies
        within `tol` [N] bool, and whether it is inside the region [N] bool."""
        dist, nearest = self._tree.query(points)
        return dist <= self.tol, self.inside[nearest]

    def mirror_agreement(
        self, plane: np.ndarray, views: list[tuple[np.ndarray, np.ndarray]]
    ) -> tuple[float, int]:
        """How well the region mirrored in `plane` (n, D) agrees with other views' masks on the
        surface the editing view did not see: (IoU, pixels compared) over `views`, each (surface
        points [N, 3], editable [N] bool) of a view's object pixels. A pixel is compared where
        its surface point lies within `tol` of a mirrored point and farther from every point the
        editing view saw; the mirror says it may change where that mirrored point is inside.
        (nan, 0) when no pixel is compared."""
        from edit.shape_prior import reflect

        if not len(self.points):
            return float("nan"), 0
        mirror = LiftedRegion(reflect(self.points, plane), self.inside, self.tol)
        both = either = compared = 0
        for points, editable in views:
            if not len(points):
                continue
            near_seen, _ = self.near(points)
            near_mirror, said = mirror.near(points)  # said: what the mirror says
            use = near_mirror & ~near_seen
            said, masked = said[use], np.asarray(editable, bool)[use]
            both += int((said & masked).sum())
            either += int((said | masked).sum())
            compared += int(use.sum())
        return (both / either if either else float("nan")), compared

    def editable(self, view: ViewSamples) -> torch.Tensor:
        """[P] bool pixels of `view` that may change: their surface point is near one the
        editing view saw inside the region."""
        return self._seen(view, inside=True)

    def kept(self, view: ViewSamples) -> torch.Tensor:
        """[P] bool pixels of `view` whose surface point is near one the editing view saw
        outside the region: the user saw that surface and did not paint it."""
        return self._seen(view, inside=False)

    def _seen(self, view: ViewSamples, inside: bool) -> torch.Tensor:
        """[P] bool pixels whose surface point's nearest lifted point lies within `tol` and is
        inside (or outside) the region."""
        out = np.zeros(view.n_pixels, bool)
        points, pixels = surface_points(view)
        if len(pixels) and len(self.points):
            near, nearest_inside = self.near(points)
            out[pixels] = near & (nearest_inside == inside)
        return torch.from_numpy(out).to(view.opacity.device)
