"""The editing field and its dual volume rendering (paper Sec. 3.1, DESIGN.md sections 6-7).

`EditingField` holds F_dG (edited -> template space), F'_dG (template -> edited space, warps the
proxy mesh) and F_dT (modification colour). `edited_query` is the field callback the renderer
takes: a sample x in edited space goes to x' = F_dG(x) in the frozen template, which gives the
density and the template colour c'; F_dT(x) gives the modification colour m'. The renderer
composites every channel with the same weights, so one pass gives C_o ("rgb", over the background),
C_e ("mod"), the opacity and the depth. Geometry edits combine them as C_o + C_e; the 2D
compositor of texture edits takes the two images instead.

The sampler of the edited space is the proxy band around the proxy mesh warped by F'_dG
(`warp_vertices`; during training, united with the prior mesh M_P, see `edit.geometry_edit`).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from edit.deformation import DeformationField
from edit.edit_gate import EditGate
from edit.texture_field import TextureField
from render.hashgrid import HashGridConfig
from render.renderer import FieldQuery


class EditingField(nn.Module):
    """F_dG, F'_dG and F_dT of one edit, all three scaled by one `EditGate` (1 everywhere until
    it is set: see edit/edit_gate.py)."""

    def __init__(
        self, texture_grid: HashGridConfig | None = None, n_freqs: int = 4, texture_cond: int = 0
    ):
        """texture_cond: F_dT reads the template's geometry feature (its width) besides the
        position; 0: the position only (see edit/texture_field.py)."""
        super().__init__()
        self.gate = EditGate()
        self.deform = DeformationField(n_freqs, gate=self.gate)
        self.forward_deform = DeformationField(n_freqs, gate=self.gate)
        self.texture = TextureField(texture_grid, gate=self.gate, cond_dim=texture_cond)

    @classmethod
    def from_state(cls, texture_grid: HashGridConfig, state: dict) -> EditingField:
        """An editing field shaped for the saved `state` (F_dT's condition width is read off its
        first layer: files written before F_dT had one load as position-only)."""
        editing = cls(texture_grid)
        grid_dim = editing.texture.grid.output_dim
        cond = int(state["texture.mlp.0.weight"].shape[1]) - grid_dim
        if cond:
            editing = cls(texture_grid, texture_cond=cond)
        editing.load_state_dict(state)
        return editing


def edited_query(template: nn.Module, editing: EditingField, strength: float = 1.0) -> FieldQuery:
    """The field callback of the edited scene: points [M, 3], dirs [M, 3] in edited space ->
    {"sigma" [M], "rgb" [M, 3] (template colour at x'), "mod" [M, 3] (modification colour),
    "geo_feat" [M, F] (the template's geometry feature at x', F_dT's condition when it reads one)}.

    The template must be frozen with `render.template_field.freeze` (not `torch.no_grad`), so
    gradients reach F_dG through the template's positions."""

    def query(points: torch.Tensor, dirs: torch.Tensor) -> dict[str, torch.Tensor]:
        x_template = editing.deform(points, strength)
        out = template(x_template, dirs)
        cond = out["geo_feat"] if editing.texture.cond_dim else None
        return {
            "sigma": out["sigma"],
            "rgb": out["rgb"],
            "mod": strength * editing.texture(points, cond),
            "geo_feat": out["geo_feat"],
        }

    return query


def combine(out: dict[str, torch.Tensor]) -> torch.Tensor:
    """Edited colour of geometry edits, C_o + C_e: rendered channels -> rgb [R, 3] (or [H, W, 3])."""
    if "mod" not in out:
        return out["rgb"]
    return (out["rgb"] + out["mod"]).clamp(0.0, 1.0)


@torch.no_grad()
def warp_vertices(
    forward_deform: DeformationField, vertices: np.ndarray, strength: float = 1.0, chunk=65536
) -> np.ndarray:
    """Proxy vertices [V, 3] (template space) -> F'_dG(v) [V, 3] in edited space (numpy)."""
    param = next(forward_deform.parameters())
    out = []
    for start in range(0, len(vertices), chunk):
        v = torch.as_tensor(vertices[start : start + chunk], dtype=param.dtype, device=param.device)
        out.append(forward_deform(v, strength).cpu().numpy())
    return np.concatenate(out).astype(np.float32) if out else np.zeros((0, 3), np.float32)
