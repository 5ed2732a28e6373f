"""Choosing and starting a Mitsuba variant: ``auto``, ``llvm_ad_rgb`` (CPU) or ``cuda_ad_rgb`` (GPU).

Dr.Jit's CPU backend needs libLLVM ≥ 16; with Debian's libLLVM 14/15 it aborts inside LLVM on the first kernel.
:func:`set_variant` finds a suitable library first and otherwise stops with one line naming the fix. On the CPU it
then chooses how kernels read tables (:func:`guiding.llvm_gathers.use_hardware_gathers`, the package's one private
hook into Dr.Jit, contained in that module).
"""

from __future__ import annotations

import glob
import os
import re

from guiding.errors import GuidingError
from guiding.llvm_gathers import use_hardware_gathers

VARIANTS = ("auto", "llvm_ad_rgb", "cuda_ad_rgb")
MIN_LLVM = 16
LLVM_FIX = "apt-get install libllvm19"
CUDA_FIX = "--variant llvm_ad_rgb (the CPU) or --variant auto"

_LLVM_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib",
              "/usr/local/lib", "/opt/homebrew/opt/llvm/lib", "/usr/local/opt/llvm/lib")

#: Called after every :func:`set_variant`: the package registers its Mitsuba plugins for the new variant here
#: (``guiding/__init__.py``), so that this module imports nothing above it.
VARIANT_HOOKS: list = []


class BackendError(GuidingError):
    """The requested variant cannot run on this machine; the message says how to fix it."""


def _llvm_major(path: str) -> int:
    match = re.search(r"LLVM[-.]?(?:so\.)?(\d+)", os.path.basename(path))
    return int(match.group(1)) if match else 0


def find_libllvm() -> str | None:
    """Path of the newest libLLVM ≥ 16 in a standard place, or ``DRJIT_LIBLLVM_PATH`` if the user set one."""
    explicit = os.environ.get("DRJIT_LIBLLVM_PATH")
    if explicit:
        return explicit if os.path.exists(explicit) else None
    candidates = []
    for folder in _LLVM_DIRS:
        candidates += glob.glob(os.path.join(folder, "libLLVM*.so*")) + glob.glob(os.path.join(folder, "libLLVM*.dylib"))
    usable = [c for c in candidates if _llvm_major(c) >= MIN_LLVM]
    return max(usable, key=_llvm_major) if usable else None


def cuda_available() -> bool:
    """True when an NVIDIA driver with OptiX is loadable (cheap check, no Dr.Jit initialisation)."""
    import ctypes

    for name in ("libcuda.so.1", "libcuda.so"):
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            continue
    return False


def resolve_variant(variant: str = "auto") -> str:
    """The concrete variant ``auto`` stands for on this machine (CUDA when usable, else LLVM)."""
    if variant not in VARIANTS:
        raise BackendError(f"unknown variant '{variant}' (choose from {', '.join(VARIANTS)})")
    if variant == "auto":
        return "cuda_ad_rgb" if cuda_available() else "llvm_ad_rgb"
    return variant


def set_variant(variant: str = "auto", threads: int | None = None) -> str:
    """Select the Mitsuba variant (checking libLLVM first on the CPU) and the CPU thread count; returns the variant."""
    variant = resolve_variant(variant)
    if variant.startswith("llvm"):
        lib = find_libllvm()
        if lib is None:
            raise BackendError(f"the CPU backend needs libLLVM >= {MIN_LLVM} and none was found: run `{LLVM_FIX}` "
                               "(or set DRJIT_LIBLLVM_PATH)")
        os.environ["DRJIT_LIBLLVM_PATH"] = lib
    if variant.startswith("cuda") and not cuda_available():
        raise BackendError(f"variant {variant} needs an NVIDIA GPU and its driver, and this machine has neither "
                           f"(libcuda.so.1 not found): use {CUDA_FIX}")
    import drjit as dr
    import mitsuba as mi

    if variant.startswith("cuda") and not dr.has_backend(dr.JitBackend.CUDA):
        raise BackendError(f"variant {variant}: the NVIDIA driver is installed but Dr.Jit cannot start a CUDA device "
                           f"(none present, or the driver is too old for Dr.Jit {dr.__version__}): use {CUDA_FIX}")
    try:
        mi.set_variant(variant)
    except (ImportError, AttributeError, RuntimeError) as error:
        raise BackendError(f"cannot start variant {variant}: {error}") from None
    if variant.startswith("llvm"):
        use_hardware_gathers()
    if threads is not None:
        if threads < 1:
            raise BackendError(f"thread count must be >= 1, got {threads}")
        dr.set_thread_count(threads)
    for hook in VARIANT_HOOKS:
        hook()
    return variant
