"""The `Scene` of an edit (RUN/edits/NAME), for `sine render/export/view/eval` and previews.

Ours: the frozen template behind the editing field, sampled in the band around the proxy warped by
F'_dG; `strength` t scales the edit (0 = template, 1 = the edit). Naive: the fine-tuned template
with the template's proxy (it has no notion of a changed surface). Texture edits
(`TextureEditScene`): the template image I_o and F_dT's modification image I_m blended by the 2D
compositor (`edit.compositor`; without one, I_o + I_m); `strength` t blends the images,
(1 - t) I_o + t I. With the template's `--supersample` s > 1 the compositor blends each of the
s x s sub-pixel images (one ray per pixel, as the edit was trained on) and the pixel is their
mean, not the composite of the box-filtered images. Hybrid edits (`edit.hybrid_edit`): a
texture edit whose template is the geometric edit (`deformed_template`: the template behind
F_dG as a plain field, sampled around F'_dG(proxy)); `strength` t scales the deformation and
blends the images.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from edit.compositor import Compositor, composite_hwc
from edit.editing_field import EditingField, combine, edited_query, warp_vertices
from edit.template_scene import Scene, TemplateScene, load_template_scene, radial_normals
from recon.formats import check_format
from recon.rundir import RunDir
from render.errors import SineError
from render.io import load_torch
from render.mesh_export import surface_colors
from render.renderer import render_image
from render.sampler import BandSampler, ProxyRaycaster
from render.template_field import freeze


def load_edit_field(edit_dir: Path, device) -> dict:
    path = Path(edit_dir) / "edit_field.pt"
    if not path.is_file():
        raise SineError(
            f"{path} not found; run `sine edit` first (or it was interrupted: re-run it)"
        )
    data = load_torch(path, rebuild=edit_command(edit_dir))
    check_format(data, path, "edit", edit_command(edit_dir))
    return data


def edit_command(edit_dir: Path) -> str:
    """The `sine edit ... --force` that makes the edit RUN/edits/NAME again, from its edit.json
    (its options beyond the inputs, when not the defaults, must be given again)."""
    edit_dir = Path(edit_dir)
    words = ["sine edit", str(edit_dir.parent.parent), "--name", edit_dir.name]
    try:
        settings = json.loads((edit_dir / "edit.json").read_text())
    except (OSError, ValueError):
        settings = {}
    if settings.get("view") is not None:
        words += ["--view", str(settings["view"])]
    words += ["--mode", str(settings.get("mode", "geometry"))]
    flags = {"target": "--target", "mask": "--mask", "region": "--region"}
    flags["reference"] = "--reference"
    if settings.get("mode") == "hybrid" and not settings.get("one_target"):
        flags.update(target="--target-geometry", texture_target="--target-texture")
    if settings.get("texture_region") != settings.get("region"):
        flags["texture_region"] = "--region-texture"
    words += [f"{flag} {settings[key]}" for key, flag in flags.items() if settings.get(key)]
    return f"`{' '.join(words)} --force` (and the options it was made with)"


def edited_sampler(
    editing: EditingField,
    proxy_vertices,
    triangles,
    band: float,
    samples: tuple[int, int],
    strength=1.0,
    extra=None,
    warped=None,
) -> BandSampler:
    """Band sampler (`samples`: band and coarse samples per ray) around F'_dG(proxy), united with
    `extra` vertices [V, 3] of the same triangles (e.g. the prior mesh) when given; `warped`
    [V, 3]: F'_dG(proxy) already computed."""
    if warped is None:
        warped = warp_vertices(editing.forward_deform, proxy_vertices, strength)
    verts, tris = warped, triangles
    if extra is not None:
        verts = np.concatenate([warped, extra])
        tris = np.concatenate([triangles, triangles + len(warped)])
    return BandSampler(ProxyRaycaster((verts, tris), inflate=band), *samples)


class EditedField(nn.Module):
    """A geometric edit as a plain radiance field (the template of a hybrid edit's texture
    phase): points [M, 3], dirs [M, 3] in edited space -> {"sigma" [M], "rgb" [M, 3]}, the
    template's density and colour at F_dG(x) plus F_dT's modification, clamped to [0, 1], and its
    geometry feature {"geo_feat" [M, F]} at F_dG(x)."""

    def __init__(self, template: nn.Module, editing: EditingField, strength: float = 1.0):
        super().__init__()
        self.template, self.editing, self.strength = template, editing, float(strength)

    @property
    def grid(self):
        """The template's hash grid (a texture edit's F_dT takes its shape)."""
        return self.template.grid

    def canonical(self, points: torch.Tensor) -> torch.Tensor:
        """Points [M, 3] in edited space -> F_dG(x) [M, 3], where the template is queried."""
        return self.editing.deform(points, self.strength)

    def geometry(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points [M, 3] in edited space -> (sigma [M], geo_feat [M, F]) of the template at
        F_dG(x) (what the feature field's rendering takes from a template)."""
        return self.template.geometry(self.canonical(points))

    def forward(self, points: torch.Tensor, dirs: torch.Tensor) -> dict[str, torch.Tensor]:
        out = edited_query(self.template, self.editing, self.strength)(points, dirs)
        return {
            "sigma": out["sigma"],
            "rgb": (out["rgb"] + out["mod"]).clamp(0.0, 1.0),
            "geo_feat": out["geo_feat"],
        }


def deformed_template(
    template: TemplateScene, editing: EditingField, band: float, strength: float = 1.0
) -> TemplateScene:
    """The template scene with a geometric edit applied: field `EditedField`, mesh F'_dG(proxy),
    sampled in the band of half-width `band` around it (the frozen `template` stays as is)."""
    vertices, triangles = template.mesh()
    warped = warp_vertices(editing.forward_deform, vertices, strength)
    fit_cfg = template.fit_config
    samples = (fit_cfg.band_samples, fit_cfg.coarse_samples)
    sampler = edited_sampler(editing, None, triangles, band, samples, warped=warped)
    field = EditedField(template.field, editing, strength)
    return dataclasses.replace(template, field=field, sampler=sampler, _mesh=(warped, triangles))


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
            vertices, triangles = self.mesh()
            samples = (fit_cfg.band_samples, fit_cfg.coarse_samples)
            self._sampler = edited_sampler(
                self.editing, None, triangles, self.band_width, samples, warped=vertices
            )
        return self._sampler

    def render_view(self, camera, chunk: int = 16384) -> dict[str, np.ndarray]:
        out = render_image(
            camera,
            self.query(),
            self.sampler(),
            self.template.background,
            chunk,
            self.device,
            self.supersample,
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


@dataclass
class TextureEditScene(EditScene):
    """A texture edit: I_o and I_m rendered with the same weights, then the compositor."""

    compositor: Compositor | None = None
    compositor_region: bool = False  # the compositor's g is the edit's gate rendered
    part_colour: bool = False  # the affine head transforms the part's share P (compositor doc)
    color_views: int = 8  # views rendered to colour exported vertices

    def render_view(self, camera, chunk: int = 16384) -> dict[str, np.ndarray]:
        edited_colours = edited_query(self.template.field, self.editing, 1.0)

        def query(points, dirs):
            out = edited_colours(points, dirs)
            if self.compositor_region:  # composited like the colours: g of each pixel
                out["region"] = self.editing.gate(points)[:, None]
                if self.part_colour:  # and P, the part's share of I_o
                    out["part"] = out["region"] * out["rgb"]
            return out

        channels = ("rgb", "mod", "region") if self.compositor_region else ("rgb", "mod")
        channels += ("part",) if self.compositor_region and self.part_colour else ()
        out = render_image(
            camera,
            query,
            self.sampler(),
            self.template.background,
            chunk,
            self.device,
            self.supersample,
            subpixels=channels,
        )
        # the compositor was trained on images of one ray per pixel: it composites each of the
        # s x s sub-pixel images, and the pixel's box filter averages the composites (not the
        # composite of the averaged images; toycar +0.13 dB, spot / figurine -0.03 / -0.07,
        # bench/HISTORY.md)
        sub = {k: torch.from_numpy(out[f"{k}_subpixels"]).to(self.device) for k in channels}
        with torch.no_grad():
            composites = [
                composite_hwc(
                    self.compositor,
                    sub["rgb"][i],  # I_o [H, W, 3]
                    sub["mod"][i],  # I_m [H, W, 3]
                    sub["region"][i, ..., 0] if "region" in sub else None,  # g [H, W]
                    sub["part"][i] if "part" in sub else None,  # P [H, W, 3]
                )
                for i in range(len(sub["rgb"]))
            ]
        template = torch.from_numpy(out["rgb"]).to(self.device)
        # pixels a silhouette crosses were rendered again with more rays (`render_image`): the
        # edit's change of the sub-pixel images carried onto the template's finer pixel, so a
        # pixel the edit leaves alone is exactly the template's
        edited = torch.stack(composites).mean(dim=0) + template - sub["rgb"].mean(dim=0)
        rgb = (1.0 - self.strength) * template + self.strength * edited
        return {"rgb": rgb.cpu().numpy(), **{k: out[k] for k in ("opacity", "depth", "z")}}

    def colors_at(self, points: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
        """The compositor works on images: each point takes its colour from the rendered view
        (of `color_views` around the ring) that sees it most frontally; points no view sees keep
        the field's own colour c' + m'."""
        points = np.asarray(points, np.float32).reshape(-1, 3)
        normals = radial_normals(points) if normals is None else np.asarray(normals, np.float32)
        colours = super().colors_at(points, normals)
        best = np.full(len(points), 0.1)  # least cosine between normal and view direction
        frames = self.run.load_cameras().frames
        count = min(self.color_views, len(frames))
        for k in np.linspace(0, len(frames), count, endpoint=False).astype(int):
            cam = frames[k]
            out = self.render_view(cam)
            row, col, ok, z = cam.pixels_of(points)
            seen = ok & (np.abs(out["z"][row, col] - z) < 2 * self.band_width)
            seen &= out["opacity"][row, col] > 0.5
            to_camera = cam.center[None] - points
            to_camera /= np.maximum(np.linalg.norm(to_camera, axis=1, keepdims=True), 1e-9)
            facing = (to_camera * normals).sum(axis=1)
            better = seen & (facing > best)
            colours[better] = np.clip(out["rgb"][row[better], col[better]], 0, 1)
            best[better] = facing[better]
        return colours


def load_edit_scene(run: RunDir, name: str, strength: float, device: torch.device) -> Scene:
    """The scene of RUN/edits/NAME (see the module doc)."""
    return scene_from_folder(run, run.edit(name), strength, device)


def scene_from_folder(run: RunDir, edit_dir, strength: float, device: torch.device) -> Scene:
    """The scene of the edit whose edit_field.pt is in `edit_dir`."""
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

    def loaded(module: nn.Module, state: dict) -> nn.Module:
        module = module.to(device)
        module.load_state_dict({k: v.to(device) for k, v in state.items()})
        return module.eval()

    def editing_field(state: dict) -> EditingField:
        grid = template.field.grid.cfg
        return EditingField.from_state(grid, state).to(device).eval()

    band = float(data["band_width"])
    texture = data
    if data["method"] == "hybrid":  # the texture edit of the geometric edit
        geometry = editing_field(data["geometry"]["editing"])
        template = deformed_template(template, freeze(geometry), band, strength)
        texture = data["texture"]
    editing = editing_field(texture["editing"])
    common = dict(
        run=run,
        device=device,
        name=name,
        supersample=template.supersample,
        template=template,
        editing=editing,
        strength=float(strength),
        band_width=band,
    )
    if data["method"] in ("texture", "hybrid"):
        compositor = None
        if texture.get("compositor") is not None:
            state = texture["compositor"]
            compositor = loaded(Compositor.for_state(state), state)
        return TextureEditScene(
            **common,
            compositor=compositor,
            compositor_region=bool(texture.get("compositor_region", False)),
            part_colour=bool(texture.get("part_colour", False)),
        )
    return EditScene(**common)
