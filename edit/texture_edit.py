"""Texture editing from one image (`sine edit RUN --mode texture`; paper Sec. 3.3 + supplementary).

Inputs: a run with a fitted template, the index K of the edited view and either the target (the
user's repaint of view K: the aligned case) or a reference photo of another object whose look is
wanted (`--reference`: the unaligned case), optionally the painted region of view K. Outputs in
RUN/edits/NAME/, as for geometry edits:

    target.png, region.png, template_view.png   what the edit was learnt from (working size)
    reference.png                                the reference photo (unaligned case), what
                                                 is not its object showing the run's background
    edit.json                                    mode, view, method and every option
    checkpoint.pt                                resumable training state
    edit_field.pt                                {"method": "texture", "editing": F_dG (the
                                                 identity), F'_dG, F_dT, "compositor": the UNet
                                                 (None with --no-compositor),
                                                 "compositor_region" (g is the gate rendered),
                                                 "part_colour" (the affine head's P),
                                                 "band_width"}; or
                                                 the naive fine-tune ({"method": "naive"})
    metrics.json, log.json, edited_view.png, previews/

Ours (`--method ours`): the template and F_dG stay frozen (F_dG exactly the identity), so every
view's template image I_o and sample weights are constants (`edit.texture_views`); F_dT (hash
grid with a coarse-to-fine window over its levels, fully open at `coarse_to_fine` of training;
with `template_feature`, beyond the paper, its MLP also reads the template's geometry feature
at the point, kept per sample with the view) renders the modification image I_m with those
weights, and the compositor (`edit.compositor`) blends I_o and I_m into the edited image I.
Each step, with deferred back-propagation (`edit.deferred`: full images rendered without a
graph, the image losses' gradient cached, then the images re-rendered tile by tile with a
graph, F_dT queried in chunks of samples):

- aligned case, a crop of view K (`patch_size`, working resolution): photometric
  ||I - target||^2 on the painted region's pixels, L_reg ||I - I_o||^2 on the others; a share
  `mod_dropout` of these crops is composited with I_m = 0 (beyond the paper: the compositor
  must then make the change from the template image alone, which is what carries it to the
  part's sides view K does not show, where F_dT has learnt nothing);
- `tex_views` views around the object (the run's training cameras, each in `jitter_copies`
  copies turned by a random rotation of `jitter_deg`; rendered at `tex_size` px, DINO resizes
  them to 224): L_tex = w_cls ||cls(I_t) - cls(I)|| + w_structure ||S(I_o) - S(I)||_F
  (`edit.texture_loss`; I_t the target, or the reference photo) and L_reg on the pixels outside
  the edited part; with a reference photo, beyond the paper, the colour term w_color
  SW(I[part], photo) pulls the edited part's colours to the photo's object colours (its opaque
  pixels; in a photo without alpha the object keyed from a plain backdrop, `reference_mask`,
  else every pixel; squared sliced Wasserstein distance of the two colour distributions, so
  shading and the template's structure stay: the CLS term alone moves DINO's token but barely
  the colours).
  The edited part of a view comes from the semantic masks (K-means of the DINO
  feature field, as `sine masks`) when RUN/features exists, else from the painted region lifted
  onto the surface (`edit.texture_views.LiftedRegion`): view K's object pixels become surface
  points (rendered depth) inside or outside the region; a pixel of another view may change
  when its surface point is near one seen inside the region; the rest, surface view K never saw
  included, keeps the template (`mask_source`; run `sine features` to reach the part's unseen
  sides). With semantic masks, beyond the paper (`keep_seen`): a pixel whose surface point is
  near one view K showed outside the region keeps the template too (the part's mask may reach
  beyond what the user painted; what they saw and left stays in every view). `symmetric`: view
  K's lifted painting mirrored across the proxy's mirror plane counts as seen too (the mirrored
  painted surface may change, the mirrored unpainted one stays); `symmetric_auto` (default)
  mirrors it without being asked where the proxy has a mirror plane and the semantic masks of
  the surface view K did not see agree with the mirrored painting (IoU >= `symmetric_agreement`):
  there the masks follow the part one DINO patch at a time, the mirror places its edge (spot's
  far flank, whose part ends at a plane no feature marks). The 3D side of
  L_reg (the paper's holds F_dG to zero at background points; here F_dT): w_reg_field
  ||m'(x)||^2 (weighted by the samples' rendering weights) at the samples of the step's
  unedited pixels, so F_dT's hash table and MLP cannot leak the edit's colour over the whole
  object. Beyond the paper (as geometry edits): F_dT is multiplied by a 3D gate
  (`edit.edit_gate.EditGate`) that is 1 near the samples of view K's region and of every
  training camera's editable pixels and 0 farther than `gate_outer`: there the edit is exactly
  the template; rendered into each view, the same gate is the compositor's g (its output acts
  on the part's pixels only, on every side of the part). `gate_vote` (semantic masks): the other
  pixels' samples vote against, so one view's stray editable pixels do not open the gate, and
  it ends where what may not change is nearer than the part; a hole the part's voxels enclose
  (a spot of the part a few views' masks miss) stays the part's.

`--compositor-head affine` (beyond the paper, the default): the compositor's UNet predicts a
colour transform per pixel (A I + b in RGB) instead of a residual (`residual`, the paper's);
its head's bias is the transform every pixel shares, learnt at `lr_transform` (a part's
recolouring is mostly one transform, the same in every view: it carries to the sides and
shades view K does not show; the UNet's per-pixel part adds what differs). `part_colour`: the
transform acts on the part's share of each pixel's colour (the gate-weighted colours of its
samples, `edit.compositor`), so a rim pixel's neighbour share stays. The UNet learns at
half the residual head's rate (`COMPOSITOR_LR`): at the residual head's rate its per-pixel
part drifts after 300 steps (red streaks on the toycar's edges, bench/HISTORY.md).
`fit_transform` (aligned case): the shared transform is fitted by least squares from view K's
template pixels to the target's (`edit.compositor.fit_shared_transform`). Where it explains the
painted change (|residual| / |change| <= `fit_max_residual`: a hue turned, a colour painted over
a part's shades) the edit starts from it, F_dT learns at `fitted_lr_factor` x its rate and the
UNet at `fitted_compositor_factor` x (frozen by default): from that start, at full rates, they
fit view K's own template error and carry it to other views as mottling and stray colours.
Where it does not (a pattern painted on part of the part), the edit starts from no change at
full rates, as without the option. `quadratic_transform`: the shared transform has a quadratic
term in the part's colour, so a recolouring that is not linear in RGB (the figurine's hue turn
that also turns white stripes pink) needs no per-pixel help after the fit.

`--no-compositor` (a baseline): I = clamp(I_o + I_m), i.e. m' added to c' inside volume
rendering (`edit.editing_field.combine`), same losses. `--method naive` (a baseline): the
template's colour MLP fine-tuned on view K's rays (target inside the region, the template's own
colours outside), no editing field, no L_tex.

Where the pieces are: the options in `edit.texture_config`, view K's preparation and the masks
in `edit.texture_setup`, F_dT and the compositor's training in `edit.texture_training`.
"""

from __future__ import annotations

import copy
import time
from pathlib import Path

import numpy as np
import torch

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
from edit.geometry_losses import photometric
from edit.texture_config import (
    RUNTIME_KEYS,
    TEXTURE_INPUTS,
    TextureEditConfig,
    options_in_effect,
    uses_part_colour,
)
from edit.texture_setup import TextureSetup, prepare, scale_learning_rates
from edit.texture_training import texture_parts, texture_steps
from recon.fit import load_fitted
from recon.fit_proxy import make_sampler
from recon.rundir import RunDir
from recon.training import loop_options
from render.configs import to_dict, validate
from render.device import pick_device, torch_threads
from render.errors import SineError
from render.io import file_sha256, write_image, write_json
from render.metrics import psnr
from render.renderer import render_rays
from render.template_field import freeze


# ---- training -----------------------------------------------------------------------------
def run_texture_edit(
    run_dir,
    view: int,
    target,
    name: str,
    cfg: TextureEditConfig | None = None,
    region=None,
    reference=None,
    force: bool = False,
    progress: bool = True,
    stop_at: int | None = None,
) -> dict:
    """Learns a texture edit into RUN/edits/NAME; returns its metrics (resumes when re-run)."""
    cfg = options_in_effect(with_preset(cfg or TextureEditConfig()), reference)
    validate(cfg)
    if target is None and reference is None:
        raise SineError("a texture edit needs --target (view K repainted) or --reference (a photo)")
    if target is not None and reference is not None:
        raise SineError(
            "give --target (view K repainted) or --reference (a photo of another object), not both"
        )
    if cfg.method == "naive" and target is None:
        raise SineError("--method naive needs --target (it fits view K's pixels)")
    run, out = open_edit(run_dir, view, name)
    device = pick_device(cfg.device)
    with editing(out), torch_threads(cfg.threads):
        return _edit(
            run, out, view, target, region, reference, cfg, device, force, progress, stop_at
        )


def _edit(run, out, view, target, region, reference, cfg, device, force, progress, stop_at):
    t_start = time.perf_counter()
    digests = input_digests(target, None, region)
    if reference is not None and not Path(reference).is_file():
        raise SineError(f"reference image {reference} does not exist")
    settings = {
        "mode": "texture",
        "view": view,
        **{k: v for k, v in digests.items() if not k.startswith("mask")},
        "reference": None if reference is None else str(reference),
        "reference_sha256": None if reference is None else file_sha256(reference),
        **to_dict(cfg),
    }
    trainer = edit_trainer(
        out,
        settings,
        (*RUNTIME_KEYS, *PATH_KEYS),
        loop_options(cfg),
        to_dict(TextureEditConfig()),
        TEXTURE_INPUTS,
        force=force,
        progress=progress,
        manual_backward=cfg.method == "ours",
        advice="lower learning rates (--lr-grid, --lr-compositor, --lr-naive)",
    )
    done = trainer.finished()
    if done is not None:
        return done
    work = trainer.work_dir
    work.mkdir(parents=True, exist_ok=True)

    template, background, fit_cfg = load_fitted(run.root, device)
    freeze(template)
    sampler = make_sampler(fit_cfg, run)
    setup = prepare(
        run, work, view, target, region, reference, cfg, template, background, sampler, device
    )
    write_json(work / "edit.json", settings)
    torch.manual_seed(cfg.seed)
    if cfg.method == "naive":
        field, step = _naive(cfg, trainer, template, background, sampler, setup, device)
    else:
        editing, compositor, step, mask_source = _ours(
            run, cfg, trainer, template, sampler, background, setup, device
        )

    if not trainer.run(step, stop_at=stop_at):
        return {"step": trainer.step}

    # ---- save the result and score the edited view ----
    from edit.editing_scene import scene_from_folder

    if cfg.method == "naive":
        save_edit_field(work, "naive", field=field.state_dict())
    else:
        save_edit_field(
            work,
            "texture",
            editing=editing.state_dict(),
            compositor=None if compositor is None else compositor.state_dict(),
            compositor_region=bool(cfg.gate),  # g = the gate rendered (else from I_m)
            part_colour=uses_part_colour(cfg),  # the head's P (module doc)
            band_width=float(fit_cfg.band_width),
        )
    scene = scene_from_folder(run, work, 1.0, device)
    rendered = np.clip(scene.render_view(setup.camera)["rgb"], 0, 1)
    template_rgb = setup.view.template_rgb.reshape(*setup.view.size, 3).clamp(0, 1).cpu().numpy()
    inside = setup.region
    metrics = {
        "method": cfg.method,
        "compositor": bool(cfg.compositor) if cfg.method == "ours" else None,
        "view": view,
        "aligned": setup.target_rgb is not None,
        "unedited_view_psnr": psnr(rendered[~inside], template_rgb[~inside])
        if (~inside).any()
        else None,
        **loop_metrics(trainer, device),
        "final_losses": {k: v for k, v in trainer.log[-1].items() if k not in ("step", "seconds")},
    }
    if cfg.method == "ours":
        metrics["mask_source"] = mask_source
        if cfg.gate:
            metrics["gate_resolution"] = int(editing.gate.grid.shape[-1])
    if setup.transform_fit is not None:
        metrics["transform_fit"] = setup.transform_fit
    if setup.mirror is not None:
        metrics["mirror"] = setup.mirror
    if setup.photo is not None:
        metrics["reference_pixels"] = setup.photo.pixels
    panels = [template_rgb, rendered]
    if setup.target_rgb is not None:
        metrics["edited_view_psnr"] = psnr(rendered, setup.target_rgb)
        metrics["edited_view_psnr_region"] = psnr(rendered[inside], setup.target_rgb[inside])
        panels.append(setup.target_rgb)
    write_image(work / "edited_view.png", np.concatenate(panels, axis=1))
    metrics.update(write_previews(run, scene, work / "previews", cfg.previews, setup, device))
    return publish_edit(trainer, metrics, t_start, cfg)


def _naive(cfg, trainer, template, background, sampler, setup: TextureSetup, device):
    """The baseline: the template's colour MLP fine-tuned on view K's rays."""
    field = copy.deepcopy(template)
    for p in field.color_net.parameters():
        p.requires_grad_(True)
    groups = [{"params": list(field.color_net.parameters()), "lr": cfg.lr_naive, "name": "color"}]
    trainer.start({"field": field}, groups, lr_final_factor=cfg.lr_final_factor)
    o, d = (torch.from_numpy(a).to(device) for a in setup.camera.rays())
    hits = sampler.cast(o, d)
    pool = torch.nonzero(hits.hit)[:, 0]
    region = setup.view.editable
    goal = torch.where(
        region[:, None],
        torch.from_numpy(setup.target_rgb.reshape(-1, 3)).to(device),
        setup.view.template_rgb,
    )

    def step(i: int) -> dict[str, torch.Tensor]:
        idx = pool[torch.randint(len(pool), (cfg.batch_rays,), generator=trainer.generator)]
        res = render_rays(
            field,
            o[idx],
            d[idx],
            sampler,
            background,
            hits=hits[idx],
            perturb=True,
            generator=trainer.generator,
        )
        inside = region[idx]
        zero = 0 * res["rgb"].sum()
        return {
            "photometric": cfg.w_photometric * photometric(res["rgb"][inside], goal[idx][inside])
            if inside.any()
            else zero,
            "reg": cfg.w_reg * photometric(res["rgb"][~inside], goal[idx][~inside])
            if (~inside).any()
            else zero,
        }

    return field, step


def _ours(run, cfg, trainer, template, sampler, background, setup: TextureSetup, device):
    """F_dT + compositor with deferred back-propagation (see the module doc)."""
    editing, compositor, state, groups = texture_parts(template, cfg, device)
    trainer.start(state, groups, lr_final_factor=cfg.lr_final_factor)
    step, mask_source = texture_steps(
        run,
        cfg,
        trainer.generator,
        editing,
        compositor,
        template,
        sampler,
        background,
        setup,
        device,
        slow_down=(lambda names, f: scale_learning_rates(trainer, names, f))
        if trainer.step == 0
        else None,
    )
    return editing, compositor, step, mask_source


# ---- results ------------------------------------------------------------------------------
def write_previews(run: RunDir, scene, folder: Path, n: int, setup: TextureSetup, device) -> dict:
    """Template | edit for n views around the ring; returns the mean DINO CLS distance of both
    to the style image (target or reference) over those views: did the look move towards it?"""
    if n <= 0:
        return {}
    from edit.dino import load_dino
    from edit.scene import load_scene

    template = load_scene(run.root, None, device=str(device))
    dino = load_dino(device)

    def cls(image: np.ndarray) -> torch.Tensor:
        with torch.no_grad():
            return dino.cls(torch.from_numpy(image).permute(2, 0, 1)[None].to(device))[0]

    style = cls(setup.style_image)
    before, after = [], []
    frames = run.load_cameras().frames
    for k in np.linspace(0, len(frames), n, endpoint=False).astype(int):
        cam = frames[k]
        a = np.clip(template.render_view(cam)["rgb"], 0, 1)
        b = np.clip(scene.render_view(cam)["rgb"], 0, 1)
        write_image(folder / f"{Path(cam.name).stem}.png", np.concatenate([a, b], axis=1))
        before.append(float(torch.linalg.vector_norm(cls(a) - style)))
        after.append(float(torch.linalg.vector_norm(cls(b) - style)))
    return {
        "preview_cls_distance_before": float(np.mean(before)),
        "preview_cls_distance_after": float(np.mean(after)),
    }
