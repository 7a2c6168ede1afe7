"""Capture formats of `sine ingest`: a capture as read from disk (SourceView, Capture), the
format names and file conventions (FORMATS, SPLIT_FILES, ...), `detect_format`, and the file
helpers the readers share (image files, COLMAP model and projection-file lookup, image sizes
from the file headers)."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from render.cameras import Camera
from render.errors import SineError
from render.io import IMAGE_SUFFIXES

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


# ---- file helpers shared by the readers ------------------------------------------------
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


def _short_list(items, n: int = 8) -> str:
    items = [str(x) for x in items]
    return ", ".join(items[:n]) + (f" and {len(items) - n} more" if len(items) > n else "")
