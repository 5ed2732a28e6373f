"""The render parameters' defaults, in one place for the plugin, the command line, the harness and the benchmarks."""

#: Samples per pixel of the first passes; the guide updates between passes, and later passes grow to
#: ``PASS_SPP·2^k`` up to its next update (:mod:`guiding.render.pass_schedule`).
PASS_SPP = 8
#: Longest path, in vertices after the camera (Mitsuba's convention: 1 shows only directly visible emitters).
MAX_DEPTH = 16
#: Depth from which Russian roulette may end a path (the paper's protocol, without next-event estimation).
RR_DEPTH = 8
#: The same with next-event estimation: Mitsuba's ``path`` default, so that paths are as long as that integrator's
#: and ``brdf`` with NEE costs what ``path`` costs per spp (results/nee_cost/).
RR_DEPTH_NEE = 5
#: Lower bound of Russian roulette's continuation probability ``q = max(max_rgb(β), RR_MIN)`` (the paper's protocol).
RR_MIN = 0.05
