"""Small hostile scenes built with ``mi.load_dict``, rendered progressively, and the sanity checks every render of
them must pass."""

from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from guiding.render.integrator import GuidedPathIntegrator
from guiding.guides.methods import grid_parameters, make_guide
from guiding.metrics import nonfinite_pixels
from guiding.render.progressive import Budget, render
from guiding.experiments.validation import Z_LIMIT
from arrays import EPS32, TINY32
from hostile import record_violations
from sdtree_parts import forest_violations

#: Methods every scene is rendered with: the baseline, the paper's method, and the SD-tree.
SCENE_METHODS = ("brdf", "ours", "sdtree")
#: Film side (pixels), passes and spp per pass of the scene cases: small, so the suite stays fast.
SCENE_PIXELS, SCENE_PASSES, SCENE_PASS_SPP = 16, 8, 4
ALBEDO = 0.5


def _transform(offset: float = 0.0, scale: float = 1.0):
    """``x ↦ scale·x + offset`` (on every axis), applied to a whole scene: shapes and camera."""
    return mi.ScalarTransform4f().translate([offset] * 3) @ mi.ScalarTransform4f().scale(scale)


def _sensor(origin, target, up=(0, 0, 1), fov: float = 50, scale: float = 1.0, transform=None) -> dict:
    """A perspective camera; with the scene scaled by ``scale``, its clip planes scale too (Mitsuba's default far
    plane, 1e4, would cut a scene of size 1e5 out of the picture)."""
    transform = transform or _transform()
    return {"type": "perspective", "fov": fov, "near_clip": 1e-2 * scale, "far_clip": 1e4 * scale,
            "to_world": mi.ScalarTransform4f().look_at(transform @ mi.ScalarPoint3f(origin),
                                                       transform @ mi.ScalarPoint3f(target), up),
            "film": {"type": "hdrfilm", "width": SCENE_PIXELS, "height": SCENE_PIXELS, "rfilter": {"type": "box"}},
            "sampler": {"type": "independent"}}


def _diffuse(albedo: float = ALBEDO) -> dict:
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": albedo}}


def closed_room(light_radius: float | None = 0.25, light_radiance: float = 10.0) -> dict:
    """A closed diffuse box [-1, 1]³ seen from inside, with a spherical light near the ceiling (or none)."""
    scene = {"type": "scene", "sensor": _sensor((0, -0.9, 0), (0, 1, 0), fov=80),
             "room": {"type": "cube", "flip_normals": True, "bsdf": _diffuse()},
             "box": {"type": "cube", "to_world": mi.ScalarTransform4f().translate([0.3, 0.3, -0.7]).scale(0.3),
                     "bsdf": _diffuse(0.8)}}
    if light_radius is not None:
        scene["light"] = {"type": "sphere", "center": [0, 0.2, 0.6], "radius": light_radius,
                          "emitter": {"type": "area", "radiance": {"type": "rgb", "value": light_radiance}}}
    return scene


def open_plane(with_cube: bool = True, offset: float = 0.0, scale: float = 1.0) -> dict:
    """A diffuse plane (z = 0, side 8), optionally a cube standing on it, under a uniform sky of radiance 1, seen
    from above; moved to ``offset`` and scaled by ``scale`` (geometry and camera)."""
    transform = _transform(offset, scale)
    scene = {"type": "scene", "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
             "plane": {"type": "rectangle", "to_world": transform @ mi.ScalarTransform4f().scale(4),
                       "bsdf": _diffuse()}}
    if with_cube:
        scene["sensor"] = _sensor((0, -3, 2.5), (0, 0, 0.3), scale=scale, transform=transform)
        scene["cube"] = {"type": "cube", "bsdf": _diffuse(0.8), "to_world": transform @ mi.ScalarTransform4f()
                         .translate([0, 0, 0.5]).scale(0.5)}
    else:
        scene["sensor"] = _sensor((0, 0, 2), (0, 0, 0), up=(0, 1, 0), fov=40, scale=scale, transform=transform)
    return scene


@dataclass
class SceneRun:
    """One progressive render of a stress scene: per-pass images ``(passes, H, W, 3)`` and their means
    ``(passes, 3)``, the final image, the per-pass statistics (:class:`~guiding.render.progressive.PassStats`) and the guide."""

    method: str
    pass_images: np.ndarray
    image: np.ndarray
    passes: list
    guide: object

    @property
    def means(self) -> np.ndarray:
        return self.pass_images.mean(axis=(1, 2))


def render_scene(scene_dict: dict, method: str, max_depth: int = 16, seed: int = 0,
                 passes: int = SCENE_PASSES) -> SceneRun:
    """Render a scene (a ``mi.load_dict`` dictionary) with ``method``: ``passes`` passes of SCENE_PASS_SPP spp."""
    props = mi.Properties()
    props["max_depth"] = max_depth
    # Grid guides count what they sample (statistics on): the checks below read the counters.
    guide = make_guide(method, statistics=True) if grid_parameters(method) is not None else make_guide(method)
    integrator = GuidedPathIntegrator(props, guide=guide)
    images = []
    result = render(mi.load_dict(scene_dict), integrator, Budget(spp=passes * SCENE_PASS_SPP, pass_spp=SCENE_PASS_SPP,
                                                                 growing_passes=False),
                    seed=seed, progress=False, on_pass=lambda stats, image: images.append(image))
    return SceneRun(method, np.array(images), result.image, result.passes, integrator.guide)


def _nonfinite_numbers(value, path: str = "") -> list[str]:
    """Paths of the non-finite numbers in a nested statistics dictionary."""
    if isinstance(value, dict):
        return [p for key, item in value.items() for p in _nonfinite_numbers(item, f"{path}.{key}")]
    if isinstance(value, (list, tuple)):
        return [p for i, item in enumerate(value) for p in _nonfinite_numbers(item, f"{path}[{i}]")]
    if isinstance(value, (int, float)) and not isinstance(value, bool) and not np.isfinite(value):
        return [f"{path} = {value}"]
    return []


def scene_run_violations(run: SceneRun) -> list[str]:
    """What is not sane about a render: a non-finite pixel or pass mean, a hit rate outside [0, 1], a non-finite
    statistic, an invalid share or acceptance rate outside [0, 1], proposals per sample above the cap, accumulator
    entries dropped or clamped (a physical scene has no bad input), or invalid guide tables."""
    problems = []
    if nonfinite_pixels(run.image):
        problems.append(f"{nonfinite_pixels(run.image)} non-finite pixels")
    if not np.isfinite(run.means).all():
        problems.append("a non-finite pass mean")
    for p in run.passes:
        if not 0 <= p.hit_rate <= 1:
            problems.append(f"pass {p.index}: hit rate {p.hit_rate}")
        problems += [f"pass {p.index}: {item}" for item in _nonfinite_numbers(p.guide, "guide")]
        for key in ("invalid_share", "acceptance_rate"):
            if p.guide.get(key) is not None and not 0 <= p.guide[key] <= 1:
                problems.append(f"pass {p.index}: {key} = {p.guide[key]}")
        if (p.guide.get("proposals_per_sample") or 0) > getattr(getattr(run.guide, "parameters", None),
                                                                "max_proposals", np.inf):
            problems.append(f"pass {p.index}: {p.guide['proposals_per_sample']} proposals per sample")
        for key in ("dropped_entries", "clamped_entries"):
            if p.guide.get(key):
                problems.append(f"pass {p.index}: {p.guide[key]} accumulator entries {key.split('_')[0]}")
    if hasattr(run.guide, "record_table"):
        problems += record_violations(run.guide.record_table)
    elif getattr(run.guide, "_sampling", None) is not None:
        problems += forest_violations(run.guide._sampling)
    return problems


def mean_difference_excess(means, expected) -> float:
    """How far the mean of per-pass means is from ``expected`` (a number, or another run's per-pass means), in
    units of the allowed difference: Z_LIMIT standard errors of the difference plus float32 rounding of the
    values (8 ε₃₂, for estimators without variance). ≤ 1 means they agree."""
    means = np.asarray(means, dtype=np.float64)
    variance = means.var(axis=0, ddof=1) / len(means)
    if isinstance(expected, np.ndarray):
        variance = variance + expected.var(axis=0, ddof=1) / len(expected)
        expected = expected.mean(axis=0)
    allowed = Z_LIMIT * np.sqrt(variance) + 8 * EPS32 * np.abs(expected)
    return float(np.max(np.abs(means.mean(axis=0) - expected) / np.maximum(allowed, TINY32)))

