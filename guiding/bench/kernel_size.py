"""The size of each method's render kernel in machine instructions (CPU backend): ``bench --part kernel-size``.

Why it is measured: on the CPU, Dr.Jit compiles the path loop into one kernel that runs the loop's whole body for
every packet of lanes (8 with AVX2, 16 with AVX-512), and the parts a lane does not need are masked, not skipped
(only a symbolic ``if`` whose condition no lane of the packet meets is skipped). Where LLVM deems the CPU's gather
instruction slow (AVX2 without AVX-512 and without fast-gather tuning: AMD Zen 3, say), it turns each gather into a
loop over the lanes (a branch and a scalar load per lane), so a table read costs tens of instructions; elsewhere
(AVX-512, Intel since Skylake) it emits ``vpgatherdd``, counted in ``hardware_gathers``. On Zen 3 the package asks
for the instruction (:func:`guiding.llvm_gathers.use_hardware_gathers`), so counts made there before it are not
comparable with later ones. The instruction count of a method's kernel against ``brdf``'s is a noise-free account of
the code the guided bounce adds, which its time follows in part (results/bench/README.md, "Arithmetic is not
free"); the table reads among them and where the paths go count too (``bench``'s ``[hot rows]`` stage,
results/bench/README.md, "The `[hot rows]` stage").

How: each method runs in a fresh process on one Dr.Jit thread (the kernels hold some 20 instructions more with two)
and an empty kernel cache, so that every kernel is compiled, with Dr.Jit logging at its trace level (which prints
the disassembly of each compiled kernel). A kernel is a module of functions (the path loop and the BSDF/emitter
calls it makes); the largest module compiled in the first passes, the trained guide's path loop, is counted.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile

import pandas as pd

from guiding.bench.child import child_failure, method_driver
from guiding.errors import GuidingError

#: Passes each method renders (1 spp each) while its kernels are compiled: the first may be untrained (grid guides
#: sample the BSDF until their first update), the later ones use the trained guide.
PASSES = 3
_FUNCTION = re.compile(r"jit_llvm_disasm\(\): =+ (\d+) =+")
_INSTRUCTION = re.compile(r"jit_llvm_disasm\(\): 0x[0-9a-f]+\s")
_GATHER = re.compile(r"jit_llvm_disasm\(\): 0x[0-9a-f]+\s+v(p)?gather[dq]")


def parse_disassembly(log: str) -> list[list[tuple[int, int]]]:
    """(instructions, hardware gathers) of the functions of each kernel module in a Dr.Jit trace log (function 0
    opens a module)."""
    modules: list[list[list[int]]] = []
    for line in log.splitlines():
        function = _FUNCTION.search(line)
        if function:
            if int(function.group(1)) == 0 or not modules:
                modules.append([])
            modules[-1].append([0, 0])
        elif _INSTRUCTION.search(line) and modules:
            modules[-1][-1][0] += 1
            modules[-1][-1][1] += bool(_GATHER.search(line))
    return [[(count, gathers) for count, gathers in module] for module in modules]


def count_instructions(method: str, scene: str, scale: float) -> dict:
    """Instructions and functions of ``method``'s largest render kernel on ``scene`` at ``scale`` (CPU backend)."""
    with tempfile.TemporaryDirectory() as cache:
        run = subprocess.run([sys.executable, "-m", "guiding.bench.kernel_size", method, scene, str(scale)],
                             env={**os.environ, "DRJIT_CACHE_DIR": cache}, capture_output=True, text=True)
    if run.returncode != 0:
        raise child_failure(f"kernel-size run of '{method}' on {scene}", run.stderr)
    modules = parse_disassembly(run.stdout)     # Dr.Jit writes its log to stdout
    if not modules:
        raise GuidingError(f"kernel-size run of '{method}' on {scene} logged no disassembly (is the backend LLVM?)")
    largest = max(modules, key=lambda module: sum(count for count, _ in module))
    return {"method": method, "instructions": sum(count for count, _ in largest), "functions": len(largest),
            "largest_function": max(count for count, _ in largest),
            "hardware_gathers": sum(gathers for _, gathers in largest)}


def kernel_table(scenes: list[tuple[str, float]], methods: list[str]) -> pd.DataFrame:
    """One row per scene (name, scale) and method, ``brdf`` first: its render kernel's instructions and their ratio
    to ``brdf``'s on the same scene."""
    frames = []
    for scene, scale in scenes:
        frame = pd.DataFrame([count_instructions(m, scene, scale) for m in ["brdf", *[m for m in methods if m != "brdf"]]])
        frame.insert(0, "scene", scene)
        frame["ratio_to_brdf"] = frame["instructions"] / frame.loc[0, "instructions"]
        frames.append(frame)
    return pd.concat(frames, ignore_index=True)


def _compile_and_log(method: str, scene_name: str, scale: float) -> None:
    """The child process: render ``PASSES`` 1-spp passes of ``method`` with Dr.Jit's trace log (on stdout)."""
    import drjit as dr

    driver = method_driver(method, scene_name, scale, threads=1)    # the kernel's code varies with the thread count
    dr.set_log_level(dr.LogLevel.Trace)
    for seed in range(PASSES):
        driver.run(seed, 1)


if __name__ == "__main__":
    _compile_and_log(sys.argv[1], sys.argv[2], float(sys.argv[3]))
