"""Geometric editing from one edited image (`sine edit RUN --mode geometry`; paper Sec. 3.2).

Inputs: a run with a fitted template, the index K of the edited view and the target image (the
user's edit of view K). Outputs in RUN/edits/NAME/:

    target.png, target_mask.png, region.png   what the edit was learnt from (at the working size)
    template_view.png                         the template's rendering of view K
    prior_mesh.ply, prior_preview.png         the ARAP shape prior M_P (+ 4 views of it)
    edit.json                                 view, mode, method and every option
    checkpoint.pt                             resumable training state
    edit_field.pt                             the learnt editing field (or the naive fine-tune)
    metrics.json, log.json, previews/         losses, target-view fit, held-out previews

Ours (`--method ours`): the editing field (F_dG, F'_dG, F_dT) in front of the frozen template,
trained with L_geo = w_gp L_gp + L_gt + w_gr L_gr + w_cyc L_cyc + w_reg L_reg:
- L_gt on rays of view K: photometric (C_o + C_e vs the target) + silhouette BCE, the target
  being the user's image inside the editable region and the template's rendering outside it;
- L_gp: F'_dG(proxy vertices) against M_P at the prior's handles (the visible vertices the
  target moved, lifted to 3D; `prior_vertices all`: every vertex, the paper's, where the far
  side is ARAP's guess), a random subset each step, at the paper's constant weight w_gp: by
  default vertex to vertex in both directions (F'_dG(v_i) = p_i and F_dG(p_i) = v_i: the ARAP
  prior keeps the proxy's vertex order, so its correspondences are known), or the paper's
  two-way Chamfer (`--prior-match chamfer`, for a prior without correspondences);
- L_gr: smoothness of F_dG at points around the edited surface;
- L_cyc: F_dG and F'_dG invert each other at uniform points and surface points;
- L_reg: neither field moves the surface the prior left in place (points in the sampling band
  around it) nor does F_dT colour it, and view K's rays outside the editable region keep the
  template's colours.
Rays are sampled in the band around the union of F'_dG(proxy) and M_P (rebuilt every
`rebuild_every` steps), so the edited surface is sampled before F'_dG has learnt to reach it.

Naive baseline (`--method naive`): the template itself fine-tuned on view K with L_gt + L_reg
(its rays outside the region keep their colours), no editing field, no priors, the template's
proxy band for sampling.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from edit import geometry_losses as losses
from edit.edit_inputs import difference_region, read_region, read_target
from edit.edit_stage import (
    EDIT_INPUTS,
    PATH_KEYS,
    edit_trainer,
    editing,
    input_digests,
    loop_metrics,
    open_edit,
    pick_view,
    publish_edit,
    save_edit_field,
    with_preset,
)
from edit.editing_field import EditingField, combine, edited_query, warp_vertices
from edit.editing_scene import edited_sampler, scene_from_folder
from edit.geometry_config import RUNTIME_KEYS, GeometryEditConfig, with_fit_band
from edit.shape_prior import PriorMesh, build_prior_mesh, object_axes
from edit.template_scene import load_template_scene
from recon.fit import load_fitted
from recon.fit_proxy import make_sampler
from recon.rundir import RunDir
from recon.training import (
    exponential_decay,
    loop_options,
)
from render.configs import to_dict, validate
from render.device import pick_device, torch_threads
from render.io import (
    atomic_path,
    write_image,
    write_json,
    write_mask,
)
from render.metrics import psnr
from render.raycast import MeshRaycaster
from render.renderer import render_image, render_rays
from render.template_field import freeze


# ---- preparation --------------------------------------------------------------------------
@dataclass
class EditSetup:
    """Everything an edit trains from, prepared once (and written to the edit's folder)."""

    camera: object  # render.cameras.Camera of view K
    target_rgb: np.ndarray  # [H, W, 3]
    target_alpha: np.ndarray  # [H, W] {0, 1}
    template_rgb: np.ndarray  # [H, W, 3] template rendering of view K
    template_alpha: np.ndarray  # [H, W]
    region: np.ndarray  # [H, W] bool, editable
    proxy_vertices: np.ndarray  # [V, 3]
    triangles: np.ndarray  # [T, 3]
    prior: PriorMesh | None


def prepare(
    run: RunDir, out: Path, view: int, target, mask, region, cfg, field, background, sampler, device
) -> EditSetup:
    camera = pick_view(run, view)
    size = (camera.width, camera.height)
    bg = background().detach().cpu().numpy()
    tgt = read_target(target, size, mask, bg)
    rendered = render_image(camera, field, sampler, background, device=device)
    t_rgb, t_alpha = np.clip(rendered["rgb"], 0, 1), rendered["opacity"]
    if region is not None:
        editable = read_region(region, size)
    else:
        editable = difference_region(tgt, t_rgb, t_alpha, cfg.region_dilate, follow_silhouette=True)
    proxy = sampler.raycaster
    vertices, triangles = proxy.vertices.copy(), proxy.triangles.copy()
    prior = None
    if cfg.method == "ours":
        depth = MeshRaycaster((vertices, triangles)).depth(camera)
        up = run.load_cameras().up
        prior = build_prior_mesh(
            camera,
            vertices,
            triangles,
            depth,
            t_rgb,
            t_alpha,
            tgt.rgb,
            tgt.silhouette,
            editable,
            cfg.visibility_tol,
            cfg.symmetric,
            cfg.arap_iterations,
            up=up,
            axes=object_axes(vertices, up),
        )
        save_prior(out, prior, run)
    write_image(out / "target.png", tgt.rgb)
    write_mask(out / "target_mask.png", tgt.silhouette)
    write_mask(out / "region.png", editable)
    write_image(out / "template_view.png", t_rgb)
    return EditSetup(
        camera, tgt.rgb, tgt.silhouette, t_rgb, t_alpha, editable, vertices, triangles, prior
    )


def save_prior(out: Path, prior: PriorMesh, run: RunDir) -> None:
    """prior_mesh.ply and a preview of it from 4 views around the ring (shaded by normals)."""
    import trimesh

    mesh = trimesh.Trimesh(prior.vertices, prior.triangles, process=False)
    with atomic_path(out / "prior_mesh.ply") as tmp:
        mesh.export(str(tmp), file_type="ply")
    with atomic_path(out / "prior_displacement.npy") as tmp, open(tmp, "wb") as f:
        np.save(f, prior.displacement.astype(np.float32))
    frames = run.load_cameras().frames
    caster = MeshRaycaster((prior.vertices, prior.triangles))
    tiles = []
    for k in np.linspace(0, len(frames), 4, endpoint=False).astype(int):
        cam = frames[k]
        hits = caster.cast_camera(cam)
        light = np.abs(hits.normal @ np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]))
        moved = prior.displacement[prior.triangles[np.maximum(hits.triangle, 0)]].max(axis=1)
        shade = np.where(hits.hit, 0.25 + 0.75 * light, 1.0)
        tint = np.where((moved > 0.01) & hits.hit, 1.0, 0.0)
        rgb = np.stack([shade, shade * (1 - 0.5 * tint), shade * (1 - 0.5 * tint)], axis=-1)
        tiles.append(rgb.reshape(cam.height, cam.width, 3))
    write_image(out / "prior_preview.png", np.concatenate(tiles, axis=1))


# ---- training -----------------------------------------------------------------------------
def _image_rays(camera, device):
    o, d = camera.rays()
    return torch.from_numpy(o).to(device), torch.from_numpy(d).to(device)


@dataclass
class GeometryTraining:
    """A geometric edit's training, ready for `Trainer.start(state, groups, schedules)`; then
    `begin(trainer.generator)` gives the step function (it reads the resumed state)."""

    state: dict  # "editing" (ours) or "field" (naive), and what resuming must restore
    groups: list[dict]  # Adam parameter groups, named
    schedules: dict  # group name -> learning-rate factor of the step
    begin: Callable[[torch.Generator], Callable[[int], dict[str, torch.Tensor]]]


def geometry_training(
    cfg: GeometryEditConfig,
    setup: EditSetup,
    template,
    background,
    fit_cfg,
    sampler,
    device,
    fit_colour: bool = True,
) -> GeometryTraining:
    """The editing field (or the naive fine-tune) and the step of L_geo (see the module doc).

    fit_colour False (hybrid edits whose one target also recolours the part): inside the
    editable region only the silhouette and the priors drive the deformation, and F_dT stays
    zero (frozen); the texture phase learns the colours."""
    o_all, d_all = _image_rays(setup.camera, device)
    # L_gt's targets: the user's edit inside the editable region, the template's own rendering
    # outside it (identical for a target edited from a snapshot; a target from elsewhere, e.g. a
    # photo, must not make the field warp the unedited part to fix the template's own errors)
    inside = setup.region[..., None]
    tgt_rgb = np.where(inside, setup.target_rgb, setup.template_rgb)
    tgt_sil = np.where(setup.region, setup.target_alpha, setup.template_alpha > 0.5)
    tgt = torch.from_numpy(tgt_rgb.reshape(-1, 3).astype(np.float32)).to(device)
    sil = torch.from_numpy(tgt_sil.reshape(-1).astype(np.float32)).to(device)
    outside = torch.from_numpy(~setup.region.reshape(-1)).to(device)
    tmpl = torch.from_numpy(setup.template_rgb.reshape(-1, 3)).to(device)
    if cfg.method == "naive":
        field = copy.deepcopy(template).train()
        state = {"field": field}
        groups = [{"params": list(field.parameters()), "lr": cfg.lr_naive, "name": "template"}]
        query = field
    else:
        freeze(template)
        editing = EditingField(template.grid.cfg)
        if cfg.gate:
            moved = setup.prior.moved(cfg.moved_tol)
            ends = (setup.proxy_vertices[moved], setup.prior.vertices[moved])
            path = [(1 - a) * ends[0] + a * ends[1] for a in np.linspace(0, 1, 5)]
            editing.gate.set_from_points(np.concatenate(path), cfg.band_width, cfg.gate_margin)
        editing = editing.to(device)
        tex = editing.texture
        deform_params = list(editing.deform.parameters()) + list(
            editing.forward_deform.parameters()
        )
        groups = [{"params": deform_params, "lr": cfg.lr_deform, "name": "deform"}]
        if fit_colour:
            groups += [
                {
                    "params": [tex.grid.table],
                    "lr": cfg.lr_texture_grid,
                    "eps": 1e-15,
                    "name": "texture_grid",
                },
                {
                    "params": list(tex.mlp.parameters()),
                    "lr": cfg.lr_texture_mlp,
                    "name": "texture_mlp",
                },
            ]
        else:
            freeze(tex)  # its output layer starts at zero: m' = 0
        # the proxy as F'_dG warped it at the last rebuild: checkpointed, so a resumed run
        # samples as the uninterrupted one until the next rebuild
        warped = warp_vertices(editing.forward_deform, setup.proxy_vertices)
        state = {"editing": editing, "prior_vertices": setup.prior.vertices, "warped": warped}
        query = edited_query(template, editing)
    decay = exponential_decay(cfg.lr_final_factor, cfg.iterations)
    warm = max(cfg.warmup_steps, 1)
    # Adam's first steps move every weight by ~lr at once: the deformation would jump far from
    # the identity (and the cycle loss with it) before the losses can steer it
    schedules = {"deform": lambda k: min(1.0, (k + 1) / warm) * decay(k)}

    def begin(gen: torch.Generator):
        """The step function, once `Trainer.start` has restored a resumed run's state."""
        edit_sampler = sampler
        if cfg.method == "ours":  # after `start`: a resumed run's prior is the checkpointed one
            proxy_v = torch.from_numpy(setup.proxy_vertices).float().to(device)
            prior_v = torch.from_numpy(setup.prior.vertices).float().to(device)
            unmoved = prior_v[torch.from_numpy(~setup.prior.moved(cfg.moved_tol)).to(device)]
            surface = torch.cat([proxy_v, prior_v])
            matched = torch.arange(len(proxy_v), device=device)
            if cfg.prior_vertices == "handles":
                matched = torch.from_numpy(setup.prior.handle_ids).long().to(device)

        def rebuild(rewarp: bool = True):
            """The sampler of the edited space and the view-K rays that need the field."""
            nonlocal edit_sampler
            if cfg.method == "ours":
                if rewarp:
                    warped[...] = warp_vertices(editing.forward_deform, setup.proxy_vertices)
                edit_sampler = edited_sampler(
                    editing,
                    setup.proxy_vertices,
                    setup.triangles,
                    cfg.band_width,
                    (fit_cfg.band_samples, fit_cfg.coarse_samples),
                    extra=setup.prior.vertices,
                    warped=warped,
                )
            hits = edit_sampler.cast(o_all, d_all)
            return hits, torch.nonzero(hits.hit)[:, 0]

        hits, pool = rebuild(rewarp=False)  # fresh: F'_dG at init; resumed: as checkpointed

        def pick(points, n):
            return points[torch.randint(len(points), (n,), generator=gen).to(device)]

        def jittered(points, n):
            p = pick(points, n)
            return p + cfg.jitter * torch.randn(p.shape, generator=gen).to(device)

        def prior_term(template_points, prior_points):
            if cfg.prior_match == "chamfer":
                return losses.chamfer(editing.forward_deform(template_points), prior_points)
            return losses.vertex_match(
                editing.deform, editing.forward_deform, template_points, prior_points
            )

        def step(i: int) -> dict[str, torch.Tensor]:
            nonlocal hits, pool
            if cfg.method == "ours" and i % cfg.rebuild_every == 0 and i > 0:
                hits, pool = rebuild()
            idx = pick(pool, cfg.batch_rays)
            res = render_rays(
                query,
                o_all[idx],
                d_all[idx],
                edit_sampler,
                background,
                hits=hits[idx],
                perturb=True,
                generator=gen,
            )
            pred = combine(res)
            out_rays = outside[idx]
            reg = losses.photometric(pred[out_rays], tmpl[idx][out_rays]) if out_rays.any() else 0
            terms = {
                "silhouette": cfg.w_silhouette * losses.silhouette_bce(res["opacity"], sil[idx])
            }
            if fit_colour:
                terms = {"photometric": losses.photometric(pred, tgt[idx]), **terms}
            if cfg.method == "naive":
                return {**terms, "reg": cfg.w_reg * (reg + 0 * pred.sum())}
            deform, fwd = editing.deform, editing.forward_deform
            sub = matched[
                torch.randint(len(matched), (cfg.prior_points,), generator=gen).to(device)
            ]
            uniform = torch.rand(cfg.cycle_points // 2, 3, generator=gen).to(device) * 2 - 1
            cyc_pts = torch.cat([uniform, jittered(surface, cfg.cycle_points - len(uniform))])
            eps = cfg.jitter * torch.randn(cfg.smooth_points, 3, generator=gen).to(device)
            if len(unmoved):
                # both fields leave the unedited surface (and its band) in place and F_dT adds
                # no colour there: its hash table, trained on view K alone, would otherwise leak
                # the edited view's colours into unseen parts through hash collisions
                still = pick(unmoved, cfg.anchor_points)
                still = still + 0.5 * cfg.band_width * torch.randn(still.shape, generator=gen).to(
                    device
                )
                reg = reg + losses.displacement_l1(deform, still)
                reg = reg + losses.displacement_l1(fwd, still)
                reg = reg + editing.texture(still).abs().sum(dim=-1).mean()
            smooth_at = jittered(prior_v, cfg.smooth_points)
            return {
                **terms,
                # L_gp sums over the matched vertices (the paper's: the whole mesh), estimated
                # from the random subset
                "gp": cfg.w_gp * len(matched) / len(sub) * prior_term(proxy_v[sub], prior_v[sub]),
                "cyc": cfg.w_cyc * losses.cycle(deform, fwd, cyc_pts),
                "gr": cfg.w_gr * losses.deformation_smoothness(deform, smooth_at, eps),
                "reg": cfg.w_reg * (reg + 0 * pred.sum()),
            }

        return step

    return GeometryTraining(state, groups, schedules, begin)


def run_geometry_edit(
    run_dir,
    view: int,
    target,
    name: str,
    cfg: GeometryEditConfig | None = None,
    mask=None,
    region=None,
    force: bool = False,
    progress: bool = True,
    stop_at: int | None = None,
) -> dict:
    """Learns a geometric edit into RUN/edits/NAME; returns its metrics (resumes when re-run)."""
    cfg = validate(with_preset(cfg or GeometryEditConfig()))
    run, out = open_edit(run_dir, view, name)
    device = pick_device(cfg.device)
    with editing(out), torch_threads(cfg.threads):
        return _edit(run, out, view, target, mask, region, cfg, device, force, progress, stop_at)


def _edit(run, out, view, target, mask, region, cfg, device, force, progress, stop_at) -> dict:
    t_start = time.perf_counter()
    settings = {
        "mode": "geometry",
        "view": view,
        **input_digests(target, mask, region),
        **to_dict(cfg),
    }
    trainer = edit_trainer(
        out,
        settings,
        (*RUNTIME_KEYS, *PATH_KEYS),
        loop_options(cfg),
        to_dict(GeometryEditConfig()),
        EDIT_INPUTS,
        force=force,
        progress=progress,
        advice="a lower --lr-deform (or --lr-naive)",
    )
    done = trainer.finished()
    if done is not None:
        return done
    work = trainer.work_dir
    work.mkdir(parents=True, exist_ok=True)

    template, background, fit_cfg = load_fitted(run.root, device)
    cfg = with_fit_band(cfg, fit_cfg)
    sampler = make_sampler(fit_cfg, run)
    setup = prepare(
        run, work, view, target, mask, region, cfg, template, background, sampler, device
    )
    write_json(work / "edit.json", settings)

    torch.manual_seed(cfg.seed)
    training = geometry_training(cfg, setup, template, background, fit_cfg, sampler, device)
    trainer.start(
        training.state, training.groups, training.schedules, lr_final_factor=cfg.lr_final_factor
    )
    step = training.begin(trainer.generator)
    field, editing = training.state.get("field"), training.state.get("editing")

    if not trainer.run(step, stop_at=stop_at):
        return {"step": trainer.step}

    # ---- save the result and score the edited view ----
    if cfg.method == "naive":
        save_edit_field(work, "naive", field=field.state_dict())
    else:
        save_edit_field(work, "ours", editing=editing.state_dict(), band_width=cfg.band_width)
    scene = scene_from_folder(run, work, 1.0, device)
    rendered = scene.render_view(setup.camera)
    obj = (setup.target_alpha > 0.5) | (rendered["opacity"] > 0.5)
    pred_sil = rendered["opacity"] > 0.5
    tgt_sil = setup.target_alpha > 0.5
    metrics = {
        "method": cfg.method,
        "view": view,
        "edited_view_psnr": psnr(rendered["rgb"], setup.target_rgb),
        "edited_view_psnr_object": psnr(rendered["rgb"][obj], setup.target_rgb[obj]),
        "edited_view_silhouette_iou": float(
            (pred_sil & tgt_sil).sum() / max((pred_sil | tgt_sil).sum(), 1)
        ),
        **loop_metrics(trainer, device),
        "final_losses": {k: v for k, v in trainer.log[-1].items() if k not in ("step", "seconds")},
    }
    if setup.prior is not None:
        plane = setup.prior.mirror_plane
        metrics.update(
            prior_handles=int(len(setup.prior.handle_ids)),
            prior_anchors=int(len(setup.prior.anchor_ids)),
            prior_max_displacement=float(setup.prior.displacement.max()),
            prior_mirror_plane=None if plane is None else plane.tolist(),
        )
    write_image(
        work / "edited_view.png",
        np.concatenate([setup.template_rgb, rendered["rgb"], setup.target_rgb], axis=1),
    )
    write_previews(run, scene, work / "previews", cfg.previews, device)
    return publish_edit(trainer, metrics, t_start, cfg)


def write_previews(run: RunDir, scene, folder: Path, n: int, device) -> None:
    """Template | edit side by side for n views spread around the ring (test views first)."""
    if n <= 0:
        return
    template = load_template_scene(run, device)
    frames = run.load_cameras().frames
    for k in np.linspace(0, len(frames), n, endpoint=False).astype(int):
        cam = frames[k]
        before = template.render_view(cam)["rgb"]
        after = scene.render_view(cam)["rgb"]
        write_image(folder / f"{Path(cam.name).stem}.png", np.concatenate([before, after], axis=1))
