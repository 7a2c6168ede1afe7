"""The fit's proxy and its band: the proxy a template was fitted around (`template_proxy`), the
ray sampler around it (`make_sampler`), the band's width by refinement round (`band_widths`,
`band_at_round`), when the proxy is refined (`refinement_steps`) and the refinement from the
partly trained field (`refine_with_field`)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from recon.fit_config import FitConfig
from recon.rundir import RunDir
from render.sampler import BandSampler, ProxyRaycaster, UniformSampler


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
