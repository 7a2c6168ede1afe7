"""The training of a texture edit's F_dT and compositor (`edit.texture_edit`'s `--method ours`,
and a hybrid edit's texture steps): the trained parts (`texture_parts`), the training step
(`texture_steps`) and the edited image of a view in tiles for the deferred back-propagation
(`edited_image`)."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from edit.compositor import HALO, Compositor, composite_hwc
from edit.deferred import DeferredImage, deferred_backward, image_tiles
from edit.editing_field import EditingField
from edit.geometry_losses import photometric
from edit.texture_config import (
    TextureEditConfig,
    compositor_lr,
    fits_transform,
    gate_resolution,
    uses_part_colour,
)
from edit.texture_setup import (
    TextureSetup,
    ViewBank,
    editable_masker,
    start_from_fit,
    training_cameras,
)
from edit.texture_views import (
    ViewSamples,
    box_pixels,
    render_gate,
    render_modification,
    sample_view,
)
from render.template_field import freeze


def geometry_feature_dim(field) -> int:
    """Width of the geometry feature ("geo_feat") a radiance field returns."""
    param = next(field.parameters())
    x = torch.zeros(1, 3, dtype=param.dtype, device=param.device)
    d = torch.tensor([[0.0, 0.0, 1.0]], dtype=param.dtype, device=param.device)
    with torch.no_grad():
        return int(field(x, d)["geo_feat"].shape[1])


def texture_parts(template, cfg: TextureEditConfig, device):
    """(editing field, compositor or None, state, parameter groups) of a texture edit on the
    frozen `template` field, before `Trainer.start`: F_dT learns (reading the template's
    geometry feature with `cfg.template_feature`), F_dG and F'_dG are exactly the identity."""
    cond = geometry_feature_dim(template) if cfg.template_feature else 0
    editing = EditingField(template.grid.cfg, texture_cond=cond).to(device)
    for deform in (editing.deform, editing.forward_deform):  # exactly the identity, frozen
        nn.init.zeros_(deform.mlp[-1].weight)
        nn.init.zeros_(deform.mlp[-1].bias)
        freeze(deform)
    texture = editing.texture
    compositor = None
    if cfg.compositor:
        quadratic = cfg.quadratic_transform and cfg.compositor_head == "affine"
        compositor = Compositor(head=cfg.compositor_head, quadratic=quadratic).to(device)
    groups = [
        {"params": [texture.grid.table], "lr": cfg.lr_grid, "eps": 1e-15, "name": "grid"},
        {"params": list(texture.mlp.parameters()), "lr": cfg.lr_mlp, "name": "mlp"},
    ]
    state = {"editing": editing}
    if compositor is not None:
        shared = ("head.bias", "quadratic") if compositor.kind == "affine" else ()
        rest = [p for n, p in compositor.named_parameters() if n not in shared]
        groups.append({"params": rest, "lr": compositor_lr(cfg), "name": "compositor"})
        if shared:
            transform = [p for n, p in compositor.named_parameters() if n in shared]
            groups.append({"params": transform, "lr": cfg.lr_transform, "name": "transform"})
        state["compositor"] = compositor
    return editing, compositor, state, groups


def texture_steps(
    run,
    cfg,
    gen,
    editing,
    compositor,
    template,
    sampler,
    background,
    setup: TextureSetup,
    device,
    feature_geometry=None,
    slow_down: Callable[[tuple[str, ...], float], None] | None = None,
):
    """(step, mask source) of F_dT + compositor, once `Trainer.start` has restored a resumed
    run's state: `template` (frozen field) and `sampler` render the views I_o comes from, `gen`
    is the trainer's generator; step(i) is step i of this training (0..cfg.iterations-1).
    feature_geometry: the scene of `template` and `sampler` when it is not the run's template
    (a hybrid edit's `deformed_template`): the semantic masks' feature maps are rendered on it.
    slow_down: for a fresh (not resumed) edit, (names, factor) -> multiplies the learning rates
    of those parameter groups ("grid", "mlp": F_dT; "compositor": the UNet) by the factor
    (`scale_learning_rates`); with it, `fit_transform` applies."""
    from edit.dino import load_dino
    from edit.texture_loss import TextureLoss, sliced_wasserstein

    texture = editing.texture
    use_tex = cfg.tex_views > 0 and (cfg.w_cls > 0 or cfg.w_structure > 0)
    tex_loss = None
    if use_tex:
        dino = load_dino(device)
        dino.requires_grad_(False)
        style = torch.from_numpy(setup.style_image).permute(2, 0, 1).to(device)
        tex_loss = TextureLoss(dino, style, cfg.w_cls, cfg.w_structure)
    masker, mask_source = editable_masker(run, setup, cfg, device, feature_geometry)
    reference_colors = None
    if use_tex and setup.photo is not None and cfg.w_color > 0:
        reference_colors = torch.from_numpy(setup.photo.colors).to(device)

    def make_view(camera) -> ViewSamples:
        view = sample_view(
            camera,
            template,
            sampler,
            background,
            cfg.min_weight,
            device=device,
            features=cfg.template_feature,
        )
        view.editable = masker(view)
        if tex_loss is not None:
            image = view.template_rgb.reshape(*view.size, 3).clamp(0, 1).permute(2, 0, 1)[None]
            view.template_sim = tex_loss.template_similarity(image)
        return view

    train = training_cameras(run)
    bank = ViewBank(train, cfg.jitter_copies, cfg.jitter_deg, cfg.tex_size, cfg.seed, make_view)
    if cfg.gate:  # F_dT is zero away from the edited part as the views' masks see it
        views = [setup.view] + [bank[j] for j in range(len(train))]

        # the samples that make the editable pixels' colour (a fuzzy template spreads weight
        # along the ray: the faint ones would grow the gate over neighbouring parts)
        def surface(v: ViewSamples, editable: bool) -> torch.Tensor:  # [M, 3]
            return v.points[(v.editable[v.pixel] == editable) & (v.weights >= cfg.gate_weight)]

        points = torch.cat([surface(v, True) for v in views]).cpu().numpy()
        others = None
        # the other pixels' surface votes against (EditGate); lifted masks are one 3D region
        # seen from every view, with no stray pixels to outvote
        if cfg.gate_vote and mask_source == "features":
            others = torch.cat([surface(v, False) for v in views]).cpu().numpy()
        editing.gate.set_from_points(
            points, cfg.gate_inner, cfg.gate_outer, gate_resolution(cfg, train), others
        )

    def with_region(view: ViewSamples) -> ViewSamples:
        """The view with the gate rendered into it (the compositor's g), once per view."""
        if cfg.gate and view.region is None:
            view.region, part_rgb = render_gate(view, editing.gate)
            view.part_rgb = part_rgb if uses_part_colour(cfg) else None
        return view

    k_view = with_region(setup.view)
    h_k, w_k = k_view.size
    target = None
    if setup.target_rgb is not None:  # kept with the view, so crops carry it along
        target = torch.from_numpy(setup.target_rgb.reshape(-1, 3)).to(device)
        k_view.goal = target
        if slow_down is not None and fits_transform(cfg):  # the gate: k_view has its region
            setup.transform_fit = start_from_fit(cfg, compositor, k_view, slow_down)
    region_px = torch.nonzero(k_view.editable)[:, 0].cpu()
    object_px = torch.nonzero(k_view.opacity > 0.5)[:, 0].cpu()
    if len(object_px) == 0:
        object_px = torch.arange(k_view.n_pixels)

    def crop() -> ViewSamples:
        """A crop of view K centred on a region pixel or an object pixel (even odds)."""
        ph = h_k if cfg.patch_size == 0 else min(cfg.patch_size, h_k)
        pw = w_k if cfg.patch_size == 0 else min(cfg.patch_size, w_k)
        pool = region_px if torch.rand(1, generator=gen).item() < 0.5 else object_px
        c = int(pool[torch.randint(len(pool), (1,), generator=gen)])
        y0 = min(max(c // w_k - ph // 2, 0), h_k - ph)
        x0 = min(max(c % w_k - pw // 2, 0), w_k - pw)
        return k_view.crop(y0, y0 + ph, x0, x0 + pw)

    def kept(pred, goal, mask):
        return photometric(pred[mask], goal[mask]) if mask.any() else 0 * pred.sum()

    tile = cfg.tile + cfg.tile % 2

    def unedited_samples(views: list[ViewSamples]):
        """Up to `reg_points` kept samples of the views' pixels that must not change: points
        [M, 3], their template features [M, F] (None when F_dT reads none) and weights [M]."""
        still = [~v.editable[v.pixel] for v in views]  # [S] per view
        points = torch.cat([v.points[m] for v, m in zip(views, still, strict=True)])
        weights = torch.cat([v.weights[m] for v, m in zip(views, still, strict=True)])
        features = None
        if texture.cond_dim:
            features = torch.cat([v.features[m] for v, m in zip(views, still, strict=True)])
        if len(points) > cfg.reg_points:
            pick = torch.randperm(len(points), generator=gen)[: cfg.reg_points].to(device)
            points, weights = points[pick], weights[pick]
            features = None if features is None else features[pick]
        return points, features, weights

    def step(i: int) -> dict[str, torch.Tensor]:
        texture.set_progress(i / max(1.0, cfg.coarse_to_fine * cfg.iterations))
        views, kinds = [], []
        dirs = None
        if reference_colors is not None:  # the colour term's directions of this step
            dirs = nn.functional.normalize(torch.randn(cfg.color_directions, 3, generator=gen))
            dirs = dirs.to(device)
        if target is not None:
            views.append(crop())
            kinds.append("edit")
        for _ in range(cfg.tex_views if use_tex else 0):
            views.append(with_region(bank[int(torch.randint(len(bank), (1,), generator=gen))]))
            kinds.append("tex")

        def loss_fn(leaves):
            terms: dict[str, torch.Tensor] = {}

            def add(name, value):
                terms[name] = terms.get(name, 0) + value

            for view, kind, leaf in zip(views, kinds, leaves, strict=True):
                image = leaf["rgb"].reshape(-1, 3)  # I [h * w, 3]
                add("reg", cfg.w_reg * kept(image, view.template_rgb, ~view.editable))
                if kind == "edit":
                    add("photometric", cfg.w_photometric * kept(image, view.goal, view.editable))
                else:
                    chw = leaf["rgb"].permute(2, 0, 1)[None]
                    tex = tex_loss.terms(chw, template_sim=view.template_sim)
                    add("cls", cfg.w_cls * tex["cls"])
                    add("structure", cfg.w_structure * tex["structure"])
                    if reference_colors is not None:
                        colors = image[view.editable]
                        add(
                            "color",
                            cfg.w_color * sliced_wasserstein(colors, reference_colors, dirs),
                        )
            return sum(terms.values()), terms

        # I_m dropout: some crops of view K go through the compositor without F_dT's colours, so
        # it learns the part's change from the template image alone (what it must do where F_dT
        # learnt nothing: the part's sides view K does not see)
        drop = compositor is not None and torch.rand(1, generator=gen).item() < cfg.mod_dropout
        fields = [None if kind == "edit" and drop else texture for kind in kinds]
        images = [
            edited_image(v, f, compositor, tile, cfg.chunk)
            for v, f in zip(views, fields, strict=True)
        ]
        _, terms = deferred_backward(images, loss_fn)
        if cfg.w_reg_field > 0:  # F_dT itself is zero where unedited pixels look
            points, features, weights = unedited_samples(views)
            if len(points):
                m2 = texture(points, features).pow(2).sum(-1)
                reg_field = cfg.w_reg_field * (weights * m2).sum() / weights.sum()
                reg_field.backward()
                terms["reg_field"] = reg_field
        return {k: v.detach() for k, v in terms.items()}

    return step, mask_source


def edited_image(
    view: ViewSamples,
    texture,
    compositor,
    tile: int,
    chunk: int | None = 32768,
) -> DeferredImage:
    """The edited image I of a view ({"rgb": [h, w, 3]}) in tiles for `deferred_backward`:
    I_m of the whole view is computed once without a graph (`chunk` samples at a time); each
    tile passes its part of it (with a halo of HALO px) through the compositor, and F_dT is
    queried again, with a graph, only when the tile back-propagates. texture None: I_m = 0
    (the compositor alone)."""
    h, w = view.size
    known = None
    if chunk is not None and texture is not None:
        with torch.no_grad():
            known = render_modification(view, texture, chunk)

    def render(y0, y1, x0, x1):
        part = view.crop(y0, y1, x0, x1)
        size = (y1 - y0, x1 - x0, 3)
        if texture is None:
            mod = part.template_rgb.new_zeros(size)
        else:
            part_known = None
            if known is not None:
                part_known = known[box_pixels(w, y0, y1, x0, x1, known.device)]
            mod = render_modification(part, texture, chunk, part_known).reshape(size)
        region = None if part.region is None else part.region.reshape(size[:2])
        template_rgb = part.template_rgb.reshape(size)
        part_rgb = None if part.part_rgb is None else part.part_rgb.reshape(size)
        return {"rgb": composite_hwc(compositor, template_rgb, mod, region, part_rgb)}

    return image_tiles(render, h, w, tile, HALO if compositor is not None else 0)
