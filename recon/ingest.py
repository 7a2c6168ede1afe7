"""Capture ingestion (`sine ingest`): any supported capture -> the start of a run directory.

Reads a folder of images, a video, a NeRF/nerfstudio `transforms.json`, a NeRF-synthetic
(Blender) folder with `transforms_train.json` (+ `_test`, `_val`), a COLMAP model, a Middlebury
ring (`*_par.txt`), a NeuS/IDR folder (`cameras_sphere.npz`) or images with per-image 3x4
projection matrices, and writes (DESIGN.md section 3):

- `images/<stem>.png`: working images, undistorted, resized (never upscaled) to `width`;
- `captures.json`: source files, sizes, hashes, per-image status, the ingest config;
- `cameras.json`: only when the input carries poses (intrinsics scaled to the working size);
  with `ignore_poses` the extrinsics are dropped but the intrinsics are kept (per image record,
  `intrinsics`: fx, fy, cx, cy at the working size) as a fixed prior for SfM, unless
  `ignore_intrinsics` drops them too;
- `masks/<stem>.png`, `depth/<stem>.npy`: when the input carries them (resized with nearest).

Splits: every `holdout_every`-th view is held out ('test'), except for a NeRF-synthetic folder:
the frames of `transforms_train.json` are 'train', those of `transforms_test.json` and
`transforms_val.json` are 'test' (an image listed in several files counts once; the Blender
datasets' val and test views are both held out). Passing one split file (`.../transforms_train.json`)
reads that file alone, with the `holdout_every` rule.

RGBA images (NeRF synthetic, cut-outs): where alpha is not all opaque, it becomes the mask
(unless a mask comes with the view) and the RGB is composited over `background_color` (white by
default, the NeRF-synthetic convention), since the RGB of transparent pixels is arbitrary.

Lenient where it can be: a pose file listing images that do not exist keeps the ones that do
(a warning in the notes; fewer than 3 is an error); with `ignore_poses` a pose file that cannot
be used at all is no error (images only, a note); `NNNNN_P.txt` projection files match images
by their leading number (`NNNNN._c.png`); a JPEG's EXIF orientation is applied to images
without a camera (phone photos come in upright).

The stage is idempotent: the same source with the same options is skipped unless `force`.
"""

from __future__ import annotations

import contextlib
import hashlib
import re
import shutil
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from recon.rundir import RunDir
from render.cameras import (
    Camera,
    CameraSet,
    camera_from_krt,
    camera_from_projection,
    cameras_from_neus,
    cameras_from_transforms,
    read_colmap_model,
    read_middlebury_par,
)
from render.configs import option, to_dict
from render.errors import SineError
from render.io import (
    IMAGE_SUFFIXES,
    read_image_rgba,
    read_json,
    write_depth,
    write_image,
    write_mask,
)
from render.locks import lock_folder

FORMATS = ("auto", "images", "video", "transforms", "colmap", "middlebury", "neus", "projections")
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".gif")
# Files that may sit beside the images of a capture and are not images (never an error).
SIDECAR_SUFFIXES = (
    ".txt", ".json", ".mat", ".npz", ".npy", ".p", ".md", ".yaml", ".yml", ".csv", ".xml",
    ".ply", ".obj", ".mtl", ".log", ".db", ".ini", ".bin", ".pdf", ".html", ".zip",
)  # fmt: skip
MIN_VIEWS = 3
# NeRF-synthetic (Blender) split files: the file and the split its frames get, in reading order.
SPLIT_FILES = (
    ("transforms_train.json", "train"),
    ("transforms_test.json", "test"),
    ("transforms_val.json", "test"),
)
BACKGROUND_NAMES = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


@dataclass
class IngestConfig:
    """Options of `sine ingest`."""

    width: int = option(
        400, "working image width in pixels; images narrower than this keep their size"
    )
    frames: int = option(36, "for a video: number of frames to sample, evenly spaced")
    holdout_every: int = option(
        8, "every Nth view (the 8th, 16th, ...) gets split 'test', the others 'train'; 0 = none"
    )
    format: str = option("auto", "capture format (auto = detect it)", choices=FORMATS)
    ignore_poses: bool = option(
        False,
        "do not write cameras.json even if the capture carries poses (recon runs SfM); the "
        "capture's intrinsics are still kept as a fixed prior for SfM (see --ignore-intrinsics)",
    )
    ignore_intrinsics: bool = option(
        False,
        "with --ignore-poses: drop the capture's intrinsics too (SfM estimates focal length "
        "and principal point itself)",
    )
    masks: Path | None = option(
        None, "folder of foreground masks (0/255 images) matched to images by file stem; wins "
        "over masks that come with the capture"
    )  # fmt: skip
    background_color: list[str] = option(
        ["white"],
        "colour RGBA images (e.g. NeRF synthetic) are composited over, where their alpha becomes "
        "the mask: white (the NeRF-synthetic convention), black, or R G B in [0, 1]",
    )
    force: bool = option(False, "re-ingest even if this run already holds the same capture")


@dataclass
class SourceView:
    """One view of a capture before ingestion."""

    stem: str  # working file stem (images/<stem>.png)
    source: str  # where it comes from (a path, or `video#frame=N`)
    path: Path | None = None  # image file (None for a decoded video frame)
    frame: np.ndarray | None = None  # decoded video frame, BGR uint8 [H, W, 3]
    camera: Camera | None = None  # in source pixels, possibly distorted
    mask: Path | None = None
    depth: Path | None = None
    depth_scale: float = 1.0  # multiplies integer depth images (nerfstudio: mm -> m)
    split: str | None = None  # given by the capture (NeRF-synthetic split files), else the rule


@dataclass
class Capture:
    """A capture as read from disk: its views and what the format carried."""

    format: str
    views: list[SourceView]
    has_poses: bool
    notes: list[str] = field(default_factory=list)
    extra: dict = field(default_factory=dict)  # goes into cameras.json


# ---- public API ---------------------------------------------------------------------------
def assign_splits(n: int, holdout_every: int) -> list[str]:
    """Split labels for n views: every `holdout_every`-th view (1-based) is 'test'; 0 = none."""
    if holdout_every < 0 or holdout_every == 1:
        raise SineError(
            f"holdout_every={holdout_every} is invalid: use 0 (no held-out views) or N >= 2 "
            "(every Nth view is held out for testing)"
        )
    if holdout_every == 0:
        return ["train"] * n
    return ["test" if (i + 1) % holdout_every == 0 else "train" for i in range(n)]


def ingest_capture(capture: Path, run: RunDir, cfg: IngestConfig | None = None) -> dict:
    """Reads `capture` (format detected unless cfg.format says) into `run`; returns a summary."""
    cfg = cfg or IngestConfig()
    t0 = time.perf_counter()
    capture = Path(capture)
    _check_config(cfg)
    if not capture.exists():
        raise SineError(
            f"capture {capture} does not exist: pass a folder of images, a video file, a "
            "transforms.json, a COLMAP model folder, a Middlebury or NeuS folder"
        )
    capture = capture.resolve()
    root = run.root.resolve()
    if root == capture or root in capture.parents or capture in root.parents:
        raise SineError(
            f"--out {run.root} and the capture {capture} overlap: write the run to a folder "
            "outside the capture (inputs are never modified)"
        )
    with removed_if_refused(run.root), lock_folder(run.root, f"run {run.root}"):
        return _ingest(capture, run, cfg, t0)


@contextlib.contextmanager
def removed_if_refused(root: Path, new: bool | None = None):
    """For the block that ingests a capture into the run folder `root`: when the folder is `new`
    (default: it does not exist yet) and the block ends on a user error (a capture refused
    half-way), the folder is removed again, so no half-made run is left behind."""
    new = not Path(root).exists() if new is None else new
    try:
        yield
    except SineError:
        if new:
            shutil.rmtree(root, ignore_errors=True)
        raise


def _ingest(capture: Path, run: RunDir, cfg: IngestConfig, t0: float) -> dict:
    source = str(capture)
    config = _config_key(cfg)
    previous = _previous(run, source, config)
    if previous is not None and not cfg.force:
        return {**summarize(previous, run), "skipped": True}
    _refuse_another_capture(run, source, cfg.force)

    fmt = detect_format(capture) if cfg.format == "auto" else cfg.format
    if fmt not in READERS:
        raise SineError(f"unknown camera format '{fmt}': use one of {', '.join(FORMATS)}")
    cap = _read_capture(fmt, capture, cfg)
    if len(cap.views) < MIN_VIEWS:
        raise SineError(
            f"{capture} gives only {len(cap.views)} view(s) ({fmt}); a reconstruction needs at "
            f"least {MIN_VIEWS} (better 20-150) views of the object from around it"
        )
    _check_unique_stems(cap.views)
    if cfg.masks is not None:
        _attach_user_masks(cap.views, Path(cfg.masks))
    sizes = _probe_sizes(cap.views)
    if not any(v.camera for v in cap.views):
        _check_same_size(cap.views, sizes, capture)
    use_poses = cap.has_poses and not cfg.ignore_poses

    # Start over: a half-finished earlier ingest must never look complete.
    run.root.mkdir(parents=True, exist_ok=True)
    run.captures.unlink(missing_ok=True)
    splits = assign_splits(len(cap.views), cfg.holdout_every)
    if any(v.split for v in cap.views):  # the capture says which views are held out
        splits = [v.split or "train" for v in cap.views]
    background = background_rgb(cfg.background_color)
    records, cameras = [], []
    for view, split, size in tqdm(
        list(zip(cap.views, splits, sizes, strict=True)),
        desc="ingest",
        unit="view",
        leave=False,
        disable=None,  # no bar in a log: a refused capture leaves one line
    ):
        record, cam = _ingest_view(view, size, cfg, run, split, background)
        records.append(record)
        cameras.append(cam)
    alpha = sum(r["alpha"] for r in records)
    if alpha:
        colour = ", ".join(f"{c:g}" for c in background)
        cap.notes.append(
            f"{alpha} RGBA image(s): alpha used as the mask (where no mask came with the view), "
            f"RGB composited over the background colour ({colour})"
        )
    _remove_stale(run, records)
    if use_poses:
        extra = {"source_format": fmt, **cap.extra}
        run.save_cameras(CameraSet(frames=cameras, extra=extra))
    else:
        run.cameras.unlink(missing_ok=True)
        if cap.has_poses:
            cap.notes.append("poses in the capture were ignored (--ignore-poses)")
            if cfg.ignore_intrinsics:
                cap.notes.append("intrinsics in the capture were ignored (--ignore-intrinsics)")
            else:
                for record, cam in zip(records, cameras, strict=True):
                    if cam is not None:
                        record["intrinsics"] = {
                            k: float(getattr(cam, k)) for k in ("fx", "fy", "cx", "cy")
                        }
    captures = {
        "source": source,
        "format": cap.format,
        "working_width": max(r["width"] for r in records),
        "poses": use_poses,
        "alpha_background": background.tolist() if alpha else None,
        "config": config,
        "notes": cap.notes,
        "images": records,
    }
    run.save_captures(captures)
    return {**summarize(captures, run), "skipped": False, "seconds": time.perf_counter() - t0}


def summarize(captures: dict, run: RunDir) -> dict:
    """A short summary of an ingested capture (what the CLI prints)."""
    images = captures["images"]
    work = sorted({(r["width"], r["height"]) for r in images})
    src = sorted({(r["source_width"], r["source_height"]) for r in images})
    return {
        "run": str(run.root),
        "source": captures["source"],
        "format": captures["format"],
        "views": len(images),
        "train": sum(r["split"] == "train" for r in images),
        "test": sum(r["split"] == "test" for r in images),
        "poses": bool(captures.get("poses")),
        "masks": sum(bool(r.get("mask")) for r in images),
        "alpha_masks": sum(bool(r.get("alpha")) for r in images),
        "background": captures.get("alpha_background"),
        "depth": sum(bool(r.get("depth")) for r in images),
        "undistorted": sum(bool(r.get("undistorted")) for r in images),
        "working_size": "mixed" if len(work) > 1 else f"{work[0][0]}x{work[0][1]}",
        "source_size": "mixed" if len(src) > 1 else f"{src[0][0]}x{src[0][1]}",
        "notes": list(captures.get("notes", [])),
    }


def detect_format(capture: Path) -> str:
    """The format of a capture path (see FORMATS); raises SineError when none fits."""
    capture = Path(capture)
    if capture.is_file():
        suffix = capture.suffix.lower()
        if suffix == ".json":
            return "transforms"
        if capture.name == "cameras_sphere.npz":
            return "neus"
        if capture.name.endswith("_par.txt"):
            return "middlebury"
        if suffix in IMAGE_SUFFIXES:
            raise SineError(
                f"{capture} is a single image; pass the folder that holds all the views"
            )
        if suffix in SIDECAR_SUFFIXES:
            raise SineError(
                f"unknown camera format: {capture} is neither a video nor a transforms.json; "
                "pass the capture folder (images + cameras) instead"
            )
        return "video"
    if not capture.is_dir():
        raise SineError(f"{capture} is neither a file nor a folder")
    if (capture / "transforms.json").is_file():
        return "transforms"
    if (capture / SPLIT_FILES[0][0]).is_file():  # NeRF synthetic (Blender)
        return "transforms"
    if (capture / "cameras_sphere.npz").is_file():
        return "neus"
    if _find_colmap_model(capture) is not None:
        return "colmap"
    if sorted(capture.glob("*_par.txt")):
        return "middlebury"
    folder = _image_folder(capture)
    if folder is not None and any(_projection_file(p) for p in _image_files(folder)):
        return "projections"
    split_files = sorted(p.name for p in capture.glob("transforms_*.json"))
    if split_files:
        raise SineError(
            f"{capture} holds {', '.join(split_files)} but neither transforms.json nor "
            f"{SPLIT_FILES[0][0]}: pass the file to ingest (e.g. CAPTURE/{split_files[0]})"
        )
    if folder is not None:
        return "images"
    entries = sorted(p.name for p in capture.iterdir() if not p.name.startswith("."))
    if not entries:
        raise SineError(f"{capture} is empty: put the photos of the capture in it")
    raise SineError(
        f"no images found in {capture} (it holds: {_short_list(entries)}); expected images "
        f"({', '.join(IMAGE_SUFFIXES)}), optionally in an images/ subfolder, or a known camera "
        "format (transforms.json, COLMAP sparse/0, *_par.txt, cameras_sphere.npz)"
    )


def _read_capture(fmt: str, capture: Path, cfg: IngestConfig) -> Capture:
    """The format's reader; with --ignore-poses a pose file it cannot use is no error: the
    images are read alone (SfM then estimates the intrinsics too)."""
    try:
        return READERS[fmt](capture, cfg)
    except SineError as exc:
        if not cfg.ignore_poses or fmt in ("images", "video"):
            raise
        folder = capture if capture.is_dir() else capture.parent
        try:
            cap = _read_images(folder, cfg)
        except SineError:
            raise exc from None
        note = f"the {fmt} cameras could not be used ({exc}); --ignore-poses: images only"
        print(f"[ingest] {note}")
        cap.notes.append(note)
        return cap


# ---- format readers -----------------------------------------------------------------------
def _read_images(capture: Path, cfg: IngestConfig) -> Capture:
    if not capture.is_dir():
        raise SineError(f"format 'images' needs a folder of images; {capture} is not a folder")
    folder = _image_folder(capture)
    if folder is None:
        detect_format(capture)  # raises the detailed "empty / no images" message
        raise SineError(f"no images found in {capture}")
    files = _image_files(folder)
    views = [SourceView(p.stem, str(p), path=p) for p in files]
    notes = []
    ignored = sorted(p.name for p in capture.glob("*.mat"))
    if ignored:
        notes.append(f"ignored {', '.join(ignored)} (not a metric calibration we can use)")
    return Capture("images", views, has_poses=False, notes=notes)


def _read_video(capture: Path, cfg: IngestConfig) -> Capture:
    if not capture.is_file():
        raise SineError(f"format 'video' needs a video file; {capture} is not a file")
    cap = cv2.VideoCapture(str(capture))
    if not cap.isOpened():
        raise SineError(
            f"cannot open video {capture}: OpenCV has no decoder for it or the file is damaged; "
            "convert it to MP4 (H.264) or extract the frames to a folder of images"
        )
    try:
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if count <= 0:  # some containers do not know: count by decoding
            count = 0
            while cap.grab():
                count += 1
            cap.release()
            cap = cv2.VideoCapture(str(capture))
        if count == 0:
            raise SineError(f"video {capture} has no frames that OpenCV can decode")
        wanted = np.unique(np.round(np.linspace(0, count - 1, min(cfg.frames, count))).astype(int))
        wanted_set = set(wanted.tolist())
        views, index = [], 0
        while len(views) < len(wanted) and cap.grab():
            if index in wanted_set:
                ok, frame = cap.retrieve()
                if ok and frame is not None:
                    views.append(
                        SourceView(
                            f"{capture.stem}_{index:05d}",
                            f"{capture}#frame={index}",
                            frame=np.ascontiguousarray(frame),
                        )
                    )
            index += 1
    finally:
        cap.release()
    notes = [f"sampled {len(views)} of {count} frames evenly"]
    return Capture("video", views, has_poses=False, notes=notes)


def _read_transforms(capture: Path, cfg: IngestConfig) -> Capture:
    split_folder = capture.is_dir() and not (capture / "transforms.json").is_file()
    if split_folder and (capture / SPLIT_FILES[0][0]).is_file():
        return _read_split_transforms(capture)
    path = capture / "transforms.json" if capture.is_dir() else capture
    if not path.is_file():
        raise SineError(f"format 'transforms' needs a transforms.json; {path} does not exist")
    views, notes = _transforms_views(path)
    return Capture("transforms", views, has_poses=True, notes=notes)


def _read_split_transforms(folder: Path) -> Capture:
    """A NeRF-synthetic (Blender) folder: the frames of every split file present, each image
    once (the first file listing it gives its split; see SPLIT_FILES)."""
    views, notes, seen, repeated = [], [], set(), Counter()
    for name, split in SPLIT_FILES:
        path = folder / name
        if not path.is_file():
            continue
        minimum = MIN_VIEWS if split == "train" else 0
        file_views, file_notes = _transforms_views(path, minimum)
        notes += file_notes
        for view in file_views:
            key = view.path.resolve()
            if key in seen:
                repeated[name] += 1
                continue
            seen.add(key)
            view.split = split
            views.append(view)
    counts = Counter(v.split for v in views)
    notes.append(
        f"splits from the NeRF-synthetic split files: {counts['train']} train, "
        f"{counts['test']} test (held out)"
    )
    for name, n in repeated.items():
        notes.append(f"{name} repeats {n} image(s) of an earlier split file: counted once")
    return Capture("transforms", views, has_poses=True, notes=notes)


def _transforms_views(path: Path, minimum: int = MIN_VIEWS) -> tuple[list[SourceView], list[str]]:
    """The views of one transforms.json-style file and its notes (images it lists that do not
    exist are skipped with a warning unless fewer than `minimum` remain)."""
    data = read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise SineError(
            f"unknown camera format: {path} is JSON but not a NeRF/nerfstudio transforms.json "
            "(no 'frames' list)"
        )
    base = path.parent
    files: dict[str, Path] = {}
    missing = []
    for frame in data["frames"]:
        if "file_path" not in frame:
            raise SineError(f"{path}: every frame needs a 'file_path'")
        found = _resolve_image(base, frame["file_path"])
        if found is None:
            missing.append(frame["file_path"])
        else:
            files[frame["file_path"]] = found
    notes = _missing_note(path, missing, len(files), f"paths are relative to {base}", minimum)
    if missing:
        data = {**data, "frames": [f for f in data["frames"] if f["file_path"] in files]}
    if not data["frames"] and minimum == 0:
        return [], notes
    sizes = _probe_files(list(files.values()))
    image_sizes = {fp: sizes[p] for fp, p in files.items()}
    cams = cameras_from_transforms(data, image_sizes)
    depth_scale = float(data.get("depth_unit_scale_factor", 1e-3))
    views = []
    for frame, (fp, cam) in zip(data["frames"], cams, strict=True):
        view = SourceView(files[fp].stem, str(files[fp]), path=files[fp], camera=cam)
        for key, attr in (("mask_path", "mask"), ("depth_file_path", "depth")):
            if frame.get(key):
                p = base / frame[key]
                if not p.is_file():
                    raise SineError(f"{path}: {key} {frame[key]} of {fp} does not exist")
                setattr(view, attr, p)
        view.depth_scale = depth_scale
        views.append(view)
    return views, notes


def _read_colmap(capture: Path, cfg: IngestConfig) -> Capture:
    model = _find_colmap_model(capture)
    if model is None:
        raise SineError(
            f"no COLMAP model in {capture}: expected cameras.bin/txt + images.bin/txt in it or "
            "in sparse/0"
        )
    cams = read_colmap_model(model)
    if not cams:
        raise SineError(f"the COLMAP model in {model} has no registered images")
    image_dir = None
    for cand in (model, model.parent, model.parent.parent, model.parent.parent.parent):
        for d in (cand / "images", cand):
            if (d / cams[0][0]).is_file():
                image_dir = d
                break
        if image_dir is not None:
            break
    if image_dir is None:
        raise SineError(
            f"cannot find the images of the COLMAP model {model} (looked for {cams[0][0]} in an "
            "images/ folder beside or above it)"
        )
    missing = [n for n, _ in cams if not (image_dir / n).is_file()]
    cams = [(n, c) for n, c in cams if (image_dir / n).is_file()]
    views = [
        SourceView(Path(n).stem, str(image_dir / n), path=image_dir / n, camera=c) for n, c in cams
    ]
    notes = [f"COLMAP model {model}", *_missing_note(model, missing, len(cams), str(image_dir))]
    unregistered = len(_image_files(image_dir, strict=False)) - len(cams)
    if unregistered > 0:
        notes.append(f"{unregistered} image(s) in {image_dir} have no pose in the model: skipped")
    return Capture("colmap", views, has_poses=True, notes=notes)


def _read_middlebury(capture: Path, cfg: IngestConfig) -> Capture:
    pars = sorted(capture.glob("*_par.txt")) if capture.is_dir() else [capture]
    if not pars:
        raise SineError(f"format 'middlebury' needs a *_par.txt in {capture}")
    rows = read_middlebury_par(pars[0])
    base = pars[0].parent
    missing = [name for name, *_ in rows if not (base / name).is_file()]
    rows = [row for row in rows if (base / row[0]).is_file()]
    sizes = _probe_files([base / name for name, *_ in rows])
    views = []
    for name, K, R, t in rows:
        w, h = sizes[base / name]
        cam = camera_from_krt(K, R, t, w, h, name)
        views.append(SourceView(Path(name).stem, str(base / name), path=base / name, camera=cam))
    notes = [f"cameras from {pars[0].name}"] + (
        [f"ignored {', '.join(p.name for p in pars[1:])}"] if len(pars) > 1 else []
    )
    notes += _missing_note(pars[0], missing, len(rows), str(base))
    return Capture("middlebury", views, has_poses=True, notes=notes)


def _read_neus(capture: Path, cfg: IngestConfig) -> Capture:
    root = capture.parent if capture.is_file() else capture
    npz_path = root / "cameras_sphere.npz"
    if not npz_path.is_file():
        raise SineError(f"format 'neus' needs {npz_path}")
    image_dir = next((root / d for d in ("image", "images") if (root / d).is_dir()), None)
    if image_dir is None:
        raise SineError(f"NeuS/IDR capture {root} has no image/ (or images/) folder")
    files = _image_files(image_dir)
    sizes = _probe_files(files)
    with np.load(npz_path) as npz:
        cams, scale_mat = cameras_from_neus(npz, [sizes[p] for p in files])
    mask_dir = next((root / d for d in ("mask", "masks") if (root / d).is_dir()), None)
    masks = _image_files(mask_dir) if mask_dir else []
    by_stem = {p.stem: p for p in masks}
    views = []
    for i, (p, cam) in enumerate(zip(files, cams, strict=True)):
        mask = by_stem.get(p.stem) or (masks[i] if len(masks) == len(files) else None)
        views.append(SourceView(p.stem, str(p), path=p, camera=cam.replace(name=p.name), mask=mask))
    r, c = float(scale_mat[0, 0]), scale_mat[:3, 3]
    extra = {"source_normalization": {"scale": 1.0 / r, "center": [float(x) for x in c]}}
    return Capture("neus", views, has_poses=True, extra=extra)


def _read_projections(capture: Path, cfg: IngestConfig) -> Capture:
    folder = _image_folder(capture) if capture.is_dir() else None
    if folder is None:
        raise SineError(f"format 'projections' needs a folder of images; none in {capture}")
    files = _image_files(folder)
    pfiles = {p: _projection_file(p) for p in files}
    missing = [p.name for p, q in pfiles.items() if q is None]
    if missing:
        raise SineError(
            f"no projection matrix file (<stem>_P.txt or <stem>.P) for {_short_list(missing)} "
            f"in {folder}: give one per image, or remove the others to ingest images only"
        )
    shared = [q.name for q, n in Counter(pfiles.values()).items() if n > 1]
    if shared:
        raise SineError(
            f"several images match the same projection file ({_short_list(shared)}) in "
            f"{folder}: name them so that each image has its own <stem>_P.txt"
        )
    sizes = _probe_files(files)
    views = []
    for p in files:
        P = _read_projection_matrix(pfiles[p])
        cam = camera_from_projection(P, *sizes[p], name=p.name)
        views.append(SourceView(p.stem, str(p), path=p, camera=cam))
    return Capture("projections", views, has_poses=True)


READERS = {
    "images": _read_images,
    "video": _read_video,
    "transforms": _read_transforms,
    "colmap": _read_colmap,
    "middlebury": _read_middlebury,
    "neus": _read_neus,
    "projections": _read_projections,
}


def _missing_note(
    source: Path, missing: list[str], present: int, where: str, minimum: int = MIN_VIEWS
) -> list[str]:
    """A warning (printed and kept in captures.json's notes) for images a pose file lists that
    do not exist: the capture goes on with the ones that do, unless fewer than `minimum`."""
    if not missing:
        return []
    if present < minimum:
        raise SineError(
            f"{source} lists {len(missing) + present} images but only {present} exist "
            f"({where}; missing: {_short_list(missing)}); a reconstruction needs at least "
            f"{MIN_VIEWS}: put the images beside it"
        )
    note = (
        f"warning: {len(missing)} image(s) listed in {Path(source).name} do not exist "
        f"({_short_list(missing)}); using the {present} that do"
    )
    print(f"[ingest] {note}")
    return [note]


# ---- writing one view ---------------------------------------------------------------------
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


# ---- checks and helpers -------------------------------------------------------------------
def _check_config(cfg: IngestConfig) -> None:
    if cfg.width < 8:
        raise SineError(f"--width {cfg.width} is too small; use a working width of 8 px or more")
    if cfg.frames < MIN_VIEWS:
        raise SineError(f"--frames {cfg.frames}: sample at least {MIN_VIEWS} frames of a video")
    assign_splits(0, cfg.holdout_every)  # validates holdout_every
    background_rgb(cfg.background_color)  # validates background_color
    if cfg.format not in FORMATS:
        raise SineError(f"unknown camera format '{cfg.format}': use one of {', '.join(FORMATS)}")


def background_rgb(value) -> np.ndarray:
    """--background-color (white, black or R G B in [0, 1]) -> RGB [3] float64."""
    words = [
        str(v).strip().lower() for v in (value if isinstance(value, (list, tuple)) else [value])
    ]
    if len(words) == 1 and words[0] in BACKGROUND_NAMES:
        return np.array(BACKGROUND_NAMES[words[0]])
    try:
        rgb = np.array([float(w) for w in words])
    except ValueError:
        rgb = np.array([])
    if rgb.shape != (3,) or not np.all((rgb >= 0) & (rgb <= 1)):
        raise SineError(
            f"--background-color {' '.join(words)}: use white, black or three numbers R G B in "
            "[0, 1] (e.g. 0.5 0.5 0.5)"
        )
    return rgb


def _config_key(cfg: IngestConfig) -> dict:
    config = to_dict(cfg)
    config.pop("force", None)
    if cfg.masks is not None:
        config["masks"] = str(Path(cfg.masks).resolve())
    return config


def _refuse_another_capture(run: RunDir, source: str, force: bool) -> None:
    """A SineError when `run` already holds another capture (its own images, cameras, maybe a
    template and edits), unless --force replaces it."""
    if force:
        return
    if run.captures.is_file():
        try:
            old = read_json(run.captures).get("source")
        except SineError:
            return  # an unreadable record: ingest again
    elif run.cameras.is_file() or run.template.is_dir():
        old = "its cameras.json was not made by `sine ingest`"
    else:
        return
    if old is not None and old != source:
        raise SineError(
            f"{run.root} already holds another capture ({old}); write this one to a new --out, "
            "or give --force to replace it (its template and edits are then redone)"
        )


def _previous(run: RunDir, source: str, config: dict) -> dict | None:
    """The existing captures.json if it records this very ingest and its images exist."""
    if not run.captures.is_file():
        return None
    try:
        old = read_json(run.captures)
    except SineError:
        return None
    if old.get("source") != source or old.get("config") != config:
        return None
    if not all(run.image_path(r["name"]).is_file() for r in old.get("images", [])):
        return None
    return old


def _image_files(folder: Path, strict: bool = True) -> list[Path]:
    """Sorted image files of a folder; with `strict`, other non-sidecar files are an error."""
    images, others = [], []
    for p in sorted(folder.iterdir()):
        if p.name.startswith(".") or not p.is_file():
            continue
        suffix = p.suffix.lower()
        if suffix in IMAGE_SUFFIXES:
            images.append(p)
        elif suffix not in SIDECAR_SUFFIXES and suffix not in VIDEO_SUFFIXES:
            others.append(p.name)
    if strict and others:
        raise SineError(
            f"{folder} holds files that are not images OpenCV can read: {_short_list(others)}; "
            f"convert them to PNG/JPEG or move them out of the capture"
        )
    return images


def _image_folder(capture: Path) -> Path | None:
    """The folder holding a capture's images: the capture itself or its images/ subfolder."""
    for folder in (capture, capture / "images", capture / "image"):
        if folder.is_dir() and _image_files(folder, strict=False):
            return folder
    return None


def _find_colmap_model(root: Path) -> Path | None:
    def is_model(d: Path) -> bool:
        return any(
            (d / f"cameras{ext}").is_file() and (d / f"images{ext}").is_file()
            for ext in (".bin", ".txt")
        )

    candidates = [root, root / "sparse" / "0", root / "sparse", root / "colmap" / "sparse" / "0"]
    if (root / "sparse").is_dir():
        candidates += sorted(d for d in (root / "sparse").iterdir() if d.is_dir())
    return next((d for d in candidates if d.is_dir() and is_model(d)), None)


def _projection_file(image: Path) -> Path | None:
    """<stem>_P.txt, <stem>.P (...) beside the image, else the projection file whose number is
    the image's leading number (images named `00012._c.png` beside `00012_P.txt`)."""
    for cand in (f"{image.stem}_P.txt", f"{image.stem}.P", f"{image.name}.P", f"{image.stem}.p"):
        if (image.parent / cand).is_file():
            return image.parent / cand
    number = re.match(r"\d+", image.stem)
    if number is None:
        return None
    for p in sorted(image.parent.iterdir()):
        m = re.fullmatch(r"(\d+)(_P\.txt|\.P|\.p)", p.name)
        if m and int(m.group(1)) == int(number.group(0)) and p.is_file():
            return p
    return None


def _read_projection_matrix(path: Path) -> np.ndarray:
    values = []
    for token in path.read_text().split():
        try:
            values.append(float(token))
        except ValueError:
            continue  # headers such as "CONTOUR"
    if len(values) != 12:
        raise SineError(
            f"{path}: expected the 12 numbers of a 3x4 projection matrix, found {len(values)}"
        )
    return np.array(values).reshape(3, 4)


def _resolve_image(base: Path, file_path: str) -> Path | None:
    p = base / file_path
    if p.is_file():
        return p
    if not p.suffix or p.suffix.lower() not in IMAGE_SUFFIXES:  # NeRF blender: "./train/r_0"
        for suffix in (".png", *IMAGE_SUFFIXES):
            q = p.with_name(p.name + suffix)
            if q.is_file():
                return q
    return None


def _probe_files(paths: list[Path]) -> dict[Path, tuple[int, int]]:
    """(width, height) of each image from its header; lists every unreadable file at once."""
    from PIL import Image

    sizes, bad = {}, []
    for p in paths:
        try:
            with Image.open(p) as im:
                sizes[p] = im.size
                continue
        except Exception:
            pass
        raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if raw is None:
            bad.append(p.name)
        else:
            sizes[p] = (raw.shape[1], raw.shape[0])
    if bad:
        raise SineError(
            f"cannot read these files as images (corrupt, empty or not images): "
            f"{_short_list(bad)}; fix or remove them"
        )
    return sizes


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


def _check_same_size(views, sizes, capture: Path) -> None:
    counts = Counter(sizes)
    if len(counts) <= 1:
        return
    parts = []
    for (w, h), n in counts.most_common():
        example = next(v.source for v, s in zip(views, sizes, strict=True) if s == (w, h))
        parts.append(f"{w}x{h}: {n} image(s), e.g. {Path(example).name}")
    raise SineError(
        f"images of mixed sizes in {capture} ({'; '.join(parts)}) and no per-image intrinsics: "
        "one capture needs one camera. Resize/crop them to one size, remove the odd ones, or give "
        "per-image cameras (transforms.json, COLMAP)"
    )


def _check_unique_stems(views: list[SourceView]) -> None:
    counts = Counter(v.stem for v in views)
    if all(n == 1 for n in counts.values()):
        return
    # e.g. train/r_0 and test/r_0: prefix the parent folder
    for v in views:
        if counts[v.stem] > 1 and v.path is not None:
            v.stem = f"{v.path.parent.name}_{v.stem}"
    dup = [s for s, n in Counter(v.stem for v in views).items() if n > 1]
    if dup:
        raise SineError(
            f"several images share the file stem {_short_list(dup)} (e.g. a.jpg and a.png); "
            "rename them so that every view has its own name"
        )


def _attach_user_masks(views: list[SourceView], folder: Path) -> None:
    if not folder.is_dir():
        raise SineError(f"--masks {folder} is not a folder")
    by_stem: dict[str, Path] = {}
    for p in _image_files(folder, strict=False):
        by_stem.setdefault(p.stem, p)
    missing = []
    for v in views:
        src_stem = Path(v.source.split("#")[0]).stem if v.path is None else v.path.stem
        mask = by_stem.get(v.stem) or by_stem.get(src_stem)
        if mask is None and v.path is not None:
            mask = by_stem.get(v.path.name)  # masks named like "img.jpg.png"
        if mask is None:
            missing.append(v.stem)
        v.mask = mask
    if missing:
        raise SineError(
            f"--masks {folder} has no mask for {len(missing)} of {len(views)} images: "
            f"{_short_list(missing)} (masks are matched by file stem, e.g. img_001.jpg -> "
            "img_001.png); add them or leave --masks out to compute masks automatically"
        )


def _remove_stale(run: RunDir, records: list[dict]) -> None:
    """Drops working files of an earlier ingest that this one did not write."""
    written = set()
    for r in records:
        written.add(run.image_path(r["name"]))
        if r["mask"]:
            written.add(run.mask_path(r["name"]))
        if r["depth"]:
            written.add(run.depth_path(r["name"]))
    for folder in (run.images, run.masks, run.depth):
        if folder.is_dir():
            for p in folder.iterdir():
                if p.is_file() and p not in written:
                    p.unlink()


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _short_list(items, n: int = 8) -> str:
    items = [str(x) for x in items]
    return ", ".join(items[:n]) + (f" and {len(items) - n} more" if len(items) > n else "")
