"""How the CPU backend's kernels read tables: the gather instruction or one scalar load per lane.

**A private hook into Dr.Jit.** Dr.Jit's Python module does not expose the LLVM backend's target, so this module
reaches four C++ functions of the already loaded ``libdrjit-core.so`` by their mangled names through ctypes
(``RTLD_NOLOAD``: the copy Dr.Jit runs on, never a second one): ``jit_llvm_target_cpu``,
``jit_llvm_target_features``, ``jit_llvm_vector_width`` and ``jit_llvm_set_target``. It changes only the target's
feature flags ``+fast-gather``/``-fast-gather``, and only on AVX2 CPUs without AVX-512, where LLVM's choice of the
gather instruction depends on the CPU's tuning; images are bit-identical either way.

**Fallback.** Where the symbols are missing (another Dr.Jit build or version, another OS) or the LLVM backend has
not started, every function here does nothing and reports None ("LLVM decides"): kernels are compiled as Dr.Jit
compiles them by itself. Which case a run was in is recorded in its provenance (``table_reads`` in ``stats.json``
and the device label: gather instructions, scalar loads, or null) by :func:`gathers_in_use`.
"""

from __future__ import annotations

import functools
import os
from contextlib import contextmanager

from guiding.errors import GuidingError

#: LLVM target CPUs on which the CPU backend's table reads are compiled into the CPU's gather instruction. LLVM uses it
#: only on CPUs with AVX-512 or tuned ``fast-gather`` (Intel's since Skylake); elsewhere every gather of a kernel
#: becomes a loop of one scalar load per lane. On AMD's Zen 3 the instruction is the faster of the two for every
#: method (``bench --part gathers``, results/bench/hardware_gathers.md); other AVX2-only CPUs (Zen 2, Haswell), not
#: measured, keep LLVM's choice.
HARDWARE_GATHER_CPUS = ("znver3",)
#: Overrides :data:`HARDWARE_GATHER_CPUS`: ``1`` uses the gather instruction on any AVX2 CPU, ``0`` keeps LLVM's choice
#: everywhere.
HARDWARE_GATHERS_ENV = "GUIDING_HARDWARE_GATHERS"
_FAST_GATHER, _SLOW_GATHER = "+fast-gather", "-fast-gather"
#: How provenance names table reads that LLVM chooses by itself (the fallback, or a CPU whose name decides).
LLVM_DECIDES = "table reads as LLVM chooses"



class GathersError(GuidingError):
    """A bad value of :data:`HARDWARE_GATHERS_ENV`."""


@functools.cache
def _target_functions():
    """The loaded ``libdrjit-core``'s ``jit_llvm_target_cpu``, ``…_features``, ``…_vector_width`` and
    ``jit_llvm_set_target``, which Dr.Jit's Python module does not expose; None where they are missing. Looked up
    once: ctypes' library objects and their functions refer to each other, and a cycle made at every call would
    have the garbage collector run during frozen passes (see :mod:`guiding.render.frozen_pass`)."""
    import ctypes

    import drjit as dr

    try:
        # RTLD_NOLOAD: the copy Dr.Jit runs on, never a second, uninitialised one.
        core = ctypes.CDLL(os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.so"),
                           mode=os.RTLD_NOLOAD | os.RTLD_NOW)
        cpu_of, features_of = core._Z19jit_llvm_target_cpuv, core._Z24jit_llvm_target_featuresv
        width_of, set_target = core._Z21jit_llvm_vector_widthv, core._Z19jit_llvm_set_targetPKcS0_j
    except (OSError, AttributeError):
        return None
    cpu_of.restype = features_of.restype = ctypes.c_char_p
    width_of.restype = ctypes.c_uint32
    set_target.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
    return cpu_of, features_of, width_of, set_target


def _llvm_target():
    """Dr.Jit's CPU target: (CPU name, feature flags, a function that sets the flags); None where Dr.Jit's library
    does not tell (:func:`_target_functions`), or before its LLVM backend started (it has no target then, and
    ignores a new one)."""
    functions = _target_functions()
    if functions is None:
        return None
    cpu_of, features_of, width_of, set_target = functions
    cpu = (cpu_of() or b"").decode()
    if not cpu:
        return None
    flags = [flag for flag in (features_of() or b"").decode().split(",") if flag]

    def retarget(new_flags: list[str]) -> None:
        set_target(cpu.encode(), ",".join(new_flags).encode(), width_of())

    return cpu, flags, retarget


def _gathers(flags: list[str]) -> bool | None:
    """Whether LLVM compiles gathers into the gather instruction for these target flags; None where the CPU's name
    decides (an AVX2 CPU without AVX-512 and without our tuning flag: Intel's since Skylake are tuned fast-gather)
    and where the CPU has no gather instruction (not x86)."""
    if "+avx512f" in flags:
        return True
    if "+avx2" not in flags:
        return False if "+sse2" in flags else None
    return True if _FAST_GATHER in flags else False if _SLOW_GATHER in flags else None


def _choosable(flags: list[str]) -> bool:
    """Whether the gather instruction is a choice for these target flags: AVX2 has it, and LLVM always takes it with
    AVX-512."""
    return "+avx2" in flags and "+avx512f" not in flags


def gathers_choosable() -> bool:
    """Whether this CPU backend's table reads can be either gather instructions or scalar loads
    (:func:`use_hardware_gathers`); elsewhere both settings give LLVM's own."""
    target = _llvm_target()
    return target is not None and _choosable(target[1])


def _environment_choice() -> bool | None:
    """$GUIDING_HARDWARE_GATHERS: True (``1``), False (``0``) or None (unset)."""
    choice = os.environ.get(HARDWARE_GATHERS_ENV, "")
    if choice not in ("", "0", "1"):
        raise GathersError(f"{HARDWARE_GATHERS_ENV} must be 0 or 1, got '{choice}'")
    return None if choice == "" else choice == "1"


def use_hardware_gathers(enable: bool | None = None) -> bool | None:
    """Set how the CPU backend's kernels compiled from now on read tables, and return it (:func:`gathers_in_use`).

    On a CPU with AVX2 and without AVX-512: the gather instruction where ``enable`` is True, a scalar load per lane
    where it is False; None: as $GUIDING_HARDWARE_GATHERS says (``1`` the instruction, ``0`` LLVM's choice), else
    the instruction on :data:`HARDWARE_GATHER_CPUS` and LLVM's choice elsewhere. Other CPUs keep LLVM's choice.
    Call it after the LLVM variant is set (:func:`set_variant` does) and before the first pass of an integrator
    (a frozen pass replays the kernels it recorded). Results are bit-identical either way; Dr.Jit's kernel cache
    keys on the target, so each setting compiles its own kernels."""
    environment = _environment_choice()
    target = _llvm_target()
    if target is None:
        return None
    cpu, flags, retarget = target
    if not _choosable(flags):
        return _gathers(flags)
    if enable is None:
        wanted = cpu in HARDWARE_GATHER_CPUS if environment is None else environment
        enable = True if wanted else None         # not wanted: LLVM's choice
    tuned = [flag for flag in flags if flag not in (_FAST_GATHER, _SLOW_GATHER)]
    tuned += [] if enable is None else [_FAST_GATHER if enable else _SLOW_GATHER]
    if tuned != flags:
        retarget(tuned)
    return _gathers(tuned)


def gathers_in_use() -> bool | None:
    """Whether the CPU backend's kernels compiled now read tables with the gather instruction (True), a scalar load
    per lane (False), or as LLVM decides from the CPU's name (None; also where Dr.Jit's target cannot be read)."""
    target = _llvm_target()
    return None if target is None else _gathers(target[1])


@contextmanager
def llvm_target_kept():
    """Whatever the block does to the CPU backend's target (:func:`use_hardware_gathers`), it is as before after."""
    target = _llvm_target()
    try:
        yield
    finally:
        if target is not None:
            target[2](target[1])
