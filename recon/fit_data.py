"""The fit's training data: a run's views (`load_views`), the background colour from them, and
the pool of training rays cast once against the proxy (`RayPool`, `build_ray_pool`) with the
per-step ray draw (`RaySelector`) and the sub-pixel rays of the box filter (`subpixel_dirs`)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from recon.rundir import RunDir
from render.errors import SineError
from render.io import read_image, read_mask
from render.sampler import RayHits, sampler_window


def load_views(run: RunDir, split: str) -> list[tuple]:
    """[(camera, image [H, W, 3], mask [H, W] bool or None)] for the frames of `split`."""
    cams = run.load_cameras().frames
    out = []
    for cam in cams:
        if cam.split != split:
            continue
        path = run.image_path(cam.name)
        if not path.is_file():
            raise SineError(f"{path} is missing (cameras.json names it); re-run `sine ingest`")
        image = read_image(path)
        if image.shape[:2] != (cam.height, cam.width):
            cam = cam.resized(image.shape[1], image.shape[0])
        mpath = run.mask_path(cam.name)
        mask = read_mask(mpath) if mpath.is_file() else None
        out.append((cam, image, mask))
    return out


def background_color(views, mode: str) -> tuple[np.ndarray, bool]:
    """(colour [3], learnable) from the mode and, for auto, the masked-out pixels."""
    if mode == "white":
        return np.ones(3, np.float32), False
    if mode == "black":
        return np.zeros(3, np.float32), False
    mode = "learn" if mode == "capture" else mode
    pixels = [img[~m] for _, img, m in views if m is not None and (~m).any()]
    if not pixels:  # no masks: learn it, starting from the image borders
        border = np.concatenate(
            [np.concatenate([img[0], img[-1], img[:, 0], img[:, -1]]) for _, img, _ in views]
        )
        return np.median(border, axis=0).astype(np.float32), True
    bg = np.concatenate(pixels)
    median = np.median(bg, axis=0).astype(np.float32)
    spread = float(np.abs(bg - median).mean())
    return median, mode == "learn" or spread > 0.02


@dataclass
class RayPool:
    """Every training ray that needs the field, cast once against the proxy."""

    origins: torch.Tensor  # [P, 3]
    dirs: torch.Tensor  # [P, 3]
    rgb: torch.Tensor  # [P, 3]
    mask: torch.Tensor  # [P] float (1 = foreground; 1 everywhere without masks)
    hits: RayHits  # [P]
    n_total: int  # all training rays, hit or not
    has_masks: bool
    miss_rgb: torch.Tensor  # [Q, 3] colours of rays that miss (for a learned background)
    errors: torch.Tensor  # [P] each ray's squared error when it was last trained on
    view: torch.Tensor  # [P] int64 index of the ray's training view
    edge: torch.Tensor  # [P] bool: the pixel is within one pixel of the object's silhouette
    pixel_axes: torch.Tensor  # [V, 3, 3] per view: world vectors of +1 px in u, in v, and z


def pixel_axes(cam) -> np.ndarray:
    """[3, 3]: the world vectors of one pixel step in u and in v on the camera's z = 1 plane,
    and the camera's z axis."""
    rot = cam.camera_to_world[:3, :3]
    return np.stack([rot[:, 0] / cam.fx, rot[:, 1] / cam.fy, rot[:, 2]])


def subpixel_dirs(dirs: torch.Tensor, axes: torch.Tensor, s: int) -> torch.Tensor:
    """Unit directions through pixel centres [n, 3] -> through the centres of each pixel's
    s x s sub-pixels [n * s * s, 3] (pixel by pixel; the box filter of `render_image`'s
    supersample); axes [n, 3, 3] from `pixel_axes`."""
    on_plane = dirs / (dirs * axes[:, 2]).sum(-1, keepdim=True)  # [n, 3] at camera z = 1
    offsets = (torch.arange(s, dtype=dirs.dtype, device=dirs.device) + 0.5) / s - 0.5  # [s]
    du, dv = offsets.repeat(s), offsets.repeat_interleave(s)  # [s*s] u fastest, as in images
    moved = (
        on_plane[:, None]
        + du[None, :, None] * axes[:, None, 0]
        + dv[None, :, None] * axes[:, None, 1]
    )  # [n, s*s, 3]
    moved = moved / moved.norm(dim=-1, keepdim=True)
    return moved.reshape(-1, 3)


class RaySelector:
    """Draws each step's rays: `error_fraction` of them in proportion to the rays' last
    errors (`pool.errors`, updated by `record`), the rest uniformly, so the rays still wrong --
    silhouettes, fine texture -- come back more often. Rays never trained on keep the initial
    error, the mean error the field starts with, so they are drawn like average ones."""

    def __init__(self, pool: RayPool, error_fraction: float, generator: torch.Generator):
        self.pool, self.generator = pool, generator
        self.error_fraction = error_fraction

    def draw(self, n: int) -> torch.Tensor:
        """Indices [n] into the pool."""
        n_error = int(round(n * self.error_fraction))
        n_pool = len(self.pool.errors)
        idx = torch.randint(n_pool, (n - n_error,), generator=self.generator)
        if n_error:
            weights = self.pool.errors.cpu()
            by_error = torch.multinomial(
                weights, n_error, replacement=True, generator=self.generator
            )
            idx = torch.cat([idx, by_error])
        return idx.to(self.pool.errors.device)

    def record(self, idx: torch.Tensor, errors: torch.Tensor) -> None:
        """Stores the squared errors [n] of the rays `idx` [n] just trained on."""
        self.pool.errors[idx] = errors.detach().clamp_min(1e-6)


def silhouette_edge(mask: np.ndarray) -> np.ndarray:
    """[H, W] mask -> [H, W] bool: pixels whose 3 x 3 neighbourhood holds both object and
    background (the one-pixel rings on both sides of the silhouette)."""
    inside = (np.asarray(mask) > 0.5).astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    return cv2.dilate(inside, kernel) != cv2.erode(inside, kernel)


def build_ray_pool(views, sampler, device: torch.device) -> RayPool:
    """Casts every training pixel's ray (only the sampler's `pixel_window` of each view: the
    others miss) and keeps those that hit, view by view in row-major order."""
    o_all, d_all, c_all, m_all, h_all, miss, v_all, axes = [], [], [], [], [], [], [], []
    e_all = []
    n_total = 0
    has_masks = all(m is not None for _, _, m in views)
    for i, (cam, image, mask) in enumerate(views):
        chosen, centres = cam.window_pixels(sampler_window(sampler, cam))  # [N], [N, 2]
        chosen = torch.from_numpy(chosen).to(device)
        o, d = (torch.from_numpy(a).to(device) for a in cam.rays(centres))
        hits = sampler.cast(o, d)
        hit = torch.zeros(cam.height * cam.width, dtype=torch.bool, device=device)
        hit[chosen] = hits.hit  # [H*W]
        rgb = torch.from_numpy(image.reshape(-1, 3)).to(device)
        m = torch.from_numpy(mask.reshape(-1)).float().to(device) if mask is not None else None
        n_total += len(hit)
        o_all.append(o[hits.hit])
        d_all.append(d[hits.hit])
        c_all.append(rgb[hit])
        m_all.append(m[hit] if m is not None else torch.ones(int(hit.sum()), device=device))
        v_all.append(torch.full((int(hit.sum()),), i, dtype=torch.int64, device=device))
        inside = mask if mask is not None else hit.reshape(cam.height, cam.width).cpu().numpy()
        e_all.append(torch.from_numpy(silhouette_edge(inside).reshape(-1)).to(device)[hit])
        axes.append(pixel_axes(cam))
        h_all.append(hits[hits.hit])
        miss.append(rgb[~hit][:: max(1, int((~hit).sum()) // 2000 + 1)])
    origins = torch.cat(o_all)
    pool = RayPool(
        origins,
        torch.cat(d_all),
        torch.cat(c_all),
        torch.cat(m_all),
        RayHits.cat(h_all),
        n_total,
        has_masks,
        torch.cat(miss),
        errors=torch.full((len(origins),), 0.05, device=device),  # ~ an untrained field's MSE
        view=torch.cat(v_all),
        edge=torch.cat(e_all),
        pixel_axes=torch.as_tensor(np.stack(axes), dtype=torch.float32, device=device),
    )
    if len(pool.origins) == 0:
        raise SineError(
            "no training ray hits the proxy mesh: check proxy_mesh.ply and cameras.json"
        )
    return pool
