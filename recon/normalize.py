"""Normalisation: the run frame has the object at the origin, inside the unit sphere, up = +z.

Up axis = turntable axis = normal of the plane fitted to the camera centres (their smallest
principal direction). Its sign: cameras look slightly down at the object when they clearly do
(mean viewing direction . up < -0.02); otherwise the images' "up" (-y of each camera) agrees with
it on average. The azimuth is fixed so that the first camera sits on the -y side.
Centre and size: the bounding box of the visual hull carved from masks + cameras (see
visual_hull.py); the object's bounding sphere gets radius `target_radius` (< 1, a margin).

Stored in cameras.json as normalization {scale, center, rotation}:
    x_run = scale * rotation @ (x_in - center)
with `rotation` a 3x3 row-major nested list (omitted when identity). Applying a normalisation to
an already normalised set composes them, so the stored one always maps the original input frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon.visual_hull import carve, hull_bounds
from render.cameras import Camera, CameraSet


@dataclass
class Normalization:
    scale: float
    center: np.ndarray  # [3]
    rotation: np.ndarray  # [3, 3]

    def apply_points(self, x: np.ndarray) -> np.ndarray:  # [N, 3] -> [N, 3]
        return self.scale * (np.asarray(x) - self.center) @ self.rotation.T

    def apply_camera(self, cam: Camera) -> Camera:
        c2w = np.eye(4)
        c2w[:3, :3] = self.rotation @ cam.camera_to_world[:3, :3]
        c2w[:3, 3] = self.apply_points(cam.center[None])[0]
        return cam.replace(camera_to_world=c2w)


def up_axis(cameras: list[Camera]) -> np.ndarray:
    """Unit turntable axis from the camera centres (plane normal), sign as in the module doc."""
    centres = np.array([c.center for c in cameras])
    if len(centres) < 3:
        return np.array([0.0, 0.0, 1.0])
    _, _, vt = np.linalg.svd(centres - centres.mean(0))
    n = vt[2]
    forward = np.array([c.camera_to_world[:3, 2] for c in cameras]).mean(0)
    image_up = -np.array([c.camera_to_world[:3, 1] for c in cameras]).mean(0)
    look = float(forward @ n)
    if abs(look) > 0.02:
        return n if look < 0 else -n
    return n if image_up @ n >= 0 else -n


def rotation_to_up(up: np.ndarray, first_center: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] taking `up` to +z and the first camera's azimuth (about `pivot`) to -y."""
    z = up / np.linalg.norm(up)
    v = first_center - pivot
    v = v - (v @ z) * z
    if np.linalg.norm(v) < 1e-9:
        v = np.cross(z, [1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.cross(z, [0.0, 1.0, 0.0])
    y = -v / np.linalg.norm(v)  # the first camera is at -y
    x = np.cross(y, z)
    return np.stack([x, y, z])  # rows: new axes in input coordinates


def compute_normalization(
    cameras: list[Camera],
    masks: list[np.ndarray],
    target_radius: float = 0.85,
    resolution: int = 96,
) -> tuple[Normalization, dict]:
    """Normalisation of `cameras`' frame from their masks; returns it and stats for the report."""
    lo, hi = hull_bounds(cameras, masks)
    occ, origin, voxel = carve(cameras, masks, lo, hi, resolution, dilate_px=1, tolerance=0)
    idx = np.argwhere(occ)
    if len(idx) == 0:  # tolerate one disagreeing view before giving up
        occ, origin, voxel = carve(cameras, masks, lo, hi, resolution, dilate_px=1, tolerance=1)
        idx = np.argwhere(occ)
    pts = origin + idx * voxel  # [N, 3] voxel centres
    center = 0.5 * (pts.min(0) + pts.max(0))
    radius = float(np.linalg.norm(pts - center, axis=1).max() + 0.87 * voxel)
    up = up_axis(cameras)
    rotation = rotation_to_up(up, cameras[0].center, center)
    norm = Normalization(scale=target_radius / radius, center=center, rotation=rotation)
    stats = {
        "hull_voxels": int(len(idx)),
        "hull_radius_input_units": radius,
        "up_axis_input": [float(x) for x in up],
    }
    return norm, stats


def apply_normalization(cameras: CameraSet, norm: Normalization) -> CameraSet:
    """New CameraSet in the normalised frame; its stored normalisation composes with the old one."""
    s1, c1, r1 = cameras.scale, np.asarray(cameras.center), np.asarray(cameras.rotation)
    # x_run = s2 R2 (s1 R1 (x - c1) - c2) = s2 s1 R2 R1 (x - (c1 + R1^T c2 / s1))
    return CameraSet(
        frames=[norm.apply_camera(c) for c in cameras.frames],
        up=np.array([0.0, 0.0, 1.0]),
        scale=norm.scale * s1,
        center=c1 + r1.T @ norm.center / s1,
        extra=dict(cameras.extra),
        rotation=norm.rotation @ r1,
    )
