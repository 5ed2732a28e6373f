"""What a trained guide learned: its directional distributions saved beside a render (``guide.npz``, written by
``python -m guiding render --save-guide``) and drawn as a picture (``python -m guiding show-guide``).

Two kinds of guide are understood:

* ``grid`` (the grid methods, :class:`~guiding.guides.grid.guide.GridGuide`): per cell of a uniform ``S³`` grid, the
  policy P over the ``2·D²`` equal-area bins of :class:`~guiding.guides.directions.SphereBins` (each of solid angle
  ``4π/B``, so the density is ``P·B/(4π)`` per steradian);
* ``dtrees`` (``sdtree``: one D-tree per leaf of its spatial S-tree; ``quadtree-grid``: one per cell of a uniform
  grid): every leaf of every sampling D-tree over the cylindrical square ``(u, v)``, ``u = (cos θ + 1)/2`` and
  ``v = φ/2π``, with its energy; a leaf's density is its share of its tree's energy over its area, ``/(4π)`` per
  steradian (a tree without energy is uniform).

Both are the guide's own distribution, before the mixture with BSDF sampling that the samplers draw from.

A *cell* is the index of one distribution: a grid cell ``(z·S + y)·S + x``, or a D-tree. The state also holds how
to find the cell of a point (the grid's bounds, or the S-tree) and a weight per cell (the grid's visits, a
D-tree's energy), so the best-trained cell can be shown by default.

The guides' attributes are read in :func:`capture` alone (by name, not by importing the guide classes, which may
move between modules): a rename inside :mod:`guiding.guides` is one line to fix here.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from guiding.errors import GuidingError

#: The file a render's saved guide state goes to.
STATE_FILE = "guide.npz"


# ------------------------------------------------------------------------------------------ saving

def _vector(value) -> np.ndarray:
    """A Mitsuba 3-vector (a width-1 Dr.Jit array) or a sequence as a float64 array of shape (3,)."""
    return np.asarray(value, dtype=np.float64).reshape(3)


def _cells_state(cells) -> dict:
    """How to find a point's cell in a uniform grid (:class:`~guiding.guides.grid_cells.GridCells`)."""
    return {"locator": "grid", "S": cells.S, "bbox_min": _vector(cells.bbox_min),
            "inv_extent": _vector(cells.inv_extent)}


def _grid_state(record) -> dict:
    """The state of a grid guide's radiance record (:class:`~guiding.guides.grid.record.RadianceRecord`)."""
    bins = record.bins.count
    return {"kind": "grid", **_cells_state(record.grid), "D": record.bins.resolution,
            "policy": np.asarray(record.policy.numpy(), np.float32).reshape(record.cells, bins),
            "weight": record.totals()[1].reshape(record.cells, bins).sum(axis=1)}


def _dtree_state(forest) -> dict:
    """The leaves of a sampling forest of D-trees (``Forest``: its ``leaf_table`` and tree count)."""
    tree, _, u0, v0, side, energy = forest.leaf_table()
    return {"kind": "dtrees", "trees": forest.n_trees, "leaf_tree": tree.astype(np.int32), "leaf_u0": u0,
            "leaf_v0": v0, "leaf_side": side, "leaf_energy": energy,
            "weight": np.bincount(tree, weights=energy, minlength=forest.n_trees)}


def _stree_state(stree) -> dict:
    """The S-tree of an SD-tree guide: node boxes, first child (-1: leaf), split axis and the leaves' D-trees."""
    return {"locator": "stree", "stree_lo": np.asarray(stree.lo, np.float64),
            "stree_hi": np.asarray(stree.hi, np.float64),
            "stree_child": np.asarray(stree.child, np.int64), "stree_axis": np.asarray(stree.axis, np.int64),
            "stree_tree": np.asarray(stree.tree, np.int64)}


def capture(guide) -> dict:
    """The state of a trained ``guide`` (host arrays; see the module docstring). The only place that knows the
    guides' attribute names."""
    name = getattr(guide, "name", type(guide).__name__)
    if getattr(guide, "record_table", None) is not None:                      # GridGuide
        return {"method": name, **_grid_state(guide.record_table)}
    if getattr(guide, "stree", None) is not None:                             # SDTreeGuide
        return {"method": name, **_dtree_state(guide._sampling_host), **_stree_state(guide.stree)}
    if getattr(guide, "_forest", None) is not None:                           # QuadtreeGridGuide
        return {"method": name, **_dtree_state(guide._forest), **_cells_state(guide._cells)}
    raise GuidingError(f"method '{name}' learns no directional distribution to save (only the grid methods, "
                       "sdtree and quadtree-grid do)")


def save(path: str | Path, state: dict) -> None:
    """Write ``state`` (:func:`capture`) as a compressed .npz file to ``path`` (a file name ending in .npz)."""
    np.savez_compressed(path, **{key: np.asarray(value) for key, value in state.items()})


def load(path: str | Path) -> dict:
    """A state written by :func:`save`; a missing or unreadable file is a GuidingError."""
    try:
        with np.load(path, allow_pickle=False) as data:
            state = {key: data[key] for key in data.files}
    except FileNotFoundError:
        raise GuidingError(f"no saved guide state '{path}': render with --save-guide") from None
    except (OSError, ValueError) as error:
        raise GuidingError(f"cannot read guide state '{path}': {error}") from None
    return {key: (value.item() if value.ndim == 0 else value) for key, value in state.items()}


# ------------------------------------------------------------------------------------------ cells

def cell_count(state: dict) -> int:
    return len(state["weight"])


def check_cell(state: dict, cell: int) -> int:
    if not 0 <= cell < cell_count(state):
        raise GuidingError(f"cell {cell} does not exist: the guide has cells 0..{cell_count(state) - 1}")
    return cell


def best_cell(state: dict) -> int:
    """The cell with the most training (visits of a grid cell, energy of a D-tree)."""
    return int(np.argmax(state["weight"]))


def cell_of_point(state: dict, point) -> int:
    """The cell whose distribution guides directions at world position ``point``."""
    p = np.asarray(point, dtype=np.float64).reshape(3)
    if state["locator"] == "grid":
        S = int(state["S"])
        index = np.clip(np.floor((p - state["bbox_min"]) * state["inv_extent"] * S).astype(int), 0, S - 1)
        return int((index[2] * S + index[1]) * S + index[0])
    node = 0
    child, axis = state["stree_child"], state["stree_axis"]
    while child[node] >= 0:
        a = axis[node]
        middle = 0.5 * (state["stree_lo"][node, a] + state["stree_hi"][node, a])
        node = child[node] + int(p[a] >= middle)
    return int(state["stree_tree"][node])


def cell_bounds(state: dict, cell: int) -> tuple[np.ndarray, np.ndarray]:
    """(lower corner, upper corner) of the region of space where ``cell`` guides."""
    if state["locator"] == "grid":
        S = int(state["S"])
        index = np.array([cell % S, cell // S % S, cell // (S * S)], dtype=np.float64)
        extent = 1.0 / state["inv_extent"]
        return state["bbox_min"] + index / S * extent, state["bbox_min"] + (index + 1) / S * extent
    node = int(np.nonzero((state["stree_child"] < 0) & (state["stree_tree"] == cell))[0][0])
    return state["stree_lo"][node], state["stree_hi"][node]


# ------------------------------------------------------------------------------------------ densities

def square_directions(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """World directions (..., 3) of points of the cylindrical square: ``cos θ = 2u − 1`` (θ from +z),
    ``φ = 2πv``."""
    u, v = np.broadcast_arrays(np.asarray(u, np.float64), np.asarray(v, np.float64))
    cos_theta = 2 * u - 1
    sin_theta = np.sqrt(np.maximum(1 - cos_theta ** 2, 0))
    phi = 2 * np.pi * v
    return np.stack([np.cos(phi) * sin_theta, np.sin(phi) * sin_theta, cos_theta], axis=-1)


def _grid_density(state: dict, cell: int, directions: np.ndarray) -> np.ndarray:
    import mitsuba as mi

    from guiding.guides.directions import SphereBins

    bins = SphereBins(int(state["D"]))
    flat = directions.reshape(-1, 3)
    index = bins.index(mi.Vector3f(flat[:, 0], flat[:, 1], flat[:, 2])).numpy()
    return state["policy"][cell][index].astype(np.float64) * bins.count / (4 * math.pi)


def _dtree_density(state: dict, cell: int, directions: np.ndarray) -> np.ndarray:
    flat = directions.reshape(-1, 3)
    norm = np.linalg.norm(flat, axis=1)
    u = np.clip((flat[:, 2] / norm + 1) / 2, 0, np.nextafter(1, 0))
    v = np.mod(np.arctan2(flat[:, 1], flat[:, 0]) / (2 * np.pi), 1.0)
    mine = state["leaf_tree"] == cell
    energy, total = state["leaf_energy"][mine], state["leaf_energy"][mine].sum()
    if total <= 0:
        return np.full(len(flat), 1 / (4 * math.pi))
    density = np.zeros(len(flat))
    for u0, v0, side, e in zip(state["leaf_u0"][mine], state["leaf_v0"][mine], state["leaf_side"][mine], energy):
        inside = (u >= u0) & (u < u0 + side) & (v >= v0) & (v < v0 + side)
        density[inside] = e / total / (side * side)
    return density / (4 * math.pi)


def density(state: dict, cell: int, directions: np.ndarray) -> np.ndarray:
    """The guide's density per steradian in ``cell`` at world ``directions`` (..., 3); shape (...)."""
    check_cell(state, cell)
    directions = np.asarray(directions, dtype=np.float64)
    values = (_grid_density if state["kind"] == "grid" else _dtree_density)(state, cell, directions)
    return values.reshape(directions.shape[:-1])


def density_image(state: dict, cell: int, width: int = 360, height: int = 180) -> np.ndarray:
    """The density (per steradian) of ``cell`` on an equal-area grid of ``height × width`` directions: columns
    φ from 0 to 2π, rows cos θ from +1 (top: world +z) to −1. Every pixel covers the same solid angle, so the
    mean of the image times 4π is the distribution's total mass (1)."""
    v = (np.arange(width) + 0.5) / width
    u = 1 - (np.arange(height) + 0.5) / height
    return density(state, cell, square_directions(u[:, None], v[None, :]))


# ------------------------------------------------------------------------------------------ pictures

def first_vertex(stats: dict, x: int, y: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(position, {"normal": n, "to camera": ω}) of the first surface seen through the centre of pixel (x, y) of
    the render ``stats`` (its stats.json: scene file and scale), by one ray cast; the normal faces the camera."""
    import mitsuba as mi

    from guiding.scenes import load_scene

    scene = load_scene(stats["scene_file"], stats["scale"])
    sensor = scene.sensors()[0]
    width, height = (int(v) for v in sensor.film().size())
    if not (0 <= x < width and 0 <= y < height):
        raise GuidingError(f"pixel ({x}, {y}) is outside the {width}x{height} image")
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f((x + 0.5) / width, (y + 0.5) / height), mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    if not bool(si.is_valid()[0]):
        raise GuidingError(f"pixel ({x}, {y}) sees no surface (the ray leaves the scene)")
    to_camera = -_vector(ray.d)
    normal = _vector(si.sh_frame.n)
    return _vector(si.p), {"normal": normal if normal @ to_camera >= 0 else -normal, "to camera": to_camera}


def _square_position(direction: np.ndarray) -> tuple[float, float]:
    """(φ in degrees, cos θ) of a world direction: where it lies in :func:`density_image`."""
    d = direction / np.linalg.norm(direction)
    return float(np.degrees(np.arctan2(d[1], d[0])) % 360), float(d[2])


def draw(state: dict, cell: int, out: str | Path, title: str, marks: dict[str, np.ndarray] | None = None) -> None:
    """Write a picture of ``cell``'s distribution to ``out`` (PNG): the density per steradian over the equal-area
    square of directions (φ across, cos θ up; log colour scale down to 1/1000 of the peak), the cell's bounds, and
    ``marks`` (name → world direction) as labelled points."""
    from matplotlib.colors import LogNorm

    from guiding.experiments.figures import new_figure, save_figure

    image = density_image(state, cell)
    peak = float(image.max())
    norm = LogNorm(vmin=peak * 1e-3, vmax=peak) if peak > 0 else None
    figure = new_figure(8.0, 4.6)
    ax = figure.subplots()
    shown = ax.imshow(np.maximum(image, peak * 1e-3), extent=(0, 360, -1, 1), aspect="auto", cmap="inferno",
                      norm=norm, interpolation="nearest")
    for (name, direction), marker in zip((marks or {}).items(), "o^sv"):
        phi, cos_theta = _square_position(direction)
        ax.plot(phi, cos_theta, marker, markersize=8, markerfacecolor="none", markeredgecolor="cyan", label=name)
    if marks:
        ax.legend(fontsize=8, loc="lower right")
    ax.set_xticks(range(0, 361, 45))
    ax.set_xlabel("φ (degrees, about the world z axis)")
    ax.set_ylabel("cos θ (world z)")
    low, high = cell_bounds(state, cell)
    kind = "grid cell" if state["kind"] == "grid" else "D-tree"
    ax.set_title(f"{title}\n{state['method']}: {kind} {cell}, from ({', '.join(f'{v:.3g}' for v in low)}) to "
                 f"({', '.join(f'{v:.3g}' for v in high)}); equal-area map, the guide alone (no BSDF share)",
                 fontsize=8)
    figure.colorbar(shown, ax=ax, label="guide density (1/sr)")
    save_figure(figure, out)
