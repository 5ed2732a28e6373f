"""Where a pass's CPU time goes, by the code that runs it: ``bench --part profile`` (Linux ``perf``, CPU backend).

Why it is measured: the cost breakdown (``bench``) and the kernel sizes (``bench --part kernel-size``) say how much
more a guided bounce costs than ``brdf``'s; this says *in what*. Sampled with ``perf record -e cpu-clock``, a pass's
time splits into the Dr.Jit-compiled kernels (the path loop with its BSDF calls and the guide's sampling and
recording; ``perf`` labels this JIT code ``[JIT] tid …``), Embree's ray traversal, the Python that traces the loop,
the Dr.Jit runtime and the operating system. Embree's share is the same for every method on a scene (the same number
of rays, about), so a guided method's excess lies in the kernel's own instructions.

How: each method runs in a child process with one Dr.Jit thread; it renders ``WARMUP_PASSES`` passes (compilation
and the guide's first updates), then waits while ``perf`` attaches to it, then renders the profiled passes (their
updates included, as a pass pays them) and exits.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

from .errors import GuidingError

WARMUP_PASSES = 3
PASS_SPP = 8
#: ``perf report --sort dso`` shared objects, grouped: the first pattern that matches names the group.
#: perf names the code of anonymous executable memory ``[JIT] tid …`` (``[unknown]`` or ``//anon`` in older versions):
#: in this process only Dr.Jit's kernels live there.
GROUPS = (("jit_kernels", re.compile(r"^\[JIT\]|^\[unknown\]|//anon")),
          ("embree", re.compile(r"libembree")),
          ("llvm_compile", re.compile(r"libLLVM")),
          ("drjit_runtime", re.compile(r"drjit|nanothread|nanobind|mitsuba|llvm_ad_rgb")),
          ("python", re.compile(r"libpython|cpython|^python")),
          ("os", re.compile(r"^\[kernel|^\[vdso|libc\.|libm\.|ld-linux|libstdc\+\+|libgcc")))
_ROW = re.compile(r"^\s*[\d.]+%\s+(\d+)\s+(.+?)\s*$")


def parse_report(text: str) -> dict[str, float]:
    """Seconds per group (:data:`GROUPS`, ``other`` for the rest) from ``perf report --sort dso --stdio
    --show-total-period`` output (the period of the cpu-clock event is in nanoseconds)."""
    seconds = {name: 0.0 for name, _ in GROUPS} | {"other": 0.0}
    for line in text.splitlines():
        row = _ROW.match(line)
        if not row or line.lstrip().startswith("#"):
            continue
        period, dso = int(row.group(1)), row.group(2)
        group = next((name for name, pattern in GROUPS if pattern.search(dso)), "other")
        seconds[group] += period * 1e-9
    return seconds


def profile_method(method: str, scene: str, scale: float, passes: int) -> dict:
    """The CPU seconds per spp of ``passes`` passes of ``method``, by group, sampled in a child process."""
    with tempfile.TemporaryDirectory() as folder:
        data = Path(folder) / "perf.data"
        child = subprocess.Popen([sys.executable, "-m", "guiding.cpu_profile", method, scene, str(scale), str(passes)],
                                 stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        if child.stdout.readline().strip() != "ready":
            raise RuntimeError(f"profile run of '{method}' failed: {child.communicate()[1].strip().splitlines()[-1:]}")
        perf = subprocess.Popen(["perf", "record", "-q", "-e", "cpu-clock", "-o", str(data), "-p", str(child.pid)],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        time.sleep(0.5)     # perf attaches before the profiled passes start
        child.communicate("go\n")
        _, perf_errors = perf.communicate()
        if child.returncode != 0 or not data.exists():
            raise RuntimeError(f"profile run of '{method}' failed: {perf_errors.strip().splitlines()[-1:]}")
        report = subprocess.run(["perf", "report", "-i", str(data), "--sort", "dso", "--stdio", "--show-total-period"],
                                capture_output=True, text=True, check=True).stdout
    spp = passes * PASS_SPP
    return {"method": method, **{f"{group}_ms_per_spp": 1e3 * s / spp for group, s in parse_report(report).items()}}


def profile_table(scenes: list[tuple[str, float]], methods: list[str], passes: int) -> pd.DataFrame:
    """One row per scene (name, scale) and method, ``brdf`` first: CPU ms per spp by group, and the JIT kernels' and
    Embree's time as ratios to ``brdf``'s on the same scene."""
    if shutil.which("perf") is None:
        raise GuidingError("bench --part profile needs Linux perf on the PATH (e.g. apt install linux-tools-generic)")
    frames = []
    for scene, scale in scenes:
        rows = []
        for method in ["brdf", *[m for m in methods if m != "brdf"]]:
            print(f"profile: {scene} (scale {scale:g}) {method}", file=sys.stderr, flush=True)
            rows.append(profile_method(method, scene, scale, passes))
        frame = pd.DataFrame(rows)
        frame.insert(0, "scene", scene)
        groups = [c for c in frame.columns if c.endswith("_ms_per_spp")]
        frame["total_ms_per_spp"] = frame[groups].sum(axis=1)
        for column in ("total", "jit_kernels", "embree"):
            frame[f"{column}_ratio_to_brdf"] = frame[f"{column}_ms_per_spp"] / frame.loc[0, f"{column}_ms_per_spp"]
        frames.append(frame)
    return pd.concat(frames, ignore_index=True)


def _render_when_told(method: str, scene_name: str, scale: float, passes: int) -> None:
    """The child process: warm-up passes, ``ready`` on stdout, then the profiled passes once a line comes on stdin."""
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    dr.set_thread_count(1)
    from .driver import PassDriver
    from .integrator import GuidedPathIntegrator
    from .methods import make_guide
    from .scenes import load_scene

    driver = PassDriver(load_scene(scene_name, scale=scale), GuidedPathIntegrator(guide=make_guide(method)))
    driver.prepare()
    for seed in range(WARMUP_PASSES):
        driver.run(seed, PASS_SPP)
    print("ready", flush=True)
    sys.stdin.readline()
    for seed in range(WARMUP_PASSES, WARMUP_PASSES + passes):
        driver.run(seed, PASS_SPP)


if __name__ == "__main__":
    _render_when_told(sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[4]))
