"""Self-checks of a reconstruction: do the poses (and the proxy mesh) explain the masks?

SfM can be wrong and confident: on a symmetric or texture-poor turntable the global mapper
"registers" every view at a sub-pixel reprojection error with cameras off by up to 180 degrees.
Three checks catch that before anything is trained on it:

- silhouette consistency: the visual hull carved from all masks with these cameras (coarse,
  one view may disagree), ray cast back into every view, against that view's mask (IoU). Right
  poses give a hull whose silhouettes fill the masks; wrong ones carve the object away.
  After the proxy mesh the report stage does the same with the proxy's silhouettes.
- reprojection error of the sparse SfM points: finite and below a threshold.
- for a turntable (--turntable on, and an SfM model seeding the turntable model): the camera
  centres' fit to one circle (RMS distance to the circle / its radius) and monotone angles
  around it in capture order; otherwise only measured.

`check_poses` turns the numbers into a verdict: "ok", or "poor" with reasons; the pipeline
stops on "poor" (`stop_message` says what was measured, the likely cause and what to try)
unless told to accept it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from recon.visual_hull import carve, hull_bounds, hull_mesh
from render.cameras import Camera
from render.errors import SineError
from render.metrics import mask_iou


@dataclass
class CheckThresholds:
    """Where a reconstruction counts as poor."""

    min_silhouette_iou: float = 0.8  # mean over views
    max_reprojection_px: float = 2.0  # mean, at the SfM image size
    max_ring_residual: float = 0.1  # RMS distance of the centres to their circle / radius
    max_backward_deg: float = 5.0  # largest step against the turning direction


@dataclass
class Verdict:
    verdict: str  # "ok" or "poor"
    reasons: list[str] = field(default_factory=list)
    numbers: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"verdict": self.verdict, "reasons": list(self.reasons), **self.numbers}


# ---- silhouette consistency ---------------------------------------------------------------
def small_views(
    cameras: list[Camera], masks: list[np.ndarray], width: int
) -> tuple[list[Camera], list[np.ndarray]]:
    """Cameras and masks [h, w] bool scaled down (area) to at most `width` pixels wide."""
    cams, out = [], []
    for cam, mask in zip(cameras, masks, strict=True):
        s = min(1.0, width / cam.width)
        small, small_mask = resized_view(
            cam, mask, max(8, round(cam.width * s)), max(8, round(cam.height * s))
        )
        cams.append(small)
        out.append(small_mask)
    return cams, out


def resized_view(
    cam: Camera, mask: np.ndarray | None, w: int, h: int
) -> tuple[Camera, np.ndarray | None]:
    """The camera and its mask [H, W] bool at w x h pixels (a pixel is in the mask when at
    least half of its area was)."""
    if mask is not None:
        mask = cv2.resize(mask.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) >= 0.5
    return cam.resized(w, h), mask


def hull_silhouettes(
    cameras: list[Camera], masks: list[np.ndarray], resolution: int = 64, tolerance: int = 1
) -> list[np.ndarray]:
    """Silhouettes [H, W] bool of the visual hull of `masks` seen by `cameras` (all empty when
    the masks and cameras share no 3D point)."""
    from render.raycast import MeshRaycaster

    empty = [np.zeros((c.height, c.width), bool) for c in cameras]
    try:
        lo, hi = hull_bounds(cameras, masks)
    except SineError:
        return empty
    occ, origin, voxel = carve(cameras, masks, lo, hi, resolution, dilate_px=1, tolerance=tolerance)
    if not occ.any():
        return empty
    verts, faces = hull_mesh(occ, origin, voxel)
    caster = MeshRaycaster((verts, faces))
    return [caster.silhouette(c) for c in cameras]


def silhouette_consistency(
    cameras: list[Camera], masks: list[np.ndarray], width: int = 200, resolution: int = 64
) -> np.ndarray:
    """Per view IoU [N] of its mask with the silhouette of the visual hull of all views, the
    silhouette kept within the mask grown by one pixel: with one view allowed to disagree, the
    hull may overshoot a view's own mask (wherever only that view carves), which says nothing
    about the poses; a hull that does not fill the mask does. The silhouette is first shrunk by
    the one pixel the carving grew every mask by (`hull_silhouettes`), so that an object of thin
    parts, all outline, is not scored by that margin."""
    cams, small = small_views(cameras, masks, width)
    sils = hull_silhouettes(cams, small, resolution)
    kernel = np.ones((3, 3), np.uint8)
    return np.array(
        [
            mask_iou(
                m,
                (cv2.erode(s.astype(np.uint8), kernel) > 0)
                & (cv2.dilate(m.astype(np.uint8), kernel) > 0),
            )
            for m, s in zip(small, sils, strict=True)
        ]
    )


# ---- the ring of a turntable --------------------------------------------------------------
def fit_circle_2d(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares circle (Kasa) through points [N, 2]: centre [2], radius."""
    A = np.column_stack([2 * points, np.ones(len(points))])
    b = (points**2).sum(1)
    sol = np.linalg.lstsq(A, b, rcond=None)[0]
    centre = sol[:2]
    return centre, float(np.sqrt(max(sol[2] + centre @ centre, 0.0)))


def ring_fit(cameras: list[Camera]) -> dict:
    """How well the camera centres lie on one circle, in the given (capture) order.

    Returns the ring's axis [3] and centre [3], radius, `ring_residual` (RMS distance of the
    centres to the circle, in- and out-of-plane, / radius), the angles (degrees, unwrapped,
    first = 0, turning positive), `backward_deg` (the largest step against the turning
    direction, 0 when monotone) and `monotone`.
    """
    centres = np.array([c.center for c in cameras])  # [N, 3]
    n = len(centres)
    if n < 3:
        return {"ring_residual": 0.0, "monotone": True, "backward_deg": 0.0, "angles_deg": []}
    mean = centres.mean(0)
    _, _, vt = np.linalg.svd(centres - mean)
    e1, e2, axis = vt
    local = np.column_stack([(centres - mean) @ e1, (centres - mean) @ e2])  # [N, 2]
    off_plane = (centres - mean) @ axis  # [N]
    c2, radius = fit_circle_2d(local)
    radial = np.linalg.norm(local - c2, axis=1) - radius
    residual = float(np.sqrt(np.mean(radial**2 + off_plane**2)) / max(radius, 1e-12))
    ang = np.arctan2(local[:, 1] - c2[1], local[:, 0] - c2[0])
    steps = np.degrees(np.angle(np.exp(1j * np.diff(ang))))  # wrapped to (-180, 180]
    if steps.sum() < 0:  # turning direction: the one most of the way goes
        steps = -steps
    backward = float(max(0.0, -steps.min())) if len(steps) else 0.0
    return {
        "axis": axis,
        "centre": mean + c2[0] * e1 + c2[1] * e2,
        "radius": radius,
        "ring_residual": residual,
        "angles_deg": np.concatenate([[0.0], np.cumsum(steps)]).tolist(),
        "backward_deg": backward,
        "monotone": backward == 0.0,
    }


def looks_like_turntable(masks: list[np.ndarray], min_views: int = 8) -> bool:
    """An ordered turntable-like sequence: the object stays in place in the image and each
    mask resembles its successor clearly more (IoU + 0.05) than the views a quarter turn or
    more away (or all masks look alike: a body of revolution)."""
    n = len(masks)
    if n < min_views:
        return False
    small = [
        cv2.resize(m.astype(np.uint8), (64, 64), interpolation=cv2.INTER_AREA) > 0 for m in masks
    ]
    centroids = np.array([np.argwhere(m).mean(0) if m.any() else [32.0, 32.0] for m in small])
    if centroids.std(0).max() > 0.15 * 64:
        return False
    near = np.mean([mask_iou(small[i], small[(i + 1) % n]) for i in range(n)])
    far = [
        mask_iou(small[i], small[(i + k) % n]) for i in range(n) for k in range(n // 4, n // 2 + 1)
    ]
    return bool(near > np.median(far) + 0.05 or np.median(far) > 0.9)


# ---- verdicts -----------------------------------------------------------------------------
def check_poses(
    cameras: list[Camera],
    masks: list[np.ndarray],
    thresholds: CheckThresholds,
    reprojection_px: float | None = None,
    turntable: bool = False,
    width: int = 200,
) -> Verdict:
    """Silhouette consistency, reprojection sanity and the ring of `cameras`.

    `turntable`: the centres must lie on one circle, monotone in capture order; otherwise the
    ring is only measured (a ring need not be captured in order: Middlebury's templeSparseRing
    jumps around it, and its SfM poses are right).
    """
    ious = silhouette_consistency(cameras, masks, width)
    order = np.argsort(ious)
    numbers = {
        "hull_iou_mean": round(float(ious.mean()), 4),
        "hull_iou_min": round(float(ious.min()), 4),
        "hull_iou_worst_views": [cameras[i].name for i in order[:3]],
    }
    reasons = []
    if ious.mean() < thresholds.min_silhouette_iou:
        reasons.append(
            f"the visual hull of the masks explains them poorly (mean silhouette IoU "
            f"{ious.mean():.2f} < {thresholds.min_silhouette_iou:.2f}; worst "
            f"{', '.join(f'{cameras[i].name} {ious[i]:.2f}' for i in order[:3])})"
        )
    if reprojection_px is not None:
        numbers["reprojection_px"] = float(reprojection_px)
        if not np.isfinite(reprojection_px) or reprojection_px > thresholds.max_reprojection_px:
            reasons.append(
                f"the SfM reprojection error is {reprojection_px:.3g} px "
                f"(> {thresholds.max_reprojection_px:g} px)"
            )
    ring = ring_fit(cameras)
    numbers["ring_residual"] = round(float(ring["ring_residual"]), 4)
    numbers["ring_backward_deg"] = round(float(ring["backward_deg"]), 2)
    if turntable and ring["ring_residual"] > thresholds.max_ring_residual:
        reasons.append(
            f"the camera centres are not on one circle (RMS distance {ring['ring_residual']:.2f}"
            f" of its radius > {thresholds.max_ring_residual:g})"
        )
    if turntable and ring["backward_deg"] > thresholds.max_backward_deg:
        reasons.append(
            f"the angles around the ring are not monotone in capture order (a step of "
            f"{ring['backward_deg']:.0f} deg backwards)"
        )
    return Verdict("poor" if reasons else "ok", reasons, numbers)


def check_proxy(names: list[str], ious: list[float], thresholds: CheckThresholds) -> Verdict:
    """The proxy mesh's silhouettes against the masks (per view IoU within a pixel,
    `render.metrics.mask_iou_within`, as the report computes it)."""
    ious_arr = np.asarray(ious, dtype=np.float64)
    order = np.argsort(ious_arr)
    reasons = []
    if ious_arr.mean() < thresholds.min_silhouette_iou:
        reasons.append(
            f"the proxy mesh's silhouettes match the masks poorly (mean IoU within a pixel "
            f"{ious_arr.mean():.2f} "
            f"< {thresholds.min_silhouette_iou:.2f}; worst "
            f"{', '.join(f'{names[i]} {ious_arr[i]:.2f}' for i in order[:3])})"
        )
    return Verdict("poor" if reasons else "ok", reasons, {})


def stop_message(stage: str, reasons: list[str], pose_source: str) -> str:
    """One paragraph for the SineError: what was measured, the likely cause, what to try."""
    if pose_source.startswith("sfm"):
        cause = (
            "the poses are probably wrong (structure from motion can register every view "
            "confidently and still be wrong on symmetric or texture-poor objects)"
        )
        tries = ["--turntable on (a turntable pose model solved from the silhouettes)"]
    elif pose_source == "turntable":
        cause = "the object or the capture does not fit the turntable model, or the masks are bad"
        tries = ["--turntable-step DEG when the object turned by a known step"]
    else:
        cause = "the poses or the masks are probably wrong"
        tries = []
    tries = [
        "look at masks/ (and recon_contact_sheet.png when written) for bad masks",
        *tries,
        "keep the capture's own poses (drop --ignore-poses) if it has them",
        "--accept-poor-poses to go on anyway",
    ]
    return (
        f"self-check after {stage} failed: {'; '.join(reasons)}. Likely cause: {cause}. "
        f"Try: {'; '.join(tries)}. Numbers in recon_report.json (verdict 'poor')"
    )


def require_trusted_poses(run) -> None:
    """Refuses a run whose recon_report.json says its poses are poor and nobody accepted them
    (for the stages that train on the poses: `sine fit`)."""
    from render.io import read_json

    if not run.recon_report.is_file():
        return
    report = read_json(run.recon_report)
    if report.get("verdict") == "poor" and not report.get("poor_accepted"):
        raise SineError(
            f"{run.root}: the reconstruction's self-check found its poses poor "
            f"({'; '.join(report.get('verdict_reasons', []))}); fix the run (see `sine recon "
            "--help`: --turntable, masks) or re-run `sine recon` with --accept-poor-poses"
        )
