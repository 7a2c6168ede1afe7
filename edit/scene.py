"""What every output command (`sine render/export/view/eval`) needs from a run: one interface
for the template and for an edit of it.

`load_scene(RUN)` gives the fitted template (`TemplateScene`, edit/template_scene.py, where the
`Scene` interface is defined); `load_scene(RUN, edit=NAME, strength=T)` the edit RUN/edits/NAME
(edit/editing_scene.py).
"""

from __future__ import annotations

import numpy as np

from edit.editing_scene import load_edit_scene
from edit.template_scene import Scene, TemplateScene, load_template_scene, radial_normals
from recon.rundir import RunDir
from render.device import pick_device
from render.errors import SineError

__all__ = [
    "RenderCache",
    "Scene",
    "TemplateScene",
    "load_scene",
    "load_template_scene",
    "radial_normals",
]


def load_scene(
    run_dir,
    edit: str | None = None,
    strength: float = 1.0,
    device: str = "auto",
    supersample: int | None = None,
) -> Scene:
    """The template of `run_dir`, or its edit `edit` (RUN/edits/NAME) at `strength` (0..1),
    rendered with `supersample` rays per pixel side (None: the template's `sine fit
    --supersample`)."""
    run = RunDir(run_dir)
    run.require("cameras")
    dev = pick_device(device) if isinstance(device, str) else device
    scene = _load(run, edit, strength, dev)
    if supersample is not None:
        if supersample < 1:
            raise SineError(f"--supersample must be >= 1 (got {supersample})")
        scene.supersample = int(supersample)
    return scene


def _load(run: RunDir, edit: str | None, strength: float, dev) -> Scene:
    if edit is None:
        return load_template_scene(run, dev)
    if not run.edit(edit).is_dir():
        have = sorted(
            p.name
            for p in (run.root / "edits").glob("*")
            if p.is_dir() and not p.name.startswith(".") and p.suffix not in (".partial", ".old")
        )
        raise SineError(
            f"edit {edit} not found in {run.root / 'edits'} "
            f"(edits there: {', '.join(have) or 'none'}); create it with `sine edit`"
        )
    return load_edit_scene(run, edit, float(strength), dev)


class RenderCache:
    """A scene whose `render_view` results are kept per camera (name, size, intrinsics, pose),
    for callers that render the same views more than once (the demo scores held-out views, then
    shows some of them on its summary sheet). Everything else is the wrapped scene's. The
    returned arrays are shared: do not modify them."""

    def __init__(self, scene: Scene):
        self.scene = scene
        self._renders: dict[tuple, dict] = {}

    def __getattr__(self, name: str):
        return getattr(self.scene, name)

    def render_view(self, camera, chunk: int = 16384) -> dict:
        pose = np.asarray(camera.camera_to_world, np.float64).tobytes()
        key = (
            camera.name,
            camera.width,
            camera.height,
            camera.fx,
            camera.fy,
            camera.cx,
            camera.cy,
            pose,
        )
        if key not in self._renders:
            self._renders[key] = self.scene.render_view(camera, chunk)
        return self._renders[key]
