"""Held-out evaluation of a fitted template: PSNR/SSIM on object pixels and whole images, and
the side-by-side previews (`evaluate`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from render.io import write_image
from render.metrics import masked_psnr, masked_ssim, psnr
from render.renderer import render_image


def evaluate(
    field,
    background,
    sampler,
    views,
    device,
    chunk=16384,
    preview_dir=None,
    n_previews=0,
    supersample=1,
):
    """Renders held-out views -> metrics: on object pixels (the views' masks; the headline,
    since a plain background inflates whole-image figures) and over whole images."""
    from skimage.metrics import structural_similarity

    field.eval()
    psnrs, ssims, samples, obj_psnrs, obj_ssims = [], [], [], [], []
    for i, (cam, image, mask) in enumerate(views):
        out = render_image(cam, field, sampler, background, chunk, device, supersample)
        pred = np.clip(out["rgb"], 0.0, 1.0)
        psnrs.append(psnr(pred, image))
        ssims.append(float(structural_similarity(image, pred, channel_axis=2, data_range=1.0)))
        samples.append(float(out["samples_per_pixel"]))
        if mask is not None and mask.any():
            obj_psnrs.append(masked_psnr(pred, image, mask))
            obj_ssims.append(masked_ssim(pred, image, mask))
        if preview_dir is not None and i < n_previews:
            write_image(
                Path(preview_dir) / (Path(cam.name).stem + ".png"),
                np.concatenate([pred, image], axis=1),
            )
    field.train()
    if not psnrs:
        return {}
    obj = {}
    if obj_psnrs:
        obj = {
            "heldout_psnr_object": float(np.mean(obj_psnrs)),
            "heldout_ssim_object": float(np.mean(obj_ssims)),
        }
    return {
        **obj,
        "heldout_psnr": float(np.mean(psnrs)),
        "heldout_ssim": float(np.mean(ssims)),
        "heldout_views": len(psnrs),
        "heldout_psnr_min": float(np.min(psnrs)),
        "heldout_samples_per_pixel": float(np.mean(samples)),
    }
