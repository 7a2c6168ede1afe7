"""The `sine view` scene: template and edited meshes side by side, camera frustums, in Open3D's
legacy Visualizer (interactive with a display; an invisible window + screenshot without one).

Headless: `Visualizer.create_window(visible=False)` falls back to Mesa EGL offscreen rendering
when there is no display (DESIGN.md section 10). `draw_geometries` / `Visualizer.run()` without
a display hang forever: `interactive` refuses to start without $DISPLAY.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from render.cameras import Camera
from render.errors import SineError

FRUSTUM_COLOR = (0.45, 0.45, 0.5)
HIGHLIGHT_COLOR = (1.0, 0.35, 0.0)
BACKGROUND = (1.0, 1.0, 1.0)


@dataclass
class ViewerScene:
    """Open3D geometries to show, and where to look from."""

    geometries: list = field(default_factory=list)  # everything shown from the start
    toggled: list = field(default_factory=list)  # shown/hidden with the 'T' key (edited mesh)
    lookat: np.ndarray = field(default_factory=lambda: np.zeros(3))  # [3]
    front: np.ndarray = field(default_factory=lambda: np.array([0.0, -1.0, 0.3]))  # [3] to eye
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))  # [3]


def o3d_mesh(vertices: np.ndarray, triangles: np.ndarray, colors: np.ndarray | None = None):
    """Legacy Open3D TriangleMesh with vertex normals (and colours [V, 3] in [0, 1])."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
        o3d.utility.Vector3iVector(np.asarray(triangles, np.int32)),
    )
    if colors is not None:
        mesh.vertex_colors = o3d.utility.Vector3dVector(np.clip(colors, 0, 1).astype(np.float64))
    else:
        mesh.paint_uniform_color([0.7, 0.7, 0.7])
    mesh.compute_vertex_normals()
    return mesh


def frustum_lines(camera: Camera, size: float) -> tuple[np.ndarray, np.ndarray]:
    """A camera's frustum as lines: points [5, 3] (centre, 4 image corners at depth `size`) and
    index pairs [8, 2]."""
    w, h = camera.width, camera.height
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)
    cam_pts = np.stack(
        [(corners[:, 0] - camera.cx) / camera.fx, (corners[:, 1] - camera.cy) / camera.fy], 1
    )
    cam_pts = np.concatenate([cam_pts, np.ones((4, 1))], 1) * size  # [4, 3] at z = size
    c2w = camera.camera_to_world
    world = cam_pts @ c2w[:3, :3].T + c2w[:3, 3]
    points = np.concatenate([c2w[:3, 3][None], world])
    lines = np.array([[0, 1], [0, 2], [0, 3], [0, 4], [1, 2], [2, 3], [3, 4], [4, 1]])
    return points, lines


def frustums_lineset(cameras: list[Camera], size: float, highlight: int | None = None):
    """One LineSet with every camera's frustum; camera `highlight` drawn in another colour and
    twice as large."""
    import open3d as o3d

    points, lines, colors = [], [], []
    for i, cam in enumerate(cameras):
        hi = i == highlight
        p, li = frustum_lines(cam, size * (2.0 if hi else 1.0))
        lines.append(li + sum(len(q) for q in points))
        points.append(p)
        colors += [HIGHLIGHT_COLOR if hi else FRUSTUM_COLOR] * len(li)
    ls = o3d.geometry.LineSet(
        o3d.utility.Vector3dVector(np.concatenate(points)),
        o3d.utility.Vector2iVector(np.concatenate(lines).astype(np.int32)),
    )
    ls.colors = o3d.utility.Vector3dVector(np.array(colors, np.float64))
    return ls


def build_scene(
    template: tuple[np.ndarray, np.ndarray, np.ndarray | None],
    edited: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None,
    cameras: list[Camera] | None = None,
    highlight: int | None = None,
    frustum_size: float = 0.15,
) -> ViewerScene:
    """Template mesh at its place, the edited mesh beside it (shifted to the right on screen by
    1.2 times the template's width seen from the viewing direction), the cameras' frustums
    around the template.

    Meshes are (vertices [V, 3], triangles [T, 3], colours [V, 3] or None). The view looks at
    the midpoint of the meshes from the cameras' mean elevation and from the azimuth of the
    highlighted (edited) view, or of the first capture; the edited mesh is shifted to the right
    on screen, perpendicular to the viewing direction.
    """
    tv, tt, tc = template
    scene = ViewerScene()
    if cameras:
        toward = cameras[highlight] if highlight is not None else None
        scene.front = view_direction(cameras, toward)
    scene.geometries.append(o3d_mesh(tv, tt, tc))
    lo, hi = tv.min(0), tv.max(0)
    centre = 0.5 * (lo + hi)
    if edited is not None:
        ev, et, ec = edited
        right = screen_right(scene.front, scene.up)
        extent = float(np.ptp(np.asarray(tv, np.float64) @ right))
        shift = 1.2 * extent * right  # the edit on the right on screen
        scene.toggled.append(o3d_mesh(np.asarray(ev) + shift, et, ec))
        centre = centre + 0.5 * shift
    scene.lookat = centre
    if cameras:
        scene.geometries.append(frustums_lineset(cameras, frustum_size, highlight))
    return scene


def view_direction(cameras: list[Camera], toward: Camera | None = None) -> np.ndarray:
    """Unit vector towards the eye [3]: the captures' mean elevation, at the azimuth of `toward`
    (the edited view: the edit is seen as the user drew it) or else of the first capture."""
    centres = np.array([c.center for c in cameras])
    dist = np.linalg.norm(centres, axis=1)
    elev = float(np.mean(np.arcsin(np.clip(centres[:, 2] / np.maximum(dist, 1e-9), -1, 1))))
    c = (toward or cameras[0]).center
    az = float(np.arctan2(c[1], c[0]))
    return np.array([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)])


def screen_right(front: np.ndarray, up: np.ndarray) -> np.ndarray:
    """The horizontal direction [3] that points right on screen for a viewer whose eye is along
    `front` (looking along -front) with `up` up."""
    right = np.cross(-np.asarray(front, np.float64), np.asarray(up, np.float64))
    right[2] = 0.0  # keep the side-by-side shift horizontal
    norm = np.linalg.norm(right)
    return right / norm if norm > 1e-9 else np.array([1.0, 0.0, 0.0])


def _setup(vis, scene: ViewerScene, zoom: float) -> None:
    for g in scene.geometries + scene.toggled:
        vis.add_geometry(g)
    opt = vis.get_render_option()
    opt.background_color = np.array(BACKGROUND)
    opt.line_width = 2.0
    opt.mesh_show_back_face = True
    ctl = vis.get_view_control()
    ctl.set_lookat(scene.lookat)
    ctl.set_front(scene.front)
    ctl.set_up(scene.up)
    ctl.set_zoom(zoom)


def screenshot(
    scene: ViewerScene, path: str | Path, width: int = 960, height: int = 540, zoom: float = 0.45
) -> np.ndarray:
    """Renders the scene in an invisible window, writes a PNG; returns the image [H, W, 3]."""
    import open3d as o3d

    from render.io import write_image

    vis = o3d.visualization.Visualizer()
    if not vis.create_window(window_name="sine view", width=width, height=height, visible=False):
        raise SineError(
            "Open3D could not create an offscreen window (no display and no EGL); "
            "run under `xvfb-run -a sine view ...`"
        )
    try:
        _setup(vis, scene, zoom)
        vis.poll_events()
        vis.update_renderer()
        image = np.asarray(vis.capture_screen_float_buffer(True), np.float32).copy()
    finally:
        vis.destroy_window()
    write_image(path, image)
    return image


def interactive(scene: ViewerScene, width: int = 1280, height: int = 720) -> None:
    """The interactive viewer ('T' shows/hides the edited mesh). Needs a display."""
    import open3d as o3d

    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        raise SineError(
            "no display: pass --screenshot out.png to render the view to a PNG, "
            "or run under a virtual display (`xvfb-run -a sine view ...`)"
        )
    vis = o3d.visualization.VisualizerWithKeyCallback()
    vis.create_window(
        window_name="sine view (T: toggle the edited mesh)", width=width, height=height
    )
    _setup(vis, scene, zoom=0.45)
    shown = {"on": True}

    def toggle(v):
        shown["on"] = not shown["on"]
        for g in scene.toggled:
            if shown["on"]:
                v.add_geometry(g, reset_bounding_box=False)
            else:
                v.remove_geometry(g, reset_bounding_box=False)
        return True

    vis.register_key_callback(ord("T"), toggle)
    vis.run()
    vis.destroy_window()
