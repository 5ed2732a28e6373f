"""The sweep on a SLURM cluster (docs/slurm.md): config/ci.yaml through the profile users copy
(config/profiles/slurm) and Snakemake's SLURM executor plugin, on the single-node SLURM that scripts/slurm.sh runs
on this machine, against a local run of the same configuration.

The test's profile differs from the one users copy only in what the profile leaves to the site (cluster_profile):
account, partition, memory where the node has little, the timed renders' threads (its node's CPUs) and GPU model,
status checks every 2 s, and the renderer. The node's two GPUs are stand-ins that SLURM schedules but nothing
renders on, so the renders run on the CPU (llvm_ad_rgb) while requesting the GPU that cuda_ad_rgb requests. Where
SLURM cannot run here (no root, no apt-get, daemons that do not start), the tests fail with the script's one-line
reason, and the rest of the suite runs on.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from datetime import datetime
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from guiding import imageio
from guiding.experiments.configuration import load_config
from guiding.experiments.plan import plan
from workflow_runs import CI_CONFIG, ROOT, checkout_env, snakemake, snakemake_command

SCRIPT = ROOT / "scripts" / "slurm.sh"
PROFILE = ROOT / "config" / "profiles" / "slurm" / "config.yaml"
ACCOUNT = "guiding-test"   # any name: without an accounting database SLURM checks none
PARTITION = "gpu"          # not the cluster's default (cpu): a job there did not get the profile's partition
GPU_MODEL = "standin"      # the type scripts/slurm.sh gives its stand-in GPUs
GPU_RULES = ("reference", "render", "render_timed")
#: squeue's fields of a job, in this order (squeue -O); the controller keeps finished jobs for an hour.
JOB_FIELDS = ("JobID", "State", "Partition", "Account", "NumCPUs", "MinMemory", "TimeLimit", "tres-per-job",
              "OverSubscribe", "SubmitTime", "StartTime", "EndTime", "Comment")


def _script(command: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), command], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="session")
def slurm():
    """The test cluster for the session (stopped after it unless it ran before): its node's CPUs and memory (MB)."""
    was_running = _script("status").returncode == 0
    started = _script("start")
    if started.returncode != 0:
        reason = (started.stderr.strip().splitlines() or [f"scripts/slurm.sh start: exit {started.returncode}"])[-1]
        pytest.fail(f"the local SLURM did not start: {reason}", pytrace=False)
    node = subprocess.run(["sinfo", "-h", "-N", "-p", PARTITION, "-o", "%c %m"], capture_output=True, text=True,
                          check=True).stdout.split()
    yield SimpleNamespace(cpus=int(node[0]), memory_mb=int(node[1]))
    if not was_running:
        stopped = _script("stop")
        assert stopped.returncode == 0, stopped.stderr


def cluster_profile(folder: Path, node) -> dict:
    """config/profiles/slurm with the test cluster's site values, written to ``folder``; returns its settings."""
    profile = yaml.safe_load(PROFILE.read_text())
    assert {"<account>", "<gpu partition>"} <= set(profile["default-resources"].values())  # what users fill in
    config = dict(entry.split("=", 1) for entry in profile["config"])
    config.update(variant="llvm_ad_rgb", timed_threads=str(node.cpus))
    profile["config"] = [f"{key}={value}" for key, value in config.items()]
    resources = profile["default-resources"]
    # Two jobs side by side, as the node's two CPUs allow, however little memory a CI machine has.
    resources.update(slurm_account=ACCOUNT, slurm_partition=PARTITION,
                     mem_mb=min(resources["mem_mb"], node.memory_mb // 2))
    for rule in GPU_RULES:  # what cuda_ad_rgb requests (the Snakefile's gpu=1), on the CPU renderer
        profile["set-resources"].setdefault(rule, {})["gpu"] = 1
    profile["set-resources"]["render_timed"]["gpu_model"] = GPU_MODEL
    # Status every few seconds, not the plugin's 40 s first wait for a cluster's long jobs: the renders take seconds.
    profile.update({"slurm-init-seconds-before-status-checks": 2, "seconds-between-status-checks": 2})
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "config.yaml").write_text(yaml.safe_dump(profile, sort_keys=False))
    return profile


def cluster_jobs(output: str) -> dict[str, dict]:
    """The SLURM jobs of the Snakemake run that printed ``output``, by their comment (rule and wildcards)."""
    run_id = re.search(r"SLURM run ID: (\S+)", output).group(1)
    lines = subprocess.run(["squeue", "--states=all", "-h", "--name", run_id,
                            "-O", ",".join(f"{field}:|" for field in JOB_FIELDS)],
                           capture_output=True, text=True, check=True).stdout.splitlines()
    jobs = [dict(zip(JOB_FIELDS, line.split("|"))) for line in lines]
    return {job["Comment"]: job for job in jobs}


@pytest.fixture(scope="module")
def slurm_run(slurm, tmp_path_factory):
    folder = tmp_path_factory.mktemp("slurm-run")
    profile = cluster_profile(folder / "profile", slurm)
    result = snakemake("--profile", folder / "profile", "--configfile", CI_CONFIG, "--directory", folder / "work",
                       timeout=1800)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-4000:]
    return SimpleNamespace(workdir=folder / "work", jobs=cluster_jobs(output), profile=profile, node=slurm)


def _time_limit(minutes: int) -> str:
    """A runtime in minutes as squeue shows a time limit."""
    return f"{minutes // 60}:{minutes % 60:02d}:00" if minutes >= 60 else f"{minutes}:00"


def _comment(rule: str, *wildcards) -> str:
    """The comment the plugin gives a job: its rule and its wildcards' values."""
    return f"rule_{rule}_wildcards_" + "_".join(map(str, wildcards))


def test_slurm_run_makes_what_a_local_run_makes(slurm_run, ci_run):
    out = slurm_run.workdir / "results" / "ci"
    local = ci_run[0] / "results" / "ci"
    files = {path.relative_to(out) for path in out.rglob("*") if path.is_file()}
    assert files == {path.relative_to(local) for path in local.rglob("*") if path.is_file()}
    for path in files:
        if path.suffix == ".json":   # every stats.json, metrics.json and provenance.json complete
            json.loads((out / path).read_text())
        elif path.suffix == ".exr":
            assert imageio.read_exr(out / path).size > 0


def test_only_references_and_renders_go_to_slurm_with_the_profiles_resources(slurm_run):
    the_plan = plan(load_config(CI_CONFIG))
    profile = slurm_run.profile
    stats_files = {_comment("render_timed" if run.timed else "render", run.experiment, run.scene, run.method,
                            run.budget.tag, run.seed): the_plan.render_file(run, "stats.json") for run in the_plan.runs}
    stats_files.update({_comment("reference", ref.scene, ref.scale, ref.spp): the_plan.reference_file(ref, "stats.json")
                        for ref in the_plan.references.values()})
    assert set(slurm_run.jobs) == set(stats_files)   # metrics, tables, figures, provenance: on this machine
    defaults, rules = profile["default-resources"], profile["set-resources"]
    for comment, job in slurm_run.jobs.items():
        rule = re.match(r"rule_(\w+?)_wildcards_", comment).group(1)
        resources = {**defaults, **rules.get(rule, {})}
        assert job["State"] == "COMPLETED", (comment, job)
        assert (job["Partition"], job["Account"]) == (PARTITION, ACCOUNT), comment
        assert job["TimeLimit"] == _time_limit(resources["runtime"]), (comment, job["TimeLimit"])
        assert job["MinMemory"] == f"{resources['mem_mb']}M", comment
        gpu = f"gres:gpu:{GPU_MODEL}:1" if rule == "render_timed" else "gres:gpu:1"
        assert job["tres-per-job"] == gpu, (comment, job["tres-per-job"])
        assert (job["OverSubscribe"] == "NO") == (rule == "render_timed"), comment   # --exclusive
        # The threads a render used are the CPUs its job was given: config threads, or the timed renders'.
        stats = json.loads((slurm_run.workdir / stats_files[comment]).read_text())
        assert int(job["NumCPUs"]) == stats["provenance"]["threads"] == (
            slurm_run.node.cpus if rule == "render_timed" else the_plan.config["threads"]), comment


def test_timed_renders_never_overlap(slurm_run):
    """From the renders' own clocks (stats.json started, finished), and from SLURM's: Snakemake submitted each timed
    render only after the one before had ended (the profile's timing=1), which --exclusive alone would not do on a
    cluster of more than one node."""
    the_plan = plan(load_config(CI_CONFIG))
    timed = [run for run in the_plan.runs if run.timed]
    assert len(timed) > 1
    spans = sorted((datetime.fromisoformat(stats["started"]), datetime.fromisoformat(stats["finished"]), run.key)
                   for run in timed
                   for stats in [json.loads((slurm_run.workdir / the_plan.render_file(run, "stats.json")).read_text())])
    for before, after in zip(spans, spans[1:]):
        assert after[0] >= before[1], f"{after[2]} started before {before[2]} finished"
    jobs = sorted((job for comment, job in slurm_run.jobs.items() if comment.startswith("rule_render_timed_")),
                  key=lambda job: job["SubmitTime"])
    assert len(jobs) == len(timed)
    for before, after in zip(jobs, jobs[1:]):   # whole seconds: submitted in the second the last ended at the earliest
        assert after["SubmitTime"] >= before["EndTime"], (
            f"{after['Comment']} submitted at {after['SubmitTime']}, before {before['Comment']} ended at "
            f"{before['EndTime']}")


def _render_processes(workdir: Path, folder: str) -> list[int]:
    """Pids of `python -m guiding render --out FOLDER` processes in ``workdir`` (SLURM starts them: no children of
    ours)."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            if (entry.name.isdigit() and f"\0--out\0{folder}\0".encode() in (entry / "cmdline").read_bytes()
                    and Path(os.readlink(entry / "cwd")) == workdir.resolve()):
                found.append(int(entry.name))
        except OSError:
            continue
    return found


def _running_render_job(workdir: Path, folder: str, comment: str) -> str:
    """Waits until the render of ``folder`` runs in its SLURM job and is well inside it: the job's id."""
    deadline = time.time() + 240
    while not _render_processes(workdir, folder) and time.time() < deadline:
        time.sleep(0.5)
    assert _render_processes(workdir, folder), "the render never started"
    time.sleep(3.0)  # Dr.Jit started, the clock running
    queue = subprocess.run(["squeue", "-h", "-o", "%i %k"], capture_output=True, text=True, check=True).stdout
    return next(line.split()[0] for line in queue.splitlines() if line.split()[1] == comment)


def _left_behind(folder: Path) -> list[str]:
    return sorted(path.name for path in folder.iterdir()) if folder.exists() else []


def test_a_render_cancelled_by_scancel_leaves_nothing_and_is_rerun(slurm, tmp_path):
    """scancel a timed render mid-way, first under a live Snakemake (which reports the cancelled job), then after
    Snakemake itself was killed (a lost login session: nobody cleans up). Neither leaves anything in the render's
    folder, and the same command renders it again, whole (after --unlock, for the killed Snakemake's lock)."""
    config = load_config(CI_CONFIG)
    config["budgets"]["equal_time"]["seconds"] = 8
    (tmp_path / "long.yaml").write_text(yaml.safe_dump(config))
    cluster_profile(tmp_path / "profile", slurm)
    folder, workdir = "results/ci/renders/equal_time/cornell/brdf/8s/seed0", tmp_path / "work"
    comment = _comment("render_timed", "equal_time", "cornell", "brdf", "8s", 0)
    args = ["--profile", tmp_path / "profile", "--configfile", tmp_path / "long.yaml", "--directory", workdir,
            f"{folder}/stats.json"]
    for snakemake_dies in (False, True):
        process = subprocess.Popen(snakemake_command(*args), cwd=ROOT, env=checkout_env(), stdout=subprocess.PIPE,
                                   stderr=subprocess.STDOUT, text=True, start_new_session=True)
        try:
            job = _running_render_job(workdir, folder, comment)
            if snakemake_dies:
                os.killpg(process.pid, signal.SIGKILL)
            subprocess.run(["scancel", job], check=True)
            output, _ = process.communicate(timeout=180)
        finally:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
        if not snakemake_dies:
            assert f"SLURM-job '{job}' failed, SLURM status is: 'CANCELLED'" in output, output[-4000:]
        assert process.returncode != 0
        deadline = time.time() + 60   # SLURM ends the job's processes (TERM, then KILL after KillWait)
        while _render_processes(workdir, folder) and time.time() < deadline:
            time.sleep(0.5)
        assert not _render_processes(workdir, folder) and _left_behind(workdir / folder) == [], snakemake_dies
    assert snakemake("--unlock", *args).returncode == 0
    rerun = snakemake(*args, timeout=600)
    assert rerun.returncode == 0, (rerun.stdout + rerun.stderr)[-4000:]
    stats = json.loads((workdir / folder / "stats.json").read_text())
    assert stats["budget_seconds_counted"] >= 8 and imageio.read_exr(workdir / folder / "image.exr").size
