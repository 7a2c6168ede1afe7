"""The fit's colour-detail phase after the main steps (`_train_detail`): with the main field
frozen, the training rays' samples cached once, the check that the branch helps on held-out
training views, and the branch's steps (the steps themselves: recon/colour_detail.py)."""

from __future__ import annotations

import time

import torch

from recon.fit_config import FitConfig


def _detail_cache(cfg: FitConfig, field, sampler, pool, background, behind_capture) -> tuple:
    """The main field frozen, its colour-detail branch trainable and on; the training rays of
    the colour-detail phase and their samples cached -> (rays, cache)."""
    from recon.colour_detail import build_detail_cache, detail_rays

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
    return rays, cache


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
    from recon.colour_detail import check_psnr, check_views, detail_step, reset_branch

    t_cache = time.perf_counter()
    rays, cache = _detail_cache(cfg, field, sampler, pool, background, behind_capture)
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
