"""Rendering camera paths to files: PNG frames, colour-mapped depth / opacity, a side-by-side
before|after strip, the MP4 and the `camera_path.json` used.

Works with any scene object that has `render_view(camera, chunk) -> {"rgb", "opacity", "z", ...}`
(edit/scene.py's `Scene`). Layout of the output folder:

    DIR/rgb/NAME.png        the frames (colour over the run's background)
    DIR/depth/NAME.png      camera depth, turbo colour map over [|c| - 1, |c| + 1] (the object
                            lies in the unit sphere; c the camera centre), black where empty
    DIR/opacity/NAME.png    accumulated opacity, grey levels
    DIR/features/NAME.png   the DINO feature field's first three PCA components as RGB (one
                            colour range for every frame: the first frame's 1-99 percentiles)
    DIR/compare/NAME.png    reference | scene, side by side (with a reference scene)
    DIR/camera_path.json    the cameras, nerfstudio format (render/camera_paths.py)
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from render.camera_paths import write_camera_path
from render.cameras import Camera
from render.feature_field import pca_rgb
from render.io import remove_partial_writes, write_image
from render.locks import lock_folder
from render.video import VideoWriter


def depth_colormap(z: np.ndarray, opacity: np.ndarray, near: float, far: float) -> np.ndarray:
    """Camera depth [H, W] -> RGB [H, W, 3] in [0, 1]: turbo colour map, `near` red to `far`
    blue, black where the opacity is below 0.5."""
    t = np.clip((far - z) / max(far - near, 1e-6), 0.0, 1.0)  # 1 = near
    rgb = cv2.applyColorMap((t * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    rgb = rgb.astype(np.float32) / 255.0
    rgb[opacity < 0.5] = 0.0
    return rgb


def label(image: np.ndarray, text: str) -> np.ndarray:
    """`text` written in the top-left corner of an image [H, W, 3] (skipped below 96 px)."""
    if image.shape[1] < 96:
        return image
    # OpenCV 5 draws text on 8-bit images only
    out = np.ascontiguousarray((np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8))
    scale = max(0.35, image.shape[0] / 600.0)
    pos = (4, int(22 * scale) + 4)  # baseline below a text line of height ~22 * scale
    cv2.putText(out, text, pos, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(out, text, pos, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return out.astype(np.float32) / 255.0


def side_by_side(left: np.ndarray, right: np.ndarray, names=("template", "edit")) -> np.ndarray:
    """Two images [H, W, 3] next to each other with a 2-pixel white gap: [H, 2W + 2, 3]."""
    return strip([left, right], names)


def strip(images: list[np.ndarray], names: list[str]) -> np.ndarray:
    """Images [H, W, 3] left to right, each labelled, with 2-pixel white gaps between."""
    gap = np.ones((images[0].shape[0], 2, 3), np.float32)
    parts = []
    for image, name in zip(images, names, strict=True):
        parts += [gap, label(image, name)] if parts else [label(image, name)]
    return np.concatenate(parts, axis=1)


def render_frames(
    scene,
    cameras: list[Camera],
    out_dir: str | Path,
    video: str | Path | None = None,
    fps: float = 24.0,
    depth: bool = False,
    opacity: bool = False,
    reference=None,
    chunk: int = 16384,
    progress: bool = True,
    feature_map=None,
) -> dict:
    """Renders every camera with `scene` (and `reference`, for the comparison strip) into
    `out_dir`; the video shows the strip when there is a reference, else the frames.
    `feature_map(camera) -> (PCA coefficients [H, W, D >= 3], object mask [H, W])` adds the
    feature images."""
    out_dir = Path(out_dir)
    with lock_folder(out_dir, f"the render folder {out_dir}"):
        remove_partial_writes(out_dir)  # frames an interrupted render was writing
        write_camera_path(out_dir / "camera_path.json", cameras, fps)
        names = [Path(c.name).stem if c.name else f"{i:04d}" for i, c in enumerate(cameras)]
        if len(set(names)) != len(names):
            names = [f"{i:04d}" for i in range(len(cameras))]
        coverage, feature_range = [], None
        with contextlib.ExitStack() as stack:
            writer = stack.enter_context(VideoWriter(video, fps)) if video is not None else None
            pairs = list(zip(cameras, names, strict=True))
            for cam, name in tqdm(pairs, desc="render", unit="frame", disable=not progress):
                out = scene.render_view(cam, chunk)
                rgb = np.clip(out["rgb"], 0.0, 1.0)
                coverage.append(float((out["opacity"] > 0.5).mean()))
                write_image(out_dir / "rgb" / f"{name}.png", rgb)
                if depth:
                    dist = float(np.linalg.norm(cam.center))
                    image = depth_colormap(out["z"], out["opacity"], max(dist - 1, 0), dist + 1)
                    write_image(out_dir / "depth" / f"{name}.png", image)
                if opacity:
                    image = np.repeat(np.clip(out["opacity"], 0, 1)[..., None], 3, axis=2)
                    write_image(out_dir / "opacity" / f"{name}.png", image)
                if feature_map is not None:
                    coeffs, on_object = feature_map(cam)
                    if feature_range is None:  # one colour mapping for the whole path
                        sel = coeffs[..., :3][on_object] if on_object.any() else coeffs[..., :3]
                        sel = sel.reshape(-1, 3)
                        feature_range = np.percentile(sel, 1, 0), np.percentile(sel, 99, 0)
                    image = pca_rgb(coeffs, on_object, *feature_range, background=0.0)
                    write_image(out_dir / "features" / f"{name}.png", image)
                frame = rgb
                if reference is not None:
                    ref = np.clip(reference.render_view(cam, chunk)["rgb"], 0.0, 1.0)
                    frame = side_by_side(ref, rgb, (reference.name, scene.name))
                    write_image(out_dir / "compare" / f"{name}.png", frame)
                if writer is not None:
                    writer.write(frame)
        return {
            "frames": len(cameras),
            "width": cameras[0].width,
            "height": cameras[0].height,
            "out": str(out_dir),
            "video": None if video is None else str(video),
            "mean_object_coverage": float(np.mean(coverage)),
        }
