"""Output writers of `sine synth` (recon.synth): the views in the sine layout (images/, masks/,
depth/, labels/, transforms.json, cameras.json, mesh.ply, parts.json) and in the Blender /
NeRF-synthetic layout.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from recon.mesh_data import MeshData
from render.cameras import Camera, CameraSet, cameras_to_transforms, save_cameras
from render.errors import SineError
from render.io import (
    write_bytes_atomic,
    write_depth,
    write_image,
    write_json,
    write_label_map,
    write_mask,
)

OUTPUT_FORMATS = ("sine", "nerf-synthetic")
NERF_SYNTHETIC_DIR = "nerf_synthetic"  # where --format nerf-synthetic writes its layout


def write_views(out_dir: Path, cameras: list[Camera], views: list[dict], mesh: MeshData) -> dict:
    """Writes images/, masks/, depth/, labels/, transforms.json, cameras.json, mesh.ply, parts.json."""
    import trimesh  # noqa: F401  (PLY export)

    out_dir = Path(out_dir)
    for sub in ("images", "masks", "depth", "labels"):
        (out_dir / sub).mkdir(parents=True, exist_ok=True)
        for stale in (out_dir / sub).glob("r_*.*"):  # a previous run with more views
            stale.unlink()
    paths = []
    for cam, view in zip(cameras, views, strict=True):
        stem = Path(cam.name).stem
        write_image(out_dir / "images" / f"{stem}.png", view["rgb"])
        write_mask(out_dir / "masks" / f"{stem}.png", view["mask"])
        write_depth(out_dir / "depth" / f"{stem}.npy", view["depth"])
        write_label_map(out_dir / "labels" / f"{stem}.png", view["labels"])
        paths.append(f"images/{stem}.png")
    transforms = cameras_to_transforms(cameras, paths)
    for frame, cam in zip(transforms["frames"], cameras, strict=True):
        stem = Path(cam.name).stem
        frame["mask_path"] = f"masks/{stem}.png"
        frame["depth_file_path"] = f"depth/{stem}.npy"
        frame["label_path"] = f"labels/{stem}.png"
        frame["split"] = cam.split
    transforms["ply_file_path"] = "mesh.ply"
    transforms["depth_unit_scale_factor"] = 1.0
    write_json(out_dir / "transforms.json", transforms)
    save_cameras(
        out_dir / "cameras.json",
        CameraSet(frames=cameras, extra={"source": "sine synth", "depth": "camera z, run units"}),
    )
    write_json(out_dir / "parts.json", {str(k): v for k, v in sorted(mesh.part_names.items())})
    tm = mesh.to_trimesh()
    from render.io import atomic_path

    with atomic_path(out_dir / "mesh.ply") as tmp:
        tm.export(str(tmp), file_type="ply")
    with atomic_path(out_dir / "mesh_vertex_parts.npy") as tmp, open(tmp, "wb") as f:
        np.save(f, mesh.welded_vertex_labels().astype(np.uint16))
    coverage = float(np.mean([v["mask"].mean() for v in views]))
    return {"views": len(views), "mean_mask_coverage": coverage, "mesh_vertices": len(tm.vertices)}


def write_nerf_synthetic(out_dir: Path, cameras: list[Camera], views: list[dict]) -> dict:
    """Writes the views in the Blender / NeRF-synthetic layout into `out_dir`.

    - `train/<stem>.png`, `test/<stem>.png`: 8-bit RGBA, alpha = the object mask (255 / 0), RGB
      the object's colour (straight, not premultiplied), 0 on background pixels;
    - `transforms_train.json`, `transforms_test.json`: `camera_angle_x` (horizontal field of view
      in radians; square pixels, principal point at the image centre, as the Blender data) and per
      frame `file_path` without extension (`./train/r_000`) and `transform_matrix` (camera-to-
      world, OpenGL axes);
    - `transforms_val.json`: the test views again (the same files): the held-out views are
      `sine ingest`'s split rule (every 8th view), and ingest does not count them twice.
    Returns {"train": n, "test": n, "val": n}.
    """
    out_dir = Path(out_dir)
    fx = cameras[0].fx
    for cam in cameras:
        centred = abs(cam.cx - cam.width / 2) < 1e-9 and abs(cam.cy - cam.height / 2) < 1e-9
        if abs(cam.fy - cam.fx) > 1e-9 * cam.fx or abs(cam.fx - fx) > 1e-9 * fx or not centred:
            raise SineError("the NeRF-synthetic format needs one centred square-pixel camera")
    angle = float(2.0 * np.arctan(0.5 * cameras[0].width / fx))
    gl = cameras_to_transforms(cameras, [cam.name for cam in cameras])["frames"]
    frames: dict[str, list[dict]] = {"train": [], "test": []}
    for split in frames:
        (out_dir / split).mkdir(parents=True, exist_ok=True)
        for stale in (out_dir / split).glob("r_*.png"):  # a previous run with more views
            stale.unlink()
    for cam, view, frame in zip(cameras, views, gl, strict=True):
        split = "test" if cam.split == "test" else "train"
        stem = Path(cam.name).stem
        rgba = np.zeros((cam.height, cam.width, 4), np.uint8)
        rgb = (np.clip(view["rgb"], 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)  # as write_image
        rgba[..., :3] = np.where(view["mask"][..., None], rgb, 0)
        rgba[..., 3] = np.where(view["mask"], 255, 0)
        ok, buf = cv2.imencode(".png", rgba[..., [2, 1, 0, 3]])  # RGBA -> BGRA
        if not ok:
            raise SineError(f"cannot encode {out_dir / split / stem}.png")
        write_bytes_atomic(out_dir / split / f"{stem}.png", buf.tobytes())
        frames[split].append(
            {"file_path": f"./{split}/{stem}", "transform_matrix": frame["transform_matrix"]}
        )
    frames["val"] = frames["test"]
    for split, split_frames in frames.items():
        write_json(
            out_dir / f"transforms_{split}.json",
            {"camera_angle_x": angle, "frames": split_frames},
        )
    return {split: len(split_frames) for split, split_frames in frames.items()}
