"""The summary of `sine demo` (edit.demo): the output stages (render, export, view, eval and
the summary sheet's renders, `output_stages`), the pictures and tables they make (the
template | edit | ground truth sheet OUT/summary.png, the side-by-side orbit video), the numbers
of OUT/demo_summary.json and OUT/summary.html."""

from __future__ import annotations

import dataclasses
import html
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from edit.demo_stages import EDIT_NAME, FAST, FULL, MASKS_EDIT, TEXTURE_NAME, Clock, mtimes
from render.errors import SineError
from render.io import read_json, read_mask, write_json

if TYPE_CHECKING:
    from edit.demo import DemoConfig


# ---- pictures -----------------------------------------------------------------------------
def resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    if image.shape[:2] == (height, width):
        return image
    return cv2.resize(image.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)


def silhouette_iou(opacity: np.ndarray, mask: np.ndarray) -> float:
    a, b = opacity > 0.5, mask > 0.5
    return float((a & b).sum() / max((a | b).sum(), 1))


def object_psnr(pred: np.ndarray, gt: np.ndarray, pred_alpha, gt_mask) -> float:
    from render.metrics import psnr

    sel = (pred_alpha > 0.5) | (gt_mask > 0.5)
    return psnr(pred[sel], gt[sel])


def text_strip(lines: list[str], width: int, scale: float = 0.4) -> np.ndarray:
    """White strip [h, width, 3] with black text lines."""
    step = int(22 * scale + 8)
    strip = np.full((step * len(lines) + 6, width, 3), 255, np.uint8)  # OpenCV draws on 8 bits
    for i, line in enumerate(lines):
        cv2.putText(
            strip, line, (4, step * (i + 1)), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1,
            cv2.LINE_AA,
        )  # fmt: skip
    return strip.astype(np.float32) / 255.0


def sheet_rows(frames, k: int, rows: int) -> list[int]:
    """View K first, then every held-out view, then training views spread around the ring."""
    test = [i for i, c in enumerate(frames) if c.split == "test"]
    chosen = [k] + [i for i in test if i != k]
    for i in np.linspace(0, len(frames), 2 * rows, endpoint=False).astype(int):
        if len(chosen) >= rows:
            break
        if all(abs(int(i) - j) > 1 for j in chosen):
            chosen.append(int(i))
    return chosen[:rows]


COLUMNS = ("template", "geometric edit", "its ground truth", "texture edit", "its ground truth")


def compare_views(template, edits: list, frames, rows: list[int], k: int) -> dict:
    """Renders the template and each edit at the views `rows`, next to each edit's GT image.
    edits: [(name, scene, GT folder)]. Returns {"tiles": [row images], "views": [numbers]}."""
    from render.frames import label
    from render.io import read_image

    tiles, numbers = [], []
    gap = np.ones((frames[0].height, 2, 3), np.float32)
    for i in rows:
        cam = frames[i]
        stem = Path(cam.name).stem
        role = "edited view K" if i == k else ("held-out" if cam.split == "test" else "train")
        before = template.render_view(cam)
        b_rgb = np.clip(before["rgb"], 0, 1)
        row = {"view": cam.name, "index": i, "role": role}
        tag = f"{stem} {'K' if i == k else ('held-out' if cam.split == 'test' else 'train')}"
        parts = [label(b_rgb, tag)]
        for name, scene, gt_dir in edits:
            gt = resize(read_image(gt_dir / "images" / f"{stem}.png"), cam.width, cam.height)
            gt_mask = read_mask(gt_dir / "masks" / f"{stem}.png").astype(np.float32)
            gt_mask = resize(gt_mask, cam.width, cam.height)
            after = scene.render_view(cam)
            a_rgb = np.clip(after["rgb"], 0, 1)
            row[f"{name}_silhouette_iou"] = silhouette_iou(after["opacity"], gt_mask)
            row[f"template_silhouette_iou_{name}"] = silhouette_iou(before["opacity"], gt_mask)
            row[f"{name}_psnr_object"] = object_psnr(a_rgb, gt, after["opacity"], gt_mask)
            row[f"template_psnr_object_{name}"] = object_psnr(b_rgb, gt, before["opacity"], gt_mask)
            caption = (
                f"IoU {row[f'{name}_silhouette_iou']:.2f}"
                if name == "geometric"
                else f"{row[f'{name}_psnr_object']:.1f} dB"
            )
            parts += [gap, label(a_rgb, caption), gap, label(gt, "ground truth")]
        numbers.append(row)
        tiles.append(np.concatenate(parts, axis=1))
    return {"tiles": tiles, "views": numbers}


def summary_sheet(tiles: list[np.ndarray], lines: list[str], tile_width: int) -> np.ndarray:
    """Header (column names) + rows of template | each edit | its ground truth + the numbers."""
    width = tiles[0].shape[1]
    header = np.full((20, width, 3), 255, np.uint8)
    for j, name in enumerate(COLUMNS[: (width + 2) // (tile_width + 2)]):
        cv2.putText(
            header, name, (j * (tile_width + 2) + 4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
            (0, 0, 0), 1, cv2.LINE_AA,
        )  # fmt: skip
    header = header.astype(np.float32) / 255.0
    sep = np.ones((2, width, 3), np.float32)
    body = [x for t in tiles for x in (t, sep)]
    scale = 0.33 if width < 400 else 0.45
    return np.concatenate([header, *body, text_strip(lines, width, scale)], axis=0)


def compare_video(dirs: list[Path], names: list[str], path: Path, fps: float) -> int:
    """Side-by-side video of folders of frames with the same file names (left to right,
    labelled `names`); returns the frame count."""
    from render.frames import strip
    from render.io import read_image
    from render.video import VideoWriter

    frames = sorted(p.name for p in (dirs[0] / "rgb").glob("*.png"))
    with VideoWriter(path, fps) as video:
        for frame in frames:
            video.write(strip([read_image(d / "rgb" / frame) for d in dirs], names))
    return len(frames)


# ---- output stages ------------------------------------------------------------------------
def output_stages(cfg: DemoConfig, run, gt_dirs: dict, k: int, record, clock: Clock) -> dict:
    """render / export / view / eval / summary pictures; returns numbers, files, sheet rows.
    gt_dirs: {"geometric": GT of the geometric edit, "texture": GT of the texture edit}."""
    from edit.eval_cli import evaluate_scene
    from edit.export_cli import export_mesh
    from edit.scene import RenderCache, load_scene
    from edit.view_cli import viewer_scene
    from render.camera_paths import orbit_cameras
    from render.frames import render_frames
    from render.viewer import screenshot

    out = cfg.out
    fields = mtimes(
        run.template / "field.pt",
        run.edit(EDIT_NAME) / "edit_field.pt",
        run.edit(TEXTURE_NAME) / "edit_field.pt",
    )
    # the held-out views are scored, then some are shown on the summary sheet: rendered once
    template = RenderCache(load_scene(run.root, None, device=cfg.device))
    edit = RenderCache(load_scene(run.root, EDIT_NAME, device=cfg.device))
    texture = RenderCache(load_scene(run.root, TEXTURE_NAME, device=cfg.device))
    frames = run.load_cameras().frames
    files = {
        "summary_png": "summary.png",
        "summary_html": "summary.html",
        "target": "target.png",
        "target_before_after": "target_before_after.png",
        "texture_target": "texture_target.png",
        "texture_target_before_after": "texture_target_before_after.png",
        "template_video": "template.mp4",
        "edit_video": "edit.mp4",
        "texture_video": "texture.mp4",
        "compare_video": "compare.mp4",
        "template_mesh": "template.glb",
        "edited_mesh": "edited.glb",
        "textured_mesh": "texture_edited.glb",
        "viewer": "viewer.png",
    }

    clock.start("render")
    key = {"orbit": cfg.orbit, "fields": fields, "supersample": cfg.video_supersample}
    videos = {
        name: dataclasses.replace(scene.scene, supersample=cfg.video_supersample)
        for name, scene in (("template", template), ("edit", edit), ("texture", texture))
    }
    paths = [out / files[f"{v}_video"] for v in videos] + [out / files["compare_video"]]
    skip = record.done("render", key, paths)
    if not skip:
        cams = orbit_cameras(frames, cfg.orbit)
        fps = max(8.0, cfg.orbit / 5.0)  # one turn in about 5 s
        for name, scene in videos.items():
            video = out / files[f"{name}_video"]
            render_frames(scene, cams, out / "orbit" / name, video=video, fps=fps)
        names = ["template", "geometric edit", "texture edit"]
        compare_video([out / "orbit" / v for v in videos], names, paths[-1], fps)
        record.record("render", key)
    clock.finish("render", skip)

    clock.start("export")
    key = {"fields": fields}
    meshes = {"template_mesh": template, "edited_mesh": edit, "textured_mesh": texture}
    skip = record.done("export", key, [out / files[f] for f in meshes])
    if not skip:
        for f, scene in meshes.items():
            stats = export_mesh(scene, out / files[f])
            print(f"export: {stats['vertices']} vertices ({scene.name}) -> {out / files[f]}")
        record.record("export", key)
    clock.finish("export", skip)

    clock.start("view")
    key = {"fields": fields}
    skip = record.done("view", key, [out / files["viewer"]])
    if not skip:
        try:
            screenshot(viewer_scene(run.root, EDIT_NAME, device=cfg.device), out / files["viewer"])
            record.record("view", key)
        except SineError as exc:  # no EGL / display: everything else is still worth having
            print(f"view: no screenshot ({exc})")
            files.pop("viewer")
    clock.finish("view", skip)

    clock.start("eval")
    key = {"fields": fields, "gt": {k: str(v) for k, v in gt_dirs.items()}}
    evals = {  # file: (scene, ground truth, edit-region masks)
        "eval_edit.json": (edit, gt_dirs["geometric"], None),
        "eval_template_vs_gt_edit.json": (template, gt_dirs["geometric"], None),
        "eval_texture.json": (texture, gt_dirs["texture"], out / "texture_part"),
        "eval_template_vs_gt_texture.json": (template, gt_dirs["texture"], out / "texture_part"),
    }
    skip = record.done("eval", key, [out / f for f in evals])
    if not skip:
        for f, (scene, gt, regions) in evals.items():
            write_json(out / f, evaluate_scene(scene, gt, regions, split="test"))
        record.record("eval", key)
    clock.finish("eval", skip)
    mean = {f: read_json(out / f)["mean"] for f in evals}

    clock.start("summary")
    rows = sheet_rows(frames, k, (FAST if cfg.fast else FULL)["rows"])
    # what the sheet's pictures and lines come from (the other numbers follow the fields)
    masks = mtimes(run.edit(MASKS_EDIT) / "semantic_masks" / "metrics.json")
    summary_key = {"fields": fields, "masks": masks, "rows": rows, "gt": key["gt"]}
    previous = out / "demo_summary.json"
    skip = record.done("summary", summary_key, [out / files["summary_png"], previous])
    if skip:  # the sheet stays; its numbers are the previous summary's
        views = {"views": read_json(previous)["views_compared"], "tiles": None}
    else:
        edits = [
            ("geometric", edit, gt_dirs["geometric"]),
            ("texture", texture, gt_dirs["texture"]),
        ]
        views = compare_views(template, edits, frames, rows, k)
    numbers = summary_numbers(views, mean)
    clock.finish("summary", skip)
    return {"numbers": numbers, "files": files, "rows": views["tiles"], "summary_key": summary_key}


# ---- numbers and pages --------------------------------------------------------------------
def summary_numbers(views: dict, mean: dict) -> dict:
    """The held-out and edited-view numbers of demo_summary.json: `views` from compare_views
    (the sheet's views), `mean` the eval files' means ({file: {metric: value}})."""
    held = [v for v in views["views"] if v["role"] == "held-out"]
    edited = views["views"][0]
    geo, geo_t = mean["eval_edit.json"], mean["eval_template_vs_gt_edit.json"]
    tex, tex_t = mean["eval_texture.json"], mean["eval_template_vs_gt_texture.json"]
    numbers = {
        "edit_heldout_psnr": geo.get("psnr"),
        "edit_heldout_psnr_object": geo.get("psnr_object"),
        "edit_heldout_ssim": geo.get("ssim"),
        "template_vs_gt_edit_heldout_psnr": geo_t.get("psnr"),
        "template_vs_gt_edit_heldout_psnr_object": geo_t.get("psnr_object"),
        "edit_heldout_silhouette_iou": float(
            np.mean([v["geometric_silhouette_iou"] for v in held])
        ),
        "template_vs_gt_edit_heldout_silhouette_iou": float(
            np.mean([v["template_silhouette_iou_geometric"] for v in held])
        ),
        "edited_view_silhouette_iou": edited["geometric_silhouette_iou"],
        "edited_view_psnr_object": edited["geometric_psnr_object"],
        "template_vs_gt_edit_edited_view_silhouette_iou": edited[
            "template_silhouette_iou_geometric"
        ],
        "texture_heldout_psnr_object": tex.get("psnr_object"),
        "texture_heldout_psnr_part": tex.get("psnr_region"),
        "texture_heldout_psnr_rest": tex.get("psnr_outside_region"),
        "template_vs_gt_texture_heldout_psnr_object": tex_t.get("psnr_object"),
        "template_vs_gt_texture_heldout_psnr_part": tex_t.get("psnr_region"),
        "template_vs_gt_texture_heldout_psnr_rest": tex_t.get("psnr_outside_region"),
        "texture_edited_view_psnr_object": edited["texture_psnr_object"],
        "views_compared": views["views"],
    }
    return numbers


def summary_lines(s: dict) -> list[str]:
    """The numbers of the summary, one short line each."""
    f = lambda x, d=2: "n/a" if x is None else f"{x:.{d}f}"  # noqa: E731
    return [
        f"{s['object']}, {s['views']} views, {s['registered_views']}/{s['views']} posed "
        f"({s.get('pose_source') or 'n/a'}); "
        f"template held-out PSNR {f(s['template_heldout_psnr'])} dB",
        f"semantic masks ({s['painted_part']}) held-out IoU "
        f"{f(s['semantic_mask_heldout_iou_mean'], 3)}",
        f"edit vs GT, held-out: PSNR {f(s['edit_heldout_psnr'])} dB "
        f"(template {f(s['template_vs_gt_edit_heldout_psnr'])}), sil. IoU "
        f"{f(s['edit_heldout_silhouette_iou'], 3)} "
        f"(template {f(s['template_vs_gt_edit_heldout_silhouette_iou'], 3)})",
        f"edited view {Path(s['edit_view']).stem}: sil. IoU {f(s['edited_view_silhouette_iou'], 3)}"
        f" (template {f(s['template_vs_gt_edit_edited_view_silhouette_iou'], 3)}), object PSNR "
        f"{f(s['edited_view_psnr_object'])} dB",
        f"texture edit ({s['texture_part']} recoloured) vs GT, held-out: object PSNR "
        f"{f(s['texture_heldout_psnr_object'])} dB (template "
        f"{f(s['template_vs_gt_texture_heldout_psnr_object'])})",
        f"  on the {s['texture_part']} {f(s['texture_heldout_psnr_part'])} dB (template "
        f"{f(s['template_vs_gt_texture_heldout_psnr_part'])}), elsewhere "
        f"{f(s['texture_heldout_psnr_rest'])} dB (template "
        f"{f(s['template_vs_gt_texture_heldout_psnr_rest'])})",
    ]


def write_html(out: Path, s: dict, tiles: list[np.ndarray] | None) -> None:
    """OUT/summary.png (unless `tiles` is None: the sheet is unchanged) and OUT/summary.html
    (pictures and videos referenced next to it)."""
    from render.io import write_image, write_text_atomic

    lines = summary_lines(s)
    if tiles is not None:
        write_image(out / "summary.png", summary_sheet(tiles, lines, s["run_size"][0]))
    files = s["files"]
    rel = {
        "recon contact sheet": "run/recon_contact_sheet.png",
        "semantic masks": f"run/edits/{MASKS_EDIT}/semantic_masks/overlay_contact_sheet.png",
        "shape prior": f"run/edits/{EDIT_NAME}/prior_preview.png",
        "edited view: template | edit | target": f"run/edits/{EDIT_NAME}/edited_view.png",
        "texture edit, edited view": f"run/edits/{TEXTURE_NAME}/edited_view.png",
    }
    rows = "".join(
        f"<tr><td>{html.escape(k)}</td><td>{v:.4g}</td></tr>"
        if isinstance(v, float)
        else f"<tr><td>{html.escape(k)}</td><td>{html.escape(str(v))}</td></tr>"
        for k, v in s.items()
        if isinstance(v, (int, float, str)) and k != "config"
    )
    videos = "".join(
        f'<figure><video src="{files[v]}" controls loop autoplay muted></video>'
        f"<figcaption>{v.replace('_', ' ')}</figcaption></figure>"
        for v in ("template_video", "edit_video", "texture_video", "compare_video")
    )
    pictures = "".join(
        f'<figure><img src="{p}"><figcaption>{html.escape(c)}</figcaption></figure>'
        for c, p in [
            ("geometric target (left: the capture of view K, right: the ground-truth edit)",
             files["target_before_after"]),
            ("texture target (left: the capture of view K, right: its part recoloured, as "
             "`sine target --recolor` makes it)", files["texture_target_before_after"]),
            *([("viewer: template | edited mesh", files["viewer"])] if "viewer" in files else []),
            *rel.items(),
        ]
        if (out / p).is_file()
    )  # fmt: skip
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>sine demo</title>
<style>body{{font-family:sans-serif;margin:1em}} img,video{{max-width:100%}}
figure{{display:inline-block;vertical-align:top;margin:0.5em}} td{{padding:0 1em}}</style>
</head><body>
<h1>sine demo: {html.escape(s["object"])}, one geometric and one texture edit</h1>
<p>{"<br>".join(html.escape(x) for x in lines)}</p>
<figure><img src="{files["summary_png"]}"><figcaption>rows: views around the ring (K = the
edited view); columns: template | geometric edit | its ground truth | texture edit | its
ground truth</figcaption></figure>
{videos}
<p>Meshes (capture units, vertex colours): <a href="{files["template_mesh"]}">template</a>,
<a href="{files["edited_mesh"]}">geometric edit</a>,
<a href="{files["textured_mesh"]}">texture edit</a>.
Numbers: <a href="demo_summary.json">demo_summary.json</a>,
<a href="eval_edit.json">eval_edit.json</a>, <a href="eval_texture.json">eval_texture.json</a>.</p>
{pictures}
<table>{rows}</table>
</body></html>
"""
    write_text_atomic(out / "summary.html", page)
