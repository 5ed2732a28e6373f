"""What the benchmark's child processes share (``bench --part kernel-size``, ``bench --part profile``): each renders
one method in a fresh process on the CPU backend, and a failure comes back to the parent as one line."""

from __future__ import annotations

from guiding.errors import GuidingError


def method_driver(method: str, scene_name: str, scale: float, threads: int | None = None):
    """In the child: a prepared :class:`~guiding.render.driver.PassDriver` of ``method`` on ``scene_name`` at ``scale``,
    on ``llvm_ad_rgb`` (with ``threads`` Dr.Jit threads; None: the default)."""
    from guiding.backend import set_variant

    set_variant("llvm_ad_rgb", threads)
    from guiding.render.driver import PassDriver
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.guides.methods import make_guide
    from guiding.scenes import load_scene

    driver = PassDriver(load_scene(scene_name, scale=scale), GuidedPathIntegrator(guide=make_guide(method)))
    driver.prepare()
    return driver


def child_failure(what: str, log: str) -> GuidingError:
    """``what`` failed, told in one line: the last line the child wrote (its exception's)."""
    lines = [line.strip() for line in log.splitlines() if line.strip()]
    return GuidingError(f"{what} failed: {lines[-1] if lines else 'no message'}")
