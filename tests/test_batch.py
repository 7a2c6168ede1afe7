"""`sine batch`: the batch file's checks, the jobs it plans, one job run by hand, and (slow) whole
batches on a local Ray: metrics equal to the CLI's, a broken capture that stops only itself, a
second run that does no work, a worker killed with SIGKILL whose task is retried."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from edit.batch_file import plan_jobs, read_batch
from edit.batch_stages import TOKEN, check_job, run_job
from render.errors import SineError

REPO = Path(__file__).resolve().parents[1]

TINY = """
[defaults]
recon = {{ width = 64 }}
fit = {{ iterations = {fit_steps}, batch_rays = 256, log2_table = 12, detail_steps = 0, previews = 0 }}
edit = {{ iterations = 10, previews = 0 }}
render = {{ orbit = 3 }}

[[capture]]
name = "car"
synth = {{ procedural = "toycar", views = 10, width = 64, height = 64, edit = ["geometric"] }}

[[capture]]
name = "mug"
synth = {{ procedural = "mug", views = 10, width = 64, height = 64, edit = ["geometric"] }}
fit = {{ iterations = {slow_steps}, checkpoint_every = 20 }}

[[capture]]
name = "broken"
source = "no/such/capture"

[[edit]]
capture = "car"
name = "taller"
view = "r_001.png"
target = "{{capture}}/edits/geometric/images/r_001.png"
mask = "{{capture}}/edits/geometric/masks/r_001.png"
outputs = ["ply", "video"]
eval = "{{capture}}/edits/geometric"

[[edit]]
capture = "mug"
name = "taller"
view = "r_001.png"
target = "{{capture}}/edits/geometric/images/r_001.png"
mask = "{{capture}}/edits/geometric/masks/r_001.png"
outputs = ["glb"]

[[edit]]
capture = "broken"
name = "any"
view = 0
target = "nowhere.png"
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "jobs.toml"
    path.write_text(text)
    return path


def tiny_batch(tmp_path: Path, fit_steps: int = 40, slow_steps: int = 40) -> Path:
    return write(tmp_path, TINY.format(fit_steps=fit_steps, slow_steps=slow_steps))


# ---- the batch file -----------------------------------------------------------------------
@pytest.mark.parametrize(
    "text, message",
    [
        ("[[capture]]\nname = 'a'\n", "give either source"),
        ("[[capture]]\nname = 'a'\nsource = 'x'\nsynth = {}\n", "give either source"),
        ("[[capture]]\nname = 'a'\nsource = 'x'\nfitt = {}\n", "unknown key 'fitt'"),
        ("[[capture]]\nname = 'a b'\nsource = 'x'\n", "needs a name of letters"),
        (
            "[[capture]]\nname = 'a'\nsource = 'x'\n[[capture]]\nname = 'a'\nsource = 'y'\n",
            "two captures",
        ),
        ("[job]\n", "unknown table 'job'"),
        (
            "[defaults]\nedits = {}\n[[capture]]\nname = 'a'\nsource = 'x'\n",
            "[defaults] has 'edits'",
        ),
        ("", "lists no [[capture]]"),
        (
            "[[capture]]\nname = 'a'\nsource = 'x'\n[[edit]]\ncapture = 'b'\nname = 'e'\nview = 1\n",
            "is not a [[capture]]",
        ),
        (
            "[[capture]]\nname = 'a'\nsource = 'x'\n[[edit]]\ncapture = 'a'\nname = 'run'\nview = 1\n",
            "are taken",
        ),
        (
            "[[capture]]\nname = 'a'\nsource = 'x'\n[[edit]]\ncapture = 'a'\nname = 'e'\n",
            "view = the edited view",
        ),
        (
            "[[capture]]\nname = 'a'\nsource = 'x'\n[[edit]]\ncapture = 'a'\nname = 'e'\nview = 1\noutputs = ['gif']\n",
            "outputs = a list of",
        ),
        (
            "[[capture]]\nname = 'a'\nsource = 'x'\n[[edit]]\ncapture = 'a'\nname = 'e'\nview = 1\nmode = 'paint'\n",
            "mode = 'paint'",
        ),
        ("[[capture]\n", "not a readable TOML file"),
    ],
)
def test_batch_file_errors_name_the_entry_and_key(tmp_path, text, message):
    with pytest.raises(SineError, match=None) as err:
        read_batch(write(tmp_path, text))
    assert message in str(err.value)


def test_jobs_chain_the_stages_and_resolve_paths(tmp_path):
    batch = read_batch(tiny_batch(tmp_path))
    jobs = {j.id: j for j in plan_jobs(batch, tmp_path / "out")}
    out = (tmp_path / "out").resolve()
    assert jobs["car/recon"].deps == ["car/synth"]
    assert jobs["car/fit"].deps == ["car/recon"]
    assert "car/features" not in jobs  # no texture edit asks for the feature field
    assert jobs["car/edit:taller"].deps == ["car/fit"]
    assert jobs["car/ply:taller"].deps == ["car/edit:taller"]
    assert jobs["car/eval:taller"].deps == ["car/edit:taller"]
    assert jobs["broken/recon"].deps == []  # a capture given by path: nothing to make
    assert jobs["broken/recon"].argv[1] == str(tmp_path / "no" / "such" / "capture")
    target = jobs["car/edit:taller"].argv[jobs["car/edit:taller"].argv.index("--target") + 1]
    assert target == str(out / "car" / "capture" / "edits" / "geometric" / "images" / "r_001.png")
    assert jobs["mug/fit"].settings["iterations"] == 40  # the entry's own over [defaults]
    assert jobs["mug/fit"].settings["batch_rays"] == 256  # [defaults] kept
    assert jobs["car/video:taller"].settings == {"orbit": 3}
    order = list(jobs)
    assert all(order.index(d) < order.index(j) for j in order for d in jobs[j].deps)


def test_texture_edits_get_the_feature_field(tmp_path):
    text = "[[capture]]\nname = 'a'\nsource = 'x'\n[[edit]]\ncapture = 'a'\nname = 'red'\n"
    text += "view = 1\nmode = 'texture'\ntarget = 't.png'\n"
    jobs = {j.id: j for j in plan_jobs(read_batch(write(tmp_path, text)), tmp_path)}
    assert jobs["a/features"].deps == ["a/fit"]
    assert jobs["a/edit:red"].deps == ["a/features"]


def test_the_example_batch_file_plans_and_parses():
    batch = read_batch(REPO / "datasets" / "batch_example.toml")
    jobs = plan_jobs(batch, Path("/tmp/out"))
    for job in jobs:
        check_job(job)  # every setting is a real one of its command, of the right type
    stages = [j.stage for j in jobs]
    assert stages.count("edit") == 3 and "features" in stages and "eval" in stages


def test_a_wrong_setting_stops_the_batch_before_any_work(tmp_path):
    from edit.batch import BatchConfig, run_batch

    path = write(tmp_path, "[[capture]]\nname = 'a'\nsource = 'x'\nfit = { iterations = 'many' }\n")
    with pytest.raises(SineError) as err:
        run_batch(BatchConfig(jobs=path, out=tmp_path / "out"))
    assert "a/fit" in str(err.value) and "setting 'iterations' must be" in str(err.value)
    assert not (tmp_path / "out").exists()


def test_a_job_after_a_failed_one_is_not_run(tmp_path):
    job = plan_jobs(read_batch(tiny_batch(tmp_path)), tmp_path / "out")[1]  # car/recon
    upstream = {"job": "car/synth", "status": "failed"}
    record = run_job(job, "token", str(tmp_path / "out"), 1, upstream)
    assert record["status"] == "failed" and record["message"] == "not run: car/synth failed"


def test_a_worker_that_does_not_see_the_output_folder_says_so(tmp_path):
    job = plan_jobs(read_batch(tiny_batch(tmp_path)), tmp_path / "out")[0]
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / TOKEN).write_text("another batch\n")
    record = run_job(job, "token", str(tmp_path / "out"), 1)
    assert record["status"] == "failed" and record["storage"] is False
    assert "does not see" in record["message"]


def test_a_job_runs_the_command_and_reports_its_error(tmp_path):
    out = tmp_path / "out"
    job = {j.id: j for j in plan_jobs(read_batch(tiny_batch(tmp_path)), out)}["broken/recon"]
    out.mkdir()
    (out / TOKEN).write_text("token\n")
    record = run_job(job, "token", str(out), 1)
    assert record["status"] == "failed"
    assert "no/such/capture does not exist" in record["message"]
    assert "does not exist" in Path(record["log"]).read_text()


# ---- whole batches on a local Ray ---------------------------------------------------------
def sine(*argv) -> None:
    """`sine ARGV` in a process of its own with one thread, as a batch task of 1 CPU has."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "sine_cli", *map(str, argv)]
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


@pytest.mark.slow
def test_batch_on_local_ray_equals_the_cli_and_survives_a_killed_worker(tmp_path):
    """One batch run by the command in another process (its own local Ray), whose mug fit's
    worker is killed with SIGKILL mid-stage; then the car's stages by hand through the CLI; then
    the batch again, in this process on a local Ray of 2 CPUs started here: no work left."""
    import ray

    jobs, out = tiny_batch(tmp_path, slow_steps=600), tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    command = [sys.executable, "-m", "sine_cli", "batch", str(jobs), "--out", str(out)]
    command += ["--cpus-per-task", "1", "--quiet"]
    driver = subprocess.Popen(command, env=env, cwd=tmp_path, stdout=subprocess.PIPE, text=True)
    marker, killed = out / "mug" / "batch" / "fit.running", None
    deadline = time.time() + 600
    while driver.poll() is None and killed is None and time.time() < deadline:
        if (out / "mug" / "run" / "template.partial" / "checkpoint.pt").is_file():  # mid-fit
            killed = int(marker.read_text().split()[0])
            os.kill(killed, signal.SIGKILL)
        time.sleep(0.5)
    stdout, _ = driver.communicate(timeout=900)
    assert killed is not None, "the mug's fit never started"
    assert driver.returncode == 1, stdout  # the broken capture failed
    summary = json.loads((out / "batch_summary.json").read_text())
    status = {j["job"]: j["status"] for j in summary["jobs"]}
    assert status["mug/fit"] == "done" and status["mug/glb:taller"] == "done"
    log = (out / "mug" / "logs" / "fit.log").read_text()
    assert log.count("== mug/fit,") == 2 and "fit: resuming from step" in log  # retried
    assert all(s == "done" for j, s in status.items() if not j.startswith("broken/")), status
    broken = {j["job"]: j["message"] for j in summary["jobs"] if j["object"] == "broken"}
    assert "no/such/capture does not exist" in broken["broken/recon"]
    assert broken["broken/edit:any"] == "not run: broken/fit failed"
    assert (out / "batch_summary.html").is_file() and (
        out / "car" / "taller" / "orbit.mp4"
    ).is_file()

    # the car by hand, one command after another, in a run of its own
    capture, run, gt = out / "car" / "capture", tmp_path / "by_hand", "edits/geometric"
    sine("recon", capture, "--out", run, "--width", "64")
    fit = ["--iterations", "40", "--batch-rays", "256", "--log2-table", "12"]
    sine("fit", run, *fit, "--detail-steps", "0", "--previews", "0", "--quiet")
    view = [c["name"] for c in json.loads((run / "cameras.json").read_text())["frames"]]
    sine(
        "edit", run, "--view", view.index("r_001.png"), "--name", "taller", "--quiet",
        "--target", capture / gt / "images" / "r_001.png",
        "--mask", capture / gt / "masks" / "r_001.png",
        "--set", "iterations=10", "--set", "previews=0",
    )  # fmt: skip
    sine("eval", run, "--edit", "taller", "--gt", capture / gt, "--quiet")
    batch = {j["job"]: j["metrics"] for j in summary["jobs"]}
    template = json.loads((run / "template" / "metrics.json").read_text())
    assert batch["car/fit"]["heldout_psnr_object"] == template["heldout_psnr_object"]
    edit = json.loads((run / "edits" / "taller" / "metrics.json").read_text())
    assert batch["car/edit:taller"]["edited_view_psnr_object"] == edit["edited_view_psnr_object"]
    scores = json.loads((run / "edits" / "taller" / "eval.json").read_text())["mean"]
    assert batch["car/eval:taller"]["psnr_object"] == scores["psnr_object"]

    # the same batch again: every stage already done
    from edit.batch import BatchConfig, run_batch

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        again = run_batch(BatchConfig(jobs=jobs, out=out, cpus_per_task=1, quiet=True))
    finally:
        ray.shutdown()
    status = {j["job"]: j["status"] for j in again["jobs"]}
    assert all(s == "skipped" for j, s in status.items() if not j.startswith("broken/")), status


GB = 2**30


class FakeRay:
    """What `edit.batch` reads of a Ray cluster: its nodes' resources."""

    def __init__(self, *nodes: dict):
        self._nodes = [{"Alive": True, "Resources": r} for r in nodes]

    def nodes(self):
        return self._nodes


@pytest.mark.parametrize(
    "nodes, cpus, gpus, expected",
    [
        (({"CPU": 2, "memory": GB * 16},), 2, None, (2, 0.0)),  # no GPU anywhere: CPU tasks
        (({"CPU": 8, "memory": GB}, {"CPU": 16, "GPU": 2, "memory": GB * 64}), 4, None, (4, 1.0)),
        (({"CPU": 8, "GPU": 1, "memory": GB * 64},), 4, 0.5, (4, 0.5)),  # half a GPU each
        (
            ({"CPU": 2, "memory": GB * 16},),
            4,
            None,
            "no Ray node has that many CPUs (the largest has 2)",
        ),
        (({"CPU": 8, "memory": GB * 16},), 1, 1.0, "the Ray cluster has no GPU"),
        (
            ({"CPU": 8, "memory": GB},),
            1,
            None,
            "no Ray node has that much memory for tasks (the largest has 1.0 GB)",
        ),
    ],
)
def test_task_resources_follow_the_cluster(nodes, cpus, gpus, expected):
    from edit.batch import BatchConfig, _resources

    cfg = BatchConfig(cpus_per_task=cpus, gpus_per_task=gpus)
    if isinstance(expected, str):
        with pytest.raises(SineError, match=expected.replace("(", r"\(").replace(")", r"\)")):
            _resources(FakeRay(*nodes), cfg)
    else:
        assert _resources(FakeRay(*nodes), cfg) == expected


def test_the_summary_has_a_row_per_edit_and_every_job(tmp_path):
    from edit.batch_summary import summary_line, write_summary

    def record(job, stage, status, result, edit=None, message="", metrics=None):
        obj = job.split("/")[0]
        return {"job": job, "object": obj, "stage": stage, "edit": edit, "status": status,
                "seconds": 1.5, "message": message, "metrics": metrics or {},
                "result": str(tmp_path / obj / result), "log": str(tmp_path / obj / "logs" / "x.log")}  # fmt: skip

    jobs = [
        record("a/fit", "fit", "done", "run/template/metrics.json", metrics={"heldout_psnr_object": 30.0}),
        record("a/edit:e", "edit", "skipped", "run/edits/e/metrics.json", "e", metrics={"iterations": 300}),
        record("a/glb:e", "mesh", "done", "e/e.glb", "e"),
        record("b/recon", "recon", "failed", "run/recon_report.json", message="no images in b"),
        record("b/edit:f", "edit", "failed", "run/edits/f/metrics.json", "f", "not run: b/recon failed"),
    ]  # fmt: skip
    summary = {"batch": "jobs.toml", "out": str(tmp_path), "seconds": 12.0, "jobs": jobs}
    write_summary(tmp_path, summary)
    data = json.loads((tmp_path / "batch_summary.json").read_text())
    assert data["counts"] == {"done": 2, "skipped": 1, "failed": 2}
    assert set(data["jobs"][0]) == {
        "job",
        "object",
        "stage",
        "edit",
        "status",
        "seconds",
        "message",
        "metrics",
    }
    page = (tmp_path / "batch_summary.html").read_text()
    assert "<a href='a/e/e.glb'>e.glb</a>" in page  # the edit's outputs, relative to DIR
    assert "failed: not run: b/recon failed" in page  # a failed edit's row says why
    assert page.count("<tr>") == 2 + 1 + len(jobs) + 1  # header + 2 edits, header + every job
    assert summary_line(summary).startswith("batch: 2 done, 1 skipped, 2 failed in 12 s")


def test_a_jobs_command_line_means_what_the_job_does(tmp_path):
    """The log's `sine ...` line, typed by hand, gives the job's own settings."""
    import shlex

    from edit.batch_stages import command_line, parse_command

    jobs = {j.id: j for j in plan_jobs(read_batch(tiny_batch(tmp_path)), tmp_path / "out")}
    for job in (jobs["mug/fit"], jobs["car/video:taller"]):
        line = shlex.split(command_line(job.argv, job.settings))
        assert line[0] == "sine"
        by_hand, batch = parse_command(line[1:], {}), parse_command(job.argv, job.settings)
        assert by_hand.settings and not batch.settings  # given as --set, or as the batch's
        assert {**vars(by_hand), "settings": None} == vars(batch)
