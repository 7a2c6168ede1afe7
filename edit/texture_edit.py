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
part drifts after 300 steps (red streaks on the toycar's edges, bench/RESULTS.md).
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
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from edit.compositor import HALO, HEADS, Compositor, composite_hwc, fit_shared_transform
from edit.deferred import DeferredImage, deferred_backward, image_tiles
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
)
from edit.editing_field import EditingField
from edit.geometry_losses import photometric
from edit.texture_views import (
    LiftedRegion,
    ViewSamples,
    box_pixels,
    jittered_camera,
    render_gate,
    render_modification,
    sample_view,
    scaled_camera,
)
from recon.fit import load_fitted, make_sampler
from recon.rundir import RunDir
from recon.training import RUNTIME_KEYS as LOOP_RUNTIME_KEYS
from recon.training import LoopOptions, loop_options
from render.configs import option, to_dict, validate
from render.device import pick_device, torch_threads
from render.errors import SineError
from render.io import (
    file_sha256,
    read_image_rgba,
    write_image,
    write_json,
    write_mask,
)
from render.metrics import psnr
from render.renderer import render_rays
from render.template_field import freeze

METHODS = ("ours", "naive")
# the semantic masks come from the feature field: distilled again, the edit is learnt again
TEXTURE_INPUTS = (*EDIT_INPUTS, "features/field.pt")


GATE_RESOLUTION_AUTO = (128, 384)  # --gate-resolution 0: the pixel-matched one, clamped here


@dataclass
class TextureEditConfig(LoopOptions):
    """Options of a texture edit (`sine edit --mode texture`). Options named as the geometry
    edit's share its defaults (one `sine edit` command line serves both modes)."""

    method: str = option(
        "ours", "ours (editing field + compositor) or naive (fine-tune)", choices=list(METHODS)
    )
    compositor: bool = option(
        True, "blend I_o and I_m with the 2D compositor (--no-compositor: I_o + I_m, a baseline)"
    )
    compositor_head: str = option(
        "affine",
        "what the compositor's UNet predicts per pixel: affine (a 3 x 3 colour transform + "
        "offset of the pixel's RGB, which recolours every shade of a part alike) or residual "
        "(the paper's: a colour residual in logit space)",
        choices=list(HEADS),
    )
    part_colour: bool = option(
        True,
        "--compositor-head affine with the gate: the transform acts on the edited part's share "
        "of each pixel's colour (weighted by the gate), so a rim pixel keeps its neighbour's "
        "share (--no-part-colour: the whole pixel)",
    )
    iterations: int = option(600, "training steps", low=1)
    template_feature: bool = option(
        True,
        "F_dT also reads the template's geometry feature at each point (as the template's own "
        "colour head): parts that look alike in the template change alike, on every side "
        "(--no-template-feature: position only, the paper's F_dT)",
    )
    lr_grid: float = option(
        1e-3,
        "Adam learning rate of F_dT's hash table (higher: sharper, but the fine levels fit "
        "view K's noise and mottle the other views)",
        low=1e-12,
    )
    lr_mlp: float = option(1e-3, "Adam learning rate of F_dT's MLP", low=1e-12)
    mod_dropout: float = option(
        0.5,
        "share of view K's crops composited without F_dT's image (the compositor learns the "
        "part's change from the template alone, which carries it to unseen sides)",
        low=0,
        high=1,
    )
    lr_compositor: float | None = option(
        None,
        "Adam learning rate of the compositor's UNet (None: 2.5e-3 with the affine head, 5e-3 "
        "with the residual head)",
        low=1e-12,
    )
    lr_transform: float = option(
        5e-3,
        "--compositor-head affine: Adam learning rate of the colour transform every pixel shares "
        "(the head's bias). Higher recolours the whole editable part alike, but spills over "
        "what the semantic masks include and the user did not paint",
        low=1e-12,
    )
    fit_transform: bool = option(
        True,
        "--compositor-head affine with the gate, aligned target: fit the shared colour "
        "transform by least squares on view K's region; where it explains the change "
        "(residual <= --fit-max-residual) the edit starts from it and the per-pixel parts "
        "learn at --fitted-lr-factor x their rates, else from no change",
    )
    quadratic_transform: bool = option(
        True,
        "--compositor-head affine: the shared colour transform gets a quadratic term (products "
        "of the colour channels), for recolourings that are not one linear map of RGB "
        "(--no-quadratic-transform: linear only)",
    )
    fit_ridge: float = option(
        1e-4,
        "--fit-transform: ridge of the least-squares fit towards no change, relative to the "
        "colours' second moments (larger shrinks the fitted map; 0: none)",
        low=0.0,
    )
    fit_max_residual: float = option(
        0.3,
        "--fit-transform: the largest |residual| / |change| over view K's region for which the "
        "fitted transform is kept (a hue turn fits well below it, a partly painted part above)",
        low=0.0,
    )
    fitted_lr_factor: float = option(
        0.1,
        "--fit-transform, the fit kept: factor on the learning rates of F_dT (1: full rates, "
        "which fit view K's own template error and carry badly to other views)",
        low=1e-6,
        high=1.0,
    )
    fitted_compositor_factor: float = option(
        0.0,
        "--fit-transform, the fit kept: factor on the learning rate of the compositor's UNet "
        "(0: frozen, the shared transform and F_dT still learn)",
        low=0.0,
        high=1.0,
    )
    lr_naive: float = option(1e-3, "naive baseline: learning rate of the colour MLP", low=1e-12)
    lr_final_factor: float = option(
        0.1, "learning rates decay exponentially to this factor", low=1e-6, high=1.0
    )
    w_photometric: float = option(1.0, "weight of the photometric term on view K's region", low=0)
    w_reg: float = option(
        3.0, "weight of the regularisation L_reg outside the edited part (as geometry's)", low=0
    )
    gate: bool = option(
        True,
        "multiply F_dT by a 3D gate: 1 near the surface the views' masks let change, 0 beyond "
        "--gate-outer (the rest of the object renders exactly as the template)",
    )
    gate_inner: float = option(0.02, "gate: 1 within this distance (run units)", low=0)
    gate_outer: float = option(0.05, "gate: 0 beyond this distance (run units)", low=0)
    gate_weight: float = option(
        0.05, "gate: built from editable pixels' samples of at least this weight", low=0
    )
    gate_resolution: int = option(
        0,
        "gate: voxels per side over [-1, 1]^3 (0: one voxel per pixel's footprint at the "
        "object's centre, within "
        f"[{GATE_RESOLUTION_AUTO[0]}, {GATE_RESOLUTION_AUTO[1]}], so the part's edge is as "
        "sharp as the pixels)",
        low=0,
    )
    gate_vote: bool = option(
        True,
        "gate, with the semantic masks: a voxel is the part's where the views' editable pixels "
        "outvote the others, and the gate ends where unchangeable surface is nearer "
        "(--no-gate-vote: every view's editable pixels count, the gate spreads --gate-outer "
        "beyond them)",
    )
    w_reg_field: float = option(
        1.0, "weight of |F_dT|^2 at surface points of unedited pixels (3D side of L_reg)", low=0
    )
    reg_points: int = option(4096, "samples of that term per step", low=1)
    w_cls: float = option(2e-4, "weight of L_tex's CLS term (appearance of the target)", low=0)
    w_structure: float = option(
        2e-4, "weight of L_tex's self-similarity term (structure of the template)", low=0
    )
    w_color: float = option(
        1.0,
        "--reference only: weight of the colour term, the sliced Wasserstein distance between "
        "the colours of the edited part in the L_tex views and the reference photo's object "
        "colours (its opaque pixels, or as --reference-mask finds them; 0: off)",
        low=0,
    )
    color_directions: int = option(
        16, "colour term: random RGB directions per step along which it is computed", low=1
    )
    reference_mask: str = option(
        "auto",
        "--reference without alpha: which of its pixels are the object whose look is taken "
        "(colours, and what L_tex's CLS sees: the rest shows the run's background): auto (the "
        "object keyed from a plain backdrop, every pixel when keying is not reliable, e.g. a "
        "close-up of a texture), saliency (the saliency prior, for an object in clutter), none "
        "(every pixel); a photo with alpha always uses its alpha",
        choices=["auto", "saliency", "none"],
    )
    tex_views: int = option(1, "views around the object with L_tex and L_reg per step", low=0)
    tex_size: int = option(128, "longer side (px) of the L_tex views' renders", low=16)
    jitter_deg: float = option(
        5.0, "pose jitter of the L_tex views: random rotations of this spread (degrees)", low=0
    )
    jitter_copies: int = option(2, "jittered copies of each training camera", low=1)
    patch_size: int = option(
        64, "side (px) of the crop of view K per step (0: the whole view)", low=0
    )
    coarse_to_fine: float = option(
        0.5, "fraction of training after which all of F_dT's hash levels are on", low=0, high=1
    )
    min_weight: float = option(
        1e-2, "samples of lower volume-rendering weight are skipped by F_dT", low=0, high=1
    )
    mask_source: str = option(
        "auto",
        "which pixels of other views may change: semantic masks from RUN/features (features), "
        "the painted region lifted onto the surface (lifted), or features when present (auto)",
        choices=["auto", "features", "lifted"],
    )
    keep_seen: bool = option(
        True,
        "semantic masks: pixels of every view whose surface view K showed outside the painted "
        "region keep the template (what the user saw and left unpainted stays, where the part's "
        "semantic mask reaches beyond the painting; texture mode only)",
    )
    mask_spatial: float = option(
        0.25,
        "semantic masks: weight of each pixel's 3D surface point beside its DINO feature (see "
        "`sine masks --spatial`): surface that looks like the painted part but lies among the "
        "rest of the object keeps the template; 0: features only (the paper)",
        low=0.0,
    )
    symmetric: bool = option(
        False,
        "the object is mirror-symmetric (the proxy's mirror plane, as for geometry edits): view "
        "K's painting mirrored across it also tells the side view K does not see; there the "
        "mirrored painted surface may change and, with --keep-seen, the mirrored unpainted "
        "surface keeps the template",
    )
    symmetric_auto: bool = option(
        True,
        "texture mode with semantic masks, without --symmetric: mirror view K's painting as "
        "--symmetric does when the proxy has a clear mirror plane and the semantic masks agree "
        "with the mirrored painting on the surface view K does not see (IoU >= "
        "--symmetric-agreement): the mirror then places the part's edge there, where the masks "
        "place it one DINO patch at a time (a painting the far side's masks do not follow is "
        "not mirrored)",
    )
    symmetric_agreement: float = option(
        0.7,
        "--symmetric-auto: the semantic masks' IoU with the mirrored painting, on the surface "
        "view K does not see, from which the painting is mirrored",
        low=0,
        high=1,
    )
    region_dilate: int = option(6, "pixels the automatic editable region is grown by", low=0)
    lift_tol: float = option(
        0.02,
        "lifted masks: distance (run units) within which a surface point counts as seen by view K",
        low=0,
    )
    batch_rays: int = option(1024, "naive baseline: rays of view K per step", low=1)
    chunk: int = option(
        32768, "F_dT is queried on at most this many samples at once (memory)", low=1
    )
    tile: int = option(
        128,
        "side (px, even) of the image tiles re-rendered with a graph by the deferred "
        "back-propagation: the step's peak memory follows it, not the image size",
        low=2,
    )
    checkpoint_every: int = option(100, "steps between checkpoints", low=1)
    log_every: int = option(25, "steps between log entries", low=1)
    previews: int = option(4, "held-out views rendered as previews at the end (0: none)", low=0)
    seed: int = option(0, "random seed")


RUNTIME_KEYS = (*LOOP_RUNTIME_KEYS, "previews", "chunk")


def gate_resolution(cfg: TextureEditConfig, cameras) -> int:
    """Voxels per side of the gate: `cfg.gate_resolution`, or 0 -> one per pixel footprint of
    the cameras (`recon.fit.pixel_resolution` over the gate's [-1, 1]^3) within
    GATE_RESOLUTION_AUTO (finer costs the distance transforms' time and memory, cubed)."""
    from recon.fit import pixel_resolution

    if cfg.gate_resolution:
        return max(2, cfg.gate_resolution)
    return int(np.clip(pixel_resolution(cameras), *GATE_RESOLUTION_AUTO))


def affine_with_gate(cfg: TextureEditConfig) -> bool:
    """The compositor's affine head with the 3D gate: what the part's share and the fitted
    transform act through."""
    return bool(cfg.compositor and cfg.gate and cfg.compositor_head == "affine")


def fits_transform(cfg: TextureEditConfig) -> bool:
    """Whether the shared transform starts at its least-squares fit (`fit_transform` with the
    affine head and the gate; `options_in_effect` turns it off without an aligned target)."""
    return affine_with_gate(cfg) and cfg.fit_transform


def uses_part_colour(cfg: TextureEditConfig) -> bool:
    """Whether the compositor transforms the part's share P of each pixel (`part_colour` with
    the affine head and the gate; the residual head has no transform to restrict)."""
    return affine_with_gate(cfg) and cfg.part_colour


# The compositor UNet's learning rate by head (`lr_compositor` None).
COMPOSITOR_LR = {"residual": 5e-3, "affine": 2.5e-3}

REFERENCE_COLORS = 65536  # pixels of a reference photo the colour term compares with, at most


# ---- preparation --------------------------------------------------------------------------
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


def compositor_lr(cfg: TextureEditConfig) -> float:
    """The compositor UNet's learning rate: `lr_compositor`, or its head's default."""
    chosen = cfg.lr_compositor
    return COMPOSITOR_LR[cfg.compositor_head] if chosen is None else chosen


def options_in_effect(cfg: TextureEditConfig, reference) -> TextureEditConfig:
    """`cfg` as it acts on an edit: the compositor's learning rate resolved for its head; without
    a reference photo the colour term is off and no photo is masked, with one no colour
    transform is fitted (each recorded so: edits made before those options existed are reused)."""
    cfg = replace(cfg, lr_compositor=compositor_lr(cfg))
    if reference is not None:  # no target to fit the transform to
        return replace(cfg, fit_transform=False)
    return replace(cfg, w_color=0.0, reference_mask="none")


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
    """view -> [P] bool pixels that may change (see the module doc); and the source's name.
    geometry: the scene whose feature maps the semantic masks take (default: the template; a
    hybrid edit's `deformed_template`, see `edit.feature_maps.FeatureMapRenderer`). Sets
    `setup.mirror` (whether view K's painting is mirrored, and why)."""
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
    cfg = options_in_effect(cfg or TextureEditConfig(), reference)
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
