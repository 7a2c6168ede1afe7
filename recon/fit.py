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

This module holds the training loop and the loading of a fitted template; the options and
presets are in recon/fit_config.py, the views and training rays in recon/fit_data.py, the
proxy band and its refinement in recon/fit_proxy.py, the colour-detail phase in
recon/fit_detail.py and the held-out metrics in recon/fit_eval.py.
"""

from __future__ import annotations

import time

import torch

from recon.fit_config import FitConfig, field_config, resolve_preset
from recon.fit_data import (
    RaySelector,
    background_color,
    build_ray_pool,
    load_views,
    subpixel_dirs,
)
from recon.fit_detail import _train_detail
from recon.fit_eval import evaluate
from recon.fit_proxy import (
    band_widths,
    make_sampler,
    refine_with_field,
    refinement_steps,
    refinements_done,
)
from recon.formats import FORMAT_VERSIONS, check_format
from recon.proxy_mesh import write_mesh
from recon.rundir import RunDir
from recon.selfcheck import require_trusted_poses
from recon.training import (
    RUNTIME_KEYS,
    Trainer,
    discard_unstarted,
    exponential_decay,
    loop_options,
)
from render.configs import from_json, to_dict, to_json, validate
from render.device import pick_device, torch_threads
from render.errors import SineError
from render.io import load_torch, save_torch
from render.locks import lock_folder
from render.metrics import psnr_of_mse
from render.renderer import render_rays
from render.template_field import Background, TemplateField, TemplateFieldConfig


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


# ---- training ---------------------------------------------------------------------------------
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


def _make_trainer(run: RunDir, cfg: FitConfig, force: bool, progress: bool) -> Trainer:
    """The fit's trainer in RUN/template.partial/ (steps: the main ones and the colour-detail
    ones)."""
    return Trainer(
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


def _fit_views(run: RunDir, cfg: FitConfig) -> tuple[list, list]:
    """(training views, held-out views: the test split's, else the val split's, the first
    --eval-views of them)."""
    train_views = load_views(run, "train")
    test_views = load_views(run, "test") or load_views(run, "val")
    if cfg.eval_views > 0:
        test_views = test_views[: cfg.eval_views]
    if not train_views:
        raise SineError(f"{run.cameras} has no frame with split 'train'")
    return train_views, test_views


def _make_field(run: RunDir, cfg: FitConfig, pool, device, bg_color, bg_learn) -> tuple:
    """The field (seeded by --seed), the background, whether rays outside the masks end on
    their captured pixel, and the moving average of the field's weights (None without
    --average-window) -> (field, background, behind_capture, averaged)."""
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
    return field, background, behind_capture, averaged


def _param_groups(cfg: FitConfig, field, background, bg_learn) -> tuple[list, dict]:
    """The optimizer's parameter groups (the field's, the learned background's, the
    colour-detail branch's) and each group's learning-rate schedule by name."""
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
    return groups + detail_groups, schedules


def _main_step(
    cfg: FitConfig,
    field,
    background,
    averaged,
    average_from,
    edge_share: list,
    sub: int,
    behind_capture,
    sampler,
    pool,
    selector,
    generator,
    device,
):
    """One main training step on `pool`'s rays around `sampler`'s proxy (made again after
    each proxy refinement) -> the step's loss terms."""

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

    return step


def _refine_round(
    run: RunDir,
    cfg: FitConfig,
    trainer,
    field,
    sampler,
    device,
    train_views,
    stereo,
    refined_proxy,
    proxy_state: dict,
    proxy_ious,
) -> tuple:
    """One proxy refinement from the partly trained field: the refined proxy written, the
    training rays cast against it, the round recorded in `proxy_state` and checkpointed ->
    (sampler, pool, selector, proxy_ious) for the next steps."""
    generator = trainer.generator
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
    return sampler, pool, selector, proxy_ious


def _use_average(field, averaged) -> None:
    """The field takes the moving average of its weights, the last step's included."""
    averaged.update_parameters(field)
    with torch.no_grad():
        for weights, average in zip(field.parameters(), averaged.module.parameters(), strict=True):
            weights.copy_(average)


def _fit(run: RunDir, cfg: FitConfig, device, force: bool, progress: bool, stop_at) -> dict:
    t_start = time.perf_counter()
    trainer = _make_trainer(run, cfg, force, progress)
    done = trainer.finished()  # before any data is loaded: a finished fit costs nothing
    if done is not None:
        return done

    train_views, test_views = _fit_views(run, cfg)
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

    field, background, behind_capture, averaged = _make_field(
        run, cfg, pool, device, bg_color, bg_learn
    )
    groups, schedules = _param_groups(cfg, field, background, bg_learn)
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
    trainer.start(state, groups, schedules)
    generator = trainer.generator
    selector = RaySelector(pool, cfg.error_sampling, generator)

    sub = cfg.train_supersample**2  # rays per box-filtered training pixel
    average_from = cfg.iterations // 2 if averaged is not None else None
    step_options = (cfg, field, background, averaged, average_from, edge_share, sub)
    step = _main_step(*step_options, behind_capture, sampler, pool, selector, generator, device)

    field.train()
    main_end = cfg.iterations
    proxy_ious = None  # the current refined proxy's silhouette IoU per view (once computed)
    for refine_at in refine_steps[refinements_done(proxy_state) :]:
        leg_end = refine_at if stop_at is None else min(stop_at, refine_at)
        trainer.run(step, leg_end)
        if trainer.step < refine_at:  # stopped early on purpose
            return {"step": trainer.step}
        sampler, pool, selector, proxy_ious = _refine_round(
            run,
            cfg,
            trainer,
            field,
            sampler,
            device,
            train_views,
            stereo,
            refined_proxy,
            proxy_state,
            proxy_ious,
        )
        step = _main_step(*step_options, behind_capture, sampler, pool, selector, generator, device)
    if trainer.step < main_end:
        trainer.run(step, main_end if stop_at is None else min(stop_at, main_end))
        if trainer.step < main_end:  # stopped early on purpose
            return {"step": trainer.step}
    if trainer.step == main_end:  # the main steps' end (resumed here: not done yet)
        phases["main_seconds"] = trainer.seconds
        if average_from is not None and main_end > average_from:  # the last step's weights too
            _use_average(field, averaged)
    detail_stats = {}
    if cfg.detail_steps:
        detail_stats = _train_detail(
            cfg, trainer, field, sampler, pool, background, behind_capture, phases, stop_at
        )
        if trainer.step < trainer.iterations:  # stopped early on purpose
            return {"step": trainer.step}
    return _finish(
        run,
        cfg,
        trainer,
        field,
        background,
        sampler,
        pool,
        test_views,
        device,
        phases,
        detail_stats,
        proxy_state,
        behind_capture,
        main_end,
        t_start,
    )


def _save_field(path, cfg: FitConfig, field, background) -> None:
    """field.pt: the final field with its config, the background colour and the fit's options."""
    save_torch(
        path,
        {
            "format_version": FORMAT_VERSIONS["fit"],
            "field_config": to_json(field.cfg),
            "field": field.state_dict(),
            "background_color": background().detach().cpu().tolist(),
            "fit_config": to_json(cfg),
        },
    )


def _finish(
    run: RunDir,
    cfg: FitConfig,
    trainer,
    field,
    background,
    sampler,
    pool,
    test_views,
    device,
    phases: dict,
    detail_stats: dict,
    proxy_state: dict,
    behind_capture,
    main_end: int,
    t_start: float,
) -> dict:
    """The trained fit saved (field.pt), evaluated on the held-out views and published to
    RUN/template/ -> its metrics (metrics.json)."""
    for entry in trainer.log:
        entry["psnr"] = psnr_of_mse(entry["rgb"])

    _save_field(trainer.work_dir / "field.pt", cfg, field, background)
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
    trainer.publish(metrics, settings=cfg)
    run.append_config("fit", cfg)
    return metrics
