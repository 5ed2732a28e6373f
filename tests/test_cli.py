"""The command line: the documented forms work, and bad input gets one line, a non-zero exit and no output."""

import json
import subprocess
import sys

import numpy as np
import pytest

from guiding import imageio
from guiding.cli import main


def _one_error_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:"), err
    return err[0]


def test_render_and_evaluate(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["render", "--scene", "cornell", "--scale", "0.1", "--method", "brdf", "--spp", "8",
                 "--out", str(out), "--quiet"]) == 0
    assert {p.name for p in out.iterdir()} == {"image.exr", "preview.png", "stats.json"}
    stats = json.loads((out / "stats.json").read_text())
    assert stats["spp"] == 8 and stats["method"] == "brdf" and stats["resolution"] == [26, 26]
    assert stats["provenance"]["variant"] == "llvm_ad_rgb" and len(stats["per_pass"]) == 1
    capsys.readouterr()
    assert main(["evaluate", str(out / "image.exr"), str(out / "image.exr")]) == 0
    metrics = json.loads(capsys.readouterr().out)
    assert metrics["mae"] == 0 and metrics["nonfinite_pixels"] == 0


def test_reference_writes_outputs(tmp_path):
    out = tmp_path / "ref"
    assert main(["reference", "--scene", "cornell", "--scale", "0.05", "--spp", "16", "--out", str(out),
                 "--quiet"]) == 0
    assert json.loads((out / "stats.json").read_text())["method"] == "reference-path"


@pytest.mark.parametrize("args, message", [
    (["--scene", "no-such-scene", "--method", "brdf", "--spp", "8"], "unknown scene"),
    (["--scene", "cornell", "--method", "no-such-method", "--spp", "8"], "unknown method"),
    (["--scene", "cornell", "--method", "brdf", "--spp", "0"], "must be > 0"),
    (["--scene", "cornell", "--method", "brdf", "--seconds", "-2"], "must be > 0"),
    (["--scene", "cornell", "--method", "brdf"], "required"),
])
def test_bad_render_input(tmp_path, capsys, args, message):
    out = tmp_path / "out"
    assert main(["render", *args, "--out", str(out)]) == 2
    assert message in _one_error_line(capsys)
    assert not out.exists() or not any(out.iterdir())


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
    assert "not a readable EXR" in _one_error_line(capsys)


def test_real_process_prints_no_traceback(tmp_path):
    done = subprocess.run([sys.executable, "-m", "guiding", "render", "--scene", "nope", "--method", "brdf",
                           "--spp", "4", "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert done.returncode == 2
    assert done.stderr.strip().startswith("error: unknown scene") and "Traceback" not in done.stderr
