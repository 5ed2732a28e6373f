"""guiding: grid path guiding learned online (Kim & Kim 2021) for Mitsuba 3, and its experiment harness.

Modules: :mod:`~guiding.backend` (variant selection), :mod:`~guiding.integrator` (the path loop),
:mod:`~guiding.guides` (direction sampling and learning), :mod:`~guiding.render` (progressive passes under a
budget), :mod:`~guiding.metrics`, :mod:`~guiding.imageio`, :mod:`~guiding.scenes`, :mod:`~guiding.cli`.
"""

__version__ = "0.1.0"
