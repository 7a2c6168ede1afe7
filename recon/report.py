"""recon_report.json (flat keys) and a contact sheet of masks vs the proxy mesh's silhouettes.

Verdict: "ok", or "poor" with the reasons of every self-check that failed (recon/selfcheck.py:
the poses stage's hull consistency / reprojection / ring, the proxy's silhouettes here), and
`poor_accepted` when --accept-poor-poses let the run go on.

Silhouette IoU: the proxy mesh is ray cast into every registered view; its hit mask is compared
with the view's foreground mask. The contact sheet shows thumbnails with the mask outline in
green and the proxy silhouette outline in magenta.
"""

from __future__ import annotations

import cv2
import numpy as np
from tqdm import tqdm

from recon.rundir import RunDir
from recon.selfcheck import CheckThresholds, check_proxy
from render.io import contact_sheet, read_image, read_mask, write_image, write_json
from render.metrics import mask_iou, mask_iou_within
from render.raycast import MeshRaycaster

STAGE_KEYS_SKIP = ("done", "seconds", "auto")


def proxy_silhouettes(run: RunDir, cameras) -> list[np.ndarray]:
    """Proxy mesh silhouettes [H, W] bool, one per camera (render.raycast)."""
    import open3d as o3d

    caster = MeshRaycaster(o3d.t.io.read_triangle_mesh(str(run.proxy_mesh)))
    return [caster.silhouette(cam) for cam in cameras]


def outline_sheet(images, masks, silhouettes, columns: int = 6, width: int = 200) -> np.ndarray:
    """Thumbnails [H, W, 3] float: mask outline green, proxy silhouette outline magenta."""
    tiles = []
    for image, mask, sil in zip(images, masks, silhouettes, strict=True):
        h = round(image.shape[0] * width / image.shape[1])
        tile = cv2.resize(image, (width, h), interpolation=cv2.INTER_AREA)
        for m, colour in ((mask, (0.0, 1.0, 0.0)), (sil, (1.0, 0.0, 1.0))):
            small = cv2.resize(m.astype(np.uint8), (width, h), interpolation=cv2.INTER_NEAREST)
            contours, _ = cv2.findContours(small, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(tile, contours, -1, colour, 1)
        tiles.append(tile)
    return contact_sheet(tiles, columns, fill=0.0)


def flat_report(state: dict) -> dict:
    """The stages' results as flat keys (each stage's `self_check` as self_check_<stage>)."""
    report: dict = {}
    for stage, info in state["stages"].items():
        for key, value in info.items():
            if key == "self_check":
                report[f"self_check_{stage}"] = value
            elif key not in STAGE_KEYS_SKIP:
                report[key] = value
        report[f"seconds_{stage}"] = info.get("seconds")
    return report


def verdict_of(checks: list[dict], accepted: bool = False) -> dict:
    """verdict ("ok" / "poor"), its reasons and whether a poor one was accepted to go on."""
    reasons = [r for c in checks if c for r in c.get("reasons", [])]
    out = {"verdict": "poor" if reasons else "ok", "verdict_reasons": reasons}
    if reasons:
        out["poor_accepted"] = bool(accepted)
    return out


def write_partial_report(run: RunDir, state: dict) -> None:
    """recon_report.json of a run stopped by a self-check: the stages so far and the verdict."""
    report = flat_report(state)
    checks = [info.get("self_check") for info in state["stages"].values()]
    report.update(verdict_of(checks))
    report["stopped_after"] = list(state["stages"])[-1]
    write_json(run.recon_report, report)


def write_report(
    run: RunDir, state: dict, columns: int = 6, thresholds=None, accepted: bool = False
) -> dict:
    """Computes silhouette IoU, writes the contact sheet and recon_report.json (with the
    verdict of every self-check); returns IoU stats and the proxy's self-check."""
    cams = run.load_cameras().frames
    masks = [read_mask(run.mask_path(c.name)) for c in cams]
    sils = proxy_silhouettes(run, cams)
    ious, near_ious = [], []
    for mask, sil in tqdm(list(zip(masks, sils, strict=True)), desc="report", unit="view"):
        ious.append(mask_iou(mask, sil))
        near_ious.append(mask_iou_within(mask, sil))
    images = [read_image(run.image_path(c.name)) for c in cams]
    sheet_path = run.root / "recon_contact_sheet.png"
    write_image(sheet_path, np.clip(outline_sheet(images, masks, sils, columns), 0, 1))

    proxy_check = check_proxy([c.name for c in cams], near_ious, thresholds or CheckThresholds())
    report = flat_report(state)
    report.update(
        {
            "silhouette_iou_mean": float(np.mean(ious)),
            "silhouette_iou_min": float(np.min(ious)),
            "silhouette_iou_within_pixel_mean": float(np.mean(near_ious)),
            "silhouette_iou_per_view": {
                c.name: round(i, 4) for c, i in zip(cams, ious, strict=True)
            },
            "contact_sheet": sheet_path.name,
            "self_check_report": proxy_check.to_dict(),
        }
    )
    checks = [info.get("self_check") for info in state["stages"].values()]
    report.update(verdict_of([*checks, proxy_check.to_dict()], accepted))
    report.setdefault("registered_views", len(cams))
    report.setdefault("unregistered", [])
    stage_seconds = [v for k, v in report.items() if k.startswith("seconds_") and v is not None]
    report["seconds_total_before_report"] = float(sum(stage_seconds))
    write_json(run.recon_report, report)
    return {
        "silhouette_iou_mean": report["silhouette_iou_mean"],
        "self_check": proxy_check.to_dict(),
    }
