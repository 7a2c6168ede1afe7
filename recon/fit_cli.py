"""`sine fit RUN`: fit the template radiance field on a run directory's captures."""

from __future__ import annotations

import argparse

from render.configs import add_training_arguments, from_args

DESCRIPTION = """\
Trains the template radiance field (hash grid + small MLPs) on RUN's images, masks and cameras,
sampling only near the proxy mesh (RUN/proxy_mesh.ply, from `sine recon`). Writes checkpoints,
the final field, held-out PSNR/SSIM (metrics.json) and side-by-side previews into RUN/template/.
An interrupted fit resumes from the latest checkpoint when re-run; a finished one is skipped
unless its options changed (then it is redone); --force starts over. The old results stay in
RUN/template/ until the new fit has finished (it trains in RUN/template.partial/).
"""


NAME = "fit"
HELP = "fit the template radiance field (RUN/template/)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from recon.fit_config import FitConfig

    add_training_arguments(
        parser,
        FitConfig,
        "run directory (with cameras.json and proxy_mesh.ply)",
        shown=("preset", "iterations", "background", "device"),
    )


def run(args: argparse.Namespace) -> int:
    from recon.fit import fit_template
    from recon.fit_config import FitConfig

    cfg = from_args(FitConfig, args)
    metrics = fit_template(args.run, cfg, force=args.force, progress=not args.quiet)
    if metrics.get("skipped"):
        print(
            f"fit: already done with these options ({metrics['iterations']} steps; "
            f"{_headline(metrics)}) in {args.run / 'template'}; "
            "--force to redo"
        )
        return 0
    detail = ""
    if metrics.get("detail_steps"):
        detail = f" + {metrics['detail_steps']} colour-detail steps"
        if metrics.get("detail_kept") is False:  # dropped by the check
            detail = f" + {metrics['detail_steps_taken']} colour-detail steps (branch dropped)"
    print(
        f"fit: {metrics['iterations']} steps{detail} in {metrics['train_seconds']:.1f} s "
        f"({metrics['rays_per_second']:.0f} rays/s x {metrics['samples_per_ray']} samples/ray "
        f"= {metrics.get('samples_per_second', 0) / 1000:.0f}k samples/s); {_headline(metrics)} "
        f"-> {args.run / 'template'}"
    )
    return 0


def _headline(metrics: dict) -> str:
    """Held-out PSNR/SSIM on object pixels (when the views have masks), whole images beside."""
    nan = float("nan")
    whole = f"PSNR {metrics.get('heldout_psnr', nan):.2f} dB, SSIM {metrics.get('heldout_ssim', nan):.3f}"
    if "heldout_psnr_object" not in metrics:
        return f"held-out {whole}"
    return (
        f"held-out object PSNR {metrics['heldout_psnr_object']:.2f} dB, "
        f"SSIM {metrics['heldout_ssim_object']:.3f} (whole image: {whole})"
    )
