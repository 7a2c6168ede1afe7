"""The `Scene` of an edit (RUN/edits/NAME), for `sine render/export/view/eval` and previews.

Ours: the frozen template behind the editing field, sampled in the band around the proxy warped by
F'_dG; `strength` t scales the edit (0 = template, 1 = the edit). Naive: the fine-tuned template
with the template's proxy (it has no notion of a changed surface).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from edit.editing_field import EditingField, combine, edited_query, warp_vertices
from edit.scene import Scene, TemplateScene, load_template_scene, radial_normals
from recon.rundir import RunDir
from render.errors import SineError
from render.mesh_export import surface_colors
from render.renderer import render_image
from render.sampler import BandSampler, ProxyRaycaster
from render.template_field import freeze


@dataclass
class EditScene(Scene):
    """An edit learnt by the editing field, at a given strength."""

    template: TemplateScene = None
    editing: EditingField = None
    strength: float = 1.0
    band_width: float = 0.05
    _mesh: tuple | None = dataclasses.field(default=None, repr=False)
    _sampler: BandSampler | None = dataclasses.field(default=None, repr=False)

    def query(self):
        return edited_query(self.template.field, self.editing, self.strength)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        if self._mesh is None:
            vertices, triangles = self.template.mesh()
            warped = warp_vertices(self.editing.forward_deform, vertices, self.strength)
            self._mesh = (warped, triangles)
        return self._mesh

    def sampler(self) -> BandSampler:
        if self._sampler is None:
            fit_cfg = self.template.fit_config
            caster = ProxyRaycaster(self.mesh(), inflate=self.band_width)
            self._sampler = BandSampler(caster, fit_cfg.band_samples, fit_cfg.coarse_samples)
        return self._sampler

    def render_view(self, camera, chunk: int = 16384) -> dict[str, np.ndarray]:
        out = render_image(
            camera, self.query(), self.sampler(), self.template.background, chunk, self.device
        )
        rgb = combine({k: torch.from_numpy(v) for k, v in out.items() if k in ("rgb", "mod")})
        return {"rgb": rgb.numpy(), **{k: out[k] for k in ("opacity", "depth", "z")}}

    def colors_at(self, points: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
        normals = radial_normals(points) if normals is None else normals
        query = self.query()

        def edited_colour(x, d):
            res = query(x, d)
            return {"sigma": res["sigma"], "rgb": (res["rgb"] + res["mod"]).clamp(0, 1)}

        return surface_colors(
            edited_colour, points, normals, band=self.band_width, device=self.device
        )


def load_edit_scene(run: RunDir, name: str, strength: float, device: torch.device) -> Scene:
    """The scene of RUN/edits/NAME (see the module doc)."""
    return scene_from_folder(run, run.edit(name), strength, device)


def scene_from_folder(run: RunDir, edit_dir, strength: float, device: torch.device) -> Scene:
    """The scene of the edit whose edit_field.pt is in `edit_dir`."""
    from edit.geometry_edit import load_edit_field

    if not 0.0 <= strength <= 1.0:
        raise SineError(f"--strength must be in [0, 1], not {strength}")
    name = Path(edit_dir).name.removesuffix(".partial")
    data = load_edit_field(edit_dir, device)
    template = load_template_scene(run, device)
    if data["method"] == "naive":
        field = template.field
        field.load_state_dict(data["field"])
        if strength != 1.0:
            raise SineError("--strength needs an edit made with --method ours (not naive)")
        return dataclasses.replace(template, name=name)
    freeze(template.field)
    editing = EditingField(template.field.grid.cfg).to(device)
    editing.load_state_dict({k: v.to(device) for k, v in data["editing"].items()})
    editing.eval()
    return EditScene(
        run=run,
        device=device,
        name=name,
        template=template,
        editing=editing,
        strength=float(strength),
        band_width=float(data["band_width"]),
    )
