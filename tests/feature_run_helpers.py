"""A tiny run directory with a fitted template and a distilled feature field (shared by tests).

The procedural toycar from `sine synth` (8 views, 64x64, ground-truth part labels) is used as the
run directory directly (known cameras, the ground-truth mesh as proxy), so no reconstruction is
needed. Built once per test run under pytest's base temp folder.
"""

from __future__ import annotations

import shutil
from pathlib import Path

TINY_FIT = dict(
    iterations=40,
    batch_rays=384,
    log2_table=12,
    levels=8,
    max_resolution=128,
    band_samples=8,
    density_hidden=128,  # the width the edit tests' expectations were measured with
    coarse_samples=2,
    previews=0,
    checkpoint_every=1000,
    detail_steps=10,  # a short colour-detail phase: the edits read a template that has one
    detail_batch_rays=256,
)
# tiny editing runs (64 px, a few dozen steps) shared by the geometry, texture and hybrid tests
TINY_GEOMETRY_EDIT = dict(
    iterations=30,
    batch_rays=256,
    prior_points=300,
    cycle_points=200,
    smooth_points=200,
    anchor_points=200,
    previews=0,
    threads=1,
    log_every=1,
    rebuild_every=25,
    warmup_steps=5,
    gate=False,  # the tiny prior moves a handful of vertices: let the loss fall everywhere
    band_width=0.05,  # 30 steps, one BVH rebuild: a band wider than the fit's lets the surface move
)
TINY_TEXTURE_EDIT = dict(
    iterations=30,
    coarse_to_fine=0.2,
    tex_size=48,
    patch_size=32,
    jitter_copies=1,
    previews=0,
    threads=1,
    log_every=1,
    tile=32,
    # the tiny edits test how F_dT and the compositor learn from no change; the fitted start
    # (the default) has its own test: test_fit_transform_starts_near_the_target_...
    fit_transform=False,
)
TINY_FEATURES = dict(
    iterations=60,
    batch_rays=512,
    lr_grid=0.1,
    lr_mlp=0.02,
    log2_table=12,
    levels=8,
    max_resolution=128,
    previews=1,
    log_every=10,
    checkpoint_every=1000,
)


def tiny_feature_run(tmp_path_factory, features: bool = True) -> Path:
    """Path of the shared tiny run (synth -> fit [-> features]); built on first use."""
    from edit.feature_field_fit import FeaturesConfig, distill_features
    from recon import synth
    from recon.fit import fit_template
    from recon.fit_config import FitConfig

    root = tmp_path_factory.getbasetemp() / "tiny_feature_run"
    if not (root / "template" / "field.pt").is_file():
        shutil.rmtree(root, ignore_errors=True)
        cfg = synth.SynthConfig(out=root, procedural="toycar", views=8, width=64, height=64)
        synth.synthesize(cfg, progress=False)
        shutil.copy(root / "mesh.ply", root / "proxy_mesh.ply")
        fit_template(root, FitConfig(**TINY_FIT), progress=False)
    if features and not (root / "features" / "field.pt").is_file():
        distill_features(root, FeaturesConfig(**TINY_FEATURES), progress=False)
    return root
