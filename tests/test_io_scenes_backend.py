"""Image I/O (EXR metadata, truncated files), strict JSON, the scene search path and broken scenes, and the backend's
start-up checks."""

import json

import numpy as np
import pytest

from guiding import backend

from guiding import imageio

from guiding import scenes
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


def test_exr_metadata_round_trip(tmp_path):
    metadata = {"method": "ours", "spp": 64, "seed": 3, "parameters": {"max_depth": 16, "seconds": float("nan")},
                "versions": {"mitsuba": "3.9.1"}}
    imageio.write_exr(tmp_path / "a.exr", np.zeros((2, 3, 3)), metadata)
    assert imageio.read_exr_metadata(tmp_path / "a.exr") == {**metadata, "parameters": {"max_depth": 16,
                                                                                         "seconds": None}}


@pytest.mark.parametrize("keep", [60, 400, 0.5, -1])
def test_truncated_exr_is_one_line_and_nothing_from_openexr(tmp_path, capfd, keep):
    """OpenEXR's core prints its own lines (stdout and stderr) about a truncated file; they are captured, and the
    error says what is wrong in one line."""
    imageio.write_exr(tmp_path / "full.exr", np.random.default_rng(0).random((64, 48, 3)))
    data = (tmp_path / "full.exr").read_bytes()
    cut = {0.5: len(data) // 2, -1: len(data) - 1}.get(keep, keep)   # in the header, in the pixels, the last byte
    (tmp_path / "cut.exr").write_bytes(data[:cut])
    with pytest.raises(GuidingError) as error:
        imageio.read_exr(tmp_path / "cut.exr")
    message = str(error.value)
    assert "\n" not in message and ("truncated or corrupt" in message) and "cut.exr" in message
    assert capfd.readouterr() == ("", "")


def test_strict_json_has_no_nan_or_infinity():
    from guiding import strict_json

    text = strict_json.dumps({"hit_rate": float("nan"), "values": [np.float32(np.inf), np.int64(3), (1.5, -np.inf)],
                              "array": np.array([1.0, np.nan])})
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"hit_rate": None, "values": [None, 3, [1.5, None]], "array": [1.0, None]}


def test_broken_scene_is_one_line_naming_the_cause(tmp_path):
    broken = tmp_path / "broken.xml"
    broken.write_text((scenes.PROJECT_ROOT / "scenes" / "cornell" / "scene.xml").read_text()
                      .replace('type="diffuse"', 'type="no-such-bsdf"', 1))
    with pytest.raises(GuidingError) as error:
        scenes.load_scene(str(broken), 0.1)
    message = str(error.value)
    assert "\n" not in message and 'plugin of type "no-such-bsdf"' in message and "[parser.cpp" not in message


def test_cuda_variant_without_a_gpu_names_the_fix(monkeypatch):
    monkeypatch.setattr(backend, "cuda_available", lambda: False)   # no NVIDIA driver, whatever this machine has
    with pytest.raises(backend.BackendError) as error:
        backend.set_variant("cuda_ad_rgb")
    assert "needs an NVIDIA GPU" in str(error.value) and "--variant llvm_ad_rgb" in str(error.value)


def test_cuda_driver_without_a_device_names_the_fix(monkeypatch):
    import drjit as dr

    monkeypatch.setattr(backend, "cuda_available", lambda: True)   # a driver, but no device Dr.Jit can start
    monkeypatch.setattr(dr, "has_backend", lambda jit_backend: False)
    with pytest.raises(backend.BackendError, match="cannot start a CUDA device.*--variant llvm_ad_rgb"):
        backend.set_variant("cuda_ad_rgb")
