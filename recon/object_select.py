"""Which object: the one a user boxes in one view, carried to every view through the cameras.

For captures where the object stands in a room (a walkaround of an object on a desk): keying and
saliency cannot tell the object from the rest, but the cameras can. View K is cut by GrabCut
inside the box, which gives the object's colours (a Gaussian mixture in Lab). The object lies in
the box's cone, near the point every camera looks at (`visual_hull.object_region`): the cone is
cut to a ball around the point of the box's central ray nearest to it, `margin` times as large
as the box is at that depth. Then a few rounds of: in every view, GrabCut inside the region's
silhouette, seeded by colour (sure object where the object's colours are far likelier than the
view's background colours outside the silhouette, sure background where far less likely, sure
background outside); the masks carve the region again (`tolerance` of the views may disagree
with a voxel; the box's cone bounds it always), and the object's colours are learnt again from
every view's cut inside the region; until the region stops shrinking.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from recon.masks import _disc, _grabcut, _lab, _largest_components
from render.cameras import Camera
from render.errors import SineError

_MODEL_PIXELS = 8000  # pixels a colour model is fitted to (a random subset)
_COMPONENTS = 5  # Gaussians per colour model
_MIN_HULL_IOU = 0.8  # a mask further from the object's visual hull than this is reported


@dataclass
class SelectParams:
    """How the boxed object is carried to the other views."""

    rounds: int = 4  # GrabCut-and-carve rounds at most
    resolution: int = 96  # voxels along the region's longest side
    tolerance: float = 0.1  # fraction of the views that may disagree with a voxel
    margin: float = 1.5  # the first region's radius, in box half-sizes at the object's depth
    grabcut_iterations: int = 4
    colour_ratio: float = 3.0  # log-likelihood ratio (object : background colours) of sure labels
    stop_change: float = 0.01  # stop when the region loses less than this fraction of voxels
    work_width: int = 200  # the rounds run on images at most this wide


def check_box(box, width: int, height: int, view: str) -> tuple[int, int, int, int]:
    """The box (x0, y0, x1, y1) as integer pixels inside the view; a SineError otherwise."""
    x0, y0, x1, y1 = (float(v) for v in box)
    if not (x1 > x0 and y1 > y0):
        raise SineError(
            f"--object-box {x0:g} {y0:g} {x1:g} {y1:g}: write X0 Y0 X1 Y1 with X1 > X0 and Y1 > Y0"
        )
    if x1 <= 0 or y1 <= 0 or x0 >= width or y0 >= height:
        raise SineError(
            f"--object-box {x0:g} {y0:g} {x1:g} {y1:g} lies outside view {view} "
            f"({width}x{height} pixels)"
        )
    x0, y0 = max(0, int(np.floor(x0))), max(0, int(np.floor(y0)))
    x1, y1 = min(width, int(np.ceil(x1))), min(height, int(np.ceil(y1)))
    if min(x1 - x0, y1 - y0) < 4:
        raise SineError(
            f"--object-box is {x1 - x0}x{y1 - y0} pixels inside view {view}: box the whole object"
        )
    return x0, y0, x1, y1


def box_mask(image: np.ndarray, box: tuple[int, int, int, int], iterations: int = 4) -> np.ndarray:
    """GrabCut initialised by the box -> the object's mask [H, W] bool (its largest component)."""
    x0, y0, x1, y1 = box
    gc = np.full(image.shape[:2], cv2.GC_BGD, np.uint8)  # what GrabCut's rectangle start sets
    gc[y0:y1, x0:x1] = cv2.GC_PR_FGD
    return _largest_components(_grabcut(image, gc, iterations), 1.0)


def select_object(
    cameras: list[Camera],
    images: list[np.ndarray],
    view: int,
    box: tuple[int, int, int, int],
    params: SelectParams | None = None,
    progress: bool = True,
) -> tuple[list[np.ndarray], dict]:
    """Masks [H, W] bool of the boxed object in every view (cameras and images in the same
    order, images [H, W, 3] in [0, 1]); returns them and {"rounds", "hull_iou": per view, the
    IoU of its mask with the visual hull of all the masks}. The rounds run on images at most
    `work_width` wide; the last cut is at the images' own size."""
    from recon.selfcheck import silhouette_consistency

    params = params or SelectParams()
    small = [min(1.0, params.work_width / c.width) for c in cameras]
    cams = [
        c.resized(round(c.width * s), round(c.height * s))
        for c, s in zip(cameras, small, strict=True)
    ]
    imgs = [
        cv2.resize(im, (c.width, c.height), interpolation=cv2.INTER_AREA)
        for im, c in zip(images, cams, strict=True)
    ]
    box_small = tuple(int(round(v * small[view])) for v in box)
    region, lo, hi, colours, rounds = _rounds(cams, imgs, view, box_small, params, progress)
    sils = _silhouettes(cameras, region, lo, hi)  # the last cut by colour, inside the region
    masks = [_grabcut_in(im, s, colours, params) for im, s in zip(images, sils, strict=True)]
    ious = silhouette_consistency(cameras, masks)  # with the visual hull of these masks
    return masks, {"rounds": rounds, "hull_iou": [float(v) for v in ious]}


def _rounds(cameras, images, view: int, box, params: SelectParams, progress: bool):
    """The rounds of GrabCut and carving -> (region [R, R, R] bool, lo, hi, the object's
    colour model, rounds run)."""
    from tqdm import tqdm

    mask_k = box_mask(images[view], box, params.grabcut_iterations)
    if mask_k.sum() < 16:
        raise SineError(
            f"the box in view {cameras[view].name} holds nothing GrabCut can tell from its "
            "surroundings: box the object more tightly, or paint its mask (--masks)"
        )
    lo, hi = _first_region(cameras, view, box)
    x0, y0, x1, y1 = box
    boxed = np.zeros_like(mask_k)
    boxed[y0:y1, x0:x1] = True
    cone = _carve(cameras[view : view + 1], [boxed], lo, hi, params.resolution, 0)
    region = cone & _ball(cone.shape, params.margin)  # the object lies in the box's cone
    if not region.any():
        raise SineError(f"the box in view {cameras[view].name} selects nothing the cameras see")
    colours = colour_model(images[view], mask_k)
    masks = _silhouettes(cameras, region, lo, hi)
    masks[view] = mask_k
    tolerance = int(np.ceil(params.tolerance * len(cameras)))
    rounds = 0
    for _ in tqdm(range(params.rounds), desc="object", unit="round", disable=not progress):
        rounds += 1
        keep = view if rounds == 1 else -1  # then view K's own cut is one view among the others
        masks = [
            m if i == keep else _grabcut_in(im, m, colours, params)
            for i, (im, m) in enumerate(zip(images, masks, strict=True))
        ]
        carved = _carve(cameras, masks, lo, hi, params.resolution, tolerance) & cone
        if not carved.any():
            raise SineError(
                f"the other views do not agree on the object boxed in view {cameras[view].name}: "
                "box it in a view where it is whole and unoccluded"
            )
        lost = 1.0 - carved.sum() / max(1, region.sum())
        region = carved
        sils = _silhouettes(cameras, region, lo, hi)
        # the object's colours from every view's cut inside the carved region: the sides view K
        # does not show, and parts its own cut missed, now count
        colours = colour_model(images, [m & s for m, s in zip(masks, sils, strict=True)])
        masks = sils
        if lost < params.stop_change:
            break
    return region, lo, hi, colours, rounds


# ---- the region -----------------------------------------------------------------------------
def _first_region(cameras: list[Camera], view: int, box) -> tuple[np.ndarray, np.ndarray]:
    """A cube [lo, hi] around the boxed object: centred on the point of the box's central ray
    nearest to where the cameras look, with a half-size of the box at that depth (x2)."""
    from recon.visual_hull import object_region

    cam = cameras[view]
    target, _ = object_region(cameras)
    x0, y0, x1, y1 = box
    origins, dirs = cam.rays(np.array([[0.5 * (x0 + x1), 0.5 * (y0 + y1)]]))
    o, d = origins[0], dirs[0] / np.linalg.norm(dirs[0])
    depth = max(float(np.dot(target - o, d)), 1e-6)
    centre = o + depth * d
    half = 0.5 * max((x1 - x0) / cam.fx, (y1 - y0) / cam.fy) * depth * 2.0
    return centre - half, centre + half


def _ball(shape, margin: float) -> np.ndarray:
    """Voxels [R, R, R] within `margin` box half-sizes of the grid's centre (the grid's half-size
    is two box half-sizes)."""
    axes = [np.linspace(-1.0, 1.0, n) for n in shape]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    return np.sqrt(x * x + y * y + z * z) <= margin / 2.0


def _carve(cameras, masks, lo, hi, resolution: int, tolerance: int) -> np.ndarray:
    from recon.visual_hull import carve

    occ, _, _ = carve(cameras, masks, lo, hi, resolution, dilate_px=2, tolerance=tolerance)
    return occ


def _silhouettes(cameras, occ: np.ndarray, lo, hi) -> list[np.ndarray]:
    """The region's silhouette [H, W] bool in every view (its voxel surface, ray cast)."""
    from recon.visual_hull import hull_mesh
    from render.raycast import MeshRaycaster

    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    voxel = float((hi - lo).max() / max(occ.shape))
    verts, faces = hull_mesh(occ, lo + 0.5 * voxel, voxel)
    caster = MeshRaycaster((verts, faces))
    return [caster.silhouette(c) for c in cameras]


def colour_model(images, masks, seed: int = 0):
    """A Gaussian mixture of the Lab colours of the pixels under `masks` [H, W] bool of `images`
    [H, W, 3] (one image and mask, or lists of them)."""
    from sklearn.mixture import GaussianMixture

    if isinstance(images, np.ndarray):
        images, masks = [images], [masks]
    lab = np.concatenate([_lab(im)[m] for im, m in zip(images, masks, strict=True)])
    if len(lab) > _MODEL_PIXELS:
        lab = lab[np.random.default_rng(seed).choice(len(lab), _MODEL_PIXELS, replace=False)]
    components = min(_COMPONENTS, max(1, len(lab) // 50))
    return GaussianMixture(
        components, covariance_type="full", reg_covar=1.0, random_state=seed
    ).fit(lab)


def _grabcut_in(image: np.ndarray, region: np.ndarray, object_colours, params) -> np.ndarray:
    """GrabCut inside `region` [H, W] bool (sure background outside it, grown by ~1 % of the
    image): pixels whose colour is far likelier under the object's colours (from view K) than
    under this view's background (outside the region) are sure foreground, far less likely sure
    background, the rest of the region probable foreground."""
    r = max(1, int(round(0.012 * min(region.shape))))
    outside = cv2.dilate(region.astype(np.uint8), _disc(r)) == 0
    if not region.any() or outside.sum() < 50:
        return region
    lab = _lab(image).reshape(-1, 3)
    background = colour_model(image, outside)
    ratio = object_colours.score_samples(lab) - background.score_samples(lab)
    ratio = ratio.reshape(region.shape)
    gc = np.full(region.shape, cv2.GC_PR_BGD, np.uint8)
    gc[region] = cv2.GC_PR_FGD
    gc[region & (ratio > params.colour_ratio)] = cv2.GC_FGD
    gc[region & (ratio < -params.colour_ratio)] = cv2.GC_BGD
    gc[outside] = cv2.GC_BGD
    return _largest_components(_grabcut(image, gc, params.grabcut_iterations), 1.0)


# ---- the masks stage of a capture with a selection -----------------------------------------
def select_masks(run, views: list[dict], cameras, view: str, box) -> dict:
    """Writes RUN/masks/ for the object boxed by `box` (X0 Y0 X1 Y1, pixels of the original
    image) in `view` (an index in the capture or a file name); `views` are the capture's
    records, `cameras` theirs (None when the capture has no poses). Returns the stage's record."""
    from render.io import read_image, write_mask

    if cameras is None:
        raise SineError(
            "--object-box carries the object to every view through the capture's cameras: use a "
            "capture with poses (transforms.json, COLMAP, ...) and without --ignore-poses"
        )
    if len(box) != 4:
        raise SineError(f"--object-box takes four numbers X0 Y0 X1 Y1 (got {len(box)})")
    k = _view_index(views, view)
    record = views[k]
    scale = record["width"] / record["source_width"]
    pixels = check_box([v * scale for v in box], record["width"], record["height"], record["name"])
    images = [read_image(run.image_path(r["name"])) for r in views]
    masks, info = select_object(cameras, images, k, pixels)
    names = [r["name"] for r in views]
    empty = [n for n, m in zip(names, masks, strict=True) if not m.any()]
    if empty:
        raise SineError(
            f"the boxed object is not found in {len(empty)} view(s) ({', '.join(empty[:5])}): "
            "leave out the views where it is hidden, or give masks with --masks"
        )
    for name, mask in zip(names, masks, strict=True):
        write_mask(run.mask_path(name), mask)
    coverage = [float(m.mean()) for m in masks]
    flagged = [n for n, v in zip(names, info["hull_iou"], strict=True) if v < _MIN_HULL_IOU]
    if flagged:
        print(
            f"[recon] masks: {len(flagged)} mask(s) disagree with the object's visual hull: "
            f"{', '.join(flagged[:5])}; check them in masks/"
        )
    return {
        "auto": names,
        "mask_coverage_mean": float(np.mean(coverage)),
        "mask_coverage_min": float(np.min(coverage)),
        "masks_automatic": len(names),
        "masks_given": 0,
        "masks_keying": 0,
        "masks_saliency": 0,
        "masks_selected": len(names),
        "masks_keying_unreliable": {},
        "masks_flagged": flagged,
        "masks_keyed_hull_iou": None,
        "object_view": record["name"],
        "object_rounds": info["rounds"],
        "object_hull_iou_mean": float(np.mean(info["hull_iou"])),
    }


def _view_index(views: list[dict], view: str) -> int:
    """The index of `view` (an index, a run image name or the original file's name)."""
    from pathlib import Path

    names = [r["name"] for r in views]
    if str(view).isdigit():
        if int(view) < len(views):
            return int(view)
    else:
        for i, r in enumerate(views):
            if view in (r["name"], Path(r.get("source", "")).name):
                return i
    raise SineError(
        f"--object-view {view}: the capture has {len(views)} views, 0 to {len(views) - 1} "
        f"({', '.join(names[:3])}, ...)"
    )
