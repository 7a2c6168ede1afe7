"""The `Scene` interface every output command renders (`sine render/export/view/eval`) and its
template implementation: the fitted template radiance field of a run and its proxy mesh.
Edits implement the same interface in edit/editing_scene.py; `edit.scene.load_scene` picks one.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
import torch

from recon.rundir import RunDir
from render.mesh_export import surface_colors
from render.sampler import vertex_normals


@dataclass
class Scene(ABC):
    """What every output command needs from a run (template) or from an edit of it."""

    run: RunDir
    device: torch.device
    name: str  # "template" or the edit's name
    supersample: int = 1  # rays per pixel side in `render_view` (s x s rays box-filtered)

    @abstractmethod
    def render_view(self, camera, chunk: int = 16384) -> dict[str, np.ndarray]:
        """{"rgb" [H, W, 3] over the background, "opacity" [H, W], "depth" [H, W] (ray
        distance), "z" [H, W] (camera depth)}, float32, run units."""

    @abstractmethod
    def colors_at(self, points: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
        """Surface points [N, 3] (run units) -> rgb [N, 3] in [0, 1], seen looking along
        -normal (normals [N, 3]; without them, the direction from the origin, the object's
        centre, is taken as the normal)."""

    @abstractmethod
    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices [V, 3] run units, triangles [T, 3]): the proxy (template) or the warped
        proxy (edit)."""

    def colored_mesh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vertices [V, 3], triangles [T, 3], colours [V, 3]) with colours from `colors_at`."""
        vertices, triangles = self.mesh()
        normals = vertex_normals(np.asarray(vertices, np.float32), np.asarray(triangles))
        return vertices, triangles, self.colors_at(vertices, normals)


def radial_normals(points: np.ndarray) -> np.ndarray:
    """Unit directions from the origin to `points` [N, 3] (+z for the origin itself)."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    norm = np.linalg.norm(points, axis=1, keepdims=True)
    return np.where(norm > 1e-9, points / np.maximum(norm, 1e-9), [0.0, 0.0, 1.0])


@dataclass
class TemplateScene(Scene):
    """The fitted template radiance field of a run (RUN/template/field.pt) and its proxy."""

    field: torch.nn.Module = None
    background: torch.nn.Module = None
    sampler: object = None
    fit_config: object = None
    _mesh: tuple | None = dataclasses.field(default=None, repr=False)

    def render_view(self, camera, chunk: int = 16384) -> dict[str, np.ndarray]:
        from render.renderer import render_image

        out = render_image(
            camera,
            self.field,
            self.sampler,
            self.background,
            chunk,
            self.device,
            self.supersample,
        )
        return {k: out[k] for k in ("rgb", "opacity", "depth", "z")}

    def colors_at(self, points: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
        normals = radial_normals(points) if normals is None else normals
        band = float(getattr(self.fit_config, "band_width", 0.04))
        return surface_colors(self.field, points, normals, band=band, device=self.device)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        if self._mesh is None:
            from recon.fit_proxy import template_proxy

            self.run.require("proxy_mesh")
            # the proxy the template was fitted around
            m = self.run.read_proxy(template_proxy(self.run))
            self._mesh = (np.asarray(m.vertices).copy(), np.asarray(m.triangles).copy())
        return self._mesh


def load_template_scene(run: RunDir, device: torch.device) -> TemplateScene:
    from recon.fit import load_fitted
    from recon.fit_proxy import make_sampler

    fitted_field, background, fit_cfg = load_fitted(run.root, device)
    sampler = make_sampler(fit_cfg, run)
    return TemplateScene(
        run=run,
        device=device,
        name="template",
        supersample=fit_cfg.supersample,
        field=fitted_field,
        background=background,
        sampler=sampler,
        fit_config=fit_cfg,
    )
