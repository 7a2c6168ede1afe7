"""The options of a texture edit (`sine edit --mode texture`, see `edit.texture_edit`):
TextureEditConfig, the keys that do not change what is learnt (RUNTIME_KEYS), the options as
they act on an edit (`options_in_effect`) and the small predicates on them (the gate's
resolution, the affine head with the gate, the fitted transform, the part's colour)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from edit.compositor import HEADS
from edit.edit_stage import EDIT_INPUTS, EditLoopOptions
from recon.training import RUNTIME_KEYS as LOOP_RUNTIME_KEYS
from render.configs import option

METHODS = ("ours", "naive")
# the semantic masks come from the feature field: distilled again, the edit is learnt again
TEXTURE_INPUTS = (*EDIT_INPUTS, "features/field.pt")


GATE_RESOLUTION_AUTO = (128, 384)  # --gate-resolution 0: the pixel-matched one, clamped here


@dataclass
class TextureEditConfig(EditLoopOptions):
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
    from recon.fit_config import pixel_resolution

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
