"""Rendered views against ground truth: PSNR / SSIM (scikit-image) over the whole image, on the
object's pixels, and inside / outside an edit region.

Ground truth is a folder with cameras.json, images/ and (optionally) masks/ (a run directory or
a `sine synth` output such as `synth_out/edits/geometric`). Its views are matched to the run's
cameras by file stem (the run's camera is then used, resized to the ground-truth image); views
with no match are taken in the capture's frame and moved into the run frame with the run's
normalisation (cameras.json "normalization").

Pixel sets: "object" = ground-truth mask OR rendered opacity > 0.5 (everything either image
shows of the object); "region" = the edit-region mask; "outside_region" = object pixels not in
the region. SSIM over a pixel set is the mean of the full-image SSIM map over those pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from render.cameras import Camera, CameraSet, load_cameras
from render.errors import SineError
from render.io import read_image, read_mask
from render.metrics import psnr


@dataclass
class GTView:
    camera: Camera  # in the run frame, at the ground-truth image's size
    image: np.ndarray  # [H, W, 3]
    mask: np.ndarray | None  # [H, W] bool
    region: np.ndarray | None = None  # [H, W] bool


def to_run_frame(cam: Camera, run: CameraSet) -> Camera:
    """A camera in the capture's frame -> the run frame (x_run = s R (x_in - c))."""
    R = np.asarray(run.rotation, np.float64)
    c2w = np.eye(4)
    c2w[:3, :3] = R @ cam.camera_to_world[:3, :3]
    c2w[:3, 3] = run.scale * R @ (cam.center - np.asarray(run.center, np.float64))
    return cam.replace(camera_to_world=c2w)


def _find(folder: Path, stem: str) -> Path | None:
    for sub in (folder, folder / "masks"):
        p = sub / f"{stem}.png"
        if p.is_file():
            return p
    return None


def load_gt_views(
    gt_dir: str | Path,
    run_cameras: CameraSet,
    split: str = "all",
    region_dir: str | Path | None = None,
) -> list[GTView]:
    """Ground-truth views of `gt_dir` (split "all", "train" or "test") with run-frame cameras."""
    gt_dir = Path(gt_dir)
    if not (gt_dir / "cameras.json").is_file():
        raise SineError(f"{gt_dir} has no cameras.json (expected a run or `sine synth` folder)")
    gt = load_cameras(gt_dir / "cameras.json")
    run_by_stem = {Path(c.name).stem: c for c in run_cameras.frames}
    identity = np.isclose(gt.scale, 1.0) and np.allclose(gt.center, 0.0)
    views = []
    for cam in gt.frames:
        if split != "all" and cam.split != split:
            continue
        stem = Path(cam.name).stem
        path = gt_dir / "images" / f"{stem}.png"
        if not path.is_file():
            raise SineError(f"{path} is missing (named in {gt_dir / 'cameras.json'})")
        image = read_image(path)
        h, w = image.shape[:2]
        if stem in run_by_stem:
            run_cam = run_by_stem[stem].resized(w, h)
        elif identity:
            run_cam = to_run_frame(cam.resized(w, h), run_cameras)
        else:
            raise SineError(
                f"ground-truth view {cam.name} is not in the run and {gt_dir} has its own "
                "normalisation: use ground truth in the capture's frame or with the run's names"
            )
        mpath = gt_dir / "masks" / f"{stem}.png"
        mask = read_mask(mpath) if mpath.is_file() else None
        region = None
        if region_dir is not None:
            rpath = _find(Path(region_dir), stem)
            if rpath is None:
                raise SineError(f"no region mask {stem}.png in {region_dir} (or its masks/)")
            region = read_mask(rpath)
            if region.shape != (h, w):
                import cv2

                region = cv2.resize(region.astype(np.uint8), (w, h), cv2.INTER_NEAREST) > 0
        views.append(GTView(run_cam.replace(name=cam.name), image, mask, region))
    if not views:
        raise SineError(f"{gt_dir} has no {split} views")
    return views


def image_metrics(
    pred: np.ndarray, gt: np.ndarray, sets: dict[str, np.ndarray | None]
) -> dict[str, float]:
    """{"psnr", "ssim", "psnr_<set>", "ssim_<set>"} for each non-empty pixel set [H, W] bool."""
    from skimage.metrics import structural_similarity

    ssim, ssim_map = structural_similarity(gt, pred, channel_axis=2, data_range=1.0, full=True)
    ssim_map = ssim_map.mean(axis=2)  # [H, W]
    out = {"psnr": psnr(pred, gt), "ssim": float(ssim)}
    for name, sel in sets.items():
        if sel is not None and sel.any():
            out[f"psnr_{name}"] = psnr(pred[sel], gt[sel])
            out[f"ssim_{name}"] = float(ssim_map[sel].mean())
    return out


def evaluate_views(scene, views: list[GTView], chunk: int = 16384, progress: bool = True) -> dict:
    """Renders every view with `scene` and scores it -> {"views": [per view], "mean": {...}}."""
    from tqdm import tqdm

    per_view = []
    for view in tqdm(views, desc="eval", unit="view", disable=not progress):
        out = scene.render_view(view.camera, chunk)
        pred = np.clip(out["rgb"], 0.0, 1.0).astype(np.float32)
        obj = out["opacity"] > 0.5
        if view.mask is not None:
            obj = obj | view.mask
        sets = {"object": obj}
        if view.region is not None:
            sets["region"] = view.region
            sets["outside_region"] = obj & ~view.region
        per_view.append({"name": view.camera.name, **image_metrics(pred, view.image, sets)})
    keys = sorted({k for v in per_view for k in v if k != "name"})
    mean = {k: float(np.mean([v[k] for v in per_view if k in v])) for k in keys}
    return {"views": per_view, "mean": {**mean, "n_views": len(per_view)}}


def format_table(result: dict) -> str:
    """The per-view metrics and their mean as a plain-text table."""
    keys = [k for k in result["mean"] if k != "n_views"]
    order = ["psnr", "ssim"] + [k for k in keys if k not in ("psnr", "ssim")]
    keys = [k for k in order if k in keys]
    rows = [["view", *keys]]
    for v in result["views"]:
        rows.append([v["name"], *(f"{v[k]:.3f}" if k in v else "-" for k in keys)])
    rows.append(["mean", *(f"{result['mean'][k]:.3f}" for k in keys)])
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in rows)
