"""Image metrics shared by every stage, report and benchmark (one definition each)."""

from __future__ import annotations

import math

import numpy as np


def psnr_of_mse(mse: float) -> float:
    """PSNR in dB of a mean squared error of images in [0, 1] (capped at 120 dB)."""
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


def psnr(pred: np.ndarray, gt: np.ndarray) -> float:
    """PSNR in dB of images or pixel sets (any matching shapes) with values in [0, 1]."""
    mse = float(np.mean((np.asarray(pred, np.float64) - np.asarray(gt, np.float64)) ** 2))
    return psnr_of_mse(mse)


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks [H, W] (1.0 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def mask_iou_within(a: np.ndarray, b: np.ndarray, pixels: int = 1) -> float:
    """IoU of two boolean masks [H, W] where a pixel of one within `pixels` of the other does not
    count against them: agreement / (agreement + each mask's pixels farther than that from the
    other). A silhouette off by a pixel all around scores 1.0, whatever the object's shape (thin
    parts are nearly all outline); a shifted or missing part does not."""
    import cv2

    kernel = np.ones((2 * pixels + 1, 2 * pixels + 1), np.uint8)
    near_a = cv2.dilate(a.astype(np.uint8), kernel) > 0
    near_b = cv2.dilate(b.astype(np.uint8), kernel) > 0
    agree = np.logical_and(a, b).sum()
    apart = np.logical_and(a, ~near_b).sum() + np.logical_and(b, ~near_a).sum()
    return float(agree / (agree + apart)) if agree + apart else 1.0


def masked_psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """PSNR in dB over the pixels of `mask` [H, W] bool of images [H, W, C] in [0, 1]."""
    return psnr(pred[mask], gt[mask])


def masked_ssim(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """Mean of scikit-image's SSIM map [H, W] over the pixels of `mask` (images [H, W, 3])."""
    from skimage.metrics import structural_similarity

    _, ssim_map = structural_similarity(gt, pred, channel_axis=2, data_range=1.0, full=True)
    return float(ssim_map.mean(axis=2)[mask].mean())
