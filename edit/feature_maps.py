"""Feature maps of a run's distilled DINO feature field, one camera at a time.

`FeatureMapRenderer` loads the frozen template, the feature field and the sampler once
(`edit.feature_field_fit.load_features`) and renders any camera's feature map at a fraction of
its size (DINO features are smooth: half size is ~4x faster for the same masks), upsampled
bilinearly to the camera's size, with the template's opacity as the object mask.

With `geometry` (a `TemplateScene`, e.g. `edit.editing_scene.deformed_template`: a geometric
edit), the feature maps are those of that object: rendered with its density and sampler, and
where its field is an `EditedField` the feature field (and the template's geometry feature it
may take) is queried at the template point F_dG(x') of each sample x', so the features move
with the edited shape (a hybrid edit's semantic masks).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from edit.editing_scene import EditedField
from edit.feature_field_fit import load_feature_field, load_features
from render.device import pick_device
from render.feature_field import render_feature_map


class FeatureMapRenderer:
    """camera -> (features [C, H, W] float32 tensor, object mask [H, W] bool numpy); `maps`
    adds the surface points [H, W, 3] float32 numpy (of the shape rendered: before the warp).

    space: "centred" = the field's PCA coefficients (DINO features minus the object's mean
    feature), "dino" = decoded DINO features; render_scale in (0, 1]: fraction of the camera's
    size rendered; min_opacity: template opacity from which a pixel is on the object;
    geometry: the scene whose shape the maps show (default: the run's template)."""

    def __init__(
        self,
        run_dir,
        device: str = "auto",
        space: str = "centred",
        render_scale: float = 0.5,
        min_opacity: float = 0.5,
        chunk: int = 4096,
        geometry=None,
    ):
        self.device = pick_device(device)
        self.space, self.render_scale = space, render_scale
        self.min_opacity, self.chunk = min_opacity, chunk
        self.warp = None
        if geometry is None:
            self.template, self.field, self.sampler = load_features(run_dir, self.device)
        else:  # the scene's field and sampler: the template is not loaded a second time
            self.field = load_feature_field(run_dir, self.device)
            self.template, self.sampler = geometry.field, geometry.sampler
            if isinstance(geometry.field, EditedField):
                self.warp = geometry.field.canonical

    def __call__(self, camera) -> tuple[torch.Tensor, np.ndarray]:
        feats, on_object, _ = self.maps(camera)
        return feats, on_object

    def maps(self, camera) -> tuple[torch.Tensor, np.ndarray, np.ndarray]:
        """(features [C, H, W], object mask [H, W], surface points [H, W, 3])."""
        scale = min(max(self.render_scale, 0.0), 1.0)
        w, h = max(1, round(camera.width * scale)), max(1, round(camera.height * scale))
        small = camera.resized(w, h) if (w, h) != (camera.width, camera.height) else camera
        out = render_feature_map(
            small,
            self.template,
            self.field,
            self.sampler,
            chunk=self.chunk,
            device=self.device,
            decode=self.space == "dino",
            warp=self.warp,
        )
        feats = torch.from_numpy(out["features"]).permute(2, 0, 1)  # [C, h, w]
        opacity = torch.from_numpy(out["opacity"])[None]  # [1, h, w]
        points = torch.from_numpy(out["points"]).permute(2, 0, 1)  # [3, h, w]
        if small is not camera:
            size = (camera.height, camera.width)

            def up(x: torch.Tensor) -> torch.Tensor:
                return F.interpolate(x[None], size=size, mode="bilinear", align_corners=False)[0]

            # points weighted by opacity, so a silhouette pixel is not pulled to the origin
            feats, points, opacity = up(feats), up(points * opacity), up(opacity)
            points = points / opacity.clamp_min(1e-6)
        on_object = (opacity[0] >= self.min_opacity).numpy()
        return feats, on_object, points.permute(1, 2, 0).numpy()
