"""Finding scenes by name through a search path, and loading them at a resolution scale.

A scene named ``NAME`` is the file ``DIR/NAME/scene.xml`` in the first directory ``DIR`` of the search path that
has one. The search path is, in order: directories passed explicitly (e.g. the config's ``scene_dirs``), those in
the environment variable ``GUIDING_SCENES`` (``os.pathsep``-separated), the project's own ``scenes/``, and the
shared Bitterli scenes ``../shared/scenes`` beside the project when present. A path to an XML file also works.
"""

from __future__ import annotations

import os
import re
import xml.etree.ElementTree as ElementTree
from collections.abc import Iterable
from pathlib import Path

from guiding.errors import GuidingError

PROJECT_ROOT = Path(__file__).resolve().parent.parent
ENV_VAR = "GUIDING_SCENES"


def search_path(extra_dirs: Iterable[str | os.PathLike] = ()) -> list[Path]:
    dirs = [Path(d) for d in extra_dirs]
    dirs += [Path(d) for d in os.environ.get(ENV_VAR, "").split(os.pathsep) if d]
    dirs += [PROJECT_ROOT / "scenes", PROJECT_ROOT.parent / "shared" / "scenes"]
    return [d for d in dirs if d.is_dir()]


def available_scenes(extra_dirs: Iterable[str | os.PathLike] = ()) -> list[str]:
    names = {p.parent.name for d in search_path(extra_dirs) for p in d.glob("*/scene.xml")}
    return sorted(names)


def find_scene(name: str, extra_dirs: Iterable[str | os.PathLike] = ()) -> Path:
    """The scene file for ``name`` (a scene name or a path to an XML file)."""
    if name.endswith(".xml"):
        if Path(name).is_file():
            return Path(name)
        raise GuidingError(f"scene file '{name}' does not exist")
    for folder in search_path(extra_dirs):
        candidate = folder / name / "scene.xml"
        if candidate.is_file():
            return candidate
    known = ", ".join(available_scenes(extra_dirs)) or "none"
    raise GuidingError(f"unknown scene '{name}' (known: {known}; add folders with ${ENV_VAR})")


def default_resolution(path: str | os.PathLike) -> tuple[int, int]:
    """The ``resx``/``resy`` defaults a scene file declares (its full resolution)."""
    try:
        root = ElementTree.parse(path).getroot()
    except (ElementTree.ParseError, OSError) as error:
        raise GuidingError(f"cannot read scene '{path}': {error}") from None
    defaults = {node.get("name"): node.get("value") for node in root.iter("default")}
    try:
        return int(defaults["resx"]), int(defaults["resy"])
    except (KeyError, ValueError):
        raise GuidingError(f"scene '{path}' does not declare integer <default name='resx'/'resy'> parameters, "
                           "so it cannot be rendered at a resolution scale") from None


def scaled_resolution(path: str | os.PathLike, scale: float) -> tuple[int, int]:
    if not scale > 0:
        raise GuidingError(f"resolution scale must be > 0, got {scale}")
    resx, resy = default_resolution(path)
    return max(1, round(resx * scale)), max(1, round(resy * scale))


def _one_line(error: Exception) -> str:
    """Mitsuba's error message on one line: its lines joined (the first often ends in a colon, the cause follows),
    without the ``[parser.cpp:1718]`` source location it starts with."""
    text = " ".join(line.strip() for line in str(error).splitlines() if line.strip())
    return re.sub(r"^\[[\w.]+:\d+\]\s*", "", text) or type(error).__name__


def load_scene(name: str, scale: float = 1.0, extra_dirs: Iterable[str | os.PathLike] = ()):
    """Load scene ``name`` at ``scale`` times its declared resolution (a Mitsuba variant must be set)."""
    import drjit as dr
    import mitsuba as mi

    path = find_scene(name, extra_dirs)
    resx, resy = scaled_resolution(path, scale)
    # Mitsuba's loader runs nested parallel tasks on Dr.Jit's thread pool, and with a single worker it deadlocks
    # (living-room with --threads 1 never finished loading). Loading is untimed, so it gets two.
    threads = dr.thread_count()
    try:
        dr.set_thread_count(max(threads, 2))
        return mi.load_file(str(path), resx=resx, resy=resy)
    except Exception as error:  # Mitsuba reports every load failure as a RuntimeError with a long message
        where = f"'{name}'" if str(path) == name else f"'{name}' ({path})"
        raise GuidingError(f"cannot load scene {where}: {_one_line(error)}") from None
    finally:
        dr.set_thread_count(threads)
