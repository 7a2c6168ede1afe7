"""Cameras, backdrops and rendering of `sine synth` (recon.synth): the camera ring(s) framing the
object, what lies behind it (a colour, a procedural cluttered room, an image) and the ray-cast
views (RGB, mask, depth, part labels) under fixed Lambertian lights.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from recon.mesh_data import MeshData
from render.cameras import Camera, look_at
from render.errors import SineError
from render.raycast import MeshRaycaster

DEFAULT_LIGHTS = (  # (direction towards the light, intensity), fixed in the world
    ((0.35, -0.55, 0.76), 0.75),  # key: above, front-right
    ((-0.5, 0.6, 0.3), 0.3),  # fill: the other side
)


# ---- cameras ------------------------------------------------------------------------------
def focal_from_fov(width: int, height: int, fov_deg: float) -> float:
    """Focal length in pixels giving `fov_deg` across the shorter image side."""
    return 0.5 * min(width, height) / np.tan(0.5 * np.radians(fov_deg))


def camera_distance(object_radius: float, fov_deg: float, fill: float = 0.7) -> float:
    """Distance at which a sphere of `object_radius` spans `fill` of the shorter image side."""
    half = np.arctan(fill * np.tan(0.5 * np.radians(fov_deg)))
    return float(object_radius / np.sin(half))


def fit_camera_distance(
    points: np.ndarray,
    n: int,
    width: int,
    height: int,
    elevations_deg=(20.0,),
    fov_deg: float = 40.0,
    fill: float = 0.7,
    max_points: int = 20000,
) -> float:
    """Ring radius at which the points [N, 3] span `fill` of the half-frame (from the image
    centre, horizontally and vertically) in the view where they extend furthest."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) > max_points:
        points = points[np.linspace(0, len(points) - 1, max_points).astype(np.int64)]
    radius = float(np.linalg.norm(points, axis=1).max())
    distance = camera_distance(radius, fov_deg, fill)  # bounding sphere: an upper bound
    for _ in range(8):  # fixed point on the (nearly 1/distance) extent; converges in a few steps
        extent = 0.0
        for cam in ring_cameras(n, width, height, elevations_deg, distance, fov_deg):
            uv, z = cam.project(points)
            if (z <= 0).any():
                break
            du = np.abs(uv[:, 0] - cam.cx) / (0.5 * width)
            dv = np.abs(uv[:, 1] - cam.cy) / (0.5 * height)
            extent = max(extent, float(du.max()), float(dv.max()))
        else:
            new = max(distance * extent / fill, 1.05 * radius)
            if abs(new - distance) < 1e-4 * distance:
                return new
            distance = new
            continue
        return camera_distance(radius, fov_deg, fill)  # a camera inside the object: be safe
    return distance


def ring_cameras(
    n: int,
    width: int,
    height: int,
    elevations_deg=(20.0,),
    radius: float = 3.0,
    fov_deg: float = 40.0,
    test_every: int = 8,
) -> list[Camera]:
    """`n` cameras on rings around +z looking at the origin (image up ~ +z).

    Views are split into contiguous blocks, one ring per elevation, azimuths evenly spaced (rings
    interleaved). Every `test_every`-th view (1-based: r_007, r_015, ...) has split "test",
    the same rule as `sine ingest` (recon.ingest.assign_splits), so held-out views agree.
    """
    from recon.ingest import assign_splits

    elevations = [float(e) for e in elevations_deg] or [20.0]
    if n < len(elevations):
        raise SineError(f"{n} views cannot cover {len(elevations)} elevations")
    f = focal_from_fov(width, height, fov_deg)
    cams = []
    splits = assign_splits(n, test_every)
    blocks = np.array_split(np.arange(n), len(elevations))
    for ring, (elev, block) in enumerate(zip(elevations, blocks, strict=True)):
        m = len(block)
        for j, i in enumerate(block):
            az = 2 * np.pi * (j + ring / len(elevations)) / m
            el = np.radians(elev)
            eye = radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
            cams.append(
                Camera(
                    width,
                    height,
                    f,
                    f,
                    width / 2.0,
                    height / 2.0,
                    camera_to_world=look_at(eye, np.zeros(3)),
                    name=f"r_{i:03d}.png",
                    split=splits[i],
                )
            )
    return cams


# ---- backdrops ----------------------------------------------------------------------------
BACKDROP_SPHERE = 4.0  # radius of the clutter sphere, in camera distances (cameras well inside)
CLUTTER_TEXTURE = (1024, 2048)  # equirectangular texture of the clutter sphere (rows, columns)


@dataclass
class Backdrop:
    """What the cameras see where the object is not: one of a colour [3], an equirectangular
    texture [H, W, 3] on a sphere of `radius` around the origin (fixed in the world) or an image
    [H, W, 3] fixed in the image plane (resized to each view)."""

    colour: np.ndarray | None = None
    texture: np.ndarray | None = None
    radius: float = 0.0
    image: np.ndarray | None = None

    def pixels(self, cam: Camera, rays: np.ndarray) -> np.ndarray:
        """Backdrop RGB [H*W, 3] float32 of the rays [H*W, 6] through `cam`'s pixels."""
        h, w = cam.height, cam.width
        if self.image is not None:
            img = cv2.resize(self.image, (w, h), interpolation=cv2.INTER_AREA)
            return np.ascontiguousarray(img, np.float32).reshape(h * w, 3).copy()
        if self.texture is None:
            colour = np.asarray(self.colour, np.float32).reshape(3)
            return np.broadcast_to(colour, (h * w, 3)).copy()
        o, d = rays[:, :3].astype(np.float64), rays[:, 3:].astype(np.float64)
        od = np.einsum("nd,nd->n", o, d)
        t = -od + np.sqrt(od**2 - np.einsum("nd,nd->n", o, o) + self.radius**2)
        p = o + t[:, None] * d  # [N, 3] on the sphere
        th, tw = self.texture.shape[:2]
        lon = np.arctan2(p[:, 1], p[:, 0])
        lat = np.arcsin(np.clip(p[:, 2] / self.radius, -1.0, 1.0))
        u = ((lon / (2 * np.pi) + 0.5) * tw - 0.5).astype(np.float32)
        v = ((0.5 - lat / np.pi) * th - 0.5).astype(np.float32)
        out = cv2.remap(
            self.texture,
            u.reshape(h, w),
            v.reshape(h, w),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_WRAP,
        )
        return out.reshape(h * w, 3).astype(np.float32)


def clutter_texture(seed: int = 0, shape: tuple[int, int] = CLUTTER_TEXTURE) -> np.ndarray:
    """A cluttered room as an equirectangular texture [H, W, 3] float32 in [0, 1]: smooth colour
    noise, then hundreds of random shapes (boxes, discs, stripes, lines, checkers) from large to
    small in random colours, then fine grain. Deterministic for a seed."""
    rng = np.random.default_rng(seed)
    h, w = shape
    base = rng.uniform(0.15, 0.85, (4, 8, 3)).astype(np.float32)
    img = cv2.resize(base, (w, h), interpolation=cv2.INTER_CUBIC)
    img = (np.clip(img, 0, 1) * 255).astype(np.uint8)

    def pick() -> tuple[int, ...]:  # muted more often than vivid, like furniture and walls
        grey, vivid = rng.uniform(40, 220), rng.uniform(0, 256, 3)
        return tuple(int(c) for c in grey + rng.uniform(0.2, 1.0) * (vivid - grey))

    for scale in (0.25, 0.12, 0.06, 0.03, 0.015):
        for _ in range(int(6 / scale)):
            colour = pick()
            cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
            sx, sy = (rng.uniform(0.3, 1.0, 2) * scale * h).astype(int) + 2
            kind = rng.integers(0, 5)
            if kind == 0:
                cv2.rectangle(img, (cx - sx, cy - sy), (cx + sx, cy + sy), colour, -1)
            elif kind == 1:
                angle = float(rng.uniform(0, 180))
                cv2.ellipse(img, (cx, cy), (int(sx), int(sy)), angle, 0, 360, colour, -1)
            elif kind == 2:  # stripes
                other = pick()
                step = max(2, int(sx) // 3)
                for k, x in enumerate(range(cx - sx, cx + sx, step)):
                    cv2.rectangle(
                        img, (x, cy - sy), (x + step - 1, cy + sy), (colour, other)[k % 2], -1
                    )
            elif kind == 3:
                end = (cx + int(rng.integers(-4, 5)) * sx, cy + int(rng.integers(-4, 5)) * sy)
                cv2.line(img, (cx, cy), end, colour, max(1, int(sy) // 4))
            else:  # checker
                other = pick()
                step = max(2, int(sx) // 2)
                for i, y in enumerate(range(cy - sy, cy + sy, step)):
                    for j, x in enumerate(range(cx - sx, cx + sx, step)):
                        c = (colour, other)[(i + j) % 2]
                        cv2.rectangle(img, (x, y), (x + step - 1, y + step - 1), c, -1)
    out = img.astype(np.float32) / 255.0
    out += rng.normal(0.0, 0.03, out.shape).astype(np.float32)  # grain
    return np.clip(out, 0.0, 1.0)


def parse_background(words) -> tuple[str, object]:
    """--background words -> ("colour", RGB [3]) | ("clutter", None) | ("image", Path)."""
    words = [str(w) for w in words]
    if len(words) == 1 and words[0].lower() == "clutter":
        return "clutter", None
    if len(words) == 3:
        try:
            rgb = np.array([float(x) for x in words])
        except ValueError:
            rgb = None
        if rgb is not None:
            if not np.all((rgb >= 0) & (rgb <= 1)):
                raise SineError("--background R G B: each value must be in [0, 1]")
            return "colour", rgb
    if len(words) == 1:
        path = Path(words[0])
        if not path.is_file():
            raise SineError(
                f"--background {words[0]}: no such image file; use three numbers R G B in [0, 1], "
                "clutter, or the path of an image"
            )
        return "image", path
    raise SineError(
        "--background takes three numbers R G B in [0, 1], the word clutter, or an image path"
    )


def make_backdrop(words, seed: int, camera_distance: float) -> Backdrop:
    """The Backdrop of a --background value (see `parse_background`)."""
    kind, value = parse_background(words)
    if kind == "colour":
        return Backdrop(colour=np.asarray(value, np.float32))
    if kind == "clutter":
        return Backdrop(texture=clutter_texture(seed), radius=BACKDROP_SPHERE * camera_distance)
    from render.io import read_image

    try:
        image = read_image(value)
    except Exception as exc:  # unreadable / not an image
        raise SineError(f"--background {value}: cannot read it as an image ({exc})") from None
    return Backdrop(image=np.ascontiguousarray(image[..., :3], np.float32))


# ---- rendering ----------------------------------------------------------------------------
def _camera_rays(cam: Camera, cache: dict) -> tuple[np.ndarray, np.ndarray]:
    """Rays [H*W, 6] (origin, unit direction; float32) through the pixel centres of `cam`, and
    camera z per unit distance [H*W]. Same maths as Camera.rays, with the camera-frame directions
    cached per intrinsics and rotated by einsum (much faster than a BLAS matmul here)."""
    key = (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    if key not in cache:
        pix = cam.pixel_grid()
        d = np.stack(
            [(pix[:, 0] - cam.cx) / cam.fx, (pix[:, 1] - cam.cy) / cam.fy, np.ones(len(pix))], 1
        )
        cache[key] = d / np.linalg.norm(d, axis=1, keepdims=True)  # [N, 3] unit, camera frame
    d_cam = cache[key]
    rays = np.empty((len(d_cam), 6), np.float32)
    rays[:, :3] = cam.center
    rays[:, 3:] = np.einsum("nk,dk->nd", d_cam, cam.camera_to_world[:3, :3])
    return rays, d_cam[:, 2].astype(np.float32)


def render_views(
    mesh: MeshData,
    cameras: list[Camera],
    background=(1.0, 1.0, 1.0),
    lights=DEFAULT_LIGHTS,
    ambient: float = 0.35,
    progress: bool = False,
    supersample: int = 1,
) -> list[dict]:
    """Ray casts `mesh` from each camera -> per view dict(rgb [H,W,3] float32, mask [H,W] bool,
    depth [H,W] float32 camera z (0 = background), labels [H,W] int part ids (0 = background)).

    `background`: an RGB colour or a `Backdrop`. `supersample` (odd): rgb is the mean of
    supersample x supersample rays spread over each pixel (a camera pixel integrates the light
    over its area; one ray per pixel aliases fine texture); mask, depth and labels come from the
    centre ray, i.e. the pixel centre, as with one ray."""
    from tqdm import tqdm

    if supersample < 1 or supersample % 2 == 0:
        raise SineError(f"supersample must be an odd number >= 1 (got {supersample})")
    caster = MeshRaycaster((mesh.vertices, mesh.faces))
    face_n, vert_n = mesh.normals()
    light_dirs = np.array([np.asarray(d) / np.linalg.norm(d) for d, _ in lights], np.float32)
    light_power = np.array([p for _, p in lights], np.float32)
    backdrop = background if isinstance(background, Backdrop) else Backdrop(colour=background)
    views, cache = [], {}
    for cam in tqdm(cameras, desc="render", unit="view", disable=not progress):
        s = supersample
        h, w = cam.height, cam.width
        fine = cam.resized(w * s, h * s) if s > 1 else cam
        rays, z_per_t = _camera_rays(fine, cache)
        dirs = rays[:, 3:]
        hits = caster.cast(rays[:, :3], dirs)
        t, mask = hits.t, hits.hit
        fid = hits.triangle[mask]
        uv = hits.uv[mask].astype(np.float64)
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)  # [N, 3]
        rest = mesh.rest_points(fid, bary)
        labels = mesh.labels_at(fid, rest)
        albedo = mesh.albedo_at(fid, bary, rest)  # [N, 3]
        # Shading normal: interpolated on smooth faces, flat elsewhere; facing the camera.
        fn = face_n[fid]
        n = np.where(
            mesh.face_smooth[fid, None], np.einsum("nk,nkd->nd", bary, vert_n[mesh.faces[fid]]), fn
        )
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        flip = np.einsum("nd,nd->n", fn, dirs[mask]) > 0
        n[flip] *= -1
        cosines = np.einsum("nd,ld->nl", n.astype(np.float32), light_dirs)  # [N, lights]
        diffuse = np.einsum("nl,l->n", np.clip(cosines, 0, None), light_power)  # [N]
        shade = np.clip(ambient + (1 - ambient) * diffuse, 0, 1.2)[:, None]

        rgb = backdrop.pixels(fine, rays)
        rgb[mask] = np.clip(albedo * shade, 0, 1)
        depth = np.zeros(len(rays), np.float32)
        depth[mask] = t[mask] * z_per_t[mask]
        lab = np.zeros(len(rays), np.int64)
        lab[mask] = labels
        # [H, s, W, s, ...]: each pixel's s x s rays; the centre one sits on the pixel centre
        rgb = rgb.reshape(h, s, w, s, 3).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)
        c = s // 2
        views.append(
            {
                "rgb": rgb,
                "mask": mask.reshape(h, s, w, s)[:, c, :, c],
                "depth": depth.reshape(h, s, w, s)[:, c, :, c],
                "labels": lab.reshape(h, s, w, s)[:, c, :, c],
            }
        )
    return views
