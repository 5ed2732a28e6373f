"""Where a pass's CPU time goes, by the code that runs it: ``bench --part profile`` (Linux ``perf``, CPU backend).

Why it is measured: the cost breakdown (``bench``) and the kernel sizes (``bench --part kernel-size``) say how much
more a guided bounce costs than ``brdf``'s; this says *in what*. Sampled with ``perf record -e cpu-clock``, a pass's
time splits into the Dr.Jit-compiled kernels (the path loop with its BSDF calls and the guide's sampling and
recording; ``perf`` labels this JIT code ``[JIT] tid …``), Embree's ray traversal, the Python that traces the loop,
the Dr.Jit runtime and the operating system. Embree's share is the same for every method on a scene (the same number
of rays, about), so a guided method's excess lies in the kernel's own instructions.

Within the kernels, each sample is put down to its instruction (the child dumps its executable anonymous memory, the
kernels' machine code, and ``objdump`` disassembles it): ``jit_table_access`` counts the samples at an access to
memory through an address the kernel computed (a gather, or a load or store through a register other than the
stack's: the guide's tables, the BSDFs' and the scene's data, the learning's sums) or at the instruction after one,
where a timer sample waiting on it lands; ``jit_other`` the rest (arithmetic, the random numbers, control flow).

How: each method runs in a child process with one Dr.Jit thread under ``perf record``, its events disabled; it
renders ``WARMUP_PASSES`` passes (compilation and the guide's first updates), then perf's events are enabled
(through its control pipe) for the profiled passes (their updates included, as a pass pays them) and disabled
before the child exits.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pandas as pd

from guiding.bench.child import child_failure, method_driver
from guiding.errors import GuidingError
from guiding.render.defaults import PASS_SPP

WARMUP_PASSES = 3
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
#: An instruction that reads or writes memory at an address the kernel computed: a gather or scatter, or a memory
#: operand through a register other than the stack and instruction pointers (spills and constants); ``lea`` and
#: ``nop`` name an address without touching it.
_TABLE_ACCESS = re.compile(r"gather|scatter|\((?!%rsp|%rbp|%rip)%r\w+")
_NO_ACCESS = re.compile(r"^\s*(lea|nop)")
#: A line of ``objdump -D`` output: address, encoding bytes, instruction (continuation lines have no instruction).
_INSTRUCTION = re.compile(r"^\s*([0-9a-f]+):\t[0-9a-f ]+\t(.+)$")


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


def table_access_share(samples: dict[int, int], disassembly: str) -> tuple[int, int]:
    """(samples at table accesses, samples in the disassembled code) of ``samples`` (instruction address → count):
    a sample counts as a table access (:data:`_TABLE_ACCESS`) when its instruction or the one before it is one."""
    instructions = [(int(m.group(1), 16), m.group(2)) for m in map(_INSTRUCTION.match, disassembly.splitlines()) if m]
    accesses = [bool(_TABLE_ACCESS.search(text)) and not _NO_ACCESS.match(text) for _, text in instructions]
    at_access = total = 0
    for i, (address, _) in enumerate(instructions):
        count = samples.get(address, 0)
        total += count
        if accesses[i] or (i > 0 and accesses[i - 1]):
            at_access += count
    return at_access, total


def _kernel_split(data: Path, regions: Path) -> float:
    """The share of the kernels' samples at table accesses (:func:`table_access_share`), from ``perf script`` and
    the code regions the child dumped into ``regions`` (files named by their start address); NaN without
    ``objdump`` or without samples in them."""
    if shutil.which("objdump") is None:
        return float("nan")
    script = subprocess.run(["perf", "script", "-i", str(data), "-F", "ip"], capture_output=True, text=True)
    if script.returncode != 0:
        raise child_failure("perf script", script.stderr)
    samples: dict[int, int] = {}
    for line in script.stdout.split():
        address = int(line, 16)
        samples[address] = samples.get(address, 0) + 1
    at_access = total = 0
    for region in regions.iterdir():
        start = int(region.name, 16)
        inside = {a: n for a, n in samples.items() if start <= a < start + region.stat().st_size}
        if inside:
            listing = subprocess.run(["objdump", "-D", "-b", "binary", "-m", "i386:x86-64", f"--adjust-vma={start:#x}",
                                      str(region)], capture_output=True, text=True).stdout
            counts = table_access_share(inside, listing)
            at_access, total = at_access + counts[0], total + counts[1]
    return at_access / total if total else float("nan")


def profile_method(method: str, scene: str, scale: float, passes: int, timeout: float = 3600) -> dict:
    """The CPU seconds per spp of ``passes`` passes of ``method``, by group: the child runs under ``perf record``
    with its events disabled, and they are enabled (through perf's control pipe) for the profiled passes only."""
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        data, log, regions = folder / "perf.data", folder / "child.log", folder / "code"
        regions.mkdir()
        control_read, control_write = os.pipe()
        ack_read, ack_write = os.pipe()
        with open(log, "w") as child_log:
            child = subprocess.Popen(["perf", "record", "-q", "-e", "cpu-clock", "-D", "-1", "-o", str(data),
                                      "--control", f"fd:{control_read},{ack_write}", "--",
                                      sys.executable, "-m", "guiding.bench.cpu_profile", method, scene, str(scale),
                                      str(passes), str(regions)], pass_fds=(control_read, ack_write),
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=child_log, text=True)
        os.close(control_read)
        os.close(ack_write)
        try:
            with open(control_write, "w") as commands, open(ack_read) as acks:
                for command, after in (("enable", "ready"), ("disable", "done")):     # around the profiled passes
                    if not _wait_for(child, after):
                        break
                    commands.write(f"{command}\n")
                    commands.flush()
                    acks.readline()
                    child.stdin.write("go\n")
                    child.stdin.flush()
                child.wait(timeout=timeout)     # perf stops at the end of its control pipe: close it after
        except (OSError, subprocess.TimeoutExpired):
            child.kill()
            child.wait()
        if child.returncode != 0 or not data.exists():
            raise child_failure(f"profile run of '{method}' on {scene}", log.read_text())
        report = subprocess.run(["perf", "report", "-i", str(data), "--sort", "dso", "--stdio", "--show-total-period"],
                                capture_output=True, text=True)
        if report.returncode != 0:
            raise child_failure(f"perf report of '{method}' on {scene}", report.stderr)
        table_share = _kernel_split(data, regions)
    spp = passes * PASS_SPP
    ms = {f"{group}_ms_per_spp": 1e3 * s / spp for group, s in parse_report(report.stdout).items()}
    split = {"jit_table_access_ms_per_spp": ms["jit_kernels_ms_per_spp"] * table_share,
             "jit_other_ms_per_spp": ms["jit_kernels_ms_per_spp"] * (1 - table_share)}
    return {"method": method, **ms, **split}


def _wait_for(child: subprocess.Popen, word: str) -> bool:
    """Read the child's stdout up to a line ``word`` (other lines are its logs); False at its end."""
    for line in child.stdout:
        if line.strip() == word:
            return True
    return False



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
        groups = [f"{name}_ms_per_spp" for name, _ in GROUPS] + ["other_ms_per_spp"]
        frame["total_ms_per_spp"] = frame[groups].sum(axis=1)
        for column in ("total", "jit_kernels", "jit_table_access", "jit_other", "embree"):
            frame[f"{column}_ratio_to_brdf"] = frame[f"{column}_ms_per_spp"] / frame.loc[0, f"{column}_ms_per_spp"]
        frames.append(frame)
    return pd.concat(frames, ignore_index=True)


def _render_when_told(method: str, scene_name: str, scale: float, passes: int, regions: str) -> None:
    """The child process: warm-up passes, ``ready`` on stdout, the profiled passes once a line comes on stdin, then
    ``done``; at the next line (perf's events are off by then) it writes its executable anonymous memory into folder
    ``regions`` and exits (so that perf leaves the interpreter's shutdown out)."""
    import drjit as dr

    driver = method_driver(method, scene_name, scale, threads=1)
    for seed in range(WARMUP_PASSES):
        driver.run(seed, PASS_SPP)
    print("ready", flush=True)
    sys.stdin.readline()
    for seed in range(WARMUP_PASSES, WARMUP_PASSES + passes):
        driver.run(seed, PASS_SPP)
    dr.sync_thread()
    print("done", flush=True)
    sys.stdin.readline()
    _dump_code(Path(regions))


def _dump_code(folder: Path) -> None:
    """Every executable anonymous mapping of this process (the JIT kernels' machine code) into ``folder``, one file
    per mapping named by its start address in hex."""
    import ctypes

    with open("/proc/self/maps") as maps:
        for line in maps:
            fields = line.split()
            name = fields[5] if len(fields) > 5 else ""
            if "x" not in fields[1] or (name and not name.startswith(("[anon", "//anon"))):
                continue
            start, end = (int(x, 16) for x in fields[0].split("-"))
            (folder / f"{start:x}").write_bytes(ctypes.string_at(start, end - start))


if __name__ == "__main__":
    _render_when_told(sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[4]), sys.argv[5])
