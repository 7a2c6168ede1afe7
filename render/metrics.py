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
