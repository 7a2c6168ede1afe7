"""`sine recon`: turntable-aware reconstruction as idempotent stages.

ingest -> masks -> poses -> normalize -> depth -> proxy_mesh -> report. Each stage reads and
writes run-directory artefacts (atomically) and records itself and the options it used (the
ReconConfig options whose help starts with its name, see `stage_options`) in
`recon_state.json`; a finished stage is skipped on the next run unless `force` is set or its
options changed (then it says which, and runs again). A stage that runs invalidates every stage
after it. The per-stage results become `recon_report.json`.

The options are in recon.recon_config, the stage bodies in recon.recon_stages and
recon.recon_poses.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from recon import recon_poses, recon_stages
from recon.formats import FORMAT_VERSIONS, format_change
from recon.recon_config import STAGES, ReconConfig, stage_options
from recon.recon_stages import GIVEN_CAMERAS, GIVEN_DEPTH
from recon.rundir import RunDir
from render.cameras import Camera
from render.configs import to_dict, validate, write_settings
from render.errors import SineError
from render.io import read_json, read_mask, remove_partial_writes, write_json
from render.locks import lock_folder


class Pipeline:
    """Runs the stages on one run directory; `state` persists in recon_state.json."""

    def __init__(
        self, run: RunDir, cfg: ReconConfig, force: bool = False, ignore_poses: bool = False
    ):
        self.run, self.cfg, self.force, self.ignore_poses = run, cfg, force, ignore_poses
        self.state_path = run.root / "recon_state.json"
        self.state = read_json(self.state_path) if self.state_path.is_file() else {"stages": {}}
        change = format_change(self.state.get("format_version"), "recon")
        if change is not None and set(self.state["stages"]) - {"ingest"}:
            print(f"[recon] {self.state_path} is out of date ({change}): every stage runs again")
            self.state["stages"] = {k: v for k, v in self.state["stages"].items() if k == "ingest"}
        self.state["format_version"] = FORMAT_VERSIONS["recon"]

    # ---- bookkeeping ------------------------------------------------------------------------
    def _done(self, stage: str) -> bool:
        return bool(self.state["stages"].get(stage, {}).get("done"))

    def _record(self, stage: str, info: dict, seconds: float) -> None:
        later = STAGES[STAGES.index(stage) + 1 :]
        for name in later:
            self.state["stages"].pop(name, None)
        self.state["stages"][stage] = {"done": True, "seconds": round(seconds, 3), **info}
        if stage != "ingest":  # ingest keeps its own options (captures.json)
            options = stage_options(self.cfg, stage, self.ignore_poses)
            self.state.setdefault("options", {})[stage] = options
        write_json(self.state_path, self.state)

    def _changed(self, stage: str) -> list[str]:
        """Options of a finished stage that differ from the ones given now (an option added
        after the stage ran counts as its default)."""
        from recon.training import changed_options

        old = self.state.get("options", {}).get(stage, {})
        new = stage_options(self.cfg, stage, self.ignore_poses)
        defaults = stage_options(ReconConfig(), stage, self.ignore_poses)
        return changed_options({**defaults, **old}, new)

    def run_stage(self, stage: str, fn, *args) -> dict:
        if self._done(stage) and not self.force:
            changes = self._changed(stage)
            if not changes:
                print(f"[recon] {stage}: done already (use --force to redo)")
                return self.state["stages"][stage]
            print(f"[recon] {stage}: options changed ({'; '.join(changes)}): running it again")
        t0 = time.perf_counter()
        if STAGES.index(stage) < STAGES.index("normalize"):
            self.drop_given_inputs()  # new cameras and depth on the way: normalise those
        info = fn(*args) or {}
        self._record(stage, info, time.perf_counter() - t0)
        if stage == "normalize":  # recorded: the inputs it kept aside are no longer needed
            self.drop_given_inputs()
        print(f"[recon] {stage}: {time.perf_counter() - t0:.1f} s")
        return self.state["stages"][stage]

    # ---- helpers ----------------------------------------------------------------------------
    def drop_given_inputs(self) -> None:
        """Removes what an interrupted normalize stage kept of its inputs (see stage_normalize)."""
        (self.run.root / GIVEN_CAMERAS).unlink(missing_ok=True)
        if self.run.depth.is_dir():
            for kept in self.run.depth.glob(f"*{GIVEN_DEPTH}"):
                kept.unlink()

    def views(self) -> list[dict]:
        return [r for r in self.run.load_captures()["images"] if r.get("status", "ok") == "ok"]

    def masks_for(self, cameras) -> list[np.ndarray]:
        return [read_mask(self.run.mask_path(c.name)) for c in cameras]

    def thresholds(self):
        from recon.selfcheck import CheckThresholds

        return CheckThresholds(
            min_silhouette_iou=self.cfg.min_silhouette_iou,
            max_reprojection_px=self.cfg.max_reprojection_px,
        )

    # ---- stages: the bodies are in recon.recon_stages and recon.recon_poses -----------------
    def stage_masks(self) -> dict:
        return recon_stages.stage_masks(self)

    def check_poses(self, cams, reprojection_px=None) -> dict:
        return recon_poses.check_poses(self, cams, reprojection_px)

    def stage_poses(self) -> dict:
        return recon_poses.stage_poses(self)

    def sfm_params(self, partial: bool):
        return recon_poses.sfm_params(self, partial)

    def prior_intrinsics(self, views: list[dict]) -> dict[str, Camera]:
        return recon_poses.prior_intrinsics(self, views)

    def sfm_poses(self, views: list[dict], partial: bool = False):
        return recon_poses.sfm_poses(self, views, partial)

    def use_sfm(self, views: list[dict], result, frames: list[Camera], info: dict) -> None:
        recon_poses.use_sfm(self, views, result, frames, info)

    def verify_dataset_depth(self, fit, depth_paths: list[Path], poses: str, info: dict) -> None:
        recon_poses.verify_dataset_depth(self, fit, depth_paths, poses, info)

    def turntable_poses(self, views: list[dict], sfm) -> dict:
        return recon_poses.turntable_poses(self, views, sfm)

    def turntable_depth_scale(self, frames: list[Camera]):
        return recon_poses.turntable_depth_scale(self, frames)

    def stage_normalize(self) -> dict:
        return recon_stages.stage_normalize(self)

    def _hull(self, cams, masks, fresh: bool = False):
        return recon_stages._hull(self, cams, masks, fresh)

    def stage_depth(self) -> dict:
        return recon_stages.stage_depth(self)

    def stage_proxy_mesh(self) -> dict:
        return recon_stages.stage_proxy_mesh(self)

    def stage_report(self) -> dict:
        return recon_stages.stage_report(self)

    def gate(self, stage: str) -> None:
        """Stops the run (SineError) after a stage whose self-check found it poor, unless
        --accept-poor-poses; recon_report.json then says why (verdict 'poor')."""
        from recon.report import write_partial_report
        from recon.selfcheck import stop_message

        info = self.state["stages"].get(stage, {})
        check = info.get("self_check")
        if not check or check.get("verdict") == "ok":
            return
        if self.cfg.accept_poor_poses:
            print(f"[recon] {stage}: self-check poor, going on (--accept-poor-poses)")
            return
        pose_source = self.state["stages"].get("poses", {}).get("pose_source", "")
        if stage != "report":
            write_partial_report(self.run, self.state)
            # the proxy of earlier poses must not meet these cameras in `sine fit`.
            self.run.proxy_mesh.unlink(missing_ok=True)
        raise SineError(stop_message(stage, check["reasons"], pose_source))


def run_recon(capture: Path | None, run: RunDir, cfg: ReconConfig, ingest_cfg=None) -> dict:
    """Runs every stage (skipping finished ones unless ingest_cfg.force or their options
    changed); returns the report."""
    from recon.ingest import IngestConfig
    from render.io import require_directory

    validate(cfg)
    ingest_cfg = validate(ingest_cfg or IngestConfig())
    require_directory(run.root, "--out")
    new_run = not run.root.exists()  # before the lock makes the folder
    with lock_folder(run.root, f"run {run.root}"):
        return _recon(capture, run, cfg, ingest_cfg, new_run)


def _recon(capture: Path | None, run: RunDir, cfg: ReconConfig, ingest_cfg, new_run) -> dict:
    from recon.ingest import ingest_capture, removed_if_refused

    for folder in (run.root, run.images, run.masks, run.depth):  # writes a kill cut short
        remove_partial_writes(folder, recursive=False)
    pipe = Pipeline(run, cfg, force=ingest_cfg.force, ignore_poses=ingest_cfg.ignore_poses)
    if capture is not None:
        t0 = time.perf_counter()
        with removed_if_refused(run.root, new_run):  # later stages' failures keep their run
            summary = ingest_capture(capture, run, ingest_cfg)
        seconds = time.perf_counter() - t0
        if not summary.get("skipped") or not pipe._done("ingest"):
            pipe.drop_given_inputs()
            pipe._record("ingest", {"total_views": summary["views"]}, seconds)
        print(f"[recon] ingest: {'done already' if summary.get('skipped') else f'{seconds:.1f} s'}")
    elif not run.captures.is_file():
        raise SineError(f"{run.root} has no captures.json: give the capture to reconstruct")
    run.append_config("recon", {"recon": to_dict(cfg), "ingest": to_dict(ingest_cfg)})
    # the settings in effect (`sine recon --config` of this file reproduces the run)
    settings = {**to_dict(ingest_cfg), **to_dict(cfg)}
    settings.pop("force")  # what to redo, not how
    write_settings(run.root / "recon_config.toml", settings)
    for stage in STAGES[1:]:
        pipe.run_stage(stage, getattr(pipe, f"stage_{stage}"))
        pipe.gate(stage)
    return read_json(run.recon_report)
