"""The grid guide's per-pass counters (``statistics``, reported in ``stats.json`` and by the benchmark): guided
vertices, samples of weight zero, and the rejection samplers' proposals and acceptances.

They are atomic adds into 1-element arrays, several per bounce, and cost the bounce a good part of its time: they
are traced only when switched on, and never touch the image.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

#: What is counted: guided vertices, guided samples of weight 0, proposals of the rejection samplers, guided samples
#: that went through a rejection sampler, and those whose proposal was accepted.
COUNTED = ("guided", "invalid", "proposals", "rejection_samples", "accepted")


class PassCounters:
    """The counters of one pass; nothing is traced unless ``enabled``.

    Parameters:
      enabled: count (the ``statistics`` parameter of :class:`~guiding.guides.parameters.GridParameters`).
    """

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.reset()

    def reset(self) -> None:
        """Zero counters for the next pass (none at all when not enabled)."""
        self.arrays = {key: mi.UInt32(0) for key in COUNTED} if self.enabled else {}

    def add(self, key: str, value, active: mi.Bool) -> None:
        """One atomic add of ``value`` into counter ``key`` in the ``active`` lanes."""
        if self.enabled:
            dr.scatter_reduce(dr.ReduceOp.Add, self.arrays[key], mi.UInt32(value), mi.UInt32(0), active)

    def add_rejection(self, searching: mi.Bool, proposals: mi.UInt32, accepted: mi.Bool) -> None:
        """Count a rejection sampler's draw: the lanes that searched, the proposals they made, those accepted."""
        self.add("rejection_samples", 1, searching)
        self.add("proposals", proposals, searching)
        self.add("accepted", 1, accepted)

    def figures(self) -> dict:
        """The pass's figures for ``stats.json`` (empty when not enabled)."""
        if not self.enabled:
            return {}
        c = {key: int(value[0]) for key, value in self.arrays.items()}
        return {"guided_samples": c["guided"],
                "invalid_share": c["invalid"] / c["guided"] if c["guided"] else 0.0,
                "acceptance_rate": c["accepted"] / c["proposals"] if c["proposals"] else None,
                "proposals_per_sample": c["proposals"] / c["rejection_samples"] if c["rejection_samples"] else None}
