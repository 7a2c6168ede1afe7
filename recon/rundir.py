"""The run directory (DESIGN.md section 3): the only contract between stages.

`RunDir` names every artefact's path, so no stage spells a file name itself, and appends each
stage's resolved config to `config.yaml`.
"""

from __future__ import annotations

import datetime
import re
from dataclasses import dataclass
from pathlib import Path

from render.cameras import CameraSet, load_cameras, save_cameras
from render.configs import to_dict
from render.errors import SineError
from render.io import read_json, read_triangle_mesh, read_yaml, write_json, write_yaml


@dataclass(frozen=True)
class RunDir:
    root: Path

    def __post_init__(self):
        object.__setattr__(self, "root", Path(self.root))

    # ---- paths ----------------------------------------------------------------------------
    @property
    def config(self) -> Path:
        return self.root / "config.yaml"

    @property
    def captures(self) -> Path:
        return self.root / "captures.json"

    @property
    def cameras(self) -> Path:
        return self.root / "cameras.json"

    @property
    def images(self) -> Path:
        return self.root / "images"

    @property
    def masks(self) -> Path:
        return self.root / "masks"

    @property
    def depth(self) -> Path:
        return self.root / "depth"

    @property
    def proxy_mesh(self) -> Path:
        return self.root / "proxy_mesh.ply"

    @property
    def recon_report(self) -> Path:
        return self.root / "recon_report.json"

    @property
    def template(self) -> Path:
        return self.root / "template"

    @property
    def features(self) -> Path:
        return self.root / "features"

    def edit(self, name: str) -> Path:
        """RUN/edits/NAME; a SineError for a name that is not a plain folder name (or that the
        run's own bookkeeping uses: hidden, *.partial, *.old)."""
        if (
            not re.fullmatch(r"[\w.+-]+", name)
            or name.startswith(".")
            or Path(name).suffix in (".partial", ".old")
        ):
            raise SineError(
                f"edit name {name!r}: use letters, digits, '_', '-', '+' and '.' (not first, and "
                "not ending in .partial or .old)"
            )
        return self.root / "edits" / name

    def image_path(self, name: str) -> Path:
        return self.images / name

    def mask_path(self, name: str) -> Path:
        return self.masks / (Path(name).stem + ".png")

    def depth_path(self, name: str) -> Path:
        return self.depth / (Path(name).stem + ".npy")

    def inputs(self, *names: str) -> dict[str, Path]:
        """{name: path} of artefacts a training stage is made from, named by their paths in the
        run (e.g. "template/field.pt"): the `Trainer` records their digests."""
        return {name: self.root / name for name in names}

    # ---- content --------------------------------------------------------------------------
    def require(self, what: str = "images") -> RunDir:
        """Fails with a clear message if this is not a run directory with `what` in it."""
        if not self.root.is_dir():
            raise SineError(
                f"run directory {self.root} does not exist (create it with `sine ingest` or `sine recon`)"
            )
        if what == "images" and not self.captures.is_file():
            raise SineError(
                f"{self.root} is not a run directory (no captures.json); run `sine ingest` first"
            )
        if what == "cameras" and not self.cameras.is_file():
            raise SineError(f"{self.root} has no cameras.json yet; run `sine recon` first")
        if what == "proxy_mesh" and not self.proxy_mesh.is_file():
            raise SineError(f"{self.root} has no proxy_mesh.ply yet; run `sine recon` first")
        return self

    def read_proxy(self, path: Path | None = None):
        """The Open3D proxy mesh at `path` (default: the run's proxy_mesh.ply), refused when
        missing or damaged, with the command that makes it again."""
        path = Path(path or self.proxy_mesh)
        rebuild = (
            f"`sine fit {self.root} --force`"
            if path.parent == self.template
            else f"`sine recon CAPTURE --out {self.root} --force`"
        )
        return read_triangle_mesh(path, rebuild)

    def refuse_output_inside(self, out: Path, option: str = "--out") -> None:
        """A SineError when `out` would write over what the run is made of (its images, masks,
        cameras, proxy, template, features or edits): outputs go elsewhere."""
        out, root = Path(out).resolve(), self.root.resolve()
        if out == root:
            raise SineError(f"{option} {out} is the run directory itself: give another path")
        if root not in out.parents:
            return
        parts = out.relative_to(root).parts
        first = parts[0]
        managed = {"images", "masks", "depth", "template", "features", "edits", "sfm", "labels"}
        if first in managed or (len(parts) == 1 and out.exists()):
            raise SineError(
                f"{option} {out} would overwrite the run's own {first}: write it elsewhere"
            )

    def load_cameras(self) -> CameraSet:
        self.require("cameras")
        try:
            return load_cameras(self.cameras)
        except (SineError, KeyError, TypeError, ValueError) as exc:
            why = str(exc) if isinstance(exc, SineError) else f"{self.cameras} is not a camera file"
            raise SineError(
                f"{why}; make it again with `sine recon CAPTURE --out {self.root} --force`"
            ) from None

    def save_cameras(self, cameras: CameraSet) -> None:
        save_cameras(self.cameras, cameras)

    def load_captures(self) -> dict:
        self.require("images")
        return read_json(self.captures)

    def save_captures(self, captures: dict) -> None:
        write_json(self.captures, captures)

    def append_config(self, stage: str, config) -> None:
        """Appends `stage`'s resolved config (a dataclass or dict) to config.yaml."""
        existing = read_yaml(self.config) if self.config.is_file() else None
        existing = existing or {"stages": []}
        entry = to_dict(config) if not isinstance(config, dict) else config
        existing["stages"].append(
            {
                "stage": stage,
                "time": datetime.datetime.now().isoformat(timespec="seconds"),
                "config": entry,
            }
        )
        write_yaml(self.config, existing)
