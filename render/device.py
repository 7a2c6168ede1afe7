"""Torch device choice: CUDA automatically when present, `--device` to force."""

from __future__ import annotations

from contextlib import contextmanager

import torch

from render.errors import SineError


def pick_device(name: str = "auto") -> torch.device:
    """'auto' -> CUDA when torch sees one, else CPU; 'cpu' / 'cuda' force (clear error if absent)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise SineError("--device cuda requested but torch sees no CUDA device; use --device cpu")
    return torch.device(name)


@contextmanager
def torch_threads(n: int):
    """Within the block torch uses n CPU threads (n <= 0: unchanged); restored afterwards."""
    before = torch.get_num_threads()
    if n > 0:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
