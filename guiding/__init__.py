"""guiding: grid path guiding learned online (Kim & Kim 2021) for Mitsuba 3, and its experiment harness.

Modules: :mod:`~guiding.backend` (variant selection), :mod:`~guiding.integrator` (the path loop),
:mod:`~guiding.guides` (direction sampling and learning), :mod:`~guiding.render` (progressive passes under a
budget), :mod:`~guiding.metrics`, :mod:`~guiding.imageio`, :mod:`~guiding.scenes`, :mod:`~guiding.cli`.
"""

__version__ = "0.1.0"


def _register_plugin() -> None:
    """Register the ``guided_path`` integrator when a Mitsuba variant is already set (``guiding.backend.set_variant``
    registers it for variants chosen later)."""
    import mitsuba as mi

    if mi.variant() is not None:
        from .integrator import register

        register()


_register_plugin()
