"""The radiance record of Kim & Kim (2021): Q, the policy and the memo tables on a uniform grid (method.md §2, §4).

Layout: ``S³`` cells × ``B = 2·D²`` direction bins, flat, index ``cell·B + bin``. Memo tables are per
(cell, normal bin), index ``cell·NB + normal_bin``. Everything lives on the device and is rebuilt between passes
with Dr.Jit reductions and prefix sums (no host round trip but one ``dr.compress`` of the visited pairs).

Life cycle: :meth:`RadianceRecord.update` turns the accumulated targets (never cleared: ``Q = Σ target / visits``,
the learning rate 1/N) into Q, the policy ``P = (1 − ε)·(Q + 1e-6)/Σ(Q + 1e-6) + ε/B`` (ε floored, see
``MIN_EXPLORATION``), the per-cell alias table of P (``cell_alias``, for ``sphere_inv``), and the memo tables of
the (cell, normal bin) pairs the last passes visited:

- ``pair_memo``, a :class:`PairMemo` per pair, its four floats side by side so that a vertex reads them with one
  packet gather (the CPU backend compiles every gather of a single float into a load per lane):
  N = ∫_H P·cos dω, the normalising term of the hemisphere samplers; the row number of the pair's alias table;
  M ≥ max_H P·cos over every normal of the normal bin (a true bound, so rejection is exact); the in-bin miss share,
- ``value`` V = ∫_H Q·cos dω, Expected SARSA's expectation,
- ``hemi_alias``, the alias table (:mod:`~guiding.guides.alias_rows`) of P·∫_bin cos over the bins (``hemi_inv``,
  and the ``bins`` proposal of the rejection samplers), one row per visited pair only (469 rows on cornell-box at
  S = 8, against the 76 800 pairs of the grid), and in a row only the bins it can draw (``row_bins``: for hemi_inv
  those with a direction above the horizon of some normal of the normal bin, 368 of D = 16's 512 at most; for the
  rejection target those above the horizon of the normal bin's centre, 286 at most; the others have nothing to
  draw, and the rebuild after every pass need not build their slots); a slot's read gives the drawn bin with its
  density:
  ``P_k·s_k`` per unit cos⁺(ω, n_c) for the ``bins`` proposal (``P_k`` alone for a refined bin, whose sub-bin
  density multiplies it), ``P_k/A`` per steradian for ``hemi_inv``.

N and V use the cosine integrals at the normal bin's centre (exact there; the error elsewhere is measured in
``results/``), from a quadrature of at least 8×8 points per bin (more below D = 16, see ``quadrature_points``).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from guiding.guides.directions import NormalBins, SphereBins
from guiding.errors import GuidingError
from guiding.guides import alias_rows
from guiding.guides.grid_cells import GridCells
from guiding.guides.grid.refinement import BinRefinement
from guiding.guides.parameters import MIN_EXPLORATION
from guiding.guides.pass_sums import add_target, entry_sums, footprint, pass_sums, planned_footprint

#: Added to Q before normalising, so that no bin has zero probability (method.md §4).
Q_OFFSET = 1e-6
#: Largest Q kept. A larger running mean (fireflies of extreme emitters, or an overflow) is clamped to it, so that
#: every sum over a cell's bins stays finite in float32 (B·Q_LIMIT ≤ 2·256²·1e30 ≪ 3.4e38: the policy's
#: normaliser, Expected SARSA's V) and the smallest policy entry, Q_OFFSET/(B·Q_LIMIT) even with ε = 0, stays a
#: normal float (the CPU backend flushes denormals to zero).
Q_LIMIT = 1e30
#: Quadrature points per bin side for the cosine integrals: at least QUADRATURE, and at least
#: QUADRATURE_PER_HEMISPHERE/D, so that coarse bins get as many points per hemisphere as D = 16's (relative error
#: of N about 1e-4 at an axis normal). With 8 per side at D = 1 (a bin per hemisphere), N at a +z normal was 3 % too
#: large: a 3 % bias of the rejection samplers (the stress test `test_scene_with_one_cell_and_one_bin`).
QUADRATURE = 8
QUADRATURE_PER_HEMISPHERE = 128
#: Most quadrature points evaluated by one kernel (bounds the temporary memory of the cosine tables at ~100 MB).
QUADRATURE_WIDTH = 1 << 22


def quadrature_points(directional_resolution: int) -> int:
    """Quadrature points per bin side of the cosine integrals for ``D = directional_resolution``."""
    return max(QUADRATURE, -(-QUADRATURE_PER_HEMISPHERE // directional_resolution))
#: A bin reachable from the normal bin but with zero cosine integral at its centre keeps this share of its area,
#: so hemi_inv can still sample it for off-centre normals (no direction with f·cos > 0 has zero density).
REACHABLE_FLOOR = 0.01
#: Proposals of the in-bin rejection of the ``bins`` proposal (a direction of the drawn bin ∝ cos(ω, n_c)), all
#: drawn; when all are rejected the BSDF's direction is used, with the pair's probability ``in_bin_miss`` of that in
#: the density. Interior bins accept ~90 % of proposals; bins across the horizon less, and they are rarely drawn.
IN_BIN_PROPOSALS = 2
#: Bytes per slot of the visited pairs' alias rows while they are built: the slots, and the temporaries of their
#: construction and of the weights.
ROW_BUILD_BYTES = alias_rows.SLOT_BYTES + alias_rows.BUILD_BYTES + 8
#: Floats per pair in ``pair_memo`` (:class:`PairMemo`).
PAIR_FIELDS = 4
#: The slot of a bin that a normal bin's rows do not hold (``row_slots``).
NO_SLOT = 0xFFFFFFFF


@dataclass
class PairMemo:
    """What the samplers read about a vertex's (cell, normal bin) pair (:meth:`RadianceRecord.memo`)."""

    norm: mi.Float          # N at the normal bin's centre; 0: no memo yet (the pair was not visited before)
    row: mi.UInt32          # the pair's row of ``hemi_alias`` (its bits stored in a float slot)
    bound: mi.Float         # M ≥ max P·cos(ω, n) over the normal bin
    in_bin_miss: mi.Float   # the chance that every in-bin proposal is rejected (``bins`` proposal)


def exploration(spp_done: int, floor: float = MIN_EXPLORATION) -> float:
    """ε = max(0.1^(N/100), floor) for N samples per pixel completed before the pass (method.md §4)."""
    return max(0.1 ** (spp_done / 100.0), floor)


def _angular_radius(directions_of, count: int, centres: mi.Vector3f) -> mi.Float:
    """Largest angle between a bin's centre and its boundary (sampled densely, with a safety margin)."""
    steps = 17
    radius = dr.zeros(mi.Float, count)
    index = dr.arange(mi.UInt32, count)
    for i in range(steps):
        t = i / (steps - 1)
        for sample in ((t, 0.0), (t, 1.0), (0.0, t), (1.0, t)):
            d = directions_of(index, mi.Point2f(*sample))
            radius = dr.maximum(radius, dr.safe_acos(dr.dot(d, centres)))
    return radius * 1.05 + 1e-3


class RadianceRecord:
    """Q, accumulators, policy and memo tables of a ``S³ × 2·D²`` grid.

    Parameters:
      spatial_resolution: S, cells per axis of the scene's bounding box.
      directional_resolution: D (``2·D²`` bins).
      normal_resolution: R, odd, of the ``6·R²`` cube-map normal bins of the memo tables.
      needs_cell_alias: build the per-cell alias table over the sphere (``sphere_inv``).
      needs_memo: build N and M for visited (cell, normal bin) pairs (hemisphere samplers).
      needs_hemi_alias: build the per-pair alias tables (``hemi_inv``; with ``needs_in_bin``, the rejection
        samplers').
      needs_in_bin: the per-pair tables weigh each bin by its exact ∫ cos⁺(ω, n_c) (the rejection target, no floor),
        and the in-bin rejection's tables are built (``in_bin_bound``, ``in_bin_scale``, ``in_bin_misses``, and
        the pairs' in-bin miss share).
      needs_value: build V (Expected SARSA).
      min_exploration: floor of ε (0 gives the paper's schedule exactly; see MIN_EXPLORATION).
      sub_resolution: R > 1 refines the entries holding ``refine_share`` of their cell's policy into R × R
        sub-bins (:class:`~guiding.guides.grid.refinement.BinRefinement`, at most ``refine_capacity`` entries); record
        indices are then ``entry·R² + sub-bin``. 1: no refinement.
    """

    def __init__(self, spatial_resolution: int, directional_resolution: int, normal_resolution: int = 5,
                 needs_cell_alias: bool = False, needs_memo: bool = False, needs_hemi_alias: bool = False,
                 needs_in_bin: bool = False, needs_value: bool = False, min_exploration: float = MIN_EXPLORATION,
                 sub_resolution: int = 1, refine_share: float = 0.05, refine_capacity: int = 0):
        self.grid = GridCells(spatial_resolution)
        self.S = spatial_resolution
        self.min_exploration = min_exploration
        self.bins = SphereBins(directional_resolution)
        self.normal_bins = NormalBins(normal_resolution)
        self.cells = self.grid.count
        self.needs_cell_alias, self.needs_hemi_alias, self.needs_value = needs_cell_alias, needs_hemi_alias, needs_value
        self.needs_in_bin = needs_in_bin
        self.needs_pairs = needs_memo or needs_hemi_alias or needs_in_bin or needs_value
        B, NB, C = self.bins.count, self.normal_bins.count, self.cells

        self.sanitised: dict[str, int] = {}
        self.row_memory_limit: int | None = None     # bytes the visited pairs' alias rows may take (None: no limit)
        self.acc_sum = dr.zeros(mi.Float64, C * B)
        self.acc_count = dr.zeros(mi.Float64, C * B)
        self.pass_targets = pass_sums(C * B)
        self.q = dr.zeros(mi.Float, C * B)
        self.policy = dr.full(mi.Float, 1.0 / B, C * B)
        self.cell_alias = alias_rows.build(self.policy, B, 1 / self.bins.solid_angle) if needs_cell_alias else None
        if self.needs_pairs:
            self.visited = dr.zeros(mi.UInt32, C * NB)
            self.pair_memo = dr.zeros(mi.Float, PAIR_FIELDS * C * NB)
            self.value = dr.zeros(mi.Float, C * NB)
            # A row of B slots (no shorter than a pair's row), never read, until a visit.
            self.hemi_alias = dr.zeros(mi.Float, alias_rows.SLOT_FIELDS * B) if needs_hemi_alias else None
            self.normal_centres = dr.ravel(self.normal_bins.normal(dr.arange(mi.UInt32, NB)))     # x, y, z per bin
            self.cos_integral, self.max_cos = self._cosine_tables()
            self.in_bin_bound, self.in_bin_scale, self.in_bin_misses = (self._in_bin_tables() if needs_in_bin
                                                                        else (None, None, None))
            reach = self._row_layout(self.max_cos)
            self.reach_bins, self.reach_length = reach[0], reach[2]
            self.row_bins, self.row_slots, self.row_length = (self._row_layout(self.cos_integral) if needs_in_bin
                                                              else reach)
        self.refinement = (BinRefinement(self.bins, C * B, sub_resolution, refine_share, refine_capacity)
                           if sub_resolution > 1 else None)
        self.sub_resolution = sub_resolution
        self.fine = sub_resolution * sub_resolution
        self.refined_stats: dict[str, int] = {}
        # In memory, not literals: the untrained passes' tables are the same kind of input to a frozen pass as the
        # trained ones' (guiding.render.frozen_pass).
        pair_tables = ((self.visited, self.pair_memo, self.value, self.hemi_alias, self.normal_centres)
                       if self.needs_pairs else ())
        dr.make_opaque(self.acc_sum, self.acc_count, self.q, self.policy, *pair_tables)

    # ------------------------------------------------------------------ geometry
    def set_bounds(self, bbox: mi.BoundingBox3f) -> None:
        """Span the grid over the scene's bounding box ``bbox`` (:meth:`GridCells.set_bounds`)."""
        self.grid.set_bounds(bbox)

    def cell(self, p: mi.Point3f) -> mi.UInt32:
        """The flat index of the cell of position ``p``."""
        return self.grid.cell(p)

    def index(self, p: mi.Point3f, d: mi.Vector3f) -> mi.UInt32:
        """The record index of position ``p`` and unit world direction ``d``: the flat (cell, bin) entry, or with
        refinement ``entry·R² + sub-bin`` (:meth:`entry` gives the entry back)."""
        return self.cell(p) * (self.bins.count * self.fine) + self.fine_bin(d)

    def fine_bin(self, d: mi.Vector3f) -> mi.UInt32:
        """The bin of unit world direction ``d``, or with refinement ``bin·R² + sub-bin``."""
        return self.bins.fine_index(d, self.sub_resolution, unit=True)

    def entry(self, index: mi.UInt32) -> mi.UInt32:
        """The (cell, bin) entry of a record index (:meth:`index`)."""
        return index // self.fine if self.refinement else index

    def policy_at(self, cell: mi.UInt32, d: mi.Vector3f, active: mi.Bool = True) -> mi.Float:
        """P of unit world direction ``d``'s bin in ``cell``."""
        return dr.gather(mi.Float, self.policy, cell * self.bins.count + self.bins.index(d, unit=True), active)

    def pair(self, cell: mi.UInt32, n: mi.Vector3f) -> mi.UInt32:
        """Flat (cell, normal bin) index of a cell and a normal."""
        return cell * self.normal_bins.count + self.normal_bins.index(n)

    def normal_bin(self, pair: mi.UInt32) -> mi.UInt32:
        """The normal bin of (cell, normal bin) pairs ``pair`` (:meth:`pair`)."""
        return pair % self.normal_bins.count

    @dr.syntax
    def mark_visited(self, pair: mi.UInt32, new: mi.Bool) -> None:
        """Mark (cell, normal bin) pairs ``pair`` visited in the lanes ``new`` (:meth:`update` memoises them). A
        branch: once the guide has learned, few packets hold such a lane, and the others skip the scatter (on the CPU
        a loop over the packet's lanes)."""
        if new:
            dr.scatter(self.visited, mi.UInt32(1), pair, new)

    def normal_centre(self, pair: mi.UInt32, active: mi.Bool = True) -> mi.Vector3f:
        """The unit normal at the centre of the normal bin of (cell, normal bin) pairs ``pair``: one read of a table
        of 6·R² normals, in place of the cube map's arithmetic at every guided vertex."""
        return self._centre_of(self.normal_bin(pair), active)

    def _centre_of(self, normal_bin: mi.UInt32, active: mi.Bool = True) -> mi.Vector3f:
        """The centre of normal bin ``normal_bin``, from the table (the precomputations' normals too: one
        definition of n_c, and the memoised values are exact at the very normal the samplers read)."""
        return dr.gather(mi.Vector3f, self.normal_centres, normal_bin, active)

    def hemi_sample(self, pair: mi.UInt32, row: mi.UInt32, u: mi.Point2f,
                    active: mi.Bool) -> tuple[mi.UInt32, mi.Float]:
        """A bin drawn with ``u`` from row ``row`` of ``hemi_alias`` (the row of pair ``pair``), and its density
        (see the module's docstring)."""
        slot, density = alias_rows.sample(self.hemi_alias, row, self.row_length, u, active)
        k = dr.gather(mi.UInt32, self.row_bins, self.normal_bin(pair) * self.row_length + slot, active)
        return k, density

    def hemi_density(self, pair: mi.UInt32, row: mi.UInt32, k: mi.UInt32, active: mi.Bool) -> mi.Float:
        """The density of bin ``k`` in row ``row`` of ``hemi_alias`` (the row of pair ``pair``); 0 for a bin the row
        does not hold."""
        slot = dr.gather(mi.UInt32, self.row_slots, self.normal_bin_flat(pair, k), active)
        held = active & (slot != NO_SLOT)
        return dr.select(held, alias_rows.density(self.hemi_alias, row, self.row_length, slot, held), 0)

    def cell_density(self, cell: mi.UInt32, k: mi.UInt32, active: mi.Bool) -> mi.Float:
        """The density (per steradian) of bin ``k`` in ``cell``'s row of ``cell_alias``."""
        return alias_rows.density(self.cell_alias, cell, self.bins.count, k, active)

    def memo(self, pair: mi.UInt32, active: mi.Bool) -> PairMemo:
        """The memo of (cell, normal bin) pairs ``pair``, read with one packet gather."""
        fields = dr.gather(mi.Vector4f, self.pair_memo, pair, active)
        return PairMemo(norm=fields.x, row=dr.reinterpret_array(mi.UInt32, fields.y), bound=fields.z,
                        in_bin_miss=fields.w)

    def memo_columns(self) -> dict:
        """Every pair's memo as NumPy columns named like :class:`PairMemo`'s fields (for checks and inspection)."""
        import numpy as np

        columns = np.array(self.pair_memo).reshape(-1, PAIR_FIELDS)
        return {"norm": columns[:, 0], "row": columns[:, 1].view(np.uint32), "bound": columns[:, 2],
                "in_bin_miss": columns[:, 3]}

    # ------------------------------------------------------------ precomputation
    def _cosine_tables(self) -> tuple[mi.Float, mi.Float]:
        """Per (normal bin, bin), flat ``nb·B + k``: ∫_bin max(0, n_c·ω) dω at the normal bin's centre, and a
        bound on ``n·ω`` over all ω in the bin and all n in the normal bin."""
        B, NB, m = self.bins.count, self.normal_bins.count, quadrature_points(self.bins.resolution)
        flat = dr.arange(mi.UInt32, NB * B)
        nb, k = flat // B, flat % B
        normal = self._centre_of(nb)
        integral = dr.zeros(mi.Float, NB * B)
        # Per kernel: one row i of quadrature points and a chunk of `columns` of its points, side by side in the
        # array (at most QUADRATURE_WIDTH entries, whatever D) and summed per (normal bin, bin). The row and the
        # chunk's first column are opaque, so one compiled kernel serves every launch.
        columns = max(1, min(m, QUADRATURE_WIDTH // (NB * B)))
        wide = dr.arange(mi.UInt32, NB * B * columns)
        wide_k, offset = (wide // columns) % B, wide % columns
        wide_normal = self._centre_of(wide // (columns * B))
        for i in range(m):
            for first in range(0, m, columns):
                column = dr.opaque(mi.UInt32, first) + offset
                d = self.bins.direction(wide_k, mi.Point2f(dr.opaque(mi.Float, (i + 0.5) / m),
                                                           (mi.Float(column) + 0.5) / m))
                cosine = dr.select(column < m, dr.maximum(dr.dot(wide_normal, d), 0), 0)
                integral += dr.block_reduce(dr.ReduceOp.Add, cosine, columns)
                dr.eval(integral)
        integral *= self.bins.solid_angle / (m * m)

        bin_centres = self.bins.centres()
        normal_centres = self._centre_of(dr.arange(mi.UInt32, NB))
        bin_radius = _angular_radius(self.bins.direction, B, bin_centres)
        normal_radius = _angular_radius(self.normal_bins.normal, NB, normal_centres)
        angle = dr.safe_acos(dr.dot(normal, dr.gather(mi.Vector3f, bin_centres, k)))
        slack = dr.gather(mi.Float, bin_radius, k) + dr.gather(mi.Float, normal_radius, nb)
        max_cos = dr.maximum(dr.cos(dr.maximum(angle - slack, 0)), 0)
        dr.eval(integral, max_cos)
        return integral, max_cos

    def _in_bin_tables(self) -> tuple[mi.Float, mi.Float, mi.Float]:
        """Per (normal bin, bin), flat ``nb·B + k``, for the in-bin rejection ∝ cos(ω, n_c) at the normal bin's
        centre: the bound ``c_max ≥ cos(ω, n_c)`` over the bin; the scale s of the accepted directions' density
        ``s·cos⁺(ω, n_c)``; the probability m that all IN_BIN_PROPOSALS = K proposals are rejected.

        With acceptance ``a = ∫_bin cos⁺/(A·c_max)`` (A the bin's solid angle), the j-th proposal is the one accepted
        with probability (1 − a)^(j−1)·cos⁺/c_max: s = (1 − (1 − a)^K)/(a·A·c_max) and m = (1 − a)^K, so that
        ``s·∫_bin cos⁺ + m = 1``. Computed in float64 (a → 0 has the limit s = K/(A·c_max))."""
        import numpy as np

        B, NB = self.bins.count, self.normal_bins.count
        k = dr.arange(mi.UInt32, NB * B) % B
        normal = self._centre_of(dr.arange(mi.UInt32, NB * B) // B)
        centres = self.bins.centres()
        radius = dr.gather(mi.Float, _angular_radius(self.bins.direction, B, centres), k)
        angle = dr.safe_acos(dr.dot(normal, dr.gather(mi.Vector3f, centres, k)))
        bound = np.array(dr.cos(dr.maximum(angle - radius, 0)), dtype=np.float64)
        integral = np.array(self.cos_integral, dtype=np.float64)
        bound = np.where((bound > 0) & (integral > 0), np.minimum(bound, 1.0), 1.0)   # unreachable bins: never drawn
        area = self.bins.solid_angle
        a = np.clip(integral / (area * bound), 0.0, 1.0)
        miss = (1.0 - a) ** IN_BIN_PROPOSALS
        gain = np.where(a > 1e-12, (1.0 - miss) / np.maximum(a, 1e-300), float(IN_BIN_PROPOSALS))
        return tuple(mi.Float(t.astype(np.float32)) for t in (bound, gain / (area * bound), miss))

    def _row_layout(self, table: mi.Float) -> tuple[mi.UInt32, mi.UInt32, int]:
        """Rows of the bins of each normal bin whose entry in ``table`` (a per-(normal bin, bin) table) is positive,
        in order, padded with ``B`` (no bin, weight 0) to the largest count, the row length L. Returns the bins
        (``nb·L + slot``), the slot of every bin (``nb·B + k``; NO_SLOT where not held) and L.

        With ``max_cos``, the bins above the horizon of some normal of the normal bin (``reach_bins``: M's maximum
        runs over them, and hemi_inv's rows hold them all); with ``cos_integral``, those above the horizon of its
        centre, the only ones the rejection target can draw (the rows of the ``bins`` proposal: 286 of 368 at D = 16,
        a fifth less to rebuild after every pass)."""
        import numpy as np

        B, NB = self.bins.count, self.normal_bins.count
        held = np.array(table).reshape(NB, B) > 0
        length = max(int(held.sum(axis=1).max()), 1)
        nb, k = np.nonzero(held)                        # row by row, bins in order
        slot = (np.cumsum(held, axis=1) - 1)[nb, k]
        bins = np.full((NB, length), B, dtype=np.uint32)
        slots = np.full((NB, B), NO_SLOT, dtype=np.uint32)
        bins[nb, slot], slots[nb, k] = k, slot
        return mi.UInt32(bins.ravel()), mi.UInt32(slots.ravel()), length

    def normal_bin_flat(self, pair: mi.UInt32, k: mi.UInt32) -> mi.UInt32:
        """Index of the per-(normal bin, bin) tables (the in-bin tables, ``row_slots``) for bin ``k`` at the normal
        bin of ``pair``."""
        return self.normal_bin(pair) * self.bins.count + k

    # ------------------------------------------------------------------ learning
    def accumulate(self, index: mi.UInt32, target: mi.Float, active: mi.Bool) -> None:
        """Add ``target`` to record index ``index`` of this pass's sums (and one to its count), in the path loop
        (:mod:`~guiding.guides.pass_sums`); :meth:`update` folds them into the totals. With refinement, the
        entry's refined sub-bin gets it too."""
        if self.refinement:
            self.refinement.accumulate(index // self.fine, index % self.fine, target, active)
            index = index // self.fine
        add_target(self.pass_targets, index, target, active)

    def totals(self):
        """The sums and visit counts of every entry as float64 NumPy arrays, this pass's targets included."""
        import numpy as np

        pending = np.array(self.pass_targets).reshape(-1, 2)
        return np.array(self.acc_sum) + pending[:, 0], np.array(self.acc_count) + pending[:, 1]

    def _fold_pass_into_q(self) -> None:
        """Add the pass's sums and counts to the totals (and clear them for the next pass), and set Q, their mean
        clamped to Q_LIMIT, in one kernel. Drops the history of (cell, bin) entries whose totals hold NaN, ±Inf or a
        negative value (a bad target, or memory corruption): never cleared, they would keep Q, and through the
        normaliser the whole cell's policy, NaN forever. ``sanitised`` counts, for this update, the entries dropped
        and the entries whose Q was clamped."""
        added, visits = entry_sums(self.pass_targets, dr.arange(mi.UInt32, dr.width(self.acc_sum)))
        total, count = self.acc_sum + added, self.acc_count + visits
        mean = total / dr.maximum(count, 1)
        bad = ~(dr.isfinite(mean) & dr.isfinite(count) & (mean >= 0) & (count >= 0))
        clamped = ~bad & (count > 0) & (mean > Q_LIMIT)
        self.acc_sum, self.acc_count = dr.select(bad, 0, total), dr.select(bad, 0, count)
        self.q = mi.Float(dr.select(bad | (count == 0), 0, dr.minimum(mean, Q_LIMIT)))
        dr.eval(self.acc_sum, self.acc_count, self.q, bad, clamped)
        dropped_count, clamped_count = dr.count(bad), dr.count(clamped)
        dr.eval(dropped_count, clamped_count)        # both read back after one wait
        self.sanitised = {"dropped_entries": int(dropped_count[0]), "clamped_entries": int(clamped_count[0])}
        self.pass_targets = pass_sums(dr.width(self.acc_sum))

    # -------------------------------------------------------------------- update
    def update(self, spp_done: int) -> int:
        """Fold the pass's targets in, rebuild Q, the policy and what the samplers need; returns the number of
        memoised pairs."""
        B = self.bins.count
        self._fold_pass_into_q()
        epsilon = dr.opaque(mi.Float, exploration(spp_done, self.min_exploration))
        shifted = self.q + Q_OFFSET
        cell_of = dr.arange(mi.UInt32, self.cells * B) // B
        totals = dr.gather(mi.Float, dr.block_reduce(dr.ReduceOp.Add, shifted, B), cell_of)
        self.policy = (1 - epsilon) * shifted / totals + epsilon / B
        dr.eval(self.policy)
        if self.needs_cell_alias:
            self.cell_alias = alias_rows.build(self.policy, B, 1 / self.bins.solid_angle)
        if self.refinement:
            self.refined_stats = self.refinement.update(self.policy, self.q, self.acc_count)
        return self._update_memo() if self.needs_pairs else 0

    def _update_memo(self) -> int:
        B = self.bins.count
        pairs = dr.compress(self.visited != 0)
        count = dr.width(pairs)
        if count == 0:
            return 0
        length = self.row_length
        row_bytes = count * length * ROW_BUILD_BYTES
        if self.row_memory_limit is not None and row_bytes > self.row_memory_limit:
            raise GuidingError(f"the grid guide visited {count} (cell, normal bin) pairs: their alias rows need "
                               f"{row_bytes / 2 ** 30:.1f} GiB to build, over the "
                               f"{self.row_memory_limit / 2 ** 30:.1f} GiB left by the memory limit; lower S or D, "
                               "or raise the limit")
        # One entry per slot of the pairs' rows (_row_layout): N and V sum over the bins a row holds, the others
        # adding nothing (their cosines at the normal bin's centre are 0); M's maximum runs over every bin some
        # normal of the normal bin reaches (reach_bins).
        cell, nb, k, held = self._row_entries(pairs, self.row_bins, length)
        p = dr.gather(mi.Float, self.policy, cell * B + k, held)
        cos_integral = dr.gather(mi.Float, self.cos_integral, nb * B + k, held)
        # Evaluated once: every reduction below would otherwise repeat the gathers in its own kernel.
        dr.eval(cell, nb, k, p, cos_integral)

        norm = dr.block_reduce(dr.ReduceOp.Add, p * cos_integral, length)
        r_cell, r_nb, r_k, r_held = self._row_entries(pairs, self.reach_bins, self.reach_length)
        bound = alias_rows.block_max(dr.gather(mi.Float, self.policy, r_cell * B + r_k, r_held)
                                     * dr.gather(mi.Float, self.max_cos, r_nb * B + r_k, r_held), self.reach_length)
        row, in_bin_miss = dr.zeros(mi.UInt32, count), dr.zeros(mi.Float, count)
        if self.needs_value:
            q = dr.gather(mi.Float, self.q, cell * B + k, held)
            dr.scatter(self.value, dr.block_reduce(dr.ReduceOp.Add, q * cos_integral, length), pairs)
        if self.needs_hemi_alias:
            if self.needs_in_bin:
                weight = p * cos_integral
                miss = dr.gather(mi.Float, self.in_bin_misses, nb * B + k, held)
                scale = dr.select(held, dr.gather(mi.Float, self.in_bin_scale, nb * B + k, held), 1)
                if self.refinement:     # a refined bin draws its direction without rejection, from its sub-bins
                    refined = self.refinement.sampled(cell * B + k, held)
                    miss, scale = dr.select(refined, 0, miss), dr.select(refined, 1, scale)
                in_bin_miss = dr.block_reduce(dr.ReduceOp.Add, weight * miss, length) / norm
            else:      # the rows hold the bins reach_bins holds: those of max_cos > 0
                weight = p * dr.maximum(cos_integral, dr.select(held, REACHABLE_FLOOR * self.bins.solid_angle, 0))
                scale = 1 / self.bins.solid_angle
            self.hemi_alias = alias_rows.build(weight, length, scale)
            row = dr.arange(mi.UInt32, count)
        dr.scatter(self.pair_memo, mi.Vector4f(norm, dr.reinterpret_array(mi.Float, row), bound, in_bin_miss), pairs)
        dr.eval(self.pair_memo, self.value, self.hemi_alias)
        return count

    def _row_entries(self, pairs: mi.UInt32, bins: mi.UInt32, length: int):
        """Per slot of the rows of ``pairs`` in a layout (``bins``, ``length``: :meth:`_row_layout`): its cell,
        normal bin and bin, and whether it holds a bin (not padding)."""
        NB = self.normal_bins.count
        flat = dr.arange(mi.UInt32, dr.width(pairs) * length)
        pair = dr.gather(mi.UInt32, pairs, flat // length)
        cell, nb = pair // NB, pair % NB
        k = dr.gather(mi.UInt32, bins, nb * length + flat % length)
        return cell, nb, k, k < self.bins.count

    @staticmethod
    def planned_bytes(spatial_resolution: int, directional_resolution: int, normal_resolution: int = 5,
                      needs_cell_alias: bool = False, needs_memo: bool = False, needs_hemi_alias: bool = False,
                      needs_in_bin: bool = False, needs_value: bool = False, sub_resolution: int = 1,
                      refine_capacity: int = 0) -> int:
        """The bytes of the tables whose size is fixed when a record is built with these arguments, computed
        without allocating anything (so that an oversized table can be refused before it is built). The alias rows
        of the visited pairs (``hemi_alias``, at most 2·D² slots per pair: the bins a row holds, ``_row_layout``)
        come on top: they grow with the visits, and :meth:`_update_memo` checks them against ``row_memory_limit``."""
        C, B, NB = spatial_resolution ** 3, 2 * directional_resolution ** 2, 6 * normal_resolution ** 2
        total = C * B * (8 + 8 + 4 + 4) + planned_footprint(C * B)     # totals, Q, policy; pass sums
        if needs_cell_alias:
            total += alias_rows.SLOT_BYTES * C * B               # the cells' alias tables
        if needs_memo or needs_hemi_alias or needs_in_bin or needs_value:
            # the normal bins' centres, cosine and in-bin tables, and the row layouts (row_bins and reach_bins at most
            # NB·B each)
            total += 4 * ((PAIR_FIELDS + 2) * C * NB + 3 * NB + (8 if needs_in_bin else 4) * NB * B)
            total += alias_rows.SLOT_BYTES * B if needs_hemi_alias else 0                      # placeholder row
        if sub_resolution > 1:
            total += BinRefinement.planned_bytes(C * B, sub_resolution, refine_capacity)
        return total

    def memory_bytes(self) -> int:
        arrays = [self.acc_sum, self.acc_count, self.q, self.policy, self.cell_alias]
        if self.needs_pairs:
            arrays += [self.visited, self.pair_memo, self.value, self.hemi_alias, self.row_bins, self.row_slots,
                       self.normal_centres,
                       None if self.reach_bins is self.row_bins else self.reach_bins,
                       self.cos_integral, self.max_cos, self.in_bin_bound, self.in_bin_scale, self.in_bin_misses]
        refined = self.refinement.memory_bytes() if self.refinement else 0
        return refined + footprint(self.pass_targets) + sum(dr.width(a) * (8 if isinstance(a, mi.Float64) else 4)
                                                            for a in arrays if a is not None)
