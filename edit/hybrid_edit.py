"""Hybrid editing (`sine edit RUN --mode hybrid`): a geometric edit and a texture edit of the
geometrically edited object, learnt in one resumable training and kept as one edit.

Inputs: a run with a fitted template, the index K of the edited view and either one target that
changes both the shape and the colours of view K (`--target`), or a geometry target and a
texture target (`--target-geometry` + `--target-texture`: view K of the new shape repainted, e.g.
the geometry target repainted; or `--reference PHOTO` for the look of another object).
`--region` (optional) is the part of view K that may change; `--region-texture` the part that
is repainted, when it is another (default: `--region`, else where the texture target differs).

One `Trainer` (one checkpoint, log, progress bar) takes `geometry.iterations` geometric steps,
then `texture.iterations` texture steps:

1. geometric steps (`edit.geometry_edit.geometry_training`): the editing field F_dG, F'_dG, F_dT
   and L_geo against the geometry target, as `--mode geometry`. With one target, only its
   silhouette and the shape prior drive the deformation inside the editable region: L_gt's
   photometric term is left out there (L_reg still keeps the rest of view K) and this F_dT stays
   zero, so the target's new colours are left to the texture steps;
2. texture steps (`edit.texture_training.texture_steps`): the geometric edit is frozen and becomes
   the texture edit's template (`edit.editing_scene.deformed_template`: the template behind
   F_dG, sampled around F'_dG(proxy)); a second editing field's F_dT and the compositor learn
   the colours from the texture target (or reference) with the texture edit's losses and
   deferred back-propagation, exactly as `--mode texture` learns them on the template.

The two kinds of step alternate once, geometry first: texture steps keep every view's samples of
a frozen geometry (what deferred back-propagation and the kept template views rely on), and the
geometry losses do not depend on F_dT. The texture steps' masks of other views (`--mask-source`,
as `--mode texture`): the semantic masks of the run's feature field (`sine features`) rendered on
the edited shape (`edit.feature_maps.FeatureMapRenderer` with the geometric edit: the feature
field is queried at F_dG(x') of each sample x' and composited with the edited density), which
carry the new colours to the sides of the part view K does not show; or the region lifted onto
the edited surface (the sides view K never saw keep their colour).

Outputs in RUN/edits/NAME/ (load_scene / `sine render` / `sine export` render both applied):

    geometry/      target.png, target_mask.png, region.png, template_view.png, prior_mesh.ply,
                   prior_preview.png: what the geometric steps learnt from
    texture/       target.png (or reference.png), region.png, template_view.png (the geometric
                   edit's rendering of view K): what the texture steps learnt from
    edit.json      mode, view, inputs and their SHA-256, every option ("geometry.*", "texture.*")
    checkpoint.pt  resumable training state
    edit_field.pt  {"method": "hybrid", "band_width", "geometry": {"editing"},
                   "texture": {"editing", "compositor", "compositor_region", "part_colour"}}
    metrics.json, log.json, edited_view.png (template | edit | target(s)), previews/
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from edit import geometry_config, geometry_edit, texture_config, texture_setup
from edit.edit_stage import (
    PATH_KEYS,
    edit_trainer,
    editing,
    input_digests,
    loop_metrics,
    open_edit,
    publish_edit,
    save_edit_field,
    with_preset,
)
from edit.editing_scene import deformed_template, scene_from_folder
from edit.geometry_config import GeometryEditConfig, with_fit_band
from edit.geometry_edit import geometry_training
from edit.template_scene import load_template_scene
from edit.texture_config import TextureEditConfig, uses_part_colour
from edit.texture_edit import write_previews
from edit.texture_training import texture_parts, texture_steps
from recon.training import exponential_decay, loop_options
from render.configs import to_dict, validate
from render.device import pick_device, torch_threads
from render.errors import SineError
from render.io import file_sha256, write_image, write_json
from render.metrics import psnr
from render.template_field import freeze


def hybrid_targets(target=None, target_geometry=None, target_texture=None, reference=None):
    """(geometry target, texture target or None, one target?) from the user's images; a
    SineError for a combination that does not make a hybrid edit."""
    both = "--target (one image that changes shape and colours) or --target-geometry + "
    both += "--target-texture"
    if target is not None and (target_geometry is not None or target_texture is not None):
        raise SineError(f"--mode hybrid takes {both}, not both kinds")
    if target is not None:
        return target, target, True
    if target_geometry is None:
        raise SineError(f"--mode hybrid needs {both}")
    if target_texture is None and reference is None:
        raise SineError(
            "--target-geometry needs --target-texture (view K of the new shape repainted) or "
            "--reference (a photo whose look to take) for the texture steps"
        )
    return target_geometry, target_texture, False


def run_hybrid_edit(
    run_dir,
    view: int,
    name: str,
    geometry_cfg: GeometryEditConfig | None = None,
    texture_cfg: TextureEditConfig | None = None,
    target=None,
    target_geometry=None,
    target_texture=None,
    reference=None,
    mask=None,
    region=None,
    region_texture=None,
    force: bool = False,
    progress: bool = True,
    stop_at: int | None = None,
) -> dict:
    """Learns a hybrid edit into RUN/edits/NAME; returns its metrics (resumes when re-run).
    `mask`: the geometry target's silhouette when it has no alpha; `region_texture`: the texture
    steps' region (default: `region`); `stop_at`: stop after that many steps of both phases
    together (as if interrupted)."""
    gcfg = with_preset(geometry_cfg or GeometryEditConfig())
    tcfg = texture_config.options_in_effect(
        with_preset(texture_cfg or TextureEditConfig()), reference
    )
    validate(gcfg)
    validate(tcfg)
    targets = hybrid_targets(target, target_geometry, target_texture, reference)
    if gcfg.method != "ours" or tcfg.method != "ours":
        raise SineError(
            "--method naive is a baseline of --mode geometry and --mode texture; a hybrid edit "
            "learns the editing field (--method ours)"
        )
    if reference is not None and not Path(reference).is_file():
        raise SineError(f"reference image {reference} does not exist")
    run, out = open_edit(run_dir, view, name)
    texture_setup.require_features(run, tcfg)  # before the geometric steps, not after
    device = pick_device(gcfg.device)
    regions = (region, region if region_texture is None else region_texture)
    with editing(out), torch_threads(gcfg.threads):
        return _edit(
            run,
            out,
            view,
            targets,
            reference,
            mask,
            regions,
            gcfg,
            tcfg,
            device,
            force,
            progress,
            stop_at,
        )


def _settings(view, targets, reference, mask, regions, gcfg, tcfg) -> dict:
    """What the edit depends on (the Trainer retrains when any of it changes)."""
    geometry_target, texture_target, one = targets
    texture = input_digests(texture_target, None, regions[1])
    return {
        "mode": "hybrid",
        "view": view,
        "one_target": one,
        **input_digests(geometry_target, mask, regions[0]),
        "texture_target": texture["target"],
        "texture_target_sha256": texture["target_sha256"],
        "texture_region": texture["region"],
        "texture_region_sha256": texture["region_sha256"],
        "reference": None if reference is None else str(reference),
        "reference_sha256": None if reference is None else file_sha256(reference),
        **_options(gcfg, tcfg),
    }


def _options(gcfg, tcfg) -> dict:
    """Both phases' options as one flat dict ("geometry.KEY", "texture.KEY")."""
    return {
        **{f"geometry.{k}": v for k, v in to_dict(gcfg).items()},
        **{f"texture.{k}": v for k, v in to_dict(tcfg).items()},
    }


def _edit(
    run, out, view, targets, reference, mask, regions, gcfg, tcfg, device, force, progress, stop_at
) -> dict:
    t_start = time.perf_counter()
    geometry_target, texture_target, one = targets
    settings = _settings(view, targets, reference, mask, regions, gcfg, tcfg)
    runtime = tuple(f"geometry.{k}" for k in geometry_config.RUNTIME_KEYS)
    runtime += tuple(f"texture.{k}" for k in texture_config.RUNTIME_KEYS) + PATH_KEYS
    n_geometry, n_texture = gcfg.iterations, tcfg.iterations
    trainer = edit_trainer(
        out,
        settings,
        runtime,
        {**loop_options(gcfg), "iterations": n_geometry + n_texture},
        _options(GeometryEditConfig(), TextureEditConfig()),
        texture_config.TEXTURE_INPUTS,
        force=force,
        progress=progress,
        manual_backward=True,
        advice="lower learning rates (--lr-deform, --lr-grid, --lr-compositor)",
    )
    done = trainer.finished()
    if done is not None:
        return done
    work = trainer.work_dir
    work.mkdir(parents=True, exist_ok=True)

    template = load_template_scene(run, device)
    gcfg = with_fit_band(gcfg, template.fit_config)
    field, background, sampler = template.field, template.background, template.sampler
    geo_setup = geometry_edit.prepare(
        run,
        work / "geometry",
        view,
        geometry_target,
        mask,
        regions[0],
        gcfg,
        field,
        background,
        sampler,
        device,
    )
    write_json(work / "edit.json", settings)
    torch.manual_seed(gcfg.seed)
    geometry = geometry_training(
        gcfg, geo_setup, field, background, template.fit_config, sampler, device, not one
    )
    tex_editing, compositor, tex_state, tex_groups = texture_parts(field, tcfg, device)

    # one optimiser: each phase's groups follow their own schedule over their own steps (a
    # group gets no gradient outside its phase, and Adam skips it)
    geo_decay = exponential_decay(gcfg.lr_final_factor, n_geometry)
    tex_decay = exponential_decay(tcfg.lr_final_factor, n_texture)
    groups, schedules = [], {}
    for g in geometry.groups:
        groups.append({**g, "name": f"geometry.{g['name']}"})
        schedules[groups[-1]["name"]] = geometry.schedules.get(g["name"], geo_decay)
    for g in tex_groups:
        groups.append({**g, "name": f"texture.{g['name']}"})
        schedules[groups[-1]["name"]] = lambda k: tex_decay(max(k - n_geometry, 0))
    state = {f"geometry.{k}": v for k, v in geometry.state.items()}
    state.update({f"texture.{k}": v for k, v in tex_state.items()})
    trainer.start(state, groups, schedules)
    geometry_step = geometry.begin(trainer.generator)
    geo_editing = geometry.state["editing"]
    phase: dict = {}  # the texture steps, built on the frozen geometric edit when they start

    def texture_phase(fresh: bool) -> dict:  # fresh: not resumed within the texture steps
        if not phase:
            edited = deformed_template(template, freeze(geo_editing), gcfg.band_width)
            try:
                setup = texture_setup.prepare(
                    run,
                    work / "texture",
                    view,
                    texture_target,
                    regions[1],
                    reference,
                    tcfg,
                    edited.field,
                    background,
                    edited.sampler,
                    device,
                    on_object=True,
                )
            except SineError as e:
                if "nothing to edit" not in str(e):
                    raise
                raise SineError(
                    "nothing to recolour: the texture target matches the geometric edit's "
                    "rendering of view K; use --mode geometry for a shape-only edit"
                ) from None
            step, mask_source = texture_steps(
                run,
                tcfg,
                trainer.generator,
                tex_editing,
                compositor,
                edited.field,
                edited.sampler,
                background,
                setup,
                device,
                feature_geometry=edited,
                slow_down=(
                    lambda names, f: texture_setup.scale_learning_rates(
                        trainer, tuple(f"texture.{n}" for n in names), f
                    )
                )
                if fresh
                else None,
            )
            phase.update(setup=setup, step=step, mask_source=mask_source)
        return phase

    def step(i: int) -> dict[str, torch.Tensor]:
        if i >= n_geometry:
            return texture_phase(i == n_geometry)["step"](i - n_geometry)
        terms = geometry_step(i)
        sum(terms.values()).backward()
        return {k: v.detach() for k, v in terms.items()}

    if not trainer.run(step, stop_at=stop_at):
        return {"step": trainer.step}

    # ---- save the result and score the edited view ----
    tex_setup = texture_phase(False)["setup"]
    save_edit_field(
        work,
        "hybrid",
        band_width=float(gcfg.band_width),
        geometry={"editing": geo_editing.state_dict()},
        texture={
            "editing": tex_editing.state_dict(),
            "compositor": None if compositor is None else compositor.state_dict(),
            "compositor_region": bool(tcfg.gate),  # g = the gate rendered
            "part_colour": uses_part_colour(tcfg),
        },
    )
    scene = scene_from_folder(run, work, 1.0, device)
    rendered = scene.render_view(geo_setup.camera)
    rgb = np.clip(rendered["rgb"], 0, 1)
    template_rgb = geo_setup.template_rgb
    target_sil = geo_setup.target_alpha > 0.5
    recoloured = tex_setup.region
    kept = ~(geo_setup.region | recoloured)
    metrics = {
        "method": "hybrid",
        "view": view,
        "one_target": one,
        "aligned": tex_setup.target_rgb is not None,
        "compositor": bool(tcfg.compositor),
        "geometry_iterations": n_geometry,
        "texture_iterations": n_texture,
        **loop_metrics(trainer, device),
        "edited_view_silhouette_iou": _iou(rendered["opacity"] > 0.5, target_sil),
        "template_view_silhouette_iou": _iou(geo_setup.template_alpha > 0.5, target_sil),
        "unedited_view_psnr": psnr(rgb[kept], template_rgb[kept]) if kept.any() else None,
        "final_losses": {
            "geometry": _last_terms([e for e in trainer.log if e["step"] <= n_geometry]),
            "texture": _last_terms([e for e in trainer.log if e["step"] > n_geometry]),
        },
        "mask_source": phase["mask_source"],
        "prior_handles": int(len(geo_setup.prior.handle_ids)),
        "prior_max_displacement": float(geo_setup.prior.displacement.max()),
    }
    panels = [template_rgb, rgb, geo_setup.target_rgb]
    if tex_setup.target_rgb is not None:
        goal = tex_setup.target_rgb
        metrics["edited_view_psnr_region"] = psnr(rgb[recoloured], goal[recoloured])
        metrics["template_view_psnr_region"] = psnr(template_rgb[recoloured], goal[recoloured])
        if not one:
            panels.append(goal)
    write_image(work / "edited_view.png", np.concatenate(panels, axis=1))
    metrics.update(write_previews(run, scene, work / "previews", tcfg.previews, tex_setup, device))
    return publish_edit(trainer, metrics, t_start, {**to_dict(tcfg), **to_dict(gcfg)})


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def _last_terms(log: list[dict]) -> dict:
    """The loss terms of the last log entry of a phase ({} when it logged none)."""
    if not log:
        return {}
    return {k: v for k, v in log[-1].items() if k not in ("step", "seconds")}
