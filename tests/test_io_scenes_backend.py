"""Image I/O, the scene search path, and the backend's start-up checks."""

import numpy as np
import pytest

from guiding import backend, imageio, scenes
from guiding.errors import GuidingError


def test_exr_round_trip_is_exact(tmp_path):
    image = np.random.default_rng(0).random((5, 7, 3)).astype(np.float32) * 100
    imageio.write_exr(tmp_path / "a.exr", image)
    np.testing.assert_array_equal(imageio.read_exr(tmp_path / "a.exr"), image)
    assert [p.name for p in tmp_path.iterdir()] == ["a.exr"]  # no temporary file left


def test_failed_write_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError):
        with imageio.atomic_path(tmp_path / "x.exr") as tmp:
            open(tmp, "w").write("partial")
            raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []


def test_preview_marks_nonfinite_pixels():
    image = np.array([[[0.5, 0.5, 0.5], [np.nan, 0, 0]]])
    preview = imageio.to_srgb8(image)
    assert tuple(preview[0, 1]) == (255, 0, 255) and preview[0, 0, 0] == 188


def test_scene_search_path(tmp_path, monkeypatch):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "scene.xml").write_text(
        '<scene version="3.0.0"><default name="resx" value="40"/><default name="resy" value="30"/></scene>')
    monkeypatch.setenv(scenes.ENV_VAR, str(tmp_path))
    assert scenes.find_scene("mine") == tmp_path / "mine" / "scene.xml"
    assert scenes.scaled_resolution(scenes.find_scene("mine"), 0.5) == (20, 15)
    assert {"cornell", "door-ajar", "mine"} <= set(scenes.available_scenes())
    with pytest.raises(GuidingError, match="unknown scene 'absent'"):
        scenes.find_scene("absent")


def test_shipped_scenes_load_at_scale():
    scene = scenes.load_scene("door-ajar", scale=0.1)
    assert [int(v) for v in scene.sensors()[0].film().size()] == [32, 24]


def test_missing_libllvm_names_the_fix(monkeypatch):
    monkeypatch.setattr(backend, "find_libllvm", lambda: None)
    with pytest.raises(backend.BackendError, match="apt-get install libllvm19"):
        backend.set_variant("llvm_ad_rgb")


def test_libllvm_version_parsing():
    assert backend._llvm_major("/usr/lib/libLLVM-19.so") == 19
    assert backend._llvm_major("/usr/lib/libLLVM.so.19.1") == 19
    assert backend._llvm_major("/usr/lib/libLLVM-15.so.1") == 15


def test_unknown_variant():
    with pytest.raises(GuidingError, match="unknown variant"):
        backend.resolve_variant("scalar_spectral")


def test_scene_with_nested_parallel_loading_loads_on_one_thread(tmp_path):
    """living-room (an environment map and many meshes) deadlocked Mitsuba's loader with --threads 1."""
    import subprocess
    import sys

    try:
        scenes.find_scene("living-room")
    except GuidingError:
        pytest.skip("the shared scene living-room is not on the search path")
    result = subprocess.run([sys.executable, "-m", "guiding", "reference", "--scene", "living-room", "--scale", "0.05",
                             "--spp", "1", "--threads", "1", "--quiet", "--out", str(tmp_path / "out")],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "out" / "image.exr").exists()
