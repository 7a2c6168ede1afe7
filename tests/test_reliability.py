"""Nothing lost: locks on what a stage writes, readable files, damaged results redone, read-only
runs, inputs compared by content, clear refusals that leave nothing behind, full disks."""

from __future__ import annotations

import errno
import os
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from feature_run_helpers import TINY_FIT, TINY_GEOMETRY_EDIT

import sine_cli
from edit.geometry_config import GeometryEditConfig
from edit.geometry_edit import run_geometry_edit
from edit.targets import write_rgba
from recon.fit import fit_template, load_fitted
from recon.fit_config import FitConfig
from render import io
from render.errors import SineError
from render.io import read_image, write_json

ROOT = Path(__file__).resolve().parents[1]
VIEW = 2


def flags(options: dict) -> list[str]:
    """A config dict as `sine` command-line flags."""
    out = []
    for key, value in options.items():
        flag = "--" + key.replace("_", "-")
        if isinstance(value, bool):
            out.append(flag if value else "--no-" + key.replace("_", "-"))
        else:
            out += [flag, str(value)]
    return out


def sine(*args, user: int | None = None, **kwargs) -> subprocess.CompletedProcess:
    """`sine ARGS` in a subprocess (as `user`, a uid, when given)."""
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "sine_cli", *map(str, args)]
    if user is not None:
        cmd = ["setpriv", f"--reuid={user}", f"--regid={user}", "--clear-groups", *cmd]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=kwargs.get("cwd", ROOT), env=env)


def one_line_error(proc: subprocess.CompletedProcess) -> str:
    """The single `error:` line of a refused command (asserting it is one, without traceback)."""
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    return lines[0]


@pytest.fixture
def run(tiny_fitted_run, tmp_path):
    """A copy of the tiny fitted run with a geometric target for view VIEW (t.png)."""
    run = tmp_path / "run"
    shutil.copytree(tiny_fitted_run, run)
    assert (
        sine(
            "target", run, "--view", VIEW, "--warp", "32,20>32,12", "--out", tmp_path / "t.png"
        ).returncode
        == 0
    )
    return run


def edit(run: Path, name: str, target: Path, **options) -> dict:
    cfg = GeometryEditConfig(**{**TINY_GEOMETRY_EDIT, **options})
    return run_geometry_edit(run, VIEW, target, name, cfg, progress=False)


# ---- locks -------------------------------------------------------------------------------------
HOLDER = """
import sys, time
from render.locks import lock_entry
with lock_entry(sys.argv[1], "edit x"):
    print("held", flush=True)
    time.sleep(60)
"""


def test_a_second_process_is_refused_at_once_and_the_lock_dies_with_its_holder(tmp_path):
    from render import locks

    target = tmp_path / "edits" / "x"
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(target)],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        t0 = time.perf_counter()
        with pytest.raises(SineError, match=rf"edit x is busy: process {holder.pid} \(") as exc:
            with locks.lock_entry(target, "edit x"):
                pass
        assert time.perf_counter() - t0 < 1.0
        assert "wait for it to finish" in str(exc.value)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    with locks.lock_entry(target, "edit x"):  # the OS released it with the killed process
        with locks.lock_entry(target, "edit x"):  # and locks nest within one process
            assert (tmp_path / "edits" / ".x.lock").read_text().startswith(f"{os.getpid()} ")


def test_a_lock_in_a_new_folder_leaves_nothing_when_the_block_wrote_nothing(tmp_path):
    from render import locks

    with pytest.raises(SineError, match="bad input"):
        with locks.lock_folder(tmp_path / "new_run", "run"):
            raise SineError("bad input")
    assert not (tmp_path / "new_run").exists()
    with locks.lock_folder(tmp_path / "kept", "run"):
        (tmp_path / "kept" / "cameras.json").write_text("{}")
    assert sorted(p.name for p in (tmp_path / "kept").iterdir()) == [".sine.lock", "cameras.json"]


@pytest.mark.slow
def test_two_edits_of_one_name_the_second_is_refused_and_the_first_completes(run, tmp_path):
    options = flags({**TINY_GEOMETRY_EDIT, "iterations": 400, "log_every": 50})
    args = ["edit", run, "--target", tmp_path / "t.png", "--view", VIEW, "--name", "x", "--quiet"]
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "PYTHONPATH": str(ROOT)}
    first = subprocess.Popen(
        [sys.executable, "-m", "sine_cli", *map(str, args), *options],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    lock = run / "edits" / ".x.lock"
    deadline = time.time() + 60
    while not (lock.is_file() and lock.read_text().startswith(str(first.pid))):
        assert time.time() < deadline and first.poll() is None, first.communicate()
        time.sleep(0.05)
    t0 = time.perf_counter()
    second = sine(*args, *options)
    seconds = time.perf_counter() - t0
    line = one_line_error(second)
    assert f"edit x of {run} is busy: process {first.pid} (`sine edit" in line
    assert seconds < 15  # python, torch and the run's checks; no training
    assert not (run / "edits" / "x").exists() or first.poll() is not None
    out, err = first.communicate(timeout=600)
    assert first.returncode == 0, err
    done = run / "edits" / "x"
    for name in ("edit_field.pt", "checkpoint.pt", "edit.json", "metrics.json", "target.png"):
        assert (done / name).is_file(), name
    assert not done.with_name("x.partial").exists()
    again = sine(*args, *options)
    assert again.returncode == 0 and "already done" in again.stdout


# ---- files: modes, full disks ------------------------------------------------------------------
def test_files_get_the_mode_the_umask_gives(tmp_path):
    old = os.umask(0o022)
    try:
        write_json(tmp_path / "a.json", {"a": 1})
        io.write_image(tmp_path / "a.png", np.zeros((4, 4, 3), np.float32))
        io.save_torch(tmp_path / "a.pt", {"x": 1})
        os.umask(0o077)
        write_json(tmp_path / "b.json", {"b": 2})
    finally:
        os.umask(old)
    for name in ("a.json", "a.png", "a.pt"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o644, name
    assert stat.S_IMODE((tmp_path / "b.json").stat().st_mode) == 0o600


def test_a_full_disk_is_one_line_and_the_previous_file_stays(tmp_path, monkeypatch):
    path = tmp_path / "metrics.json"
    write_json(path, {"psnr": 30.0})

    def full(*_):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(io.os, "replace", full)
    with pytest.raises(SineError, match=r"cannot write .*metrics.json \(no space left"):
        write_json(path, {"psnr": 0.0})
    assert io.read_json(path) == {"psnr": 30.0}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json"]  # no temporary left


def test_a_full_disk_during_a_fit_keeps_the_finished_template(run, monkeypatch, capsys):
    before = (run / "template" / "field.pt").read_bytes()
    real_replace = os.replace

    def full_at_publish(src, dst):  # the disk fills up as the new template is written
        if str(dst).endswith("field.pt"):
            raise OSError(errno.ENOSPC, "No space left on device")
        real_replace(src, dst)

    monkeypatch.setattr(io.os, "replace", full_at_publish)
    fit = {**TINY_FIT, "iterations": 12, "detail_steps": 0, "eval_views": 1, "threads": 1}
    code = sine_cli.main(["fit", str(run), "--force", "--quiet", *flags(fit)])
    assert code == 2
    assert "(no space left on the device" in capsys.readouterr().err
    assert (run / "template" / "field.pt").read_bytes() == before


# ---- damaged results ---------------------------------------------------------------------------
def test_a_truncated_template_names_the_command_that_rebuilds_it_and_fit_redoes_it(run, capsys):
    field = run / "template" / "field.pt"
    field.write_bytes(field.read_bytes()[:100_000])
    with pytest.raises(SineError) as exc:
        load_fitted(run)
    message = str(exc.value)
    assert message == (
        f"cannot read {field}: it is truncated or corrupt; make it again with "
        f"`sine fit {run} --force`"
    )
    rendered = sine("render", run, "--views", "test", "--out", run.parent / "r", "--quiet")
    assert f"`sine fit {run} --force`" in one_line_error(rendered)
    metrics = fit_template(run, FitConfig(**TINY_FIT), progress=False)
    assert not metrics.get("skipped")  # not "already done": its output does not load
    assert "field.pt does not load: it is truncated or corrupt" in capsys.readouterr().out
    load_fitted(run)


def test_a_template_of_another_format_version_is_refused_and_fitted_again(run, capsys):
    from recon import formats

    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(formats.FORMAT_VERSIONS, "fit", 2)
        with pytest.raises(SineError) as exc:
            load_fitted(run)
        assert str(exc.value) == (
            f"{run / 'template' / 'field.pt'} is out of date (written in format version 1, this "
            f"version writes 2); run `sine fit {run} --force`"
        )
        capsys.readouterr()
        metrics = fit_template(run, FitConfig(**TINY_FIT), progress=False)
        assert not metrics.get("skipped")
        assert io.read_json(run / "template" / "metrics.json")["format_version"] == 2
        assert "(written in format version 1, this version writes 2): training again" in (
            capsys.readouterr().out
        )
        load_fitted(run)


def test_an_edit_of_another_format_version_is_refused_and_made_again(run, tmp_path, capsys):
    from recon import formats

    edit(run, "x", tmp_path / "t.png")
    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(formats.FORMAT_VERSIONS, "edit", 2)
        line = cli_error(
            capsys, "render", run, "--edit", "x", "--views", "test", "--out", tmp_path / "r"
        )
        assert "(written in format version 1, this version writes 2); run `sine edit" in line
        assert not edit(run, "x", tmp_path / "t.png").get("skipped")
        assert "written in format version 1" in capsys.readouterr().out


def test_the_saved_config_reproduces_the_fit_and_the_edit(run, tmp_path, capsys):
    saved = run / "template" / "config.toml"
    assert "iterations = 40" in saved.read_text()
    capsys.readouterr()
    assert sine_cli.main(["fit", str(run), "--config", str(saved), "--quiet"]) == 0
    assert "fit: already done with these options" in capsys.readouterr().out
    edit(run, "x", tmp_path / "t.png", iterations=3)
    settings = run / "edits" / "x" / "config.toml"
    assert "iterations = 3" in settings.read_text()
    words = ["edit", run, "--target", tmp_path / "t.png", "--view", VIEW, "--name", "x"]
    assert sine_cli.main([*map(str, words), "--config", str(settings), "--quiet"]) == 0
    assert "edit x: already done with these options" in capsys.readouterr().out


def test_a_file_of_python_objects_is_never_loaded_and_torch_advice_is_not_repeated(tmp_path):
    import torch

    path = tmp_path / "field.pt"
    torch.save({"field": Path("x")}, path)  # a pickled object, not a tensor
    with pytest.raises(SineError) as exc:
        io.load_torch(path, rebuild="`sine fit RUN --force`")
    assert str(exc.value) == (
        f"cannot read {path}: it holds Python objects, which are never loaded from a file; "
        "make it again with `sine fit RUN --force`"
    )
    assert "weights_only" not in str(exc.value)


# ---- read-only runs ----------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.skipif(os.geteuid() != 0 or not shutil.which("setpriv"), reason="needs root")
def test_a_read_only_run_reads_but_refuses_to_write_in_one_line(run, tmp_path):
    probe = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]
    probe += [sys.executable, "-c", "import sine_cli"]
    if subprocess.run(
        probe, cwd=ROOT, capture_output=True, env={**os.environ, "PYTHONPATH": str(ROOT)}
    ).returncode:
        pytest.skip("the user nobody cannot run this checkout's Python here")
    edit(run, "done", tmp_path / "t.png")
    # a world-readable copy that only root may write; commands run as the user nobody
    shared = Path(tempfile.mkdtemp(prefix="sine_readonly_"))
    try:
        os.chmod(shared, 0o755)
        shutil.copytree(run, shared / "run")
        shutil.copy(tmp_path / "t.png", shared / "t.png")
        (shared / "out").mkdir()
        os.chmod(shared / "out", 0o777)
        for path in [shared / "run", *(shared / "run").rglob("*")]:
            os.chmod(path, 0o755 if path.is_dir() else 0o644)
        before = io.artefact_digest(shared / "run")
        nobody = 65534
        args = ["--view", VIEW, "--quiet", *flags(TINY_GEOMETRY_EDIT)]
        again = sine(
            "edit", "run", "--target", "t.png", "--name", "done", *args, user=nobody, cwd=shared
        )
        assert again.returncode == 0 and "already done" in again.stdout, again.stderr
        new = sine(
            "edit", "run", "--target", "t.png", "--name", "new", *args, user=nobody, cwd=shared
        )
        assert "(permission denied: make the folder writable" in one_line_error(new)
        render = ["render", "run", "--edit", "done", "--views", "test", "--out", "out/r", "--quiet"]
        assert sine(*render, user=nobody, cwd=shared).returncode == 0
        assert (shared / "out" / "r" / "rgb").is_dir()
        assert io.artefact_digest(shared / "run") == before
    finally:
        shutil.rmtree(shared)


# ---- inputs, checks and work folders -----------------------------------------------------------
def test_an_edit_is_done_whatever_the_spelling_of_its_target_path(run, tmp_path, monkeypatch):
    first = edit(run, "x", tmp_path / "t.png")
    monkeypatch.chdir(tmp_path)
    again = edit(run, "x", Path("t.png"))  # relative, same file
    assert again.get("skipped") and again["train_seconds"] == first["train_seconds"]
    shutil.copy(tmp_path / "t.png", tmp_path / "copy.png")  # another file, the same content
    assert edit(run, "x", tmp_path / "copy.png").get("skipped")


def test_a_transparent_target_is_told_and_leaves_no_work_folder(run, tmp_path):
    clear = tmp_path / "clear.png"
    write_rgba(clear, read_image(tmp_path / "t.png"), np.zeros((64, 64), np.float32))
    proc = sine("edit", run, "--target", clear, "--view", VIEW, "--name", "clear", "--quiet")
    line = one_line_error(proc)
    assert "has an empty silhouette: it is fully transparent" in line
    assert not (run / "edits").exists()  # no work folder, not even the lock (the first edit)


def test_an_interrupted_edit_says_it_resumes_and_force_says_what_it_removes(run, tmp_path, capsys):
    cfg = GeometryEditConfig(**TINY_GEOMETRY_EDIT)
    assert run_geometry_edit(run, VIEW, tmp_path / "t.png", "x", cfg, stop_at=12, progress=False)
    capsys.readouterr()
    edit(run, "x", tmp_path / "t.png")
    assert f"edit x: resuming from step 12 of {cfg.iterations}" in capsys.readouterr().out
    run_geometry_edit(run, VIEW, tmp_path / "t.png", "y", cfg, stop_at=12, progress=False)
    capsys.readouterr()
    cfg_force = GeometryEditConfig(**{**TINY_GEOMETRY_EDIT, "iterations": 14})
    run_geometry_edit(run, VIEW, tmp_path / "t.png", "y", cfg_force, force=True, progress=False)
    out = capsys.readouterr().out
    assert (
        f"edit y: --force: removing the interrupted run in {run / 'edits' / 'y.partial'} (" in out
    )
    assert " MB)" in out and not (run / "edits" / "y.partial").exists()


def test_the_edits_listed_when_one_is_missing_are_finished_ones(run, tmp_path):
    edit(run, "done", tmp_path / "t.png")
    (run / "edits" / "stale.partial").mkdir()
    proc = sine("render", run, "--edit", "nope", "--out", tmp_path / "r", "--quiet")
    assert "(edits there: done);" in one_line_error(proc)


# ---- outputs and inputs that must not meet -----------------------------------------------------
def cli_error(capsys, *args) -> str:
    """The one-line error of `sine ARGS` run in this process (exit code 2)."""
    capsys.readouterr()
    assert sine_cli.main([str(a) for a in args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


def test_outputs_never_overwrite_the_run(run, tmp_path, capsys):
    image = run / "images" / "r_001.png"
    before = image.read_bytes()
    assert "would overwrite the run's own images" in cli_error(
        capsys, "snapshot", run, "--view", VIEW, "--out", image
    )
    assert "is the run directory itself" in cli_error(
        capsys, "render", run, "--views", "test", "--out", run, "--quiet"
    )
    assert "would overwrite the run's own proxy_mesh.ply" in cli_error(
        capsys, "export", run, "--out", run / "proxy_mesh.ply"
    )
    assert image.read_bytes() == before
    (tmp_path / "folder.ply").mkdir()
    assert "is a folder: give the name of a file" in cli_error(
        capsys, "export", run, "--out", tmp_path / "folder.ply"
    )
    (tmp_path / "file").write_text("x")
    assert "is an existing file; give a folder" in cli_error(
        capsys, "render", run, "--views", "test", "--out", tmp_path / "file", "--quiet"
    )
    assert "--chunk must be >= 1" in cli_error(
        capsys, "render", run, "--views", "test", "--out", tmp_path / "r", "--chunk", 0
    )


def test_a_truncated_proxy_is_refused_with_the_command_that_rebuilds_it(run, tmp_path, capsys):
    proxy = run / "proxy_mesh.ply"
    proxy.write_bytes(proxy.read_bytes()[: proxy.stat().st_size // 2])
    rebuild = f"make it again with `sine recon CAPTURE --out {run} --force`"
    assert rebuild in cli_error(capsys, "export", run, "--out", tmp_path / "m.ply")
    fit = {**TINY_FIT, "iterations": 5, "detail_steps": 0, "threads": 1}
    assert rebuild in cli_error(capsys, "fit", run, "--force", "--quiet", *flags(fit))


def test_a_texture_edit_takes_a_target_or_a_reference(run, tmp_path, capsys):
    target = tmp_path / "t.png"
    assert "not both" in cli_error(
        capsys,
        "edit",
        run,
        "--mode",
        "texture",
        "--view",
        VIEW,
        "--target",
        target,
        "--reference",
        target,
    )


def test_ingest_keeps_captures_and_runs_apart(tmp_path, capsys):
    from recon.synth import SynthConfig, synthesize

    capture = tmp_path / "capture"
    synthesize(
        SynthConfig(out=capture, procedural="toycar", views=6, width=32, height=32, supersample=1),
        progress=False,
    )
    before = io.artefact_digest(capture)
    assert "overlap" in cli_error(capsys, "ingest", capture, "--out", capture)
    assert "overlap" in cli_error(capsys, "ingest", capture, "--out", capture / "run")
    assert io.artefact_digest(capture) == before
    assert sine_cli.main(["ingest", str(capture), "--out", str(tmp_path / "run")]) == 0
    other = tmp_path / "other"
    shutil.copytree(capture, other)
    assert "already holds another capture" in cli_error(
        capsys, "ingest", other, "--out", tmp_path / "run"
    )
    broken = tmp_path / "broken"
    shutil.copytree(capture, broken)
    frame = broken / "images" / "r_003.png"
    frame.write_bytes(frame.read_bytes()[:200])  # a PNG cut short: refused half-way
    capsys.readouterr()
    assert sine_cli.main(["ingest", str(broken), "--out", str(tmp_path / "new")]) == 2
    assert not (tmp_path / "new").exists()  # no half-made run left behind


def test_a_failed_torch_write_is_one_line(tmp_path, monkeypatch):
    import torch

    def failing_save(*args, **kwargs):
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 64 vs 0")

    monkeypatch.setattr(torch, "save", failing_save)
    with pytest.raises(SineError, match=r"cannot write .*a\.pt \("):
        io.save_torch(tmp_path / "a.pt", {"x": 1})
    assert list(tmp_path.iterdir()) == []


def test_truncated_cameras_name_the_command_that_rebuilds_them(run, tmp_path, capsys):
    cameras = run / "cameras.json"
    cameras.write_text(cameras.read_text()[:500])
    line = cli_error(capsys, "render", run, "--views", "test", "--out", tmp_path / "r", "--quiet")
    assert "cameras.json is not valid JSON" in line
    assert line.endswith(f"make it again with `sine recon CAPTURE --out {run} --force`")


def test_outputs_on_another_file_system(run, capsys):
    """The atomic writes rename within the destination folder: a tmpfs output works."""
    shm = Path("/dev/shm")
    if not shm.is_dir() or os.stat(shm).st_dev == os.stat(run).st_dev:
        pytest.skip("no second file system here")
    out = Path(tempfile.mkdtemp(dir=shm))
    try:
        assert sine_cli.main(["export", str(run), "--out", str(out / "m.ply")]) == 0
        assert (
            sine_cli.main(
                ["render", str(run), "--views", "test", "--out", str(out / "r"), "--quiet"]
            )
            == 0
        )
        assert (out / "m.ply").stat().st_size > 0 and any((out / "r" / "rgb").iterdir())
        assert stat.S_IMODE((out / "m.ply").stat().st_mode) == 0o666 & ~_umask_now()
    finally:
        shutil.rmtree(out)


def _umask_now() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_ingest_refuses_to_overwrite_a_run_it_did_not_make(run, tmp_path, capsys):
    from recon.synth import SynthConfig, synthesize

    capture = tmp_path / "capture"
    synthesize(
        SynthConfig(out=capture, procedural="toycar", views=6, width=32, height=32, supersample=1),
        progress=False,
    )
    before = io.artefact_digest(run)
    line = cli_error(capsys, "ingest", capture, "--out", run)  # `run`: a synth folder, fitted
    assert "already holds another capture (its cameras.json was not made by `sine ingest`)" in line
    assert io.artefact_digest(run) == before


def test_a_truncated_edit_names_the_edit_command_that_rebuilds_it(run, tmp_path, capsys):
    edit(run, "x", tmp_path / "t.png")
    field = run / "edits" / "x" / "edit_field.pt"
    field.write_bytes(field.read_bytes()[:1000])
    line = cli_error(
        capsys, "render", run, "--edit", "x", "--views", "test", "--out", tmp_path / "r"
    )
    command = (
        f"sine edit {run} --name x --view {VIEW} --mode geometry --target {tmp_path / 't.png'}"
    )
    assert line.endswith(
        f"make it again with `{command} --force` (and the options it was made with)"
    )
