"""The parameters of each guide, as typed values with their defaults (one dataclass per guide).

A guide is built from its parameters (``GridGuide(GridParameters(rule="mc"))``, or with keyword overrides,
``GridGuide(rule="mc")``); a method of :mod:`guiding.guides.methods` is a name for a guide class and one of these values.
They are plain dataclasses: they can be built, checked and compared before a Mitsuba variant is set.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

RULES = ("mc", "sarsa", "expected_sarsa")
#: Which surfaces a grid guide guides: ``diffuse`` (purely diffuse reflection, the paper's) or ``smooth`` (every
#: reflecting BSDF without a delta lobe: rough plastic and conductors too).
GUIDED_BSDFS = ("diffuse", "smooth")
SAMPLERS = ("sphere_inv", "hemi_inv", "hemi_rej", "hemi_rej_plus")
#: How the rejection samplers draw their target: ``bins`` (exactly: a bin from the pair's alias table of P·∫cos, then a
#: direction ∝ cos inside it) or the paper's loop of ``uniform`` proposals (see :mod:`guiding.guides.grid.samplers`).
PROPOSALS = ("bins", "uniform")
#: Least BSDF share of the rejection samplers (see :mod:`guiding.guides.grid.samplers`): it bounds hemi_rej's weight by 5·ρ
#: per bounce. A smaller share leaves the products of several bounces heavy-tailed (results/bounce_weights.md).
MIN_BSDF_SHARE = 0.2
#: The range of a BSDF share the tree guides learn (``learn_bsdf_fraction``; :mod:`~guiding.guides.trees.bsdf_fraction`):
#: the floor is the grid's ``min_bsdf_share``, for the same bound on the weights.
LEARNED_SHARE_RANGE = (MIN_BSDF_SHARE, 0.95)
#: How a renderer makes the final image of a guide whose learning runs in iterations (the SD-tree's doubling
#: schedule; :mod:`guiding.render.progressive`): ``last``, the last iteration alone (Müller et al. 2017's paper); ``automatic``,
#: the last iteration alone, training stopped early once the variance extrapolated to the end of the budget stops
#: falling (Tom94's ``sampleCombination="automatic"``, the default of his guided_path.cpp); ``inverse-variance``,
#: the last four iterations combined, as in Müller 2019's "improved" preset, but weighted by their spp, fixed before
#: they are drawn (his inverse of each one's own estimated variance biased the image; :mod:`guiding.render.progressive`).
COMBINE_LAST = "last"
COMBINE_AUTOMATIC = "automatic"
COMBINE_INVERSE_VARIANCE = "inverse-variance"
COMBINE_MODES = (COMBINE_LAST, COMBINE_AUTOMATIC, COMBINE_INVERSE_VARIANCE)
#: Where the SD-tree splats a vertex (Tom94's ``spatialFilter``): ``nearest``, the D-tree of its own S-tree leaf;
#: ``stochastic``, the D-tree of a point drawn uniformly in a box of its leaf's size around it (a box filter over
#: the leaves, in expectation).
SPATIAL_FILTERS = ("nearest", "stochastic")

#: The image size Müller et al.'s S-tree constant c = 12000 was tuned for (1280 × 720 pixels), and the spp its
#: threshold counts in: Tom94's guided_path.cpp splits after iteration k of 2^k passes of ``sppPerPass`` spp at
#: ``c·sqrt(2^k·sppPerPass/4)`` vertices, i.e. ``c·sqrt(spp_k/4)``, in units of his default pass of 4 spp.
PAPER_PIXELS = 1280 * 720
PAPER_SPP_UNIT = 4

#: Floor of the exploration share ε of the grid policy. The paper's schedule alone drives ε to 1e-10 by 1000 spp;
#: unexplored bins then get probabilities below float32 resolution in the tables, are never sampled, and the image is
#: biased (docs/history.md). With the floor every bin keeps ≥ ε_min/B.
MIN_EXPLORATION = 0.1


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


def with_overrides(parameters, overrides: dict):
    """``parameters`` with the fields in ``overrides`` replaced (a ValueError names an unknown field)."""
    unknown = sorted(set(overrides) - set(parameters.__dataclass_fields__))
    _check(not unknown, f"unknown parameter(s) {', '.join(unknown)} of {type(parameters).__name__} (known: "
                        f"{', '.join(parameters.__dataclass_fields__)})")
    return replace(parameters, **overrides)


@dataclass(frozen=True)
class GridParameters:
    """Kim & Kim's grid guide (:class:`~guiding.guides.grid.guide.GridGuide`): a ``S³ × 2·D²`` radiance record, a learning
    rule and a sampler.

    Parameters:
      spatial_resolution: S, cells per axis of the grid over the scene's bounding box (default 8).
      directional_resolution: D, the direction bins are 2·D² (default 16: 512 bins).
      rule: ``mc`` | ``sarsa`` | ``expected_sarsa``.
      sampler: ``sphere_inv`` | ``hemi_inv`` | ``hemi_rej`` | ``hemi_rej_plus``.
      normal_resolution: odd cube-map resolution of the memo tables' normal bins (default 5: 150 bins).
      bsdf_fraction: BSDF share of the inversion samplers' mixture (default 0.5; 0 is the paper's pure sampler).
      proposal: ``bins`` or ``uniform`` (the paper's loop): how rejection samplers draw their target. Default
        (None): the sampler's own, ``bins`` for ``hemi_rej_plus``, ``uniform`` for ``hemi_rej``
        (:mod:`~guiding.guides.grid.samplers`); the inversion samplers take none.
      max_proposals: cap of the ``uniform`` rejection loop (default 64).
      min_bsdf_share: least BSDF share of the rejection samplers (default :data:`MIN_BSDF_SHARE`).
      min_exploration: floor of the exploration share ε (default :data:`MIN_EXPLORATION`; 0 is the paper's
        schedule exactly).
      guided_bsdfs: ``diffuse`` (default, the paper's) or ``smooth`` (:data:`GUIDED_BSDFS`).
      smooth_bsdf_share: least BSDF share at guided vertices whose BSDF is not purely diffuse (default 0.5, the
        SD-tree's mixture): the guide knows nothing of a glossy lobe, the BSDF's sampling covers it.
      sub_resolution: R > 1 cuts each bin that holds at least ``refine_share`` of its cell's policy (once visited
        often enough) into R × R equal-area sub-bins whose distribution is learned too, and sampled where it is far
        enough from uniform (:mod:`~guiding.guides.grid.refinement`; ``bins`` proposal only, which
        :func:`~guiding.guides.grid.strategy.grid_strategy` checks); default 1, no refinement.
      refine_share: least policy share of a refined (cell, bin) entry (default 0.05, 25× a uniform bin's at D = 16).
      refine_capacity: most entries refined (default 4096; their tables are allocated up front).
      rebuild_growth: g ≥ 0: the record is rebuilt (Q, policy, memo tables, refinement) after a pass only once the
        spp reach the next multiple of the largest power of two ≤ g × the spp at the last rebuild (the spp grow by
        at most g between rebuilds, and the passes in between can be merged into one of a power-of-two size,
        :mod:`guiding.render.pass_schedule`); the targets of the passes in between are kept and folded in at the next
        rebuild. Default 0: after every pass (the paper's).
      learning_share: the share of the render's budget (its spp, or its counted seconds) the guide learns from; the
        renderer then stops its training (:meth:`~guiding.guides.base.Guide.stop_training`): from its next rebuild
        (at once if the last pass rebuilt it) the guide renders the rest without recording and without rebuilds, in
        passes that grow (default 1: it learns to the end, the paper's).
      statistics: count, per pass, guided vertices, invalid samples, rejection proposals and acceptances (default
        False; :mod:`~guiding.guides.grid.counters`). The counters are atomics on 1-element arrays, several per
        bounce, a good part of its cost (the benchmark's ``[+statistics]`` stage); they are traced only when on, and
        only then does ``update()`` report ``guided_samples``, ``invalid_share``, ``acceptance_rate`` and
        ``proposals_per_sample``. They never touch the image.
    """

    spatial_resolution: int = 8
    directional_resolution: int = 16
    rule: str = "sarsa"
    sampler: str = "hemi_rej_plus"
    normal_resolution: int = 5
    bsdf_fraction: float = 0.5
    proposal: str | None = None
    max_proposals: int = 64
    min_bsdf_share: float = MIN_BSDF_SHARE
    min_exploration: float = MIN_EXPLORATION
    guided_bsdfs: str = "diffuse"
    smooth_bsdf_share: float = 0.5
    sub_resolution: int = 1
    refine_share: float = 0.05
    refine_capacity: int = 4096
    rebuild_growth: float = 0.0
    learning_share: float = 1.0
    statistics: bool = False

    def __post_init__(self):
        _check(self.rule in RULES, f"unknown learning rule '{self.rule}' (choose from {', '.join(RULES)})")
        _check(self.sampler in SAMPLERS, f"unknown sampler '{self.sampler}' (choose from {', '.join(SAMPLERS)})")
        _check(self.proposal is None or self.proposal in PROPOSALS,
               f"unknown proposal '{self.proposal}' (choose from {', '.join(PROPOSALS)})")
        _check(1 <= self.spatial_resolution <= 256 and 1 <= self.directional_resolution <= 256,
               f"S and D must be in 1..256, got S = {self.spatial_resolution}, D = {self.directional_resolution}")
        _check(self.normal_resolution >= 1 and self.normal_resolution % 2 == 1,
               f"normal_resolution must be odd and >= 1, got {self.normal_resolution}")
        _check(0 <= self.bsdf_fraction < 1, f"bsdf_fraction must be in [0, 1), got {self.bsdf_fraction}")
        _check(0 < self.min_bsdf_share <= 1, f"min_bsdf_share must be in (0, 1], got {self.min_bsdf_share}")
        _check(self.max_proposals >= 1, f"max_proposals must be >= 1, got {self.max_proposals}")
        _check(0 <= self.min_exploration <= 1, f"min_exploration must be in [0, 1], got {self.min_exploration}")
        _check(self.guided_bsdfs in GUIDED_BSDFS,
               f"unknown guided_bsdfs '{self.guided_bsdfs}' (choose from {', '.join(GUIDED_BSDFS)})")
        _check(0 < self.smooth_bsdf_share < 1, f"smooth_bsdf_share must be in (0, 1), got {self.smooth_bsdf_share}")
        _check(1 <= self.sub_resolution <= 16, f"sub_resolution must be in 1..16, got {self.sub_resolution}")
        _check(0 < self.refine_share <= 1, f"refine_share must be in (0, 1], got {self.refine_share}")
        _check(self.rebuild_growth >= 0, f"rebuild_growth must be >= 0, got {self.rebuild_growth}")
        _check(0 < self.learning_share <= 1, f"learning_share must be in (0, 1], got {self.learning_share}")
        _check(self.refine_capacity >= 1, f"refine_capacity must be >= 1, got {self.refine_capacity}")


@dataclass(frozen=True)
class TreeParameters:
    """What the tree guides share: their D-trees and the mixture they sample.

    Parameters:
      rho: D-tree subdivision share: a leaf holding more than ``rho`` of its tree's energy splits (default 0.01).
      dtree_max_depth: deepest D-tree level (default 20).
      bsdf_fraction: BSDF share of the one-sample mixture with the D-tree (default 0.5, as Müller et al.).
      max_nodes: cap on the nodes of one D-tree (default None: no cap).
      uniform_empty_dtrees: a D-tree that holds no energy samples the sphere uniformly, still mixed with the BSDF,
        once the guide has built its trees (Tom94's ``DTree::sample`` and ``pdf``); False: such a vertex samples
        the BSDF alone (default False; the SD-tree's default is True).
      guide_delta_mixtures: a BSDF with a delta lobe beside a smooth one is guided: its smooth part is mixed with
        the D-tree, its delta lobe reached by BSDF sampling alone (Tom94's ``sampleMat``); False: every BSDF with a
        delta lobe samples the BSDF alone (default False; the SD-tree's default is True). Purely delta BSDFs are
        never guided.
      learn_bsdf_fraction: each D-tree learns its own BSDF share, starting at ``bsdf_fraction``, by minimising the
        KL divergence from the product f·cos·L to the mixture (Müller 2019; :mod:`~guiding.guides.trees.bsdf_fraction`),
        within :data:`LEARNED_SHARE_RANGE`; False: ``bsdf_fraction`` everywhere (default False).
      jump_levels: the D-tree levels a descent skips, reading where it stands after them from a table per cell of
        side 2^-jump_levels (:class:`~guiding.guides.trees.dtree.DeviceForest`; 4^jump_levels cells per tree, at most
        4); 0: from the root (default 3).
    """

    rho: float = 0.01
    dtree_max_depth: int = 20
    bsdf_fraction: float = 0.5
    max_nodes: int | None = None
    uniform_empty_dtrees: bool = False
    guide_delta_mixtures: bool = False
    learn_bsdf_fraction: bool = False
    jump_levels: int = 3

    def __post_init__(self):
        _check(0 < self.rho <= 1, f"rho must be in (0, 1], got {self.rho}")
        _check(0 <= self.jump_levels <= 4, f"jump_levels must be in [0, 4], got {self.jump_levels}")
        _check(self.dtree_max_depth >= 1, f"dtree_max_depth must be >= 1, got {self.dtree_max_depth}")
        _check(0 <= self.bsdf_fraction < 1, f"bsdf_fraction must be in [0, 1), got {self.bsdf_fraction}")
        _check(self.max_nodes is None or self.max_nodes >= 1, f"max_nodes must be >= 1, got {self.max_nodes}")
        low, high = LEARNED_SHARE_RANGE
        _check(not self.learn_bsdf_fraction or low <= self.bsdf_fraction <= high,
               f"a learned bsdf_fraction starts in [{low}, {high}], got {self.bsdf_fraction}")


@dataclass(frozen=True)
class SDTreeParameters(TreeParameters):
    """Müller et al. 2017's SD-tree (:class:`~guiding.guides.trees.sdtree.SDTreeGuide`) as Tom94's guided_path.cpp
    implements it: the fields of :class:`TreeParameters` (with ``uniform_empty_dtrees`` and
    ``guide_delta_mixtures`` on, as there), and

    Parameters:
      c: S-tree split constant (default 12000, Müller's, for ``c_pixels``).
      c_pixels: the image size ``c`` is meant for (default :data:`PAPER_PIXELS`, 1280 × 720). A leaf splits when
        the iteration recorded more than ``c·sqrt(paths / (PAPER_SPP_UNIT·c_pixels))`` vertices in it, ``paths``
        the paths the iteration traced (pixels × spp): Tom94's ``c·sqrt(spp/4)`` at 1280 × 720, and at any size a
        threshold that grows as the square root of the samples, so that the leaves, and the vertices each leaf
        learns from, grow alike (``c`` ∝ sqrt(pixels) at a given spp). Set ``c_pixels`` to the image's pixel count
        for the unscaled ``c·sqrt(spp/4)``.
      base_spp: spp of iteration 0 (default 8, one default pass); iteration ``k`` spans ``base_spp·2^k`` spp.
      budget_spp: the render's spp budget, if known (the renderer sets it): the last iteration then runs to the
        end of the budget and records nothing.
      combine: the final image a renderer makes of the iterations, one of :data:`COMBINE_MODES` (default
        ``inverse-variance``, Müller 2019's improved preset; ``last`` is the 2017 paper's).
      spatial_filter: one of :data:`SPATIAL_FILTERS` (default ``nearest``, Tom94's default; ``stochastic`` is
        Müller 2019's improved preset).
    """

    uniform_empty_dtrees: bool = True
    guide_delta_mixtures: bool = True
    c: float = 12000.0
    c_pixels: int = PAPER_PIXELS
    base_spp: int = 8
    budget_spp: int | None = None
    combine: str = COMBINE_INVERSE_VARIANCE
    spatial_filter: str = "nearest"

    def __post_init__(self):
        super().__post_init__()
        _check(self.spatial_filter in SPATIAL_FILTERS,
               f"unknown spatial filter '{self.spatial_filter}' (choose from {', '.join(SPATIAL_FILTERS)})")
        _check(self.c > 0, f"c must be > 0, got {self.c}")
        _check(self.c_pixels >= 1, f"c_pixels must be >= 1, got {self.c_pixels}")
        _check(self.base_spp >= 1, f"base_spp must be >= 1, got {self.base_spp}")
        _check(self.combine in COMBINE_MODES,
               f"unknown combination '{self.combine}' (choose from {', '.join(COMBINE_MODES)})")


@dataclass(frozen=True)
class QuadtreeGridParameters(TreeParameters):
    """Kim & Kim's "Quadtree" baseline (:class:`~guiding.guides.trees.quadtree_grid.QuadtreeGridGuide`): the fields of
    :class:`TreeParameters`, and

    Parameters:
      spatial_resolution: S, cells per axis of the uniform grid, one D-tree each (default 8, as the grid guide).
    """

    spatial_resolution: int = 8

    def __post_init__(self):
        super().__post_init__()
        _check(1 <= self.spatial_resolution <= 256, f"S must be in 1..256, got {self.spatial_resolution}")
