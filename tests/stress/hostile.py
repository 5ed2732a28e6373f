"""Hostile input for the guides: grid tables, extreme samples and synthetic paths, and finders of what an update or
a sampler got wrong. (The SD-tree's own hostile forests are in `sdtree_parts.py`.)

A guided estimator divides by learned densities, so one zero, denormal or NaN in a table could poison a whole
sweep unnoticed: these helpers put the worst values a table, a sample or a path can hold where a guide reads them.
"""

import functools
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from guiding.guides.directions import NormalBins, SphereBins
from guiding.guides.alias_rows import SLOT_FIELDS, drawn_probability
from guiding.guides.grid.guide import GridGuide
from guiding.guides.grid.record import Q_LIMIT
from guiding.guides.methods import grid_parameters
from arrays import EPS32, ONE_MINUS_EPS32, TINY32, to_numpy, vectors


@functools.lru_cache(maxsize=None)
def floor_scene():
    """A diffuse unit square at z = 0 (no sensor, no emitter): enough to prepare a guide on."""
    return mi.load_dict({"type": "scene", "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"}}})


#: Contents injected into one accumulator entry (``sum`` or ``count``), and what the update must make of it:
#: ``dropped`` entries lose their history (counted), ``clamped`` ones keep it with Q clamped to Q_LIMIT (counted).
HOSTILE_ENTRIES = {
    "all-zero": dict(),
    "1e30": dict(sum=1e30),
    "1e39 (beyond float32)": dict(sum=1e39, clamped=True),
    "float32 denormal": dict(sum=1e-40),
    "float64 denormal": dict(sum=1e-310),
    "NaN": dict(sum=float("nan"), dropped=True),
    "+Inf": dict(sum=float("inf"), dropped=True),
    "-Inf": dict(sum=float("-inf"), dropped=True),
    "negative": dict(sum=-5.0, dropped=True),
    "NaN count": dict(count=float("nan"), dropped=True),
    "Inf count": dict(count=float("inf"), dropped=True),
}


def grid_guide(method: str, S: int = 2, D: int = 4, min_exploration: float | None = None):
    """A grid guide of ``method`` at resolution S, D over the unit cube (its bounds set, nothing learnt), with its
    statistics counters on."""
    overrides = {"spatial_resolution": S, "directional_resolution": D, "statistics": True}
    if min_exploration is not None:
        overrides["min_exploration"] = min_exploration
    guide = GridGuide(grid_parameters(method), **overrides)
    guide.record_table.set_bounds(mi.BoundingBox3f(mi.ScalarPoint3f(0), mi.ScalarPoint3f(1)))
    return guide


def fill_record(record, sums: np.ndarray, counts: np.ndarray) -> None:
    """Give a record accumulators (float64, as the device holds them) and mark every (cell, normal bin) visited."""
    record.acc_sum, record.acc_count = mi.Float64(sums), mi.Float64(counts)
    if record.needs_pairs:
        record.visited = dr.full(mi.UInt32, 1, record.cells * record.normal_bins.count)


def record_arrays(record) -> dict:
    """Every table an update builds, as NumPy arrays."""
    names = ["q", "policy", "cell_alias", "value", "hemi_alias"]
    arrays = {name: np.array(getattr(record, name)) for name in names if getattr(record, name, None) is not None}
    if record.needs_pairs:
        arrays.update(record.memo_columns())
    return arrays


def record_violations(record) -> list[str]:
    """What is wrong with a record's tables after an update: anything non-finite, a policy entry that is not a
    positive normal float or a cell whose policy does not sum to 1, an alias table with a threshold outside [0, 1],
    an alias outside its row, rows that do not draw with total probability 1, density 0 for a bin it draws, an alias
    density that is not its bin's, or (sphere_inv) a density other than the drawn probability per steradian, a memo with N ≤ 0 or a bound M below the mean
    ū = N/2π of P·cos, or Q outside [0, Q_LIMIT]."""
    B = record.bins.count
    tables = record_arrays(record)
    problems = [f"{name} has {np.count_nonzero(~np.isfinite(a))} non-finite entries" for name, a in tables.items()
                if not np.isfinite(a).all()]
    q, policy = tables["q"], tables["policy"].reshape(-1, B)
    if not ((q >= 0) & (q <= Q_LIMIT)).all():
        problems.append(f"Q outside [0, {Q_LIMIT:g}]: {q[(q < 0) | (q > Q_LIMIT)][:3]}")
    if not (policy >= TINY32).all():
        problems.append(f"policy entries below the smallest normal float: {policy[policy < TINY32][:3]}")
    sums = policy.astype(np.float64).sum(axis=1)
    if not (np.abs(sums - 1) <= B * EPS32).all():
        problems.append(f"cell policies sum to {sums[np.abs(sums - 1) > B * EPS32][:3]}")
    rows = [("cell_alias", tables.get("cell_alias"), B)]
    if record.needs_pairs and record.hemi_alias is not None and np.count_nonzero(np.array(record.visited)):
        # one row of row_length slots per visited pair
        rows.append(("hemi_alias", tables["hemi_alias"], record.row_length))
    for name, slots, size in rows:
        if slots is None:
            continue
        slots = slots.reshape(-1, size, SLOT_FIELDS)
        threshold, alias, density = slots[..., 0], slots[..., 1].view(np.uint32), slots[..., 2]
        if not ((threshold >= 0) & (threshold <= 1) & (alias < size)).all():
            problems.append(f"{name} has thresholds outside [0, 1] or aliases outside the row")
        drawn = drawn_probability(slots, size)
        if not ((density >= 0).all() and (density[drawn > 0] > 0).all()):
            problems.append(f"{name} has negative densities, or density 0 for a bin it draws")
        if not (np.abs(drawn.sum(axis=1) - 1) <= size * EPS32).all():
            problems.append(f"{name} rows draw with total probability {drawn.sum(axis=1)[:3]} instead of 1")
        if not np.array_equal(slots[..., 3], np.take_along_axis(density, alias.astype(np.int64), axis=1)):
            problems.append(f"{name} slots carry an alias density other than the alias bin's")
        if name == "cell_alias" and not np.allclose(density * record.bins.solid_angle, drawn, rtol=1e-5, atol=0):
            problems.append(f"{name} densities are not the probabilities sphere_inv draws with")
    if record.needs_pairs:
        visited = np.array(record.visited) != 0
        norm, bound, value = tables["norm"][visited], tables["bound"][visited], tables["value"][visited]
        if not (norm >= TINY32).all():
            problems.append(f"N not a positive normal float: {norm[norm < TINY32][:3]}")
        if not (bound >= norm / (2 * np.pi) * (1 - 1e-5)).all():
            problems.append("bound M below the mean of P·cos")
        if not (value >= 0).all():
            problems.append(f"V negative: {value[value < 0][:3]}")
    return problems


def hostile_grid(method: str, kind: str, min_exploration: float | None) -> tuple:
    """Two guides of ``method``: one whose accumulators hold ``HOSTILE_ENTRIES[kind]`` in one entry of cell 0,
    and one holding what the update should turn that entry into (zeros if dropped, Q_LIMIT if clamped)."""
    spec = HOSTILE_ENTRIES[kind]
    hostile, expected = (grid_guide(method, min_exploration=min_exploration) for _ in range(2))
    record = hostile.record_table
    size, entry = record.cells * record.bins.count, 3
    rng = np.random.default_rng(len(kind))
    if spec:
        sums, counts = rng.uniform(0, 2, size) * 4, np.full(size, 4.0)
    else:
        sums, counts = np.zeros(size), np.zeros(size)
    bad_sums, bad_counts = sums.copy(), counts.copy()
    bad_sums[entry] = spec.get("sum", sums[entry])
    bad_counts[entry] = spec.get("count", counts[entry])
    if spec.get("dropped"):
        sums[entry] = counts[entry] = 0.0
    elif spec.get("clamped"):
        sums[entry], counts[entry] = Q_LIMIT, 1.0
    else:
        sums, counts = bad_sums, bad_counts
    fill_record(record, bad_sums, bad_counts)
    fill_record(expected.record_table, sums, counts)
    return hostile, expected


def spiked_guide(method: str, spike, normal, D: int = 16, min_exploration: float = 0.0):
    """A trained grid guide (cell 0 of S = 2) whose Q is Q_LIMIT in the bin of direction ``spike`` and 0 elsewhere,
    with the paper's exploration schedule after 10 000 spp (ε = 1e-100): the most peaked policy a table can hold.
    The (cell, normal bin) pair of ``normal`` is memoised."""
    guide = grid_guide(method, S=2, D=D, min_exploration=min_exploration)
    record = guide.record_table
    size = record.cells * record.bins.count
    sums, counts = np.zeros(size), np.zeros(size)
    k = int(np.array(record.bins.index(vectors(np.array([spike]))))[0])
    sums[k], counts[k] = Q_LIMIT, 1.0
    fill_record(record, sums, counts)
    record.visited = dr.zeros(mi.UInt32, record.cells * record.normal_bins.count)
    dr.scatter(record.visited, mi.UInt32(1), record.pair(mi.UInt32(0), vectors(np.array([normal]))))
    guide.update(spp_done=10_000)
    return guide


class FixedSampler:
    """A stand-in for ``mi.Sampler`` that returns the same chosen values at every call: ``next_1d`` gives ``u``,
    ``next_2d`` gives ``uv`` (per lane). It drives samplers to the extremes of their inputs (0 and 1 − 2⁻²⁴); only
    for code without a symbolic loop over the sampler's state."""

    def __init__(self, u, uv):
        self.u, self.uv = u, uv

    def next_1d(self, active=True):
        return self.u

    def next_2d(self, active=True):
        return self.uv


def extreme_samples(size_per_value: int = 1) -> tuple:
    """All combinations of u, and both coordinates of uv, in {0, 0.5, 1 − 2⁻²⁴}: ``(u, uv)`` as NumPy arrays."""
    values = np.array([0.0, 0.5, ONE_MINUS_EPS32], dtype=np.float32)
    grid = np.stack(np.meshgrid(values, values, values), -1).reshape(-1, 3)
    grid = np.repeat(grid, size_per_value, axis=0)
    return grid[:, 0], grid[:, 1:]


def sample_violations(si, bs, weight) -> list[str]:
    """Lanes whose direction leaves on the side the path arrived from (f·cos > 0 for a diffuse BSDF) with a
    density that is not positive and finite, and lanes whose weight is not finite."""
    pdf, w = np.array(bs.pdf), np.array(weight).reshape(3, -1)
    usable = to_numpy(bs.wo)[:, 2] * np.sign(np.array(si.wi.z)) > 0
    problems = [f"lane {i}: direction {tuple(to_numpy(bs.wo)[i])} with pdf {pdf[i]}"
                for i in np.flatnonzero(usable & ~(np.isfinite(pdf) & (pdf > 0)))]
    problems += [f"lane {i}: weight {w[:, i]}" for i in np.flatnonzero(~np.isfinite(w).all(axis=0))]
    return problems


def sampler_normals() -> np.ndarray:
    """Normals at which the samplers are driven: the axes (walls) and an oblique normal-bin centre, both sides."""
    oblique = to_numpy(NormalBins(5).normal(mi.UInt32([7])))[0]
    return np.array([(0, 0, 1), (0, 0, -1), (1, 0, 0), oblique, -oblique], dtype=np.float32)


#: Longest path of the synthetic batches (the renderer's default max_depth).
TARGET_DEPTH = 16
#: Emitted radiance at hostile vertices: none, ordinary, extreme and the largest float32.
HOSTILE_EMISSION = (0.0, 1.0, 1e30, 3e38)
#: Densities of the directions sampled at hostile vertices (the weight is 0.5/pdf): ordinary, tiny, and the
#: smallest normal float32 (weights 0.5, 5e29, 2.5e37). The last vertex of every path has pdf 0 and weight 0.
HOSTILE_PDF = (1.0, 1e-30, 2e-38)


@dataclass
class SyntheticPaths:
    """A batch of paths on :func:`floor_scene` fed to a guide's ``record`` vertex by vertex.

    ``length[l]`` vertices for lane ``l`` (every length 1 … TARGET_DEPTH occurs); at depth ``j`` all lanes leave
    in the direction of sphere bin ``j`` (D = 4: one bin per depth). ``emitted``, ``pdf`` and ``weight`` are
    ``(lanes, depth)`` arrays; a path's last vertex has pdf 0 and weight 0. ``position`` is the lanes' (x, y).
    """

    length: np.ndarray
    emitted: np.ndarray
    pdf: np.ndarray
    weight: np.ndarray
    position: tuple

    @classmethod
    def benign(cls, position=(-0.5, -0.5)) -> "SyntheticPaths":
        """Emission 1 and weight 0.5 everywhere: targets with closed forms."""
        length = np.arange(1, TARGET_DEPTH + 1)
        shape = (len(length), TARGET_DEPTH)
        return cls(length, np.ones(shape), np.ones(shape), np.full(shape, 0.5), position)._end_paths()

    @classmethod
    def hostile(cls, position=(0.5, 0.5)) -> "SyntheticPaths":
        """Every length four times, with every combination of HOSTILE_EMISSION and HOSTILE_PDF along the paths."""
        length = np.tile(np.arange(1, TARGET_DEPTH + 1), 4)
        lane, depth = np.meshgrid(np.arange(len(length)), np.arange(TARGET_DEPTH), indexing="ij")
        emitted = np.array(HOSTILE_EMISSION)[(lane + depth) % len(HOSTILE_EMISSION)]
        pdf = np.array(HOSTILE_PDF)[(lane // TARGET_DEPTH + 2 * depth) % len(HOSTILE_PDF)]
        weight = (np.float32(0.5) / pdf.astype(np.float32)).astype(np.float64)
        return cls(length, emitted, pdf, weight, position)._end_paths()

    def _end_paths(self) -> "SyntheticPaths":
        depth = np.arange(TARGET_DEPTH)[None, :]
        last = depth == self.length[:, None] - 1
        self.pdf, self.weight = np.where(last, 0.0, self.pdf), np.where(last, 0.0, self.weight)
        return self

    @property
    def lanes(self) -> int:
        return len(self.length)

    def continues(self, depth: int) -> np.ndarray:
        return depth < self.length - 1

    def records(self) -> int:
        """Targets a grid guide records: one per segment after the camera's, ``Σ (length − 1)``."""
        return int(np.sum(self.length - 1))

    def run(self, guide) -> None:
        """Feed the batch to ``guide`` (``new_paths``, ``record`` at every depth, ``finish_paths``)."""
        scene = floor_scene()
        origin = mi.Point3f(self.position[0], self.position[1], 1)
        si = scene.ray_intersect(mi.Ray3f(origin, mi.Vector3f(0, 0, -1)))
        si = dr.gather(type(si), si, dr.zeros(mi.UInt32, self.lanes))      # the same vertex in every lane
        directions = SphereBins(4).centres()
        state = guide.new_paths(self.lanes, TARGET_DEPTH)
        for depth in range(TARGET_DEPTH):
            bs = dr.zeros(mi.BSDFSample3f, self.lanes)
            bs.wo = si.to_local(dr.gather(mi.Vector3f, directions, mi.UInt32(depth)))
            bs.pdf = mi.Float(self.pdf[:, depth].astype(np.float32))
            with np.errstate(over="ignore"):
                emitted = mi.Color3f(mi.Float(self.emitted[:, depth].astype(np.float32)))
                weight = mi.Color3f(mi.Float(self.weight[:, depth].astype(np.float32)))
            active = mi.Bool(depth < self.length)
            state = guide.record(state, si, emitted, bs, weight, mi.Bool(self.continues(depth)), active)
        guide.finish_paths(state)

    def expected_grid_targets(self, rule: str) -> dict[int, tuple[float, int]]:
        """{depth i: (sum of targets, count)} recorded into the bin of depth i's direction by a guide with all-zero
        tables: MC records ``L_{i+1} = Σ_m Le_m Π w`` at every vertex that continues; SARSA and Expected SARSA
        (no memo yet) record ``Le_{i+1}`` for the segment i → i+1."""
        out = {}
        for i in range(TARGET_DEPTH - 1):
            lanes = np.flatnonzero(self.continues(i))
            if not len(lanes):
                continue
            if rule == "mc":
                radiance = np.zeros(len(lanes))
                for m in range(TARGET_DEPTH - 1, i, -1):
                    alive = m < self.length[lanes]
                    radiance = np.where(alive, self.emitted[lanes, m] + self.weight[lanes, m] * radiance, radiance)
                targets = radiance
            else:
                targets = self.emitted[lanes, i + 1]
            out[i] = (float(np.sum(targets)), len(lanes))
        return out

