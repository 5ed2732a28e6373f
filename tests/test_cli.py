"""The command line: the documented forms work (image metadata, strict JSON, error maps, show-guide), and bad input
gets one line, a non-zero exit and no output (not even an empty folder)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from guiding import backend

from guiding.experiments import guide_state

from guiding import imageio
from guiding.cli import main

ROOT = Path(__file__).resolve().parent.parent


def _png(path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as image:
        assert image.format == "PNG"
        return np.asarray(image)


def _one_error_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:"), err
    return err[0]


def strict_load(path) -> dict:
    """A JSON file parsed as strict readers do: NaN and Infinity are no JSON."""
    def refuse(token):
        raise ValueError(f"{path}: non-standard JSON token {token}")

    return json.loads(path.read_text(), parse_constant=refuse)


def test_render_and_evaluate(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["render", "--scene", "cornell", "--scale", "0.1", "--method", "brdf", "--spp", "8",
                 "--out", str(out), "--quiet", "--seed", "5"]) == 0
    assert {p.name for p in out.iterdir()} == {"image.exr", "preview.png", "stats.json"}
    stats = strict_load(out / "stats.json")
    assert stats["spp"] == 8 and stats["method"] == "brdf" and stats["resolution"] == [26, 26]
    assert stats["provenance"]["variant"] == "llvm_ad_rgb" and len(stats["per_pass"]) == 1
    capsys.readouterr()
    assert main(["evaluate", str(out / "image.exr"), str(out / "image.exr"), "--error-map",
                 str(tmp_path / "flip.png")]) == 0
    metrics = json.loads(capsys.readouterr().out)
    assert metrics["mae"] == 0 and metrics["nonfinite_pixels"] == 0
    assert {"flip", "mse", "smape", "relmse_trimmed"} <= set(metrics) and metrics["flip"] == 0
    assert _png(tmp_path / "flip.png").shape[2] in (3, 4)


def test_render_exr_carries_what_made_it(tmp_path):
    """The EXR header says what made the image: method, parameters, spp, seed, scene, variant, versions, device."""
    import drjit as dr
    import mitsuba as mi

    out = tmp_path / "run"
    assert main(["render", "--scene", "cornell", "--scale", "0.1", "--method", "ours-S4-D8", "--spp", "16",
                 "--seed", "7", "--max-depth", "5", "--out", str(out), "--quiet", "--snapshots"]) == 0
    metadata = imageio.read_exr_metadata(out / "image.exr")
    assert (metadata["method"], metadata["spp"], metadata["seed"], metadata["scene"]) == ("ours-S4-D8", 16, 7,
                                                                                          "cornell")
    assert metadata["variant"] == "llvm_ad_rgb" and metadata["device"].startswith("CPU: ")
    assert metadata["versions"]["mitsuba"] == mi.__version__ and metadata["versions"]["drjit"] == dr.__version__
    assert metadata["versions"]["guiding"] and metadata["versions"]["flip-evaluator"]
    assert metadata["parameters"]["max_depth"] == 5 and metadata["parameters"]["budget"]["spp"] == 16
    assert (metadata["guide"]["S"], metadata["guide"]["D"], metadata["guide"]["rule"]) == (4, 8, "sarsa")
    snapshot = imageio.read_exr_metadata(out / "image_snap00008.exr")
    assert snapshot["spp"] == 8 and snapshot["method"] == "ours-S4-D8"


def test_set_is_the_shorthand_bit_for_bit(tmp_path):
    """`--method ours --set spatial_resolution=4` is `--method ours-S4`: the same guide, the same image to the bit,
    and the same method label in what the render writes."""
    images, labels = [], []
    for name, method in (("shorthand", ["ours-S4"]), ("set", ["ours", "--set", "spatial_resolution=4"])):
        out = tmp_path / name
        assert main(["render", "--scene", "cornell", "--scale", "0.1", "--method", *method, "--spp", "16",
                     "--seed", "3", "--out", str(out), "--quiet"]) == 0
        images.append(imageio.read_exr(out / "image.exr"))
        stats = strict_load(out / "stats.json")
        labels.append((stats["method"], stats["guide"]["S"], stats["guide"]["D"]))
    assert np.array_equal(images[0], images[1]) and images[0].std() > 0
    assert labels == [("ours-S4", 4, 16)] * 2


def test_reference_writes_outputs_and_strict_json(tmp_path):
    out = tmp_path / "ref"
    assert main(["reference", "--scene", "cornell", "--scale", "0.05", "--spp", "16", "--out", str(out),
                 "--quiet"]) == 0
    stats = strict_load(out / "stats.json")   # Mitsuba's `path` reports no hit rate: null, not NaN
    assert stats["method"] == "reference-path" and stats["hit_rate"] is None
    assert imageio.read_exr_metadata(out / "image.exr")["method"] == "reference-path"


@pytest.mark.parametrize("args, message", [
    (["--scene", "no-such-scene", "--method", "brdf", "--spp", "8"], "unknown scene"),
    (["--scene", "cornell", "--method", "no-such-method", "--spp", "8"], "unknown method"),
    (["--scene", "cornell", "--method", "brdf", "--spp", "0"], "must be > 0"),
    (["--scene", "cornell", "--method", "brdf", "--seconds", "-2"], "must be > 0"),
    (["--scene", "cornell", "--method", "brdf"], "required"),
    (["--scene", "cornell", "--method", "ours", "--set", "spatial_res=4", "--spp", "8"],
     "method 'ours' has no parameter 'spatial_res' (its parameters: spatial_resolution, "),
    (["--scene", "cornell", "--method", "ours", "--set", "spatial_resolution=four", "--spp", "8"],
     "method 'ours': spatial_resolution='four' is not an integer"),
    (["--scene", "cornell", "--method", "ours", "--set", "spatial_resolution=0", "--spp", "8"],
     "method 'ours' with spatial_resolution=0: S and D must be in 1..256"),
    (["--scene", "cornell", "--method", "ours", "--set", "statistics", "--spp", "8"],
     "--set expects FIELD=VALUE, got 'statistics'"),
    (["--scene", "cornell", "--method", "brdf", "--set", "bsdf_fraction=0.5", "--spp", "8"],
     "method 'brdf' takes no parameters, got bsdf_fraction"),
    (["--scene", "cornell", "--method", "ours", "--spp", "8", "--path-fallback"],
     "--path-fallback hands passes to Mitsuba's path, which samples emitters: add --nee"),
])
def test_bad_render_input(tmp_path, capsys, args, message):
    out = tmp_path / "out"
    assert main(["render", *args, "--out", str(out)]) == 2
    assert message in _one_error_line(capsys)
    assert not out.exists() or not any(out.iterdir())


NO_EMITTER_SCENE = """<scene version="3.0.0">
    <default name="resx" value="16"/><default name="resy" value="16"/>
    <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="$resx"/>
        <integer name="height" value="$resy"/></film></sensor>
    <shape type="rectangle"><bsdf type="diffuse"/></shape>
</scene>"""


def test_nee_on_a_scene_without_emitters_is_one_line_and_writes_nothing(tmp_path):
    """In a real process: exit code 2, one line, no output folder; Mitsuba's path, which ignores --nee, renders."""
    scene = tmp_path / "dark.xml"
    scene.write_text(NO_EMITTER_SCENE)
    command = [sys.executable, "-m", "guiding", "render", "--scene", str(scene), "--method", "ours", "--nee", "--spp",
               "8", "--quiet", "--out", str(tmp_path / "out")]
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 2 and done.stdout == "", done.stderr[-2000:]
    assert done.stderr.splitlines() == ["error: nee samples emitters, and this scene has none: render it without nee"]
    assert not (tmp_path / "out").exists()
    command[command.index("ours")] = "path"
    assert subprocess.run(command, capture_output=True, cwd=ROOT).returncode == 0
    assert strict_load(tmp_path / "out" / "stats.json")["nee"] is True


def test_demo_entries_are_parsed_once_into_methods_and_nee():
    from guiding.cli.parser import DemoEntry, parse_args

    args = parse_args(["demo", "--methods", "path,ours+nee,ours-S4,ours+nee+fallback"])
    assert args.methods == (DemoEntry("path"), DemoEntry("ours", True), DemoEntry("ours-S4"),
                            DemoEntry("ours", True, True))
    assert [entry.name for entry in args.methods] == ["path", "ours+nee", "ours-S4", "ours+nee+fallback"]
    assert args.methods[1].render_args() == ["--method", "ours", "--nee"]
    assert args.methods[3].render_args() == ["--method", "ours", "--nee", "--path-fallback"]
    default = parse_args(["demo"])
    assert (default.seconds, default.spp) == (5.0, None)
    assert [e.name for e in default.methods][:3] == ["path", "brdf", "ours"] and any(e.nee for e in default.methods)


@pytest.mark.parametrize("args, message", [
    (["--methods", "ours+nee,ours+nee"], "'ours+nee' is given twice"),
    (["--methods", ","], "no method given"),
    (["--methods", "path,ours+nees"], "unknown method 'ours+nees'"),
    (["--methods", "path,ours+fallback"], "the path fallback needs next-event estimation, write ours+nee+fallback"),
    (["--seconds", "2", "--spp", "8"], "not allowed with argument"),
])
def test_bad_demo_input_writes_nothing(tmp_path, capsys, args, message):
    out = tmp_path / "demo"
    assert main(["demo", *args, "--out", str(out)]) == 2
    assert message in _one_error_line(capsys) and not out.exists()


def test_demo_compares_methods_with_and_without_nee_at_equal_time(tmp_path):
    """The summary: method, nee, spp, seconds (counted, each at least the budget), MAE, relMSE and the efficiency
    relative to path (MAE²·t of path over the method's; 1 for path)."""
    out = tmp_path / "demo"
    assert main(["demo", "--scene", "cornell", "--scale", "0.05", "--seconds", "0.3", "--reference-spp", "64",
                 "--methods", "path,brdf,brdf+nee,ours+nee+fallback", "--out", str(out)]) == 0
    lines = (out / "summary.md").read_text().splitlines()
    assert lines[0] == "# cornell at scale 0.05, 0.3 s each"
    header, _, *rows = [[cell.strip() for cell in line.strip("|").split("|")] for line in lines[2:8]]
    assert header == ["method", "nee", "fallback", "spp", "seconds", "mae", "relmse", "efficiency_vs_path"]
    assert [row[:3] for row in rows[:3]] == [["path", "True", ""], ["brdf", "False", ""], ["brdf", "True", ""]]
    assert rows[3][:2] == ["ours", "True"] and rows[3][2] in ("guide", "path")
    mae, seconds, efficiency = ([float(row[header.index(k)]) for row in rows] for k in ("mae", "seconds",
                                                                                       "efficiency_vs_path"))
    assert min(seconds) >= 0.3 and efficiency[0] == 1
    # The table rounds to four digits: its MAE and seconds give the efficiency to a few parts in a thousand.
    assert efficiency[2] == pytest.approx(mae[0] ** 2 * seconds[0] / (mae[2] ** 2 * seconds[2]), rel=6e-3)
    assert {p.name for p in out.iterdir()} == {"path", "brdf", "brdf+nee", "ours+nee+fallback",
                                               "reference-cornell-x0.05-64spp", "summary.md"}


def test_unwritable_output(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["render", "--scene", "cornell", "--method", "brdf", "--spp", "1", "--out", str(blocker)]) == 2
    assert "not a folder" in _one_error_line(capsys)


def test_evaluate_bad_files(tmp_path, capsys):
    small, large = tmp_path / "small.exr", tmp_path / "large.exr"
    imageio.write_exr(small, np.zeros((2, 2, 3)))
    imageio.write_exr(large, np.zeros((3, 2, 3)))
    assert main(["evaluate", str(small), str(large)]) == 2
    assert "differ in size" in _one_error_line(capsys)
    assert main(["evaluate", str(small), str(tmp_path / "missing.exr")]) == 2
    assert "no such file" in _one_error_line(capsys)
    truncated = tmp_path / "truncated.exr"
    truncated.write_bytes(large.read_bytes()[:60])
    assert main(["evaluate", str(truncated), str(small)]) == 2
    assert "header is truncated or corrupt" in _one_error_line(capsys)


def test_broken_scene_is_one_line_and_leaves_no_folder(tmp_path, capsys):
    broken = tmp_path / "broken.xml"
    broken.write_text((ROOT / "scenes" / "cornell" / "scene.xml").read_text()
                      .replace('type="diffuse"', 'type="no-such-bsdf"', 1))
    out = tmp_path / "new" / "out"
    assert main(["render", "--scene", str(broken), "--method", "brdf", "--spp", "8", "--out", str(out)]) == 2
    assert 'failed to instantiate bsdf plugin of type "no-such-bsdf"' in _one_error_line(capsys)
    assert not (tmp_path / "new").exists()   # the folders the command made are gone again
    broken.write_text(broken.read_text()[:700])   # cut off: not even XML
    assert main(["reference", "--scene", str(broken), "--spp", "8", "--out", str(out)]) == 2
    assert "cannot read scene" in _one_error_line(capsys) and not (tmp_path / "new").exists()


def test_cuda_variant_without_a_gpu(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(backend, "cuda_available", lambda: False)   # no NVIDIA driver, whatever this machine has
    out = tmp_path / "out"
    assert main(["render", "--scene", "cornell", "--method", "brdf", "--spp", "8", "--variant", "cuda_ad_rgb",
                 "--out", str(out)]) == 2
    assert "variant cuda_ad_rgb needs an NVIDIA GPU" in _one_error_line(capsys) and not out.exists()


def test_truncated_exr_in_a_real_process_is_one_line(tmp_path):
    """OpenEXR's own lines about the truncated file (its core prints them) do not reach the terminal."""
    imageio.write_exr(tmp_path / "ref.exr", np.random.default_rng(0).random((64, 48, 3)))
    data = (tmp_path / "ref.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[:len(data) // 2])
    done = subprocess.run([sys.executable, "-m", "guiding", "evaluate", str(tmp_path / "cut.exr"),
                           str(tmp_path / "ref.exr")], capture_output=True, text=True)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.count("\n") == 1 and "cut.exr': not a readable EXR file: truncated or corrupt (" in done.stderr


def test_real_process_prints_no_traceback(tmp_path):
    done = subprocess.run([sys.executable, "-m", "guiding", "render", "--scene", "nope", "--method", "brdf",
                           "--spp", "4", "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert done.returncode == 2
    assert done.stderr.strip().startswith("error: unknown scene") and "Traceback" not in done.stderr


@pytest.fixture(scope="module")
def saved_guide(tmp_path_factory):
    """A render of `ours` that saved what its guide learned (render --save-guide)."""
    out = tmp_path_factory.mktemp("guide") / "run"
    assert main(["render", "--scene", "cornell", "--scale", "0.1", "--method", "ours", "--spp", "16", "--save-guide",
                 "--out", str(out), "--quiet"]) == 0
    return out


def test_show_guide_draws_a_cell_and_the_first_vertex_of_a_pixel(saved_guide, capsys):
    capsys.readouterr()
    state = guide_state.load(saved_guide / "guide.npz")
    assert state["kind"] == "grid" and state["policy"].shape == (8 ** 3, 2 * 16 ** 2)
    assert main(["show-guide", str(saved_guide)]) == 0          # the best trained cell by default
    best = guide_state.best_cell(state)
    assert f"cell {best} of 512" in capsys.readouterr().out
    picture = _png(saved_guide / f"guide_cell{best}.png")
    assert picture.shape[0] > 300 and picture.shape[1] > 600 and picture[..., :3].std() > 10
    assert main(["show-guide", str(saved_guide), "--pixel", "13", "20", "--out", str(saved_guide / "px.png")]) == 0
    printed = capsys.readouterr().out
    point = [float(v) for v in printed.split("p = (")[1].split(")")[0].split(", ")]
    cell = int(printed.split("; cell ")[1].split(" ")[0])
    low, high = guide_state.cell_bounds(state, cell)
    assert all(low - 1e-3 <= point) and all(point <= high + 1e-3)   # the cell is where the pixel's vertex is
    assert _png(saved_guide / "px.png")[..., :3].std() > 10


@pytest.mark.parametrize("method", ["ours", "sdtree"])
def test_show_guide_draws_guides_trained_with_nee(tmp_path, capsys, method):
    """A guide trained with next-event estimation learned the full incident radiance (docs/methods.md): it saves
    and draws as without."""
    out = tmp_path / method
    assert main(["render", "--scene", "cornell", "--scale", "0.1", "--method", method, "--nee", "--spp", "64",
                 "--save-guide", "--out", str(out), "--quiet"]) == 0
    assert main(["show-guide", str(out), "--out", str(out / "guide.png")]) == 0
    assert "cell" in capsys.readouterr().out and _png(out / "guide.png")[..., :3].std() > 10
    # It learned: the density of its most trained cell is far from uniform.
    state = guide_state.load(out / "guide.npz")
    density = guide_state.density_image(state, guide_state.best_cell(state), 360, 180)
    assert state["weight"].max() > 0 and density.max() > 3 * density.mean()


@pytest.mark.parametrize("args, message", [
    (["--cell", "512"], "cell 512 does not exist: the guide has cells 0..511"),
    (["--pixel", "26", "0"], "pixel (26, 0) is outside the 26x26 image"),
])
def test_show_guide_bad_input(saved_guide, capsys, args, message):
    assert main(["show-guide", str(saved_guide), *args]) == 2
    assert message in _one_error_line(capsys)


def test_show_guide_needs_a_saved_guide(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["render", "--scene", "cornell", "--scale", "0.05", "--method", "brdf", "--spp", "8", "--save-guide",
                 "--out", str(out)]) == 2
    assert "method 'brdf' learns nothing to save" in _one_error_line(capsys) and not out.exists()
    assert main(["render", "--scene", "cornell", "--scale", "0.05", "--method", "brdf", "--spp", "8", "--out",
                 str(out), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["show-guide", str(out)]) == 2
    assert "guide.npz': render with --save-guide" in _one_error_line(capsys)
