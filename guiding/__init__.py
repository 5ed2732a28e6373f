"""guiding: grid path guiding learned online (Kim & Kim 2021) for Mitsuba 3, and its experiment harness.

The product is :mod:`guiding.render` (the ``guided_path`` integrator and its progressive passes) and
:mod:`guiding.guides` (direction sampling and learning, one guide per method); :mod:`guiding.experiments` (the
Snakemake harness, tables, figures) and :mod:`guiding.bench` (cost benchmarks and their instruments) are the lab
built on them. Small shared modules: :mod:`~guiding.backend` (variant selection), :mod:`~guiding.scenes`,
:mod:`~guiding.imageio`, :mod:`~guiding.metrics`, :mod:`~guiding.provenance`; :mod:`~guiding.cli` is the command
line. ``docs/architecture.md`` draws the layers.
"""

from guiding import backend

__version__ = "0.1.0"


def _register_plugin() -> None:
    """Register the ``guided_path`` integrator for the Mitsuba variant in use, if one is set (run at import and after
    every :func:`guiding.backend.set_variant`)."""
    import mitsuba as mi

    if mi.variant() is not None:
        from guiding.render.integrator import register

        register()


backend.VARIANT_HOOKS.append(_register_plugin)
_register_plugin()
