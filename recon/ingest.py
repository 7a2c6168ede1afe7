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
The formats and their readers are in recon.capture_formats and recon.capture_readers, the
writing of one view in recon.capture_views.
"""

from __future__ import annotations

import contextlib
import shutil
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from recon.capture_formats import (
    FORMATS,
    MIN_VIEWS,
    SourceView,
    _image_files,
    _short_list,
    detect_format,
)
from recon.capture_readers import READERS, _read_capture
from recon.capture_views import _ingest_view, _probe_sizes
from recon.rundir import RunDir
from render.cameras import CameraSet
from render.configs import option, to_dict
from render.errors import SineError
from render.io import read_json
from render.locks import lock_folder

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
