"""Synthetic scenes shared by test modules: a tilted camera ring and an analytic sphere.

Imported as `from scene_helpers import ...`: pytest puts tests/ on sys.path (tests/ is not a
package), with `pytest` and `python -m pytest` alike.
"""

from __future__ import annotations

import numpy as np

from render.cameras import Camera, look_at


def ring(n=12, center=(1.0, 2.0, 3.0), axis=(0.3, 0.1, 1.0), radius=4.0, height=1.5, w=160, h=120):
    """Cameras on a tilted ring around `center`, looking at it; returns cameras and the axis."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    e1 = np.cross(axis, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.asarray(center) + radius * (np.cos(a) * e1 + np.sin(a) * e2) + height * axis
        c2w = look_at(eye, center, up=axis)
        cams.append(Camera(w, h, 150.0, 150.0, w / 2, h / 2, c2w, name=f"v{i:02d}.png"))
    return cams, axis


def sphere_hits(cam: Camera, center, r) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel of `cam`: (hit [H*W] bool, ray distance to the sphere's front [H*W])."""
    origins, dirs = cam.rays()
    oc = origins - np.asarray(center)
    b = (oc * dirs).sum(1)
    disc = b**2 - ((oc**2).sum(1) - r**2)
    return disc >= 0, -b - np.sqrt(np.maximum(disc, 0))


def sphere_masks(cams, center, r) -> list[np.ndarray]:
    """The sphere's silhouette [H, W] bool in each camera."""
    return [sphere_hits(cam, center, r)[0].reshape(cam.height, cam.width) for cam in cams]


def sphere_depths(cams, center, r) -> list[np.ndarray]:
    """The sphere's camera-z depth [H, W] float32 in each camera (0 off the sphere)."""
    out = []
    for cam in cams:
        hit, t = sphere_hits(cam, center, r)
        z = np.where(hit, t * (cam.rays()[1] @ cam.camera_to_world[:3, 2]), 0.0)
        out.append(z.reshape(cam.height, cam.width).astype(np.float32))
    return out
