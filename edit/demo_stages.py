"""What the stages of `sine demo` (edit.demo) share: the names of the demo's edits in the run,
the stage options of the full run and of --fast (FULL, FAST), the bookkeeping that skips
finished output stages (Record, mtimes) and times every stage (Clock), and the check for the
proxy's mirror plane (`has_mirror_plane`)."""

from __future__ import annotations

import time
from pathlib import Path

from render.io import read_json, write_json

EDIT_NAME = "geometric"  # RUN/edits/geometric, learnt from the synth's edits/geometric view K
TEXTURE_NAME = "texture"  # RUN/edits/texture, learnt from a recoloured capture of view K
MASKS_EDIT = "demo"  # RUN/edits/demo/semantic_masks (the masks stage)

# SfM on a turntable of a symmetric, sparsely textured object: neighbours only (no matches
# between mirror-image views), affine SIFT with domain-size pooling.
RECON = {"exhaustive_below": 0, "sfm_affine_shape": True, "sfm_domain_size_pooling": True}
# Defaults of the full run and of --fast: views, working width, orbit frames, summary rows, and
# the stage options that differ from each command's defaults. The geometric edit mirrors its
# handles across the car's mirror plane (`sine edit --symmetric`): the taller cabin is a
# symmetric edit seen from one side (held-out PSNR +1.0 dB, bench/HISTORY.md "Demo").
FULL = {
    "views": 36,
    "run_width": 256,
    "orbit": 48,
    "rows": 6,
    "recon": {**RECON, "sequential_overlap": 5},
    "fit": {"iterations": 600, "batch_rays": 1024},
    "features": {},
    "edit": {"symmetric": True},
    "texture": {},
}
FAST = {
    "views": 24,
    "run_width": 128,
    "orbit": 24,
    "rows": 5,
    "recon": {
        **RECON,
        "sequential_overlap": 4,
        "tsdf_voxel_size": 1 / 128,
        "target_triangles": 20_000,
    },
    "fit": {"iterations": 300, "batch_rays": 512, "log2_table": 15, "previews": 2},
    "features": {"iterations": 150, "batch_rays": 2048, "log2_table": 13, "previews": 1},
    "edit": {"iterations": 120, "previews": 0, "symmetric": True},
    "texture": {"iterations": 80, "previews": 0},
}


# ---- stage bookkeeping (outputs that are not training stages) ------------------------------
class Record:
    """OUT/demo_state.json: the key (options + input files' mtimes) each output stage was made
    with; a stage is skipped when its key is unchanged and its outputs exist."""

    def __init__(self, out: Path, force: bool):
        self.path = out / "demo_state.json"
        self.state = read_json(self.path) if self.path.is_file() and not force else {}

    def done(self, name: str, key: dict, outputs: list[Path]) -> bool:
        return self.state.get(name) == key and all(Path(p).exists() for p in outputs)

    def record(self, name: str, key: dict) -> None:
        self.state[name] = key
        write_json(self.path, self.state)


def mtimes(*paths: Path) -> dict[str, int]:
    return {str(p): p.stat().st_mtime_ns if p.exists() else 0 for p in paths}


class Clock:
    """Seconds per stage. `seconds`: this invocation; `work()`: the seconds of the invocation that
    did each stage's work (a skipped stage keeps the one from the previous demo_summary.json)."""

    def __init__(self, out: Path):
        previous = out / "demo_summary.json"
        self.previous = read_json(previous).get("seconds_work", {}) if previous.is_file() else {}
        self.seconds: dict[str, float] = {}
        self.skipped: set[str] = set()
        self.t0 = time.perf_counter()

    def start(self, name: str) -> None:
        print(f"\n== sine demo: {name} ==", flush=True)
        self.seconds[name] = time.perf_counter()

    def finish(self, name: str, skipped: bool = False) -> None:
        if skipped:
            print(f"{name}: already done with these options")
            self.skipped.add(name)
        self.seconds[name] = round(time.perf_counter() - self.seconds[name], 1)

    def work(self) -> dict[str, float]:
        return {
            k: self.previous.get(k, v) if k in self.skipped else v for k, v in self.seconds.items()
        }


def has_mirror_plane(run) -> bool:
    """Whether the run's proxy mesh has a clear mirror plane (what `sine edit --symmetric` needs)."""
    from edit.shape_prior import proxy_mirror_plane

    return proxy_mirror_plane(run) is not None
