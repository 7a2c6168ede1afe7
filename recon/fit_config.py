"""The options of `sine fit` (`FitConfig`), its presets (`PRESETS`) and how the options left
at None are chosen for a run (`resolve_preset`), and the template field's config from them
(`field_config`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from recon.proxy_refine import REFINE_MIN_COMPONENT
from recon.rundir import RunDir
from recon.training import LoopOptions
from render.configs import option
from render.errors import SineError
from render.hashgrid import HashGridConfig
from render.io import read_json
from render.template_field import TemplateFieldConfig

# What `--preset` sets (options given explicitly win). Timings: 2 cores, 36 views of 256 px.
# The cheaper step of fast and default (a 64-wide density head, 12 band samples: ~1.3x the
# rays per second) costs 0.1 dB held-out object PSNR on average (-0.20..+0.09 over seven paired
# fits; bench/HISTORY.md, "Where a fit step's time goes, a cheaper step, and the quality preset") and keeps the dinosaur's default fit under
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
# recon's depth was the visual hull's alone (bench/HISTORY.md "The start band by proxy vertex")
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
