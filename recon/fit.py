"""Fit the template radiance field on a run's captures (`sine fit RUN`).

Reads images/, masks/ (optional), cameras.json (split train/test) and proxy_mesh.ply; casts every
training ray once against the proxy (and its inflated copy) and trains only on the rays that hit
it (the others are background and need no field). Trains with `recon.training.Trainer` in
RUN/template.partial/ and, once finished, moves that to RUN/template/:

    checkpoint.pt      the training state (field, its moving average, background, optimizer,
                       schedule, step, RNG states); written atomically every `checkpoint_every`
                       steps and every `checkpoint_seconds`; a re-run resumes from it
                       (`--force` starts over)
    field.pt           the final field for later stages, the moving average of the last steps'
                       weights (`--average-window`; `load_template`; configs as JSON text,
                       loads with weights_only=True)
    metrics.json       held-out PSNR/SSIM on object pixels (heldout_psnr_object, the headline)
                       and whole images (heldout_psnr, heldout_ssim), rays/s, samples/s, ...
    previews/NAME.png  held-out renders (left) next to the ground truth (right)
    log.json           loss / PSNR every `log_every` steps
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import torch

from recon.formats import FORMAT_VERSIONS, check_format
from recon.proxy_mesh import write_mesh
from recon.proxy_refine import REFINE_MIN_COMPONENT
from recon.rundir import RunDir
from recon.selfcheck import require_trusted_poses
from recon.training import (
    RUNTIME_KEYS,
    LoopOptions,
    Trainer,
    discard_unstarted,
    exponential_decay,
    loop_options,
)
from render.configs import from_json, option, to_dict, to_json, validate
from render.device import pick_device, torch_threads
from render.errors import SineError
from render.hashgrid import HashGridConfig
from render.io import (
    load_torch,
    read_image,
    read_json,
    read_mask,
    save_torch,
    write_image,
    write_json,
)
from render.locks import lock_folder
from render.metrics import masked_psnr, masked_ssim, psnr, psnr_of_mse
from render.renderer import render_image, render_rays
from render.sampler import BandSampler, ProxyRaycaster, RayHits, UniformSampler, sampler_window
from render.template_field import Background, TemplateField, TemplateFieldConfig

# What `--preset` sets (options given explicitly win). Timings: 2 cores, 36 views of 256 px.
# The cheaper step of fast and default (a 64-wide density head, 12 band samples: ~1.3x the
# rays per second) costs 0.1 dB held-out object PSNR on average (-0.20..+0.09 over seven paired
# fits; bench/RESULTS.md, "Presets") and keeps the dinosaur's default fit under
# 5 minutes; quality keeps the wider, denser step.
_CHEAP_STEP = {"density_hidden": 64, "band_samples": 12}
PRESETS: dict[str, dict[str, int]] = {
    # ~30 s: a first look
    "fast": {
        "iterations": 300,
        "batch_rays": 1024,
        "log2_table": 17,
        "detail_steps": 300,
        **_CHEAP_STEP,
    },
    # <= 5 min
    "default": {
        "iterations": 1500,
        "batch_rays": 2048,
        "log2_table": 17,
        "detail_steps": 1500,
        **_CHEAP_STEP,
    },
    # 2^19 rows per level: fewer hash collisions (spot +0.5 dB at 1500 steps), ~15 % slower;
    # colour-detail steps as the default's (3000 fitted the dinosaur's training views closer,
    # its held-out views no better)
    "quality": {
        "iterations": 3500,
        "batch_rays": 4096,
        "log2_table": 19,
        "detail_steps": 1500,
        "density_hidden": 128,
        "band_samples": 16,
    },
}


DEFAULT_REFINE_AT = 0.2  # refine an estimated proxy after every 20 % of the steps,
DEFAULT_REFINE_ROUNDS = 4  # four times (templeSparseRing 19.8 -> 21.1 dB against once at 30 %)
START_BAND = 3.0  # the band before the first refinement, in final band widths, where the
# recon's depth was the visual hull's alone (bench/RESULTS.md "The start band by proxy vertex")
EDGE_SUPERSAMPLE = 2  # rays per side on the masks' edge pixels when the masks are the capture's
FALLBACK_MAX_RESOLUTION = 512  # --max-resolution without views to match it to
DETAIL_BASE_RESOLUTION = 64  # the colour-detail grid's coarsest level (cells per axis)


def masks_from_capture(report: dict) -> bool:
    """Whether every view's mask came with the capture (a mask file or RGBA alpha), by the
    run's recon_report.json ({} when there is none), i.e. none was estimated by `sine recon`:
    renders' and alpha masks are the pixels' coverage, so their boundary is where a pixel is
    part object, part background (the box filter's `edge` pixels); estimated masks are not
    that exact."""
    return report.get("masks_automatic", 1) == 0 and report.get("masks_given", 0) > 0


def pixel_resolution(cameras, bound: float = 1.0) -> int:
    """The grid resolution over [-bound, bound]^3 whose cell is one pixel's footprint at the
    object's centre (the origin): 2 * bound / (distance / focal length), the median over the
    cameras. Rays through pixel centres sample a surface about once per such cell, so a
    finer level is constrained by no more than one ray per cell in each view: it memorises
    that view's pixels instead of the surface (held-out views get its aliasing)."""
    footprints = [
        np.linalg.norm(np.asarray(c.camera_to_world)[:3, 3]) / (0.5 * (c.fx + c.fy))
        for c in cameras
    ]
    return max(2, int(math.ceil(2.0 * bound / float(np.median(footprints)))))


@dataclass
class FitConfig(LoopOptions):
    """Options of `sine fit` (template radiance field)."""

    preset: str = option(
        "default",
        "time/quality trade-off: fast (about a tenth of default's time), default, or quality "
        "(about 4x default's time); sets --iterations, --batch-rays, --log2-table, "
        "--detail-steps, --density-hidden and --band-samples unless given",
        choices=list(PRESETS),
    )
    iterations: int | None = option(
        None, "training steps (None: the preset's: fast 300, default 1500, quality 3500)", low=1
    )
    batch_rays: int | None = option(
        None,
        "rays per step, only rays that hit the inflated proxy (None: the preset's: fast 1024, "
        "default 2048, quality 4096)",
        low=1,
    )
    lr_grid: float = option(2e-2, "Adam learning rate of the hash table", low=0.0)
    lr_mlp: float = option(1e-2, "Adam learning rate of the MLP heads", low=0.0)
    lr_final_factor: float = option(
        0.1, "learning rates decay exponentially to this factor", low=0.0, high=1.0
    )
    average_window: float = option(
        0.07,
        "the saved field is an exponential moving average of the weights over about this "
        "fraction of the last steps (from half-way on), against the noise of the last random "
        "batches (0: the last step's weights)",
        low=0.0,
        high=0.5,
    )
    log2_table: int | None = option(
        None,
        "log2 of the hash-table rows per level (CPU: 14-19; None: the preset's: 17, quality 19)",
        low=4,
        high=24,
    )
    levels: int = option(16, "hash-grid levels", low=1, high=32)
    density_hidden: int | None = option(
        None,
        "hidden width of the density MLP (one hidden layer after the hash grid; None: the "
        "preset's: fast and default 64, quality 128)",
        low=1,
    )
    detail_steps: int | None = option(
        None,
        "steps of the colour-detail phase after the main steps: with the density frozen, a "
        "second hash grid read only by the colour learns the fine texture (0: off; None: the "
        "preset's: fast 300, default and quality 1500)",
        low=0,
    )
    detail_check: float = option(
        0.2,
        "the first fraction of the colour-detail steps trains without every 6th training view "
        "(with >= 6 views); the branch is kept only if it renders those views' rays better than "
        "the field without it, then trains on all rays for the rest, else it is dropped (a "
        "sparse ring whose template fails: the branch memorises its few views; 0: no check)",
        low=0.0,
        high=1.0,
    )
    detail_batch_rays: int = option(4096, "rays per colour-detail step", low=1)
    detail_levels: int = option(
        8, "levels of the colour-detail grid (from 64 cells to --max-resolution)", low=1, high=32
    )
    detail_log2_table: int = option(
        18, "log2 of the colour-detail grid's hash-table rows per level", low=4, high=24
    )
    max_resolution: int | None = option(
        None,
        "finest hash-grid resolution over [-1, 1]^3 (None: matched to the training images, one "
        "finest cell per pixel at the object's centre; finer levels only memorise each view's "
        "pixels)",
        low=2,
    )
    sampler: str = option(
        "band", "ray sampler: proxy band or the paper's uniform 64+128", choices=["band", "uniform"]
    )
    band_samples: int | None = option(
        None,
        "samples in the band [t_hit - d, t_hit + d] (band sampler; None: the preset's: fast "
        "and default 12, quality 16); renders and edits of the template use the same",
        low=1,
    )
    coarse_samples: int = option(
        4,
        "coarse samples over the ray-in-sphere interval (band) "
        "or stratified coarse samples (uniform)",
        low=0,
    )
    importance_samples: int = option(128, "importance samples (uniform sampler only)", low=0)
    band_width: float = option(0.04, "band half-width d and proxy inflation, in run units", low=0.0)
    band_width_start: float | None = option(
        None,
        "band half-width before the first proxy refinement where the recon's depth came from "
        "the visual hull alone (an outer bound), --band-width where stereo found it, linear in "
        "between; narrowed each round to --band-width after the last (None: 3 x --band-width "
        "when the proxy is refined; 0: --band-width throughout; ignored without refinement)",
        low=0.0,
    )
    uniform_coarse: int = option(64, "stratified coarse samples (uniform sampler)", low=1)
    mask_weight: float = option(0.1, "weight of the opacity-vs-mask BCE loss (0: off)", low=0.0)
    sh_degree: int = option(
        4,
        "spherical-harmonics degree of the view direction fed to the colour (1: colour does "
        "not depend on the view, for matte objects; 4: shiny ones)",
        low=1,
        high=4,
    )
    refine_proxy: float | None = option(
        None,
        "after this fraction of the steps, replace the proxy by one fused from the field's own "
        "depth (NeuS-style refine loop; template/proxy_mesh.ply) and train the rest in its band "
        "(0: off; None: 0.2 with 4 rounds when the proxy came from hull + stereo depth, off for "
        "dataset depth or runs without recon_report.json)",
        low=0.0,
        high=0.9,
    )
    refine_rounds: int | None = option(
        None,
        "refinements of the proxy: after --refine-proxy x k of the steps for k = 1..N, each "
        "fused from the field trained in the last one's band, so the band follows the surface "
        "the field finds (rounds at or after the last step are left out; None: 4 when "
        "--refine-proxy is chosen by the run, else 1)",
        low=1,
    )
    refine_views: int = option(
        16, "training views rendered for the proxy refinement (evenly spaced; 0: all)", low=0
    )
    refine_min_component: float = option(
        REFINE_MIN_COMPONENT,
        "separate parts of a refined proxy are kept down to this fraction of the largest one's "
        "triangles (below recon's --min-component, as the carving can cut a part off at a thin "
        "joint; too low keeps TSDF specks)",
        low=0.0,
        high=1.0,
    )
    train_supersample: int | None = option(
        None,
        "train the pixels on the masks' edge (or the proxy's silhouette without masks) on the "
        "box filter of s x s rays, as a camera integrates a pixel; --batch-rays counts rays, so "
        "a batch holds fewer pixels (None: 2 when every view's mask came with the capture, "
        "else 1)",
        low=1,
        high=4,
    )
    error_sampling: float = option(
        0.5,
        "fraction of each batch drawn in proportion to the rays' last squared errors "
        "(silhouettes and fine texture get more rays; 0: all uniform)",
        low=0.0,
        high=1.0,
    )
    background: str = option(
        "auto",
        "background: auto (from masks: a plain colour, or capture when the backdrop varies), "
        "white, black, learn (one colour), capture (rays outside the masks are composited over "
        "their own captured pixel, so the field never explains a real backdrop; renders use a "
        "learned colour)",
        choices=["auto", "white", "black", "learn", "capture"],
    )
    previews: int = option(4, "held-out views written as previews (0: none)", low=0)
    seed: int = option(0, "random seed (ray batches, jitter, initialisation)", low=0)
    eval_views: int = option(0, "held-out views to render for the metrics (0: all)", low=0)
    eval_chunk: int = option(16384, "rays per chunk when rendering held-out views", low=1)
    supersample: int = option(
        2,
        "rays per pixel side when rendering this template (held-out metrics, `sine render`, "
        "`sine eval`, snapshots, edits): s x s rays box-filtered, s^2 times the render time "
        "(1: one ray through each pixel centre). With s > 1 the pixels a silhouette crosses "
        "are rendered again with 2s x 2s rays",
        low=1,
    )


def resolve_preset(cfg: FitConfig, run: RunDir | None = None) -> FitConfig:
    """`cfg` with the options left at None taken from its preset (and, for `refine_proxy`,
    from how the run's proxy was made: recon_report.json's depth_source; for
    `train_supersample`, from where its masks came from:
    `masks_from_capture`; for `max_resolution`, from the training cameras:
    `pixel_resolution`)."""
    preset = PRESETS.get(cfg.preset)
    if preset is None:
        raise SineError(f"--preset must be one of {', '.join(PRESETS)} (got {cfg.preset!r})")
    chosen = {k: v for k, v in preset.items() if getattr(cfg, k) is None}
    report = {}
    if run is not None and run.recon_report.is_file():
        report = read_json(run.recon_report)
    if cfg.refine_proxy is None:
        source = report.get("depth_source")
        estimated = source is not None and source != "dataset"
        chosen["refine_proxy"] = DEFAULT_REFINE_AT if estimated else 0.0
        if cfg.refine_rounds is None:
            chosen["refine_rounds"] = DEFAULT_REFINE_ROUNDS if estimated else 1
    elif cfg.refine_rounds is None:
        chosen["refine_rounds"] = 1
    if cfg.band_width_start is None:
        refined = chosen.get("refine_proxy", cfg.refine_proxy) > 0
        chosen["band_width_start"] = cfg.band_width * (START_BAND if refined else 1)
    if cfg.train_supersample is None:
        exact = masks_from_capture(report)
        chosen["train_supersample"] = EDGE_SUPERSAMPLE if exact else 1
    if cfg.max_resolution is None:
        known = run is not None and run.cameras.is_file()
        train = [c for c in run.load_cameras().frames if c.split == "train"] if known else []
        chosen["max_resolution"] = pixel_resolution(train) if train else FALLBACK_MAX_RESOLUTION
    return replace(cfg, **chosen)


# ---- data ---------------------------------------------------------------------------------
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


def template_proxy(run: RunDir) -> Path:
    """The proxy mesh the template was fitted around: template/proxy_mesh.ply when the fit
    refined it (`--refine-proxy`), else the run's proxy_mesh.ply."""
    refined = run.template / "proxy_mesh.ply"
    return refined if refined.is_file() else run.proxy_mesh


def band_at_round(cfg: FitConfig, stereo, mesh, done: int):
    """The band half-width around a proxy (`mesh`: vertices [V, 3], faces [F, 3]) after
    `done` refinement rounds: --band-width, or while rounds remain, one width per vertex [V]:
    `band_widths`' width for the round where the recon's depth was the visual hull's alone
    in every view that sees the vertex, --band-width where stereo measured it in all of
    them, linear in the share between (`recon.proxy_band`; `stereo`: what its
    `stereo_pixels` found in the run, None: the round's width everywhere), each narrowing
    geometrically."""
    from recon.proxy_band import unmeasured_share

    widest = band_widths(cfg)[done]
    if widest <= cfg.band_width or stereo is None:
        return widest
    share = unmeasured_share(stereo, *mesh)
    start = cfg.band_width + (cfg.band_width_start - cfg.band_width) * share  # [V]
    left = math.log(widest / cfg.band_width) / math.log(cfg.band_width_start / cfg.band_width)
    return cfg.band_width * (start / cfg.band_width) ** left  # [V]


def make_sampler(
    cfg: FitConfig, run: RunDir, proxy: Path | None = None, done: int | None = None, stereo=None
):
    """The fit's ray sampler around `proxy` (default: `template_proxy(run)`): the band
    --band-width wide, or, during the fit, the band after `done` refinement rounds
    (`band_at_round`, with `stereo`)."""
    if cfg.sampler == "uniform":
        return UniformSampler(cfg.uniform_coarse, cfg.importance_samples)
    proxy = proxy or template_proxy(run)
    mesh = run.read_proxy(proxy)
    width = cfg.band_width
    if done is not None:
        arrays = (np.asarray(mesh.vertices), np.asarray(mesh.triangles))
        width = band_at_round(cfg, stereo, arrays, done)
    return BandSampler(ProxyRaycaster(mesh, inflate=width), cfg.band_samples, cfg.coarse_samples)


def field_config(cfg: FitConfig) -> TemplateFieldConfig:
    grid = HashGridConfig(
        n_levels=cfg.levels, log2_table=cfg.log2_table, max_resolution=cfg.max_resolution
    )
    detail = None
    if cfg.detail_steps:
        detail = HashGridConfig(
            n_levels=cfg.detail_levels,
            log2_table=cfg.detail_log2_table,
            base_resolution=min(DETAIL_BASE_RESOLUTION, cfg.max_resolution),
            max_resolution=cfg.max_resolution,
        )
    return TemplateFieldConfig(
        grid=grid, density_hidden=cfg.density_hidden, sh_degree=cfg.sh_degree, detail=detail
    )


def load_fitted(run_dir, device: torch.device | None = None):
    """(field, background, FitConfig it was fitted with) of a run (RUN/template/field.pt)."""
    run = RunDir(run_dir)
    path = run.template / "field.pt"
    if not path.is_file():
        raise SineError(f"{path} not found; run `sine fit {run.root}` first")
    data = load_torch(path, rebuild=f"`sine fit {run.root} --force`")
    check_format(data, path, "fit", f"`sine fit {run.root} --force`")
    field = TemplateField(from_json(TemplateFieldConfig, data["field_config"]))
    field.load_state_dict(data["field"])
    bg = Background(data["background_color"], learnable=False)
    fit_cfg = from_json(FitConfig, data["fit_config"])
    device = device or torch.device("cpu")
    return field.to(device).eval(), bg.to(device), fit_cfg


def load_template(run_dir, device: torch.device | None = None) -> tuple[TemplateField, Background]:
    """The fitted field and background of a run (RUN/template/field.pt)."""
    field, bg, _ = load_fitted(run_dir, device)
    return field, bg


def refinement_steps(cfg: FitConfig) -> list[int]:
    """The steps after which the proxy is refined: --refine-proxy x k x iterations for k = 1..
    --refine-rounds, those at step 0 or at / after the last step left out (none for the
    uniform sampler or --refine-proxy 0)."""
    if cfg.sampler != "band" or cfg.refine_proxy <= 0:
        return []
    rounds = range(1, cfg.refine_rounds + 1)
    steps = {round(cfg.iterations * cfg.refine_proxy * k) for k in rounds}
    return sorted(s for s in steps if 0 < s < cfg.iterations)


def band_widths(cfg: FitConfig) -> list[float]:
    """The band half-width before the first proxy refinement and after each
    (`refinement_steps`): from --band-width-start to --band-width by a constant factor."""
    n = len(refinement_steps(cfg))
    start = cfg.band_width_start
    if n == 0 or start is None or start <= 0:
        return [cfg.band_width] * (n + 1)
    return [start * (cfg.band_width / start) ** (k / n) for k in range(n + 1)]


def refinements_done(proxy_state: dict | None) -> int:
    """Rounds of proxy refinement recorded in a fit's checkpointed proxy state."""
    return int((proxy_state or {}).get("rounds", 0))


def refine_with_field(
    run: RunDir,
    cfg: FitConfig,
    field,
    sampler,
    device,
    progress: bool = True,
    proxy: Path | None = None,
    old_ious: list[float] | None = None,
) -> tuple:
    """A proxy fused from the partly trained field's depth (recon.proxy_refine), the views
    seen beyond `proxy` (default: the run's proxy_mesh.ply; `old_ious` its silhouette IoU per
    training view when known) carving it -> (mesh, JSON-able stats: silhouette IoU
    before/after, triangles, seconds; the new proxy's IoU per training view or None)."""
    from recon.proxy_refine import RefineConfig, refine_run

    refine_cfg = RefineConfig(
        refine_views=cfg.refine_views, refine_min_component=cfg.refine_min_component
    )
    mesh, stats = refine_run(
        run, field, sampler, refine_cfg, device, progress, proxy=proxy, old_ious=old_ious
    )
    plain = {k: v for k, v in stats.items() if isinstance(v, bool | int | float | str)}
    print(
        f"fit: proxy refined from the field's depth: silhouette IoU "
        f"{plain.get('silhouette_iou_before', float('nan')):.3f} -> "
        f"{plain.get('silhouette_iou_after', float('nan')):.3f}"
    )
    return mesh, plain, stats.get("silhouette_ious_after")


def field_average(field: TemplateField, window: float, iterations: int):
    """An exponential moving average of `field`'s parameters over about `window` x
    `iterations` steps (torch's AveragedModel: the first `update_parameters` copies them, each
    later one moves the average by 1 / (window x iterations) towards them); buffers are not
    averaged (the field's are fixed). Started half-way, the first copy's weight in the end is
    exp(-0.5 / window): 0.0008 at 0.07, whatever the step count."""
    decay = 1.0 - 1.0 / max(1.0, window * iterations)
    return torch.optim.swa_utils.AveragedModel(
        field, multi_avg_fn=torch.optim.swa_utils.get_ema_multi_avg_fn(decay)
    )


# ---- metrics ------------------------------------------------------------------------------
def evaluate(
    field,
    background,
    sampler,
    views,
    device,
    chunk=16384,
    preview_dir=None,
    n_previews=0,
    supersample=1,
):
    """Renders held-out views -> metrics: on object pixels (the views' masks; the headline,
    since a plain background inflates whole-image figures) and over whole images."""
    from skimage.metrics import structural_similarity

    field.eval()
    psnrs, ssims, samples, obj_psnrs, obj_ssims = [], [], [], [], []
    for i, (cam, image, mask) in enumerate(views):
        out = render_image(cam, field, sampler, background, chunk, device, supersample)
        pred = np.clip(out["rgb"], 0.0, 1.0)
        psnrs.append(psnr(pred, image))
        ssims.append(float(structural_similarity(image, pred, channel_axis=2, data_range=1.0)))
        samples.append(float(out["samples_per_pixel"]))
        if mask is not None and mask.any():
            obj_psnrs.append(masked_psnr(pred, image, mask))
            obj_ssims.append(masked_ssim(pred, image, mask))
        if preview_dir is not None and i < n_previews:
            write_image(
                Path(preview_dir) / (Path(cam.name).stem + ".png"),
                np.concatenate([pred, image], axis=1),
            )
    field.train()
    if not psnrs:
        return {}
    obj = {}
    if obj_psnrs:
        obj = {
            "heldout_psnr_object": float(np.mean(obj_psnrs)),
            "heldout_ssim_object": float(np.mean(obj_ssims)),
        }
    return {
        **obj,
        "heldout_psnr": float(np.mean(psnrs)),
        "heldout_ssim": float(np.mean(ssims)),
        "heldout_views": len(psnrs),
        "heldout_psnr_min": float(np.min(psnrs)),
        "heldout_samples_per_pixel": float(np.mean(samples)),
    }


# ---- training ---------------------------------------------------------------------------------
def _train_detail(
    cfg: FitConfig,
    trainer,
    field,
    sampler,
    pool,
    background,
    behind_capture,
    phases: dict,
    stop_at,
) -> dict:
    """The colour-detail phase (recon/colour_detail.py) on the frozen main field: the training
    rays' samples cached, the check (--detail-check: the branch trained without some views,
    kept only if it renders them better; the verdict recorded in `phases`), then the branch's
    steps on all rays up to the trainer's last step. Returns its statistics for metrics.json."""
    from recon.colour_detail import (
        build_detail_cache,
        check_psnr,
        check_views,
        detail_rays,
        detail_step,
        reset_branch,
    )

    t_cache = time.perf_counter()
    for p in field.parameters():
        p.requires_grad_(False)
    for p in (*field.detail_grid.parameters(), *field.detail_net.parameters()):
        p.requires_grad_(True)
    field.detail_active = True
    # the same rays on a resume: their own generator, not the loop's
    rays = detail_rays(pool, cfg.train_supersample > 1, torch.Generator().manual_seed(cfg.seed))
    behind = background().detach().expand(len(rays), 3)
    if behind_capture:  # outside the masks, the captured pixel itself (as in the main steps)
        behind = torch.where(pool.mask[rays, None] < 0.5, pool.rgb[rays], behind)
    cache = build_detail_cache(field, sampler, pool, rays, behind, cfg.eval_chunk)
    cache_seconds = time.perf_counter() - t_cache
    held = check_views(pool.view[rays], len(pool.pixel_axes))  # every training view
    check_end = cfg.iterations + round(cfg.detail_check * cfg.detail_steps)
    checked = bool(held.any()) and check_end > cfg.iterations
    if checked and trainer.step < check_end:  # first without the held-out views
        kept_rays = torch.nonzero(~held)[:, 0]
        trainer.run(
            lambda i: detail_step(
                field, cache, cfg.detail_batch_rays, trainer.generator, among=kept_rays
            ),
            check_end if stop_at is None else min(stop_at, check_end),
        )
        if trainer.step < check_end:  # stopped early on purpose
            return {}
    if checked and "detail_check" not in phases:  # the verdict, once (kept in the checkpoint)
        without, with_branch = check_psnr(field, cache, torch.nonzero(held)[:, 0])
        phases["detail_check"] = {
            "psnr_without": without,
            "psnr_with": with_branch,
            "kept": with_branch > without,
        }
        if not phases["detail_check"]["kept"]:
            print(
                f"fit: the colour-detail branch renders the held-out training views worse "
                f"({with_branch:.2f} dB against {without:.2f} without it): dropped"
            )
        trainer.checkpoint()
    verdict = phases.get("detail_check", {})
    kept = verdict.get("kept", True)  # no check: kept
    if kept:
        trainer.run(
            lambda i: detail_step(field, cache, cfg.detail_batch_rays, trainer.generator),
            stop_at,
        )
    else:  # the field renders as without the branch; no step is left to take
        reset_branch(field)
        trainer.skip_to_end()
    field.eval()
    stats = {
        "detail_steps": cfg.detail_steps,
        "detail_cached_rays": len(cache),
        "detail_samples_per_ray": len(cache.points) / max(len(cache), 1),
        "detail_cache_seconds": cache_seconds,
    }
    if not kept:
        stats["detail_steps_taken"] = check_end - cfg.iterations
    if verdict:
        stats.update(
            detail_check_psnr_without=verdict["psnr_without"],
            detail_check_psnr_with=verdict["psnr_with"],
            detail_kept=verdict["kept"],
        )
    return stats


# Settings that do not change the result: a checkpoint made with other values still resumes.
_RUNTIME_KEYS = RUNTIME_KEYS + (
    "eval_chunk",
    "eval_views",
    "supersample",
    "previews",
)


def fit_template(
    run_dir,
    cfg: FitConfig | None = None,
    force: bool = False,
    progress: bool = True,
    stop_at: int | None = None,
) -> dict:
    """Trains (or resumes) the template of `run_dir`; returns the metrics dict (with
    "skipped": True when it was already fitted with these options).

    `stop_at` ends this call after that step, with a checkpoint (as if interrupted).
    """
    run = RunDir(run_dir)
    run.require("cameras")
    cfg = validate(resolve_preset(cfg or FitConfig(), run))
    require_trusted_poses(run)
    if not run.proxy_mesh.is_file() and cfg.sampler == "band":
        raise SineError(f"{run.root} has no proxy_mesh.ply yet; run `sine recon {run.root}` first")
    device = pick_device(cfg.device)
    with lock_folder(run.root, f"run {run.root}"), discard_unstarted(run.template):
        with torch_threads(cfg.threads):
            return _fit(run, cfg, device, force, progress, stop_at)


# what a template is made from: a run whose recon changed them is fitted again
FIT_INPUTS = ("cameras.json", "proxy_mesh.ply", "images", "masks")


def _fit(run: RunDir, cfg: FitConfig, device, force: bool, progress: bool, stop_at) -> dict:
    t_start = time.perf_counter()
    trainer = Trainer(
        run.template,
        "fit",
        to_dict(cfg),
        _RUNTIME_KEYS,
        **{**loop_options(cfg), "iterations": cfg.iterations + cfg.detail_steps},
        force=force,
        progress=progress,
        advice="lower learning rates (e.g. half of --lr-grid and --lr-mlp)",
        format_version=FORMAT_VERSIONS["fit"],
        defaults=to_dict(FitConfig()),
        inputs=run.inputs(*FIT_INPUTS),
        outputs=("field.pt",),
    )
    done = trainer.finished()  # before any data is loaded: a finished fit costs nothing
    if done is not None:
        return done

    train_views = load_views(run, "train")
    test_views = load_views(run, "test") or load_views(run, "val")
    if cfg.eval_views > 0:
        test_views = test_views[: cfg.eval_views]
    if not train_views:
        raise SineError(f"{run.cameras} has no frame with split 'train'")
    bg_color, bg_learn = background_color(train_views, cfg.background)
    refine_steps = refinement_steps(cfg)
    refined_proxy = trainer.work_dir / "proxy_mesh.ply"
    proxy_state = {"refined": False}  # + rounds, the last round's stats, IoU by round (saved)
    saved_rounds = refinements_done(trainer.saved("proxy"))
    stereo = None  # which pixels the recon's stereo measured, for the start band by vertex
    if cfg.sampler == "band" and band_widths(cfg)[0] > cfg.band_width:
        from recon.proxy_band import stereo_pixels

        stereo = stereo_pixels(run)
    start_proxy = refined_proxy if saved_rounds else run.proxy_mesh
    sampler = make_sampler(cfg, run, start_proxy, saved_rounds, stereo)
    pool = build_ray_pool(train_views, sampler, device)

    torch.manual_seed(cfg.seed)
    field = TemplateField(field_config(cfg)).to(device)
    field.detail_active = False  # the colour-detail branch learns after the main steps
    background = Background(bg_color, learnable=bg_learn).to(device)
    if cfg.background == "capture" and not pool.has_masks:
        raise SineError(
            "--background capture composites rays outside the object masks over their captured "
            f"pixels, but {run.root} has no masks: run `sine recon` (it makes them) or choose "
            "--background learn|white|black"
        )
    behind_capture = pool.has_masks and (
        cfg.background == "capture" or (cfg.background == "auto" and bg_learn)
    )
    averaged = None  # the moving average of the weights, from half-way (--average-window)
    if cfg.average_window > 0:
        averaged = field_average(field, cfg.average_window, cfg.iterations)
    groups = field.param_groups(cfg.lr_grid, cfg.lr_mlp)
    if bg_learn:
        groups.append(
            {"params": list(background.parameters()), "lr": cfg.lr_mlp, "name": "background"}
        )
    # the main steps decay over cfg.iterations; the detail branch's (no gradient before) after
    main_decay = exponential_decay(cfg.lr_final_factor, cfg.iterations)
    detail_decay = exponential_decay(cfg.lr_final_factor, cfg.detail_steps)
    schedules = {group["name"]: main_decay for group in groups}
    detail_groups = field.detail_param_groups(cfg.lr_grid, cfg.lr_mlp)
    for group in detail_groups:
        schedules[group["name"]] = lambda i: detail_decay(max(0, i - cfg.iterations))
    phases = {"main_seconds": None}  # the main steps' training time, once they are done
    edge_share = [float(pool.edge.float().mean())]  # of the last batch's pixels ("edge")
    state = {
        "edge_share": edge_share,  # sizes the next batch: resumed with the rest
        "field": field,
        "background": background,
        "ray_errors": pool.errors,
        "proxy": proxy_state,
        "phases": phases,
    }
    if averaged is not None:
        state["averaged"] = averaged
    trainer.start(state, groups + detail_groups, schedules)
    generator = trainer.generator
    selector = RaySelector(pool, cfg.error_sampling, generator)

    sub = cfg.train_supersample**2  # rays per box-filtered training pixel
    average_from = cfg.iterations // 2 if averaged is not None else None

    def step(i: int) -> dict[str, torch.Tensor]:
        if average_from is not None and i >= average_from:  # the weights after i steps
            averaged.update_parameters(field)
        boxed_fraction = edge_share[0] if sub > 1 else 0.0
        n_pixels = max(1, round(cfg.batch_rays / (1 - boxed_fraction + boxed_fraction * sub)))
        idx = selector.draw(n_pixels)  # uniform pixels first, then those drawn by error
        n_boxed = 0
        if sub > 1:  # the edge pixels last, boxed
            on_edge = pool.edge[idx]
            idx = torch.cat([idx[~on_edge], idx[on_edge]])
            n_boxed = int(on_edge.sum())
            edge_share[0] = n_boxed / len(idx)
        n_single = len(idx) - n_boxed
        dirs = pool.dirs[idx]  # [n, 3]
        rays = idx  # [r] the pool ray (pixel) of each ray rendered
        if n_boxed:  # the sub-pixel rays share their pixel's band (a pixel is << the band)
            boxed = idx[n_single:]
            sub_dirs = subpixel_dirs(
                dirs[n_single:], pool.pixel_axes[pool.view[boxed]], cfg.train_supersample
            )
            dirs = torch.cat([dirs[:n_single], sub_dirs])
            rays = torch.cat([idx[:n_single], boxed.repeat_interleave(sub)])
        behind = background
        if behind_capture:  # [r, 3]: outside the masks, the captured pixel itself
            outside = pool.mask[rays, None] < 0.5
            behind = torch.where(outside, pool.rgb[rays], background()[None].expand(len(rays), 3))
        out = render_rays(
            field,
            pool.origins[rays],
            dirs,
            sampler,
            behind,
            hits=pool.hits[rays],
            perturb=True,
            generator=generator,
        )
        if n_boxed:  # the box filter of each boxed pixel's rays
            for key in ("rgb", "opacity"):
                value = out[key]
                means = value[n_single:].reshape(n_boxed, sub, *value.shape[1:]).mean(1)
                out[key] = torch.cat([value[:n_single], means])
        ray_errors = ((out["rgb"] - pool.rgb[idx]) ** 2).mean(dim=1)  # [n]
        selector.record(idx, ray_errors)
        terms = {"rgb": ray_errors.mean()}
        if cfg.mask_weight > 0 and pool.has_masks:
            acc = out["opacity"].clamp(1e-5, 1 - 1e-5)
            bce = torch.nn.functional.binary_cross_entropy(acc, pool.mask[idx])
            terms["mask"] = cfg.mask_weight * bce
        if background.learnable and len(pool.miss_rgb):
            j = torch.randint(len(pool.miss_rgb), (256,), generator=generator).to(device)
            terms["background"] = torch.mean((background()[None] - pool.miss_rgb[j]) ** 2)
        return terms

    field.train()
    main_end = cfg.iterations
    proxy_ious = None  # the current refined proxy's silhouette IoU per view (once computed)
    for refine_at in refine_steps[refinements_done(proxy_state) :]:
        leg_end = refine_at if stop_at is None else min(stop_at, refine_at)
        trainer.run(step, leg_end)
        if trainer.step < refine_at:  # stopped early on purpose
            return {"step": trainer.step}
        current = refined_proxy if proxy_state["refined"] else run.proxy_mesh
        t_refine = time.perf_counter()
        mesh, stats, proxy_ious = refine_with_field(
            run, cfg, field, sampler, device, trainer.progress, current, proxy_ious
        )
        write_mesh(refined_proxy, mesh)
        rounds = refinements_done(proxy_state) + 1  # with this one
        sampler = make_sampler(cfg, run, refined_proxy, rounds, stereo)
        pool = build_ray_pool(train_views, sampler, device)
        selector = RaySelector(pool, cfg.error_sampling, generator)
        trainer.state["ray_errors"] = pool.errors
        if "silhouette_iou_after" in stats:  # with masks: the IoU before round 1, after each
            history = proxy_state.get("silhouette_iou_rounds", [stats["silhouette_iou_before"]])
            stats["silhouette_iou_rounds"] = [*history, stats["silhouette_iou_after"]]
        spent = proxy_state.get("refine_seconds", 0.0) + time.perf_counter() - t_refine
        proxy_state.update(stats, refined=True, rounds=rounds, refine_seconds=spent)
        trainer.checkpoint()  # the refined proxy and the rays cast against it go together
        field.train()
    if trainer.step < main_end:
        trainer.run(step, main_end if stop_at is None else min(stop_at, main_end))
        if trainer.step < main_end:  # stopped early on purpose
            return {"step": trainer.step}
    if trainer.step == main_end:  # the main steps' end (resumed here: not done yet)
        phases["main_seconds"] = trainer.seconds
        if average_from is not None and main_end > average_from:  # the last step's weights too
            averaged.update_parameters(field)
            with torch.no_grad():
                for weights, average in zip(
                    field.parameters(), averaged.module.parameters(), strict=True
                ):
                    weights.copy_(average)
    detail_stats = {}
    if cfg.detail_steps:
        detail_stats = _train_detail(
            cfg, trainer, field, sampler, pool, background, behind_capture, phases, stop_at
        )
        if trainer.step < trainer.iterations:  # stopped early on purpose
            return {"step": trainer.step}
    for entry in trainer.log:
        entry["psnr"] = psnr_of_mse(entry["rgb"])

    save_torch(
        trainer.work_dir / "field.pt",
        {
            "format_version": FORMAT_VERSIONS["fit"],
            "field_config": to_json(field.cfg),
            "field": field.state_dict(),
            "background_color": background().detach().cpu().tolist(),
            "fit_config": to_json(cfg),
        },
    )
    t_eval = time.perf_counter()
    metrics = evaluate(
        field,
        background,
        sampler,
        test_views,
        device,
        cfg.eval_chunk,
        trainer.work_dir / "previews",
        cfg.previews,
        cfg.supersample,
    )
    main_seconds = phases["main_seconds"]
    rays_per_second = main_end * cfg.batch_rays / max(main_seconds, 1e-9)
    if detail_stats:
        detail_seconds = trainer.seconds - main_seconds
        detail_stats["detail_seconds"] = detail_seconds
        taken = detail_stats.get("detail_steps_taken", cfg.detail_steps)
        rate = taken * cfg.detail_batch_rays / max(detail_seconds, 1e-9)
        detail_stats["detail_rays_per_second"] = rate
    metrics.update(
        {
            "iterations": main_end,
            "train_seconds": trainer.seconds,
            "main_seconds": main_seconds,
            **detail_stats,
            "refine_seconds": proxy_state.get("refine_seconds", 0.0),
            "eval_seconds": time.perf_counter() - t_eval,
            "total_seconds": time.perf_counter() - t_start,
            "rays_per_second": rays_per_second,
            "samples_per_ray": sampler.samples_per_ray,
            "samples_per_second": rays_per_second * sampler.samples_per_ray,
            "sampler": cfg.sampler,
            "train_rays_needing_field": len(pool.origins),
            "train_rays_total": pool.n_total,
            "final_train_psnr": trainer.log[-1]["psnr"] if trainer.log else None,
            "background_color": background().detach().cpu().tolist(),
            "background_learned": bool(background.learnable),
            "background_behind_rays": "capture" if behind_capture else "colour",
            "proxy_refined": proxy_state,
            "device": str(device),
        }
    )
    write_json(trainer.work_dir / "metrics.json", metrics)
    trainer.publish(settings=cfg)
    run.append_config("fit", cfg)
    return metrics
