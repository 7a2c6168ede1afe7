"""View K of a texture edit made ready to train from (see `edit.texture_edit`): TextureSetup
and `prepare`, the reference photo read and its object keyed, the L_tex views (ViewBank), which
pixels of each view may change (`editable_masker`, with the choice to mirror view K's painting)
and the shared colour transform started at its least-squares fit (`start_from_fit`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from edit.compositor import fit_shared_transform
from edit.edit_inputs import difference_region, read_region, read_target
from edit.edit_stage import pick_view
from edit.texture_views import (
    LiftedRegion,
    ViewSamples,
    jittered_camera,
    sample_view,
    scaled_camera,
)
from recon.rundir import RunDir
from render.errors import SineError
from render.io import read_image_rgba, write_image, write_mask

REFERENCE_COLORS = 65536  # pixels of a reference photo the colour term compares with, at most


@dataclass
class ReferencePhoto:
    """A reference photo as the edit uses it (`read_reference`)."""

    rgb: np.ndarray  # [H, W, 3] outside the object: the run's background
    colors: np.ndarray  # [M, 3] the object's colours (M <= REFERENCE_COLORS, a fixed sample)
    pixels: str  # the object's pixels: alpha, keyed, saliency or all


@dataclass
class TextureSetup:
    """What a texture edit trains from (written to the edit's folder)."""

    camera: object  # view K
    view: ViewSamples  # view K at the working size, with `editable` = the region
    target_rgb: np.ndarray | None  # [H, W, 3] (aligned case)
    style_image: np.ndarray  # [H', W', 3] the image whose CLS L_tex aims at
    region: np.ndarray  # [H, W] bool
    photo: ReferencePhoto | None = None  # the reference photo (unaligned case)
    transform_fit: dict | None = None  # `start_from_fit`'s verdict (fit_transform, fresh runs)
    mirror: dict | None = None  # mirrored across the proxy's plane, and why (`choose_mirror`)


def read_reference(path, background, mask: str = "auto") -> ReferencePhoto:
    """A reference photo with its object: the pixels of alpha > 0.5; in a photo without alpha,
    as `mask` says (see TextureEditConfig.reference_mask), or every pixel."""
    path = Path(path)
    if not path.is_file():
        raise SineError(f"reference image {path} does not exist")
    rgb, alpha = read_image_rgba(path)
    pixels = "alpha" if alpha is not None else "all"
    if alpha is None and mask != "none":
        alpha = reference_object(rgb, mask)
        pixels = "all" if alpha is None else "saliency" if mask == "saliency" else "keyed"
    colors = rgb.reshape(-1, 3)
    if alpha is not None:
        colors = rgb[alpha > 0.5]
        rgb = rgb * alpha[..., None] + np.asarray(background, np.float32) * (1 - alpha[..., None])
    if len(colors) == 0:
        raise SineError(f"reference image {path} is fully transparent: it shows no object")
    if len(colors) > REFERENCE_COLORS:  # a fixed sample: the colour term sorts it every step
        colors = colors[np.random.default_rng(0).permutation(len(colors))[:REFERENCE_COLORS]]
    return ReferencePhoto(rgb.astype(np.float32), colors.astype(np.float32), pixels)


def reference_object(rgb: np.ndarray, method: str) -> np.ndarray | None:
    """The object of a reference photo without alpha [H, W, 3] as an alpha [H, W] (0 or 1), by
    colour keying (`method` auto; None where it is not reliable) or the saliency prior."""
    from recon import masks

    if method == "saliency":
        found = masks.segment_salient(rgb, masks.saliency_map(rgb))
        return found.astype(np.float32) if found.any() else None
    keyed = masks.keyed_object(rgb)
    return None if keyed is None else keyed.astype(np.float32)


def prepare(
    run, out, view, target, region, reference, cfg, template, bg, sampler, device, on_object=False
):
    """View K through the frozen `template` and the edit's inputs (see `TextureSetup`).
    on_object: the region keeps only pixels that are the object in both the template's
    rendering and the target (a hybrid edit's texture steps: silhouette differences are the
    geometric steps' part)."""
    camera = pick_view(run, view)
    size = (camera.width, camera.height)
    background = bg().detach().cpu().numpy()
    samples = sample_view(
        camera, template, sampler, bg, cfg.min_weight, device=device, features=cfg.template_feature
    )
    h, w = camera.height, camera.width
    t_rgb = samples.template_rgb.reshape(h, w, 3).clamp(0, 1).cpu().numpy()
    t_alpha = samples.opacity.reshape(h, w).cpu().numpy()
    tgt = read_target(target, size, None, background) if target is not None else None
    if region is not None:
        editable = read_region(region, size)
    elif tgt is not None:
        editable = difference_region(tgt, t_rgb, t_alpha, cfg.region_dilate)
    else:  # a reference without a region: the whole object may change
        editable = t_alpha > 0.5
    if on_object:
        editable = editable & (t_alpha > 0.5)
        if tgt is not None:
            editable &= tgt.silhouette > 0.5
        if not editable.any():
            raise SineError(f"the region to recolour does not touch the object in view {view}")
    style, photo = tgt.rgb if tgt is not None else None, None
    if reference is not None:
        photo = read_reference(reference, background, cfg.reference_mask)
        style = photo.rgb
        if photo.pixels == "all" and cfg.reference_mask != "none":
            print(
                f"edit: no object found in {reference} (--reference-mask {cfg.reference_mask}): "
                "every pixel of it counts (auto keys a plain backdrop; an object in clutter: "
                "--reference-mask saliency, or a cut-out with alpha)"
            )
    samples.editable = torch.from_numpy(editable.reshape(-1)).to(device)
    if tgt is not None:
        write_image(out / "target.png", tgt.rgb)
    if reference is not None:
        write_image(out / "reference.png", style)
    write_mask(out / "region.png", editable)
    write_image(out / "template_view.png", t_rgb)
    return TextureSetup(
        camera,
        samples,
        None if tgt is None else tgt.rgb,
        style,
        editable,
        photo,
    )


class ViewBank:
    """The L_tex views: each training camera in `copies` jittered poses at `size` px, rendered
    through the template (with their editable mask and DINO self-similarity) on first use.
    Poses depend only on the seed and the entry, so a resumed edit sees the same views."""

    def __init__(self, cameras, copies: int, jitter: float, size: int, seed: int, make):
        self.cameras = []
        for j in range(len(cameras) * copies):
            rng = np.random.default_rng([seed, j])
            cam = jittered_camera(cameras[j % len(cameras)], jitter, rng)
            self.cameras.append(scaled_camera(cam, size))
        self.make = make
        self.cache: dict[int, ViewSamples] = {}

    def __len__(self) -> int:
        return len(self.cameras)

    def __getitem__(self, j: int) -> ViewSamples:
        if j not in self.cache:
            self.cache[j] = self.make(self.cameras[j])
        return self.cache[j]


def require_features(run: RunDir, cfg) -> bool:
    """Whether the run has a feature field; a SineError when `cfg.mask_source` needs one."""
    has_features = (run.features / "field.pt").is_file()
    if cfg.mask_source == "features" and not has_features:
        raise SineError(
            f"--mask-source features needs {run.features}/field.pt: run `sine features`"
        )
    return has_features


def training_cameras(run: RunDir) -> list:
    """The run's training cameras (every camera when none is marked for training)."""
    frames = run.load_cameras().frames
    return [c for c in frames if c.split == "train"] or list(frames)


def required_mirror_plane(run: RunDir) -> np.ndarray:
    """The proxy's mirror plane (n, D) for --symmetric; a SineError when it has none."""
    from edit.shape_prior import proxy_mirror_plane

    plane = proxy_mirror_plane(run)
    if plane is None:
        raise SineError("--symmetric: the proxy mesh has no clear mirror plane")
    return plane


def choose_mirror(run: RunDir, cfg, lifted: LiftedRegion, masks, renderer):
    """(the plane view K's painting is mirrored across, or None; the verdict for metrics.json).
    --symmetric: the proxy's plane. --symmetric-auto: the plane when the proxy has one and the
    semantic masks of the training views (at the L_tex views' size, edges not refined) agree
    with the mirrored painting on the surface view K did not see."""
    from edit.shape_prior import proxy_mirror_plane

    if cfg.symmetric:
        return required_mirror_plane(run), {"mirrored": True, "by": "--symmetric"}
    if not cfg.symmetric_auto:
        return None, {"mirrored": False, "by": "--no-symmetric-auto"}
    plane = proxy_mirror_plane(run)
    if plane is None:
        return None, {"mirrored": False, "by": "auto", "why": "no clear mirror plane"}
    views = []
    for camera in training_cameras(run):
        feats, on_object, points = renderer.maps(scaled_camera(camera, cfg.tex_size))
        editable = masks.mask(feats, points=points).cpu().numpy()
        views.append((points[on_object], editable[on_object]))
    agreement, pixels = lifted.mirror_agreement(plane, views)
    mirrored = bool(agreement >= cfg.symmetric_agreement)  # nan: nothing to compare, False
    verdict = {"mirrored": mirrored, "by": "auto", "agreement": agreement, "pixels": pixels}
    return (plane if mirrored else None), verdict


def editable_masker(run: RunDir, setup: TextureSetup, cfg, device, geometry=None):
    """view -> [P] bool pixels that may change (see `edit.texture_edit`'s module doc); and the
    source's name. geometry: the scene whose feature maps the semantic masks take (default: the
    template; a hybrid edit's `deformed_template`, see `edit.feature_maps.FeatureMapRenderer`).
    Sets `setup.mirror` (whether view K's painting is mirrored, and why)."""
    has_features = require_features(run, cfg)
    lifted = LiftedRegion.from_view(setup.view, setup.region, cfg.lift_tol)  # view K's painting

    if cfg.mask_source == "features" or (cfg.mask_source == "auto" and has_features):
        from edit.feature_maps import FeatureMapRenderer
        from edit.semantic_masks import SemanticMaskConfig, SemanticMasks

        renderer = FeatureMapRenderer(run.root, str(device), geometry=geometry)
        feats, on_object, points = renderer.maps(setup.camera)
        painted = setup.region & on_object
        if not painted.any():
            raise SineError("the editable region does not touch the object in the editing view")
        mask_cfg = SemanticMaskConfig(spatial=cfg.mask_spatial)
        masks = SemanticMasks(feats, painted, mask_cfg, object_mask=on_object, points=points)
        # view K's surface, painted or not, and its mirror image: the template's (not a
        # hybrid's edited shape: there the semantic masks alone decide)
        seen, plane = None, None
        if geometry is None:
            plane, setup.mirror = choose_mirror(run, cfg, lifted, masks, renderer)
            seen = lifted if plane is None else lifted.mirrored(plane)

        def semantic(view: ViewSamples) -> torch.Tensor:
            feats, on_obj, points = renderer.maps(view.camera)
            image = view.template_rgb.reshape(*view.size, 3).clamp(0, 1).cpu().numpy()
            editable = masks.mask(feats, image, on_obj, points).cpu().numpy() & on_obj
            editable = torch.from_numpy(editable.reshape(-1)).to(device)
            if plane is not None:  # the painting's mirror image may change
                editable |= seen.editable(view)
            if seen is not None and cfg.keep_seen:
                editable &= ~seen.kept(view)
            return editable

        return semantic, "features"
    if cfg.symmetric:
        setup.mirror = {"mirrored": True, "by": "--symmetric"}
        return lifted.mirrored(required_mirror_plane(run)).editable, "lifted"
    return lifted.editable, "lifted"


def scale_learning_rates(trainer, names: tuple[str, ...], factor: float) -> None:
    """Multiplies the learning rates of the trainer's parameter groups `names` by `factor`, now
    and for the rest of their schedules (saved with the optimiser and scheduler: a resumed run
    keeps them)."""
    for i, group in enumerate(trainer.optimizer.param_groups):
        if group["name"] in names:
            group["lr"] *= factor
            group["initial_lr"] *= factor
            trainer.scheduler.base_lrs[i] *= factor


def start_from_fit(cfg, compositor, view: ViewSamples, slow_down) -> dict:
    """`fit_transform` on view K (`view`, with its goal and gate): the least-squares shared
    transform from the template to the target on the region, kept where its relative residual
    is at most `fit_max_residual` (the per-pixel parts then slowed by `fitted_lr_factor`), else
    undone (no change, full rates). -> {"residual": |residual| / |change|, "kept": bool}."""
    px = view.editable  # [P] bool
    if int(px.sum()) < 4:  # fewer pixels than the transform's 4 unknowns per channel
        return {"residual": None, "kept": False}
    part = None if view.part_rgb is None else view.part_rgb[px]
    template, goal = view.template_rgb[px], view.goal[px]
    residual = fit_shared_transform(
        compositor, template, goal, view.region[px], part, ridge=cfg.fit_ridge
    )
    ratio = float(residual.norm() / (goal - template).norm().clamp_min(1e-12))
    kept = ratio <= cfg.fit_max_residual
    if kept:
        slow_down(("grid", "mlp"), cfg.fitted_lr_factor)  # F_dT
        slow_down(("compositor",), cfg.fitted_compositor_factor)  # the UNet
    else:
        with torch.no_grad():
            compositor.head.bias.zero_()
            if compositor.quadratic is not None:
                compositor.quadratic.zero_()
    return {"residual": ratio, "kept": kept}
