"""The unguided baseline: plain BSDF importance sampling (the paper's "BRDF" column)."""

from guiding.guides.base import Guide


class BSDFGuide(Guide):
    """Samples every direction from the BSDF and learns nothing; every other default of :class:`Guide` applies."""

    name = "brdf"

    def update_due(self, spp_done: int) -> None:
        return None     # nothing changes: passes may grow

    def sample_and_eval(self, scene, sampler, si, bsdf, bsdf_ctx, active, wo, wo_active, vertex=None):
        """One BSDF call, Mitsuba's ``eval_pdf_sample``, as its ``path`` makes at every vertex: a BSDF call less per
        bounce than evaluating, then sampling (the loop's cost against ``path``'s: results/nee_cost/README.md). It
        evaluates at every ``active`` lane (outside ``wo_active`` the value is not asked for) and samples the BSDF
        itself: a subclass that samples otherwise must override this too."""
        return bsdf.eval_pdf_sample(bsdf_ctx, si, wo, sampler.next_1d(active), sampler.next_2d(active), active)
