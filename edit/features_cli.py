"""`sine features RUN`: distil DINO patch features into a feature field on the frozen template."""

from __future__ import annotations

import argparse

from render.configs import add_training_arguments, from_args

DESCRIPTION = """\
Computes DINO patch features of every capture of RUN (cached in RUN/features/), then trains a
small feature field (hash grid + MLP, PCA coefficients of the DINO features) rendered with the
frozen template's density (from `sine fit`). Writes checkpoints, the final field, held-out cosine
similarity to DINO (metrics.json) and previews (image | DINO PCA | rendered PCA) into
RUN/features/. An interrupted run resumes from its checkpoint; a finished one is skipped unless
its options changed (then it is redone); --force starts over. The old results stay in
RUN/features/ until the new run has finished.
"""


NAME = "features"
HELP = "distil DINO features into a feature field (RUN/features/)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from edit.feature_field_fit import FeaturesConfig

    add_training_arguments(
        parser,
        FeaturesConfig,
        "run directory with a fitted template",
        shown=("iterations", "device"),
    )


def run(args: argparse.Namespace) -> int:
    from edit.feature_field_fit import FeaturesConfig, distill_features

    cfg = from_args(FeaturesConfig, args)
    m = distill_features(args.run, cfg, force=args.force, progress=not args.quiet)
    held_out = "heldout_cosine" in m
    cosine = m["heldout_cosine"] if held_out else m["train_view_cosine"]
    where = "held-out" if held_out else "training-view (the run has no held-out view)"
    if m.get("skipped"):
        print(
            f"features: already done with these options ({m['iterations']} steps; {where} "
            f"cosine to DINO {cosine:.3f}) in {args.run / 'features'}; --force to redo"
        )
        return 0
    print(
        f"features: {m['iterations']} steps in {m['train_seconds']:.1f} s "
        f"(DINO {m['dino_seconds']:.1f} s, rays {m['pool_seconds']:.1f} s); "
        f"relative error {m['final_rel_error']:.3f}, {where} cosine to DINO "
        f"{cosine:.3f} (PCA-{m['pca_dim']} bound {m['pca_cosine']:.3f}) "
        f"-> {args.run / 'features'}"
    )
    return 0
