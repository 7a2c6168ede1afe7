"""The options of a geometric edit (`sine edit --mode geometry`, see `edit.geometry_edit`):
GeometryEditConfig, the keys that do not change what is learnt (RUNTIME_KEYS) and the band the
edit samples in when none is set (`with_fit_band`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from edit.edit_stage import EditLoopOptions
from recon.training import RUNTIME_KEYS as LOOP_RUNTIME_KEYS
from render.configs import option

METHODS = ("ours", "naive")


@dataclass
class GeometryEditConfig(EditLoopOptions):
    """Options of a geometric edit (`sine edit --mode geometry`)."""

    method: str = option(
        "ours", "ours (editing field + priors) or naive (fine-tune)", choices=list(METHODS)
    )
    batch_rays: int = option(1024, "rays of the edited view per step", low=1)
    lr_deform: float = option(2e-3, "Adam learning rate of F_dG and F'_dG", low=1e-12)
    warmup_steps: int = option(50, "steps over which F_dG's learning rate ramps up linearly", low=0)
    lr_texture_grid: float = option(1e-2, "Adam learning rate of F_dT's hash table", low=1e-12)
    lr_texture_mlp: float = option(1e-3, "Adam learning rate of F_dT's MLP", low=1e-12)
    lr_naive: float = option(
        1e-3, "naive baseline: learning rate of the template's table and MLPs", low=1e-12
    )
    lr_final_factor: float = option(
        0.1, "learning rates decay exponentially to this factor", low=1e-6, high=1.0
    )
    w_gp: float = option(0.03, "weight of the shape-prior loss L_gp (paper: 0.03)", low=0)
    prior_match: str = option(
        "vertices",
        "L_gp: two-way Chamfer to the prior mesh (the paper's, for priors without "
        "correspondences) or vertex-to-vertex (the ARAP prior keeps the proxy's vertices)",
        choices=["vertices", "chamfer"],
    )
    prior_vertices: str = option(
        "handles",
        "the vertices L_gp matches: the handles (the visible vertices the target moved, lifted to "
        "3D) or all of the prior mesh (the paper's; the rest of M_P is ARAP's guess)",
        choices=["handles", "all"],
    )
    w_gr: float = option(0.1, "weight of the deformation smoothness L_gr (paper: 0.1)", low=0)
    w_cyc: float = option(10.0, "weight of the cycle loss L_cyc (paper: 10)", low=0)
    w_reg: float = option(
        3.0,
        "weight of the regularisation L_reg outside the edited region (the paper: 1; higher "
        "keeps the rest closer to the template)",
        low=0,
    )
    w_silhouette: float = option(1.0, "weight of the silhouette BCE inside L_gt", low=0)
    prior_points: int = option(
        2000, "random proxy / prior vertices per step estimating L_gp's sum over the mesh", low=1
    )
    cycle_points: int = option(1000, "points of L_cyc per step (the paper's M = 1000)", low=2)
    smooth_points: int = option(1000, "points of L_gr per step", low=1)
    anchor_points: int = option(1000, "unmoved surface points of L_reg per step", low=1)
    jitter: float = option(
        0.01, "positional jitter (run units) of L_gr and of surface samples", low=0
    )
    band_width: float | None = option(
        None,
        "half-width of the sampling band around the edited proxy (default: the template fit's "
        "band, so the edit samples exactly as the template wherever nothing moved)",
        low=1e-4,
        high=0.5,
    )
    rebuild_every: int = option(
        25, "steps between re-warping the proxy and rebuilding its BVH", low=1
    )
    region_dilate: int = option(6, "pixels the automatic editable region is grown by", low=0)
    symmetric: bool = option(
        False,
        "the object is mirror-symmetric (the proxy's mirror plane): a geometry edit mirrors the "
        "prior's handles across it; a texture edit mirrors view K's painting (the mirrored "
        "painted surface may change, with --keep-seen the mirrored unpainted surface stays)",
    )
    visibility_tol: float = option(
        0.02, "depth tolerance (run units) of visible proxy vertices", low=0
    )
    arap_iterations: int = option(50, "ARAP iterations of the shape prior", low=1)
    gate: bool = option(
        True,
        "restrict the editing field to near what the shape prior moved (beyond the paper: the "
        "rest renders exactly as the template); --no-gate relies on L_reg alone",
    )
    gate_margin: float = option(
        0.2, "distance (run units) from the prior's moved part at which the gate reaches 0", low=0
    )
    moved_tol: float = option(
        0.01, "prior displacement (run units) below which a vertex is unedited", low=0
    )
    previews: int = option(4, "held-out views rendered as previews at the end (0: none)", low=0)
    seed: int = option(0, "random seed")
    # the loop options' defaults for edits (shared with the texture edit's: one CLI option each)
    checkpoint_every: int = option(100, "steps between checkpoints", low=1)
    log_every: int = option(25, "steps between log entries", low=1)


RUNTIME_KEYS = (*LOOP_RUNTIME_KEYS, "previews")


def with_fit_band(cfg: GeometryEditConfig, fit_cfg) -> GeometryEditConfig:
    """`cfg` with an unset band_width taken from the template's fit config."""
    if cfg.band_width is not None:
        return cfg
    return dataclasses.replace(cfg, band_width=float(fit_cfg.band_width))
