"""Writing one view of a capture into the run directory (`sine ingest`): the working image
(EXIF orientation applied, RGBA composited over the background, undistorted, resized), its mask
and depth map, its camera at the working size and its captures.json record; and the size of
each view as ingested."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from recon.capture_formats import SourceView, _probe_files
from recon.rundir import RunDir
from render.cameras import Camera
from render.errors import SineError
from render.io import read_image_rgba, write_depth, write_image, write_mask

if TYPE_CHECKING:
    from recon.ingest import IngestConfig


def _ingest_view(
    view: SourceView,
    size: tuple[int, int],
    cfg: IngestConfig,
    run: RunDir,
    split: str,
    background: np.ndarray,
) -> tuple[dict, Camera | None]:
    if view.frame is not None:
        rgb = view.frame[..., ::-1].astype(np.float32) / 255.0  # [H, W, 3]
        alpha, digest = None, hashlib.sha256(view.frame.tobytes()).hexdigest()
    elif view.camera is None and exif_orientation(view.path) != 1:
        rgb, alpha = _read_oriented(view.path)  # phone photos: upright as they are viewed
        digest = _sha256(view.path)
    else:
        rgb, alpha = read_image_rgba(view.path)
        digest = _sha256(view.path)
    h, w = rgb.shape[:2]
    cam = _fit_camera(view.camera, w, h, view.source) if view.camera is not None else None
    mask = _load_mask(view.mask, w, h) if view.mask is not None else None
    use_alpha = alpha is not None and bool((alpha < 1.0).any())
    if use_alpha:  # an RGBA capture (e.g. NeRF synthetic): alpha is the foreground
        if mask is None:
            mask = alpha >= 0.5
        a = alpha[..., None]
        rgb = (rgb * a + background.astype(np.float32) * (1.0 - a)).astype(np.float32)
    depth = _load_depth(view, w, h) if view.depth is not None else None

    undistorted = cam is not None and bool(np.any(cam.distortion != 0))
    if undistorted:
        K_cv = cam.K.copy()  # OpenCV puts pixel centres at integers, we at +0.5
        K_cv[:2, 2] -= 0.5
        dist = cam.distortion
        maps = cv2.initUndistortRectifyMap(K_cv, dist, None, K_cv, (w, h), cv2.CV_32FC1)
        # Lanczos, not bilinear: sub-pixel shifts must not soften the photo (recon.poses)
        rgb = cv2.remap(rgb, *maps, cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REPLICATE)
        rgb = np.clip(rgb, 0.0, 1.0)
        if mask is not None:
            mask = cv2.remap(mask.astype(np.uint8), *maps, cv2.INTER_NEAREST) > 0
        if depth is not None:
            depth = cv2.remap(depth, *maps, cv2.INTER_NEAREST)
        cam = cam.replace(distortion=np.zeros(4))

    W = min(cfg.width, w)
    H = max(1, round(h * W / w))
    if (W, H) != (w, h):
        rgb = cv2.resize(rgb, (W, H), interpolation=cv2.INTER_AREA)
        if mask is not None:
            mask = _resize_nearest(mask.astype(np.uint8), W, H) > 0
        if depth is not None:
            depth = _resize_nearest(depth, W, H)
    name = f"{view.stem}.png"
    write_image(run.image_path(name), rgb)
    if mask is not None:
        write_mask(run.mask_path(name), mask)
    if depth is not None:
        write_depth(run.depth_path(name), depth)
    if cam is not None:
        cam = cam.resized(W, H).replace(name=name, split=split)
    record = {
        "name": name,
        "source": view.source,
        "source_width": w,
        "source_height": h,
        "width": W,
        "height": H,
        "sha256": digest,
        "status": "ok",
        "split": split,
        "mask": mask is not None,
        "alpha": use_alpha,
        "depth": depth is not None,
        "undistorted": undistorted,
    }
    return record, cam


def _fit_camera(cam: Camera, w: int, h: int, source: str) -> Camera:
    """The camera for an image of (w, h): equal, or the same aspect ratio scaled."""
    if (cam.width, cam.height) == (w, h):
        return cam
    if abs(cam.width / cam.height - w / h) < 0.01 * (w / h):
        return cam.resized(w, h)
    raise SineError(
        f"{source} is {w}x{h} but its camera says {cam.width}x{cam.height} (different aspect "
        "ratio): the intrinsics do not belong to this image"
    )


def _load_mask(path: Path, w: int, h: int) -> np.ndarray:
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise SineError(f"cannot read mask {path} (corrupt or not an image)")
    if raw.ndim == 3:
        raw = raw[..., 3] if raw.shape[2] == 4 else raw.max(axis=2)
    mask = raw > (32767 if raw.dtype == np.uint16 else 127)
    return _fit_plane(mask.astype(np.uint8), w, h, path) > 0


def _load_depth(view: SourceView, w: int, h: int) -> np.ndarray:
    path = view.depth
    if path.suffix.lower() == ".npy":
        depth = np.load(path).astype(np.float32)
    else:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise SineError(f"cannot read depth map {path} (use .npy float32 or a 16-bit PNG)")
        if raw.ndim == 3:
            raw = raw[..., 0]
        scale = view.depth_scale if np.issubdtype(raw.dtype, np.integer) else 1.0
        depth = raw.astype(np.float32) * np.float32(scale)
    if depth.ndim != 2:
        raise SineError(f"depth map {path} has shape {depth.shape}; expected [H, W]")
    return _fit_plane(depth, w, h, path)


def _fit_plane(array: np.ndarray, w: int, h: int, path: Path) -> np.ndarray:
    """A mask/depth [h', w'] brought to the image size (nearest) if the aspect ratio matches."""
    hh, ww = array.shape[:2]
    if (ww, hh) == (w, h):
        return array
    if abs(ww / hh - w / h) > 0.01 * (w / h):
        raise SineError(f"{path} is {ww}x{hh} but its image is {w}x{h}")
    return _resize_nearest(array, w, h)


def _resize_nearest(array: np.ndarray, w: int, h: int) -> np.ndarray:
    # INTER_NEAREST_EXACT samples pixel centres like INTER_AREA does (plain NEAREST is shifted).
    return cv2.resize(array, (w, h), interpolation=cv2.INTER_NEAREST_EXACT)


def _probe_sizes(views: list[SourceView]) -> list[tuple[int, int]]:
    """(width, height) of each view as ingested (EXIF orientation applied without a camera)."""
    sizes = _probe_files([v.path for v in views if v.path is not None])
    out = []
    for v in views:
        if v.path is None:
            out.append((v.frame.shape[1], v.frame.shape[0]))
        elif v.camera is None and exif_orientation(v.path) in (5, 6, 7, 8):  # turned 90 deg
            out.append(sizes[v.path][::-1])
        else:
            out.append(sizes[v.path])
    return out


def exif_orientation(path: Path) -> int:
    """The EXIF orientation tag of an image (1 = as stored; phone photos: often 6 or 8)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return int(im.getexif().get(0x0112, 1))
    except Exception:  # noqa: BLE001 - no EXIF, or not readable by PIL: as stored
        return 1


def _read_oriented(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """RGB [H, W, 3] float32 and alpha (or None) with the EXIF orientation applied."""
    from PIL import Image, ImageOps

    with Image.open(path) as im:
        im = ImageOps.exif_transpose(im)
        has_alpha = im.mode in ("RGBA", "LA") or "transparency" in im.info
        arr = np.asarray(im.convert("RGBA" if has_alpha else "RGB"), dtype=np.float32) / 255.0
    if has_alpha:
        return np.ascontiguousarray(arr[..., :3]), arr[..., 3]
    return arr, None


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
