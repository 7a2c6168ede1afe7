"""Camera paths to render: a turntable orbit, and nerfstudio's `camera_path.json` both ways.

Orbit: around the up axis (+z) through the origin (the run frame has the object at the origin),
at the captures' mean elevation and mean distance, starting at the first capture's azimuth,
with the first capture's intrinsics resized to the requested width.

`camera_path.json` (nerfstudio's `ns-render --camera-path-filename` format, read by
`nerfstudio.cameras.camera_paths.get_path_from_json`):

    {"camera_type": "perspective", "render_width": W, "render_height": H, "seconds": S,
     "fps": F, "camera_path": [{"camera_to_world": [16 floats, row-major 4x4, OpenGL axes],
                                "fov": vertical field of view in degrees, "aspect": W / H}]}

nerfstudio derives fx = fy = H / 2 / tan(fov / 2) and the image centre as principal point. To
keep cameras with fx != fy or an off-centre principal point exact, each entry also carries our
own keys `fx`, `fy`, `cx`, `cy`, `width`, `height` (pixels), which nerfstudio ignores and the
importer here prefers. Poses are in the run frame (nerfstudio's own exports are in its
dataparser's frame, which differs by a similarity transform).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from render.cameras import OPENCV_TO_OPENGL, Camera, look_at
from render.errors import SineError
from render.io import read_json, write_json


# ---- orbit --------------------------------------------------------------------------------
def mean_elevation_distance(cameras: list[Camera]) -> tuple[float, float]:
    """(mean elevation in radians above the xy plane, mean distance) of the camera centres."""
    centres = np.array([c.center for c in cameras])  # [N, 3]
    dist = np.linalg.norm(centres, axis=1)
    if not len(centres) or float(dist.min()) < 1e-9:
        raise SineError("cameras.json has no camera away from the origin to orbit from")
    elevation = np.arcsin(np.clip(centres[:, 2] / dist, -1.0, 1.0))
    return float(elevation.mean()), float(dist.mean())


def orbit_cameras(
    cameras: list[Camera],
    n_frames: int,
    width: int | None = None,
    elevation_deg: float | None = None,
    distance: float | None = None,
) -> list[Camera]:
    """`n_frames` cameras on a circle around +z looking at the origin.

    Elevation and distance default to the captures' means; the path starts at the first
    capture's azimuth and turns counter-clockwise (seen from above). Intrinsics are the first
    capture's, resized to `width` (height keeps the aspect ratio).
    """
    if n_frames < 1:
        raise SineError("--orbit needs at least one frame")
    elev, dist = mean_elevation_distance(cameras)
    if elevation_deg is not None:
        elev = math.radians(elevation_deg)
    dist = distance if distance is not None else dist
    first = cameras[0]
    if width is not None and width != first.width:
        first = first.resized(int(width), max(1, round(first.height * width / first.width)))
    az0 = math.atan2(cameras[0].center[1], cameras[0].center[0])
    out = []
    for i in range(n_frames):
        az = az0 + 2.0 * math.pi * i / n_frames
        eye = dist * np.array(
            [math.cos(elev) * math.cos(az), math.cos(elev) * math.sin(az), math.sin(elev)]
        )
        c2w = look_at(eye, np.zeros(3), up=(0.0, 0.0, 1.0))
        out.append(first.replace(camera_to_world=c2w, name=f"{i:04d}.png", split="orbit"))
    return out


# ---- nerfstudio camera_path.json ----------------------------------------------------------
def camera_path_dict(cameras: list[Camera], fps: float = 24.0) -> dict:
    """Cameras -> nerfstudio camera_path dict (see the module doc)."""
    if not cameras:
        raise SineError("an empty camera path cannot be written")
    entries = []
    for cam in cameras:
        fov = math.degrees(2.0 * math.atan(0.5 * cam.height / cam.fy))
        entries.append(
            {
                "camera_to_world": (cam.camera_to_world @ OPENCV_TO_OPENGL).ravel().tolist(),
                "fov": fov,
                "aspect": cam.width / cam.height,
                "fx": float(cam.fx),
                "fy": float(cam.fy),
                "cx": float(cam.cx),
                "cy": float(cam.cy),
                "width": cam.width,
                "height": cam.height,
                "name": cam.name,
            }
        )
    return {
        "camera_type": "perspective",
        "render_width": cameras[0].width,
        "render_height": cameras[0].height,
        "fps": float(fps),
        "seconds": len(cameras) / float(fps),
        "camera_path": entries,
    }


def cameras_from_camera_path(data: dict, width: int | None = None) -> list[Camera]:
    """nerfstudio camera_path dict -> cameras (OpenCV axes), optionally resized to `width`."""
    if data.get("camera_type", "perspective") != "perspective":
        raise SineError("camera_path.json: only perspective cameras are supported")
    entries = data.get("camera_path")
    if not entries:
        raise SineError("camera_path.json has no 'camera_path' list of cameras")
    out = []
    for i, entry in enumerate(entries):
        if "camera_to_world" not in entry:
            raise SineError(f"camera_path.json: camera {i} has no 'camera_to_world'")
        c2w_gl = np.asarray(entry["camera_to_world"], dtype=np.float64).reshape(4, 4)
        w = int(entry.get("width", data.get("render_width", 0)))
        h = int(entry.get("height", data.get("render_height", 0)))
        if w <= 0 or h <= 0:
            raise SineError("camera_path.json needs 'render_width' and 'render_height'")
        if "fx" in entry:
            fx, fy = float(entry["fx"]), float(entry["fy"])
            cx, cy = float(entry["cx"]), float(entry["cy"])
        elif "fov" in entry:  # nerfstudio: vertical fov, square pixels, centred principal point
            fx = fy = 0.5 * h / math.tan(0.5 * math.radians(float(entry["fov"])))
            cx, cy = 0.5 * w, 0.5 * h
        else:
            raise SineError(f"camera_path.json: camera {i} has no 'fov'")
        cam = Camera(
            w,
            h,
            fx,
            fy,
            cx,
            cy,
            camera_to_world=c2w_gl @ OPENCV_TO_OPENGL,
            name=entry.get("name") or f"{i:04d}.png",
            split="path",
        )
        if width is not None and width != w:
            cam = cam.resized(int(width), max(1, round(h * width / w)))
        out.append(cam)
    return out


def write_camera_path(path: str | Path, cameras: list[Camera], fps: float = 24.0) -> None:
    write_json(path, camera_path_dict(cameras, fps))


def read_camera_path(path: str | Path, width: int | None = None) -> list[Camera]:
    return cameras_from_camera_path(read_json(path), width)
