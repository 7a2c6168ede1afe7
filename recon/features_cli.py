"""`sine features RUN`: distil DINO patch features into a feature field on the frozen template."""

from __future__ import annotations

import argparse
from pathlib import Path

from render.configs import add_options, from_args

DESCRIPTION = """\
Computes DINO patch features of every capture of RUN (cached in RUN/features/), then trains a
small feature field (hash grid + MLP, PCA coefficients of the DINO features) rendered with the
frozen template's density (from `sine fit`). Writes checkpoints, the final field, held-out cosine
similarity to DINO (metrics.json) and previews (image | DINO PCA | rendered PCA) into
RUN/features/. An interrupted run resumes from its checkpoint; --force starts over.
"""


NAME = "features"
HELP = "distil DINO features into a feature field (RUN/features/)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from recon.features import FeaturesConfig

    parser.add_argument("run", type=Path, help="run directory with a fitted template")
    parser.add_argument(
        "--force", action="store_true", help="ignore existing checkpoints and start over"
    )
    parser.add_argument(
        "--quiet", action="store_true", help="no progress bar, only the summary line"
    )
    add_options(parser, FeaturesConfig)


def run(args: argparse.Namespace) -> int:
    from recon.features import FeaturesConfig, distill_features

    cfg = from_args(FeaturesConfig, args)
    m = distill_features(args.run, cfg, force=args.force, progress=not args.quiet)
    print(
        f"features: {m['iterations']} steps in {m['train_seconds']:.1f} s "
        f"(DINO {m['dino_seconds']:.1f} s, rays {m['pool_seconds']:.1f} s); "
        f"relative error {m['final_rel_error']:.3f}, held-out cosine to DINO "
        f"{m['heldout_cosine']:.3f} (PCA-{m['pca_dim']} bound {m['pca_cosine']:.3f}) "
        f"-> {args.run / 'features'}"
    )
    return 0
