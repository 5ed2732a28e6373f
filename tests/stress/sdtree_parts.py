"""What the stress tests reach inside the SD-tree guides (:mod:`guiding.guides.trees.sdtree`): its cylindrical direction
map, its forests and its accumulators. (Every import from that module is here, in one place.)"""

import drjit as dr
import mitsuba as mi
import numpy as np

from guiding.guides.trees.dtree import DeviceForest, dir_to_uv, uv_to_dir
from guiding.guides.methods import make_guide
from arrays import EPS32, ONE_MINUS_EPS32, to_numpy, unit, vectors
from direction_maps import readings, smallest_angle
from hostile import HOSTILE_ENTRIES, floor_scene
from tree_helpers import nested_forest

#: D-tree depths whose every leaf is checked, and deeper ones (to the default maximum 20) checked on random leaves.
CYLINDRICAL_DEPTHS = (1, 2, 3, 4, 6, 8)
CYLINDRICAL_DEEP = (12, 16, 20)


class CylindricalCells:
    """The SD-tree's directional square cut into ``2^depth × 2^depth`` cells: every D-tree leaf at that depth is
    one of them. ``cells`` (an ``(n, 2)`` array of (column, row)) selects which; all by default."""

    def __init__(self, depth: int, cells: np.ndarray | None = None):
        self.n = 1 << depth
        if cells is None:
            column, row = np.meshgrid(np.arange(self.n), np.arange(self.n))
            cells = np.stack([column.ravel(), row.ravel()], 1)
        self.cells = np.asarray(cells, dtype=np.int64)
        self.count = len(self.cells)
        self.solid_angle = 4 * np.pi / (self.n * self.n)

    def uv(self, k, sample):
        """The point at ``sample`` ∈ [0,1]² of cell ``k`` (float64 positions rounded once to float32)."""
        k = np.array(k, dtype=np.int64)
        s = np.broadcast_to(to_numpy(sample), (len(k), 2))
        return mi.Point2f((self.cells[k, 0] + s[:, 0]) / self.n, (self.cells[k, 1] + s[:, 1]) / self.n)

    def direction(self, k, sample):
        return uv_to_dir(self.uv(k, sample))

    def index(self, d) -> np.ndarray:
        """The position in ``cells`` of the cell of ``d`` (by :func:`~guiding.guides.trees.sdtree.dir_to_uv`), or
        ``count`` when that cell is not among them."""
        uv = to_numpy(dir_to_uv(d))
        key = np.floor(uv[:, 1] * self.n).astype(np.int64) * self.n + np.floor(uv[:, 0] * self.n).astype(np.int64)
        keys = self.cells[:, 1] * self.n + self.cells[:, 0]
        order = np.argsort(keys)
        position = np.clip(np.searchsorted(keys[order], key), 0, self.count - 1)
        found = keys[order][position] == key
        return np.where(found, order[position], self.count)


def cylindrical_cells(depth: int, count: int = 4096, seed: int = 0) -> CylindricalCells:
    """All cells at ``depth`` up to depth 8, else ``count`` random ones plus the cells at the poles and seams."""
    if depth <= 8:
        return CylindricalCells(depth)
    n = 1 << depth
    rng = np.random.default_rng(seed + depth)
    edges = [0, 1, n // 2 - 1, n // 2, n - 2, n - 1]
    special = np.array([(c, r) for c in edges for r in edges])
    return CylindricalCells(depth, np.unique(np.concatenate([special, rng.integers(0, n, size=(count, 2))]), axis=0))


#: Largest angle between a direction and its round trip through the cylindrical square: at a pole, a z error of
#: 2 ulps (u = (z + 1)/2 is rounded, then 2u − 1) moves the direction by √(2·Δz) = √(4·ε₃₂) ≈ 7e-4 rad.
CYLINDRICAL_ROUND_TRIP = float(np.sqrt(4 * EPS32)) * 1.5


def cylindrical_violations(directions: np.ndarray) -> list[str]:
    """Directions whose point on the SD-tree's square is outside [0, 1)² or NaN, or, for directions that have
    one, whose round trip through the square moves them more than :data:`CYLINDRICAL_ROUND_TRIP`."""
    directions = np.asarray(directions, dtype=np.float32).reshape(-1, 3)
    uv = dir_to_uv(vectors(directions))
    square = to_numpy(uv)
    outside = ~((square >= 0) & (square < 1)).all(axis=1)
    problems = [f"{tuple(d)} -> uv {tuple(p)}" for d, p in zip(directions[outside], square[outside])]
    kept, flushed = readings(directions)
    has_direction = np.isfinite(kept).all(axis=1) & np.isfinite(flushed).all(axis=1) & ~outside
    back = unit(to_numpy(uv_to_dir(uv)))[has_direction]
    angle = smallest_angle((kept[has_direction], flushed[has_direction]), back)
    moved = angle > CYLINDRICAL_ROUND_TRIP
    problems += [f"{tuple(x)} comes back {a:.3g} rad away" for x, a in zip(directions[has_direction][moved],
                                                                            angle[moved])]
    return problems


#: The SD-tree guides: Müller's SD-tree and Kim & Kim's uniform grid of split-only quadtrees.
TREE_METHODS = ("sdtree", "quadtree-grid")


def tree_guide(method: str):
    """A guide of ``method`` prepared on :func:`~hostile.floor_scene`, nothing learnt."""
    guide = make_guide(method)
    guide.prepare(floor_scene())
    return guide


def recording_forest(guide):
    """The host forest whose leaves the guide's energy accumulator addresses."""
    return guide._recording_host if hasattr(guide, "_recording_host") else guide._forest


def forest_violations(forest) -> list[str]:
    """What is wrong with a device forest: probabilities non-finite or outside [0, 1], or a node whose four
    probabilities do not sum to 1."""
    prob = np.array(forest.prob, dtype=np.float64)[: 4 * forest.n_nodes].reshape(-1, 4)
    problems = []
    if not np.isfinite(prob).all():
        problems.append(f"{np.count_nonzero(~np.isfinite(prob))} non-finite probabilities")
    elif not ((prob >= 0) & (prob <= 1)).all():
        problems.append("probabilities outside [0, 1]")
    elif not (np.abs(prob.sum(axis=1) - 1) <= 4 * EPS32).all():
        problems.append(f"node probabilities sum to {prob.sum(axis=1)[np.abs(prob.sum(axis=1) - 1) > 4 * EPS32][:3]}")
    return problems


def hostile_tree(method: str, kind: str) -> tuple:
    """Two prepared guides of ``method`` with recorded energies and vertex counts: one holding
    ``HOSTILE_ENTRIES[kind]`` in a leaf of tree 0, one holding it sanitised."""
    spec = HOSTILE_ENTRIES[kind]
    hostile, expected = tree_guide(method), tree_guide(method)
    slots = recording_forest(hostile).leaf_table()[1]
    energy, visits = (np.zeros(4 * recording_forest(hostile).n_nodes) for _ in range(2))
    if spec:
        energy[slots] = np.random.default_rng(len(kind)).uniform(0.5, 2, len(slots))
        visits[slots] = 100
    bad_energy, bad_visits = energy.copy(), visits.copy()
    bad_energy[slots[5]] = spec.get("sum", energy[slots[5]])
    bad_visits[slots[0]] = spec.get("count", visits[slots[0]])
    clean_energy = np.where(np.isfinite(bad_energy) & (bad_energy >= 0), bad_energy, 0)
    clean_visits = np.where(np.isfinite(bad_visits) & (bad_visits >= 0), bad_visits, 0)
    fill_sums(hostile, bad_energy, bad_visits)
    fill_sums(expected, clean_energy, clean_visits)
    dropped = int(np.count_nonzero(bad_energy != clean_energy) + np.count_nonzero(bad_visits != clean_visits))
    return hostile, expected, dropped


def fill_sums(guide, energy: np.ndarray, visits: np.ndarray) -> None:
    """Make ``guide``'s recorded sums ``energy`` and ``visits`` (per leaf slot of its recording forest), as if its
    render kernels had recorded them."""
    sums = np.zeros(dr.width(guide._leaf_sums))
    sums[0: 2 * len(energy): 2], sums[1: 2 * len(visits): 2] = energy, visits
    guide._leaf_sums = mi.Float64(sums)


def chain(depth: int, energy: float, quadrant: int = 3) -> list:
    """A nested D-tree (see :func:`tree_helpers.nested_forest`) whose energy sits in quadrant ``quadrant`` at every level
    down to ``depth``."""
    node: object = energy
    for _ in range(depth - 1):
        node = [0.0] * quadrant + [node] + [0.0] * (3 - quadrant)
    return [0.0] * quadrant + [node] + [0.0] * (3 - quadrant)


#: The most degenerate D-trees a guide can sample from: all energy in one leaf of side 2^-20 (in the last corner and
#: in the first), only denormal energies, and energies 60 orders of magnitude apart.
DEGENERATE_TREES = {"one leaf at depth 20": chain(20, 1.0), "one leaf at depth 20, corner 0": chain(20, 1.0, 0),
                    "denormal energies": [1e-40, 1e-45, [1e-40] * 4, 0.0],
                    "1e30 beside 1e-30": [1e30, 1e-30, 0.0, 1e-30]}


def sample_from(guide, method: str, tree: list) -> None:
    """Make ``guide`` (a :func:`tree_guide` of ``method``) sample every direction from the nested D-tree ``tree``."""
    forest = nested_forest([tree])
    if method == "quadtree-grid":       # every cell of the grid gets the same tree
        forest = forest.rebuild(np.zeros(guide.S ** 3, dtype=np.int64), "copy")
    guide._sampling = DeviceForest(forest)


def square_edge_directions() -> np.ndarray:
    """The directions of the corners and edges of the SD-tree's square, as float32 points of it (1 − 2⁻²⁴ is the
    largest coordinate below 1)."""
    edge = np.array([0, 2.0 ** -24, 0.5, ONE_MINUS_EPS32], dtype=np.float32)
    corners = np.stack(np.meshgrid(edge, edge), -1).reshape(-1, 2)
    return to_numpy(uv_to_dir(mi.Point2f(corners[:, 0], corners[:, 1])))
