"""Torch device choice: CUDA automatically when present, `--device` to force."""

from __future__ import annotations

import torch

from render.errors import SineError


def pick_device(name: str = "auto") -> torch.device:
    """'auto' -> CUDA when torch sees one, else CPU; 'cpu' / 'cuda' force (clear error if absent)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise SineError("--device cuda requested but torch sees no CUDA device; use --device cpu")
    return torch.device(name)
