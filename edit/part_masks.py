"""The `sine masks` stage: semantic masks of a painted part in every view of a run.

The feature field (from `sine features`) is rendered at the editing view (edit/feature_maps.py);
the features inside the user's painted region are K-means clustered (edit/semantic_masks.py, the
paper's K = 15, 1000 samples), and so are those of the rest of the object; then every view's
rendered feature map gives its editable pixels (nearer to the painted part than to the rest; or
the paper's threshold 0.5 with --rule threshold), restricted to the object (template opacity),
edges guided by the view's image. Writes DIR/masks/<view>.png (0/255),
DIR/overlay_contact_sheet.png, DIR/semantic_centres.npy ([K, C] painted part),
DIR/semantic_rest_centres.npy ([K, C] rest, contrast rule), with the spatial term the centres'
surface points DIR/semantic_centre_points.npy and DIR/semantic_rest_centre_points.npy ([K, 3],
run units), and DIR/metrics.json.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from render.configs import option, to_dict, validate
from render.errors import SineError

TINT = np.array([0.0, 0.9, 1.0], np.float32)  # editable pixels in the contact sheet (cyan)


@dataclass
class MasksConfig:
    """Rendering and output options of `sine masks` (K-means options: SemanticMaskConfig)."""

    space: str = option(
        "centred",
        "feature space of the K-means distances: the DINO features minus the object's mean "
        "feature (the field's PCA coefficients; DINOv2 tokens of one object share a large common "
        "component, so raw cosines are all high) or the raw decoded DINO features",
        choices=["centred", "dino"],
    )
    min_opacity: float = option(
        0.5, "pixels below this template opacity are never editable", low=0.0, high=1.0
    )
    thumbnail_width: int = option(160, "contact-sheet thumbnail width in pixels", low=8)
    columns: int = option(6, "contact-sheet thumbnails per row", low=1)
    tint: float = option(
        0.55, "contact sheet: opacity of the tint over editable pixels", low=0.0, high=1.0
    )
    render_scale: float = option(
        0.5,
        "feature maps are rendered at this fraction of the image size and upsampled (DINO "
        "features are smooth; the image-guided edges restore the detail; 1: full size)",
        low=0.01,
        high=1.0,
    )
    chunk: int = option(4096, "rays per chunk when rendering feature maps", low=1)
    device: str = option("auto", "torch device: auto, cpu or cuda", choices=["auto", "cpu", "cuda"])
    threads: int = option(0, "torch CPU threads (0: torch's default)", low=0)


def resolve_view(cameras, view: str | int):
    """Index (as int or digits) into the camera list, or an image name / stem -> (index, camera)."""
    text = str(view)
    names = [c.name for c in cameras]
    if text.lstrip("-").isdigit():
        i = int(text)
        if not -len(cameras) <= i < len(cameras):
            raise SineError(f"--view {i} is out of range: the run has {len(cameras)} views")
        return i % len(cameras), cameras[i]
    for i, cam in enumerate(cameras):
        if text in (cam.name, Path(cam.name).stem):
            return i, cam
    shown = ", ".join(names[:6]) + (", ..." if len(names) > 6 else "")
    raise SineError(f"--view {text!r} is neither an index nor an image of the run ({shown})")


def load_region(path, camera) -> np.ndarray:
    """The painted region [H, W] bool, checked against the camera's working-image size."""
    from render.io import read_mask

    path = Path(path)
    if not path.is_file():
        raise SineError(f"region image {path} does not exist")
    region = read_mask(path)
    if region.shape != (camera.height, camera.width):
        raise SineError(
            f"region {path} is {region.shape[1]}x{region.shape[0]} but view {camera.name} is "
            f"{camera.width}x{camera.height}: paint on the run's working image "
            f"(RUN/images/{camera.name})"
        )
    if not region.any():
        raise SineError(f"region {path} is empty: paint the part to edit in white")
    return region


def view_image(run, camera) -> np.ndarray | None:
    """The run's working image of a camera [H, W, 3] in [0, 1] (None when it is missing)."""
    from render.io import read_image

    path = run.image_path(camera.name)
    if not path.is_file():
        return None
    image = read_image(path)
    if image.shape[:2] != (camera.height, camera.width):
        import cv2

        image = cv2.resize(image, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    return image


def overlay(image: np.ndarray, mask: np.ndarray, tint: float, width: int, edit_view: bool):
    """Thumbnail [h, width, 3] of `image` with `mask` tinted cyan (a magenta frame marks the
    editing view)."""
    import cv2

    h = max(1, round(image.shape[0] * width / image.shape[1]))
    tile = cv2.resize(image, (width, h), interpolation=cv2.INTER_AREA)
    small = cv2.resize(mask.astype(np.uint8), (width, h), interpolation=cv2.INTER_NEAREST) > 0
    tile[small] = (1 - tint) * tile[small] + tint * TINT
    if edit_view:
        cv2.rectangle(tile, (0, 0), (width - 1, h - 1), (1.0, 0.1, 0.6), 2)
    return tile


def semantic_masks(
    run_dir,
    view: str | int,
    region,
    out_dir,
    cfg: MasksConfig | None = None,
    mask_cfg=None,
    progress: bool = True,
) -> dict:
    """Masks for every view of `run_dir` from a painted region ([H, W] bool or a PNG path)."""
    from edit.semantic_masks import SemanticMaskConfig
    from render.device import torch_threads
    from render.io import require_directory
    from render.locks import lock_folder

    cfg = validate(cfg or MasksConfig())
    mask_cfg = validate(mask_cfg or SemanticMaskConfig())
    require_directory(out_dir, "--out")
    with lock_folder(out_dir, f"the masks folder {out_dir}"), torch_threads(cfg.threads):
        return _semantic_masks(run_dir, view, region, out_dir, cfg, mask_cfg, progress)


def _semantic_masks(run_dir, view, region, out_dir, cfg: MasksConfig, mask_cfg, progress) -> dict:
    from edit.feature_maps import FeatureMapRenderer
    from edit.semantic_masks import SemanticMasks
    from recon.rundir import RunDir
    from recon.training import progress_bar
    from render.io import contact_sheet, write_image, write_json, write_mask

    t_start = time.perf_counter()
    run = RunDir(run_dir)
    cameras = run.load_cameras().frames
    index, edit_cam = resolve_view(cameras, view)
    if isinstance(region, (str, Path)):
        region = load_region(region, edit_cam)
    else:
        region = np.asarray(region, bool)
        if region.shape != (edit_cam.height, edit_cam.width) or not region.any():
            raise SineError(f"region must be a non-empty {edit_cam.width}x{edit_cam.height} mask")
    render = FeatureMapRenderer(
        run.root, cfg.device, cfg.space, cfg.render_scale, cfg.min_opacity, cfg.chunk
    )

    t0 = time.perf_counter()
    feats, on_object, points = render.maps(edit_cam)
    painted = region & on_object
    if not painted.any():
        raise SineError(
            f"the painted region does not touch the object in view {edit_cam.name}: "
            "paint over the object's pixels"
        )
    masks = SemanticMasks(feats, painted, mask_cfg, object_mask=on_object, points=points)
    seconds_fit = time.perf_counter() - t0

    out_dir = Path(out_dir)
    tiles, per_view, seconds_render = [], {}, 0.0
    for i, cam in enumerate(progress_bar(iterable=cameras, desc="masks", disable=not progress)):
        t0 = time.perf_counter()
        if i != index:
            feats, on_object, points = render.maps(cam)
        image = view_image(run, cam)
        editable = masks.mask(feats, image, on_object, points).cpu().numpy() & on_object
        seconds_render += time.perf_counter() - t0
        stem = Path(cam.name).stem
        write_mask(out_dir / "masks" / f"{stem}.png", editable)
        per_view[stem] = {
            "editable_pixels": int(editable.sum()),
            "object_pixels": int(on_object.sum()),
            "editable_fraction_of_object": float(editable.sum() / max(on_object.sum(), 1)),
        }
        if image is None:
            image = np.ones((cam.height, cam.width, 3), np.float32)
        tiles.append(overlay(image, editable, cfg.tint, cfg.thumbnail_width, i == index))
    write_image(out_dir / "overlay_contact_sheet.png", contact_sheet(tiles, cfg.columns))
    for stem, centres in (("semantic", masks.centres), ("semantic_rest", masks.other_centres)):
        if centres is None:
            continue
        for suffix, array in zip(("centres", "centre_points"), masks.split(centres), strict=True):
            if array is not None:
                np.save(out_dir / f"{stem}_{suffix}.npy", array.cpu().numpy().astype(np.float32))
    metrics = {
        "run": str(run.root),
        "edit_view": edit_cam.name,
        "edit_view_index": index,
        "region_pixels": int(region.sum()),
        "region_pixels_on_object": int(painted.sum()),
        "rule": masks.rule,
        "views": len(cameras),
        "seconds_fit": seconds_fit,
        "seconds_render_and_mask": seconds_render,
        "seconds_per_view": seconds_render / max(len(cameras), 1),
        "seconds_total": time.perf_counter() - t_start,
        "config": {**to_dict(mask_cfg), **to_dict(cfg)},
        "per_view": per_view,
    }
    write_json(out_dir / "metrics.json", metrics)
    return metrics
