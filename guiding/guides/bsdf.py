"""The unguided baseline: plain BSDF importance sampling (the paper's "BRDF" column)."""

from guiding.guides.base import Guide


class BSDFGuide(Guide):
    """Samples every direction from the BSDF and learns nothing; every other default of :class:`Guide` applies."""

    name = "brdf"

    def update_due(self, spp_done: int) -> None:
        return None     # nothing changes: passes may grow
