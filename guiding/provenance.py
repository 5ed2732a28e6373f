"""Where results came from: configuration, code version, software, machine and the devices of the renders."""

from __future__ import annotations

import html
import json
import os
import platform
import socket
import subprocess
import time
from pathlib import Path

from guiding.scenes import PROJECT_ROOT


def _command_output(args: list[str], cwd: str | os.PathLike = PROJECT_ROOT) -> str | None:
    try:
        result = subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return None
    return result.stdout.strip() if result.returncode == 0 else None


def software_versions() -> dict:
    """Versions of Python and of the packages results depend on (None for one not installed)."""
    from importlib import metadata

    versions = {"python": platform.python_version()}
    for package in ("guiding", "mitsuba", "drjit", "numpy", "snakemake", "OpenEXR", "matplotlib", "pandas",
                    "flip-evaluator", "tqdm"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = None
    return versions


def provenance(config: dict, stats_files: list[str], configfiles: list[str] = ()) -> dict:
    """Where the results came from: configuration, code version, software, this machine, and every render's
    machine and device (from its stats.json)."""
    from collections import Counter

    devices = Counter()
    for path in stats_files:
        try:
            prov = json.loads(Path(path).read_text()).get("provenance", {})
        except (OSError, ValueError):
            continue
        experiment = Path(path).parts[-6] if "renders" in Path(path).parts else "reference"
        devices[(experiment, prov.get("host"), prov.get("device"), prov.get("variant"), prov.get("threads"))] += 1
    commit = _command_output(["git", "rev-parse", "HEAD"])
    dirty = _command_output(["git", "status", "--porcelain", "--untracked-files=no"])
    return {
        "config": config, "configfiles": [str(p) for p in configfiles],
        "git": {"commit": commit, "dirty": bool(dirty) if dirty is not None else None},
        "versions": software_versions(),
        "machine": {"host": socket.gethostname(), "platform": platform.platform(), "cpus": os.cpu_count(),
                    "gpu": _command_output(["nvidia-smi", "--query-gpu=name,driver_version", "--format=csv,noheader"])},
        "renders": [{"experiment": e, "host": h, "device": d, "variant": v, "threads": t, "jobs": n}
                    for (e, h, d, v, t), n in sorted(devices.items(), key=lambda item: tuple(map(str, item[0])))],
    }


def provenance_html(prov: dict) -> str:
    import yaml

    def table(rows: list[dict]) -> str:
        if not rows:
            return "<p>none</p>"
        head = "".join(f"<th>{html.escape(str(k))}</th>" for k in rows[0])
        body = "".join("<tr>" + "".join(f"<td>{html.escape(str(v))}</td>" for v in row.values()) + "</tr>"
                       for row in rows)
        return f"<table border='1' cellspacing='0' cellpadding='3'><tr>{head}</tr>{body}</table>"

    git = prov["git"]
    return "\n".join([
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>Provenance</title></head><body>",
        "<h1>Provenance</h1>",
        f"<p>Code: commit <code>{html.escape(str(git['commit']))}</code>"
        f"{' with uncommitted changes' if git['dirty'] else ''}.</p>",
        "<h2>Machines and devices of the renders</h2>", table(prov["renders"]),
        "<h2>Software</h2>", table([prov["versions"]]),
        "<h2>Machine that ran the workflow</h2>", table([prov["machine"]]),
        f"<h2>Configuration</h2><p>files: {html.escape(', '.join(prov['configfiles']) or '(defaults)')}</p>",
        f"<pre>{html.escape(yaml.safe_dump(prov['config'], sort_keys=False))}</pre>",
        "</body></html>"])


def render_provenance(variant: str) -> dict:
    """The machine and software of a render in this process (its stats.json and EXR headers)."""
    import drjit as dr
    import mitsuba as mi

    return {"variant": variant, "threads": dr.thread_count() if variant.startswith("llvm") else None,
            "device": device_name(variant), "host": socket.gethostname(), "platform": platform.platform(),
            "python": platform.python_version(), "mitsuba": mi.__version__, "drjit": dr.__version__,
            "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")}


def device_name(variant: str, reads: bool = True) -> str:
    """The device a variant renders on, in words (``CPU: … (N threads)``, ``GPU: …``); with ``reads``, how the CPU
    backend's kernels read tables where it has the choice."""
    if variant.startswith("cuda"):
        try:
            names = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                                   text=True, timeout=10).stdout.strip().splitlines()
        except (OSError, subprocess.SubprocessError):
            names = []
        return f"GPU: {names[0]}" if names else "GPU: CUDA device"
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            fields = dict(line.split(":", 1) for line in cpuinfo.read().split("\n\n")[0].splitlines() if ":" in line)
    except OSError:
        return f"CPU: {platform.processor() or platform.machine()}"
    fields = {key.strip(): value.strip() for key, value in fields.items()}
    flags = fields.get("flags", "").split()
    # The widest vector extension decides Dr.Jit's packet width (8 lanes with AVX2, 16 with AVX-512), and with it
    # the cost of the guided bounce relative to brdf's: a CPU model name alone hides it (AMD EPYC: Zen 3 or Zen 4).
    vectors = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else None
    # So are table reads: LLVM compiles them into gather instructions or into a scalar load per lane (on AVX2 CPUs
    # without AVX-512, guiding.llvm_gathers.use_hardware_gathers decides; None: LLVM decides from the CPU's name).
    from guiding.llvm_gathers import LLVM_DECIDES, gathers_in_use

    table_reads = {True: "gather instructions", False: "scalar loads", None: LLVM_DECIDES}[gathers_in_use()] if reads else None
    details = ", ".join(filter(None, [vectors, table_reads, f"{os.cpu_count()} threads"]))
    return f"CPU: {fields.get('model name', platform.processor() or platform.machine())} ({details})"
