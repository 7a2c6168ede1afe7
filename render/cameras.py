"""Pinhole cameras in OpenCV axes and converters to/from every camera format we read.

Conventions (also in the README):
- intrinsics in pixels; continuous image coordinates with the centre of pixel (row i, col j) at
  (j + 0.5, i + 0.5) (COLMAP / nerfstudio convention), so resizing scales fx, fy, cx, cy exactly;
- extrinsics stored as camera-to-world 4x4, OpenCV axes (x right, y down, z forward);
- distortion in OpenCV order [k1, k2, p1, p2(, k3)].

Converters: NeRF/nerfstudio `transforms.json` (OpenGL axes), COLMAP (world-to-camera, quaternion
w-x-y-z), Middlebury `*_par.txt` (x = K[R|t]X), NeuS/IDR `cameras_sphere.npz` (world_mat,
scale_mat) and plain 3x4 projection matrices (RQ decomposition).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from render.errors import SineError

# OpenCV (x right, y down, z forward) <-> OpenGL (x right, y up, z backward): flip y and z.
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class Camera:
    """One calibrated view: pinhole intrinsics + camera-to-world pose in OpenCV axes."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    camera_to_world: np.ndarray = field(default_factory=lambda: np.eye(4))  # [4, 4]
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(4))  # [k1, k2, p1, p2]
    name: str = ""
    split: str = "train"

    def __post_init__(self):
        self.camera_to_world = np.asarray(self.camera_to_world, dtype=np.float64).reshape(4, 4)
        self.distortion = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
        self.width, self.height = int(self.width), int(self.height)

    # ---- derived quantities -------------------------------------------------------------
    @property
    def K(self) -> np.ndarray:  # [3, 3]
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def world_to_camera(self) -> np.ndarray:  # [4, 4]
        return invert_pose(self.camera_to_world)

    @property
    def center(self) -> np.ndarray:  # [3]
        return self.camera_to_world[:3, 3].copy()

    @property
    def projection(self) -> np.ndarray:  # [3, 4]  x ~ P X
        return self.K @ self.world_to_camera[:3]

    def replace(self, **changes) -> Camera:
        return dataclasses.replace(self, **changes)

    def resized(self, width: int, height: int) -> Camera:
        """The same camera for an image resized to (width, height)."""
        sx, sy = width / self.width, height / self.height
        return self.replace(
            width=width,
            height=height,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=self.cx * sx,
            cy=self.cy * sy,
        )

    # ---- projection and rays ------------------------------------------------------------
    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points [N, 3] -> pixel coordinates [N, 2] and camera depth z [N] (no distortion)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        w2c = self.world_to_camera
        cam = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack(
                [self.fx * cam[:, 0] / z + self.cx, self.fy * cam[:, 1] / z + self.cy], axis=1
            )
        return uv, z

    def pixels_of(
        self, points: np.ndarray, shape: tuple[int, int] | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The pixel each world point [N, 3] falls in, on an image of `shape` (h, w) covering
        this camera's view (default: the camera's own size; a mask at half size works too).

        -> (row [N] int64, col [N] int64, inside [N] bool: in front of the camera and within
        the image; row and col are 0 where not inside, so they index safely, camera z [N]).
        """
        h, w = shape if shape is not None else (self.height, self.width)
        uv, z = self.project(points)
        with np.errstate(invalid="ignore"):  # points in the camera plane: uv is nan
            col = np.floor(uv[:, 0] * (w / self.width))
            row = np.floor(uv[:, 1] * (h / self.height))
            inside = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        row = np.where(inside, row, 0).astype(np.int64)
        col = np.where(inside, col, 0).astype(np.int64)
        return row, col, inside, z

    def pixel_grid(self) -> np.ndarray:
        """Centres of all pixels, row-major: [H*W, 2] (u = col + 0.5, v = row + 0.5)."""
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64) + 0.5
        return np.stack([u.ravel(), v.ravel()], axis=1)

    def pixel_window(self, points: np.ndarray) -> tuple[int, int, int, int] | None:
        """The pixels whose centre ray can meet the convex hull of world points [N, 3] (a mesh's
        vertices: its image lies in the hull of theirs) -> (row0, row1, col0, col1), rows
        [row0, row1) and columns [col0, col1), with one pixel of margin, clipped to the image
        (empty when it falls outside); None when some point is not in front of the camera
        (its image is then unbounded: every pixel may see it)."""
        uv, z = self.project(points)
        if len(z) == 0:
            return 0, 0, 0, 0
        if not np.all(z > 1e-9):
            return None
        # centre u = col + 0.5 within [u_min, u_max] <=> col in [u_min - 0.5, u_max - 0.5]
        lo = np.floor(uv.min(0) - 0.5) - 1
        hi = np.floor(uv.max(0) - 0.5) + 2
        size = np.array([self.width, self.height])
        (col0, row0), (col1, row1) = np.clip(lo, 0, size), np.clip(hi, 0, size)
        return int(row0), int(max(row0, row1)), int(col0), int(max(col0, col1))

    def window_pixels(
        self, window: tuple[int, int, int, int] | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The pixels of a `pixel_window` (None: all), row-major: their indices [N] int64 into
        the H*W pixels and their centres [N, 2] (as `pixel_grid`'s rows, for `rays`)."""
        if window is None:
            return np.arange(self.height * self.width), self.pixel_grid()
        row0, row1, col0, col1 = window
        rows, cols = np.mgrid[row0:row1, col0:col1]
        centres = np.stack([cols.ravel(), rows.ravel()], axis=1).astype(np.float64) + 0.5
        return (rows * self.width + cols).ravel().astype(np.int64), centres

    def rays(self, pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Ray origins [N, 3] and unit directions [N, 3] (float32) through `pixels` [N, 2].

        Without `pixels`, one ray per pixel centre in row-major order. Distortion is ignored:
        working images are undistorted at ingestion.
        """
        if pixels is None:
            pixels = self.pixel_grid()
        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        d_cam = np.stack(
            [
                (pixels[:, 0] - self.cx) / self.fx,
                (pixels[:, 1] - self.cy) / self.fy,
                np.ones(len(pixels)),
            ],
            axis=1,
        )
        d_world = d_cam @ self.camera_to_world[:3, :3].T
        d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
        origins = np.broadcast_to(self.center, d_world.shape)
        return origins.astype(np.float32), d_world.astype(np.float32)

    def z_per_unit_distance(self, pixels: np.ndarray | None = None) -> np.ndarray:
        """For each ray, camera z gained per unit of distance along it ([N]): depth = t * this."""
        if pixels is None:
            pixels = self.pixel_grid()
        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        x = (pixels[:, 0] - self.cx) / self.fx
        y = (pixels[:, 1] - self.cy) / self.fy
        return (1.0 / np.sqrt(x * x + y * y + 1.0)).astype(np.float32)

    # ---- serialisation (cameras.json frames) --------------------------------------------
    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "split": self.split,
            "width": self.width,
            "height": self.height,
            "fx": float(self.fx),
            "fy": float(self.fy),
            "cx": float(self.cx),
            "cy": float(self.cy),
            "distortion": [float(x) for x in self.distortion],
            "camera_to_world": self.camera_to_world.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        return cls(
            width=d["width"],
            height=d["height"],
            fx=d["fx"],
            fy=d["fy"],
            cx=d["cx"],
            cy=d["cy"],
            camera_to_world=np.array(d["camera_to_world"]),
            distortion=np.array(d.get("distortion", [0, 0, 0, 0])),
            name=d.get("name", ""),
            split=d.get("split", "train"),
        )


# ---- pose helpers -------------------------------------------------------------------------
def invert_pose(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    pose = np.asarray(pose, dtype=np.float64)
    inv = np.eye(4)
    inv[:3, :3] = pose[:3, :3].T
    inv[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return inv


def pose_from_rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World-to-camera (R, t) -> camera-to-world 4x4."""
    w2c = np.eye(4)
    w2c[:3, :3] = np.asarray(R, dtype=np.float64).reshape(3, 3)
    w2c[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return invert_pose(w2c)


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """3x3 rotation -> unit quaternion [w, x, y, z] with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    trace = np.trace(R)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """Quaternion [w, x, y, z] -> 3x3 rotation."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world (OpenCV axes) of a camera at `eye` looking at `target`, image-up ~ `up`."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:  # looking along `up`: pick any perpendicular
        right = np.cross(forward, [1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
    return c2w


# ---- projection matrices (RQ decomposition) -----------------------------------------------
def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """3x4 P = K[R|t] -> (K [3,3] with positive diagonal and K[2,2] = 1, R [3,3], t [3])."""
    P = np.asarray(P, dtype=np.float64).reshape(3, 4)
    K, R, c_h = cv2.decomposeProjectionMatrix(P)[:3]
    # OpenCV's RQ may leave negative diagonal entries in K: move the signs into R.
    signs = np.sign(np.diag(K))
    signs[signs == 0] = 1.0
    K, R = K @ np.diag(signs), np.diag(signs) @ R
    if np.linalg.det(R) < 0:  # P was given up to a negative scale
        R = -R
    K = K / K[2, 2]
    center = (c_h[:3] / c_h[3]).reshape(3)
    t = -R @ center
    return K, R, t


def camera_from_projection(P: np.ndarray, width: int, height: int, name: str = "") -> Camera:
    """A Camera from a 3x4 projection matrix (skew is dropped; metric P expected)."""
    return camera_from_krt(*decompose_projection(P), width, height, name)


# ---- NeRF / nerfstudio transforms.json ----------------------------------------------------
def cameras_from_transforms(data: dict, image_sizes: dict[str, tuple[int, int]] | None = None):
    """Parses a transforms.json dict -> list of (file_path, Camera).

    Accepts nerfstudio keys (fl_x, fl_y, cx, cy, w, h, k1, k2, p1, p2 at top level or per frame)
    and the original NeRF `camera_angle_x` (then width/height come from `image_sizes` keyed by
    file_path, and cx, cy are the image centre).
    """
    out = []
    for frame in data.get("frames", []):
        if "transform_matrix" not in frame or "file_path" not in frame:
            raise SineError("transforms.json: every frame needs 'file_path' and 'transform_matrix'")

        def get(key, default=None, frame=frame):
            return frame.get(key, data.get(key, default))

        path = frame["file_path"]
        w, h = get("w"), get("h")
        if (w is None or h is None) and image_sizes and path in image_sizes:
            w, h = image_sizes[path]
        if w is None or h is None:
            raise SineError(f"transforms.json: no image size for {path} (add 'w' and 'h')")
        if get("fl_x") is not None:
            fx = float(get("fl_x"))
            fy = float(get("fl_y", fx))
        elif get("camera_angle_x") is not None:
            fx = 0.5 * w / np.tan(0.5 * float(get("camera_angle_x")))
            fy = (
                fx
                if get("camera_angle_y") is None
                else 0.5 * h / np.tan(0.5 * get("camera_angle_y"))
            )
        else:
            raise SineError("transforms.json: no focal length ('fl_x' or 'camera_angle_x')")
        c2w_gl = np.array(frame["transform_matrix"], dtype=np.float64).reshape(4, 4)
        cam = Camera(
            w,
            h,
            fx,
            fy,
            float(get("cx", w / 2.0)),
            float(get("cy", h / 2.0)),
            camera_to_world=c2w_gl @ OPENCV_TO_OPENGL,
            distortion=_transforms_distortion(get),
            name=Path(path).name,
        )
        out.append((path, cam))
    if not out:
        raise SineError("transforms.json has no frames")
    return out


def _transforms_distortion(get) -> np.ndarray:
    """nerfstudio's k1 k2 p1 p2 (k3) -> OpenCV order [k1, k2, p1, p2(, k3)]."""
    dist = [float(get(k, 0.0)) for k in ("k1", "k2", "p1", "p2")]
    if float(get("k3", 0.0)) != 0.0:
        dist.append(float(get("k3")))
    return np.array(dist)


def cameras_to_transforms(cameras: list[Camera], file_paths: list[str]) -> dict:
    """Cameras -> nerfstudio transforms.json dict (per-frame intrinsics, OpenGL axes)."""
    frames = []
    for cam, path in zip(cameras, file_paths, strict=True):
        d = cam.distortion.tolist() + [0.0] * 4
        frames.append(
            {
                "file_path": path,
                "w": cam.width,
                "h": cam.height,
                "fl_x": cam.fx,
                "fl_y": cam.fy,
                "cx": cam.cx,
                "cy": cam.cy,
                "k1": d[0],
                "k2": d[1],
                "p1": d[2],
                "p2": d[3],
                **({"k3": d[4]} if d[4] != 0.0 else {}),
                "transform_matrix": (cam.camera_to_world @ OPENCV_TO_OPENGL).tolist(),
            }
        )
    return {"camera_model": "OPENCV", "frames": frames}


# ---- COLMAP -------------------------------------------------------------------------------
def colmap_pose_to_c2w(qvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """COLMAP image pose (world-to-camera quaternion w-x-y-z + translation) -> camera-to-world."""
    return pose_from_rt(quaternion_to_rotation(qvec), tvec)


def c2w_to_colmap_pose(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-to-world -> COLMAP (qvec w-x-y-z, tvec) of world-to-camera."""
    w2c = invert_pose(c2w)
    return rotation_to_quaternion(w2c[:3, :3]), w2c[:3, 3]


def camera_from_colmap_intrinsics(model: str, params, width: int, height: int) -> Camera:
    """Intrinsics of a COLMAP camera model -> Camera (identity pose)."""
    p = [float(x) for x in params]
    dist = np.zeros(4)
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        f, cx, cy = p[:3]
        fx = fy = f
        if model != "SIMPLE_PINHOLE":
            dist[0] = p[3]
        if model == "RADIAL":
            dist[1] = p[4]
    elif model in ("PINHOLE", "OPENCV", "FULL_OPENCV"):
        fx, fy, cx, cy = p[:4]
        if model == "OPENCV":
            dist[:] = p[4:8]
        elif model == "FULL_OPENCV":  # k1 k2 p1 p2 k3 k4 k5 k6: OpenCV's 8-coefficient order
            dist = np.array(p[4:12])
    else:
        raise SineError(f"COLMAP camera model {model} is not supported (use PINHOLE/OPENCV/RADIAL)")
    return Camera(width, height, fx, fy, cx, cy, distortion=dist)


def read_colmap_model(model_dir: str | Path) -> list[tuple[str, Camera]]:
    """Reads a COLMAP sparse model (binary or text) with pycolmap -> [(image name, Camera)]."""
    import pycolmap

    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError
        raise SineError(f"cannot read a COLMAP model in {model_dir}: {exc}") from None
    out = []
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            continue
        cam = rec.cameras[image.camera_id]
        base = camera_from_colmap_intrinsics(cam.model.name, cam.params, cam.width, cam.height)
        w2c = np.eye(4)
        w2c[:3] = image.cam_from_world().matrix()
        out.append((image.name, base.replace(camera_to_world=invert_pose(w2c), name=image.name)))
    return out


def write_colmap_text(model_dir: str | Path, cameras: list[Camera]) -> None:
    """Writes cameras as a COLMAP text model (cameras.txt, images.txt, empty points3D.txt)."""
    model_dir = Path(model_dir)
    model_dir.mkdir(parents=True, exist_ok=True)
    cam_lines, img_lines = [], []
    for i, cam in enumerate(cameras, start=1):
        k = [float(x) for x in cam.distortion] + [0.0] * 8
        full = any(k[4:8])  # k3..k6 need COLMAP's FULL_OPENCV (OPENCV keeps k1 k2 p1 p2 only)
        params = k[:8] if full else k[:4]
        cam_lines.append(
            f"{i} {'FULL_OPENCV' if full else 'OPENCV'} {cam.width} {cam.height} "
            + " ".join(repr(float(v)) for v in (cam.fx, cam.fy, cam.cx, cam.cy, *params))
        )
        q, t = c2w_to_colmap_pose(cam.camera_to_world)
        img_lines.append(" ".join([str(i), *(repr(float(x)) for x in (*q, *t)), str(i), cam.name]))
        img_lines.append("")  # no 2D points
    (model_dir / "cameras.txt").write_text("\n".join(cam_lines) + "\n")
    (model_dir / "images.txt").write_text("\n".join(img_lines) + "\n")
    (model_dir / "points3D.txt").write_text("")


# ---- Middlebury *_par.txt -----------------------------------------------------------------
def read_middlebury_par(path: str | Path) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """Parses a Middlebury `*_par.txt` -> [(image name, K [3,3], R [3,3], t [3])]."""
    lines = Path(path).read_text().split("\n")
    out = []
    for line in lines[1:]:
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 22:
            raise SineError(f"{path}: expected 'name k11..k33 r11..r33 t1 t2 t3' per line")
        vals = np.array([float(x) for x in parts[1:]])
        out.append((parts[0], vals[:9].reshape(3, 3), vals[9:18].reshape(3, 3), vals[18:21]))
    return out


def camera_from_krt(K, R, t, width: int, height: int, name: str = "") -> Camera:
    """x = K[R|t]X (world-to-camera R, t) -> Camera."""
    K = np.asarray(K, dtype=np.float64)
    return Camera(
        width,
        height,
        K[0, 0],
        K[1, 1],
        K[0, 2],
        K[1, 2],
        camera_to_world=pose_from_rt(R, t),
        name=name,
    )


def write_middlebury_par(path: str | Path, cameras: list[Camera]) -> None:
    lines = [str(len(cameras))]
    for cam in cameras:
        w2c = cam.world_to_camera
        vals = [*cam.K.ravel(), *w2c[:3, :3].ravel(), *w2c[:3, 3]]
        lines.append(cam.name + " " + " ".join(repr(float(v)) for v in vals))
    Path(path).write_text("\n".join(lines) + "\n")


# ---- NeuS / IDR cameras_sphere.npz --------------------------------------------------------
def cameras_from_neus(data, sizes: list[tuple[int, int]]) -> tuple[list[Camera], np.ndarray]:
    """NeuS/IDR npz (world_mat_i, scale_mat_i) -> cameras in the world frame + scale_mat [4,4].

    world_mat = K[R|t] (4x4), scale_mat maps the unit-sphere frame to world
    (X_world = scale_mat @ X_sphere); it is returned so callers can normalise with it.
    """
    n = len(sizes)
    cams = []
    for i in range(n):
        key = f"world_mat_{i}"
        if key not in data:
            raise SineError(f"cameras_sphere.npz has no {key} for image {i}")
        P = np.asarray(data[key], dtype=np.float64)[:3, :4]
        cams.append(camera_from_projection(P, *sizes[i]))
    scale_mat = np.asarray(data.get("scale_mat_0", np.eye(4)), dtype=np.float64)
    return cams, scale_mat


def cameras_to_neus(cameras: list[Camera], scale_mat: np.ndarray | None = None) -> dict:
    out = {}
    for i, cam in enumerate(cameras):
        wm = np.eye(4)
        wm[:3] = cam.projection
        out[f"world_mat_{i}"] = wm
        out[f"scale_mat_{i}"] = np.eye(4) if scale_mat is None else scale_mat
    return out


# ---- cameras.json -------------------------------------------------------------------------
@dataclass
class CameraSet:
    """The content of a run's cameras.json."""

    frames: list[Camera]
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    scale: float = 1.0  # x_run = scale * rotation @ (x_in - center)
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    extra: dict = field(default_factory=dict)
    # [3, 3]; stored as normalization["rotation"] (row-major nested lists) when not identity.
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))

    def to_dict(self) -> dict:
        return {
            "convention": "opencv",
            "up": [float(x) for x in self.up],
            "normalization": self._normalization_dict(),
            **self.extra,
            "frames": [c.to_dict() for c in self.frames],
        }

    def _normalization_dict(self) -> dict:
        norm = {"scale": float(self.scale), "center": [float(x) for x in self.center]}
        rotation = np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)
        if not np.allclose(rotation, np.eye(3)):
            norm["rotation"] = [[float(x) for x in row] for row in rotation]
        return norm

    @classmethod
    def from_dict(cls, d: dict) -> CameraSet:
        if d.get("convention", "opencv") != "opencv":
            raise SineError("cameras.json: only the 'opencv' convention is supported")
        norm = d.get("normalization", {})
        extra = {
            k: v for k, v in d.items() if k not in ("convention", "up", "normalization", "frames")
        }
        return cls(
            frames=[Camera.from_dict(f) for f in d["frames"]],
            up=np.array(d.get("up", [0, 0, 1]), dtype=np.float64),
            scale=float(norm.get("scale", 1.0)),
            center=np.array(norm.get("center", [0, 0, 0]), dtype=np.float64),
            extra=extra,
            rotation=np.array(norm.get("rotation", np.eye(3)), dtype=np.float64).reshape(3, 3),
        )

    def by_name(self) -> dict[str, Camera]:
        return {c.name: c for c in self.frames}

    def split(self, name: str) -> list[Camera]:
        return [c for c in self.frames if c.split == name]


def load_cameras(path: str | Path) -> CameraSet:
    from render.io import read_json

    return CameraSet.from_dict(read_json(path))


def save_cameras(path: str | Path, cameras: CameraSet) -> None:
    from render.io import write_json

    write_json(path, cameras.to_dict())
