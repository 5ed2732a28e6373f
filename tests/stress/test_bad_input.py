"""Bad input: the command line's answers to bad options, broken scenes and images, unwritable outputs and Ctrl-C.

New: a scale or time budget of Inf or NaN (a traceback, or a render that never ends), a bad variant (checked
before the output folder is made), an EXR path that is a folder, Ctrl-C during the tracing of a Dr.Jit loop (it
reaches the command line as a RuntimeError whose cause is the KeyboardInterrupt: a traceback and exit 1 before),
outputs written one by one (now all together or none) and snapshots left behind by an interrupted render.
"""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import OpenEXR

from guiding import imageio
from guiding.cli import EXIT_INTERRUPTED
from guiding.guides.base import Guide
from guiding.scenes import PROJECT_ROOT
from arrays import few
from command_line import bad_input_violations, files_in, one_error_line, render_args, run_cli


def test_bad_option_values(tmp_path, figures):
    """Bad option values (scale 0, NaN or Inf; an infinite time budget; 0 threads, spp per pass or depth; a seed
    that is not a number; negative excluded passes; an unknown variant; a bad memory limit): one line, exit 2,
    nothing written. (tests/test_cli.py::test_bad_render_input: unknown method, spp 0, negative seconds, no
    budget.)"""
    out = str(tmp_path / "out")
    runs = [(f"{option} {value}", render_args(out, option, value), fragment) for option, value, fragment in (
        ("--scale", "0", "must be > 0 and finite"), ("--scale", "nan", "must be > 0 and finite"),
        ("--scale", "inf", "must be > 0 and finite"), ("--scale", "-1", "must be > 0 and finite"),
        ("--threads", "0", "must be > 0"), ("--pass-spp", "0", "must be > 0"), ("--max-depth", "0", "must be > 0"),
        ("--seed", "abc", "invalid int value"), ("--exclude-passes", "-1", "excluded passes must be >= 0"),
        ("--variant", "bogus", "unknown variant 'bogus'"), ("--memory-limit", "lots", "bad memory size"),
        ("--memory-limit", "0", "must be > 0"))]
    runs.append(("--seconds inf", [a for a in render_args(out) if a not in ("--spp", "1")] + ["--seconds", "inf"],
                 "must be > 0 and finite"))
    figures["inputs"] = len(runs)
    problems = bad_input_violations(runs, tmp_path)
    assert not problems, few(problems)


def test_bad_scenes(tmp_path, figures):
    """Missing or broken scenes (an XML path that does not exist, malformed XML, XML Mitsuba cannot load, no
    resx/resy defaults): one line, exit 2, nothing written. (tests/test_cli.py::test_bad_render_input and
    test_real_process_prints_no_traceback: unknown scene name.)"""
    scenes, folder = tmp_path / "scenes", tmp_path / "runs"
    scenes.mkdir()
    folder.mkdir()
    defaults = '<default name="resx" value="8"/><default name="resy" value="8"/>'
    files = {"malformed.xml": f'<scene version="3.0.0">{defaults}',
             "unloadable.xml": f'<scene version="3.0.0">{defaults}<shape type="no_such_plugin"/></scene>',
             "no_defaults.xml": '<scene version="3.0.0"><shape type="sphere"/></scene>'}
    for name, text in files.items():
        (scenes / name).write_text(text)
    out = str(folder / "out")
    runs = [("missing file", render_args(out, scene=f"{scenes}/absent.xml"), "does not exist"),
            ("malformed", render_args(out, scene=f"{scenes}/malformed.xml"), "cannot read scene"),
            ("unloadable", render_args(out, scene=f"{scenes}/unloadable.xml"), "cannot load scene"),
            ("no defaults", render_args(out, scene=f"{scenes}/no_defaults.xml"), "does not declare")]
    figures["inputs"] = len(runs)
    problems = bad_input_violations(runs, folder)
    assert not problems, few(problems)


def test_bad_images(tmp_path, figures):
    """Corrupt EXR input to `evaluate` (random bytes, an empty file, a folder, an EXR without RGB channels) and a
    reference of another resolution (transposed): one line, exit 2. (tests/test_cli.py::test_evaluate_bad_files:
    truncated EXR, missing file, different size.)"""
    good = tmp_path / "good.exr"
    imageio.write_exr(good, np.ones((3, 2, 3)))
    imageio.write_exr(tmp_path / "transposed.exr", np.ones((2, 3, 3)))
    (tmp_path / "random.exr").write_bytes(np.random.default_rng(0).bytes(4096))
    (tmp_path / "empty.exr").write_bytes(b"")
    (tmp_path / "folder.exr").mkdir()
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Y": np.ones((3, 2), dtype=np.float32)}) as exr:
        exr.write(str(tmp_path / "grey.exr"))
    runs = [("random bytes", ["evaluate", str(tmp_path / "random.exr"), str(good)], "not a readable EXR"),
            ("empty file", ["evaluate", str(good), str(tmp_path / "empty.exr")], "not a readable EXR"),
            ("a folder", ["evaluate", str(tmp_path / "folder.exr"), str(good)], "it is a folder"),
            ("no RGB channels", ["evaluate", str(tmp_path / "grey.exr"), str(good)], "no RGB channels"),
            ("transposed reference", ["evaluate", str(good), str(tmp_path / "transposed.exr")], "differ in size")]
    figures["inputs"] = len(runs)
    problems = [f"{label}: {p}" for label, argv, fragment in runs for p in one_error_line(run_cli(argv), fragment)]
    assert not problems, few(problems)


def test_unwritable_output(tmp_path, figures):
    """Unwritable output folders (below a file, below /proc): one line, exit 2.
    (tests/test_cli.py::test_unwritable_output: the output path is a file.)"""
    blocker = tmp_path / "file"
    blocker.write_text("x")
    runs = [("below a file", render_args(str(blocker / "out")), "cannot create output folder"),
            ("below /proc", render_args("/proc/guiding-stress/out"), "cannot create output folder")]
    figures["inputs"] = len(runs)
    problems = bad_input_violations(runs, tmp_path)
    assert not problems, few(problems)


def test_ctrl_c_mid_render(tmp_path, figures):
    """Ctrl-C (SIGINT) in the middle of a render, after its first snapshot was written: exit 130, one line, no
    traceback, and no file left in the output folder (snapshots removed)."""
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(PROJECT_ROOT), os.environ.get("PYTHONPATH", "")])}
    argv = render_args(str(out), "--spp", "1000000", "--variant", "llvm_ad_rgb", "--snapshots")
    # A process started in the background inherits SIGINT ignored; Ctrl-C needs its default disposition back.
    process = subprocess.Popen([sys.executable, "-m", "guiding", *argv], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, env=env,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    start = time.perf_counter()
    try:
        while not list(out.glob("image_snap*.exr")) and process.poll() is None:
            assert time.perf_counter() - start < 120, "no snapshot after 120 s"
            time.sleep(0.05)
        assert process.poll() is None, "the render ended before it was interrupted"
        figures["interrupted_after_seconds"] = round(time.perf_counter() - start, 2)
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    lines = stderr.strip().splitlines()
    assert process.returncode == EXIT_INTERRUPTED, f"exit code {process.returncode}: {stderr[-500:]}"
    assert len(lines) == 1 and lines[0].startswith("interrupted"), f"stderr: {lines[-3:]}"
    assert not files_in(out), f"files left: {files_in(out)}"


def test_ctrl_c_while_tracing(tmp_path, monkeypatch, figures):
    """Ctrl-C while Dr.Jit traces the path loop (which wraps the KeyboardInterrupt in a RuntimeError): exit 130,
    one line, and no file left in the output folder."""
    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(Guide, "sample", interrupt)     # brdf's sampling (Guide.sample) runs in the traced loop
    out = tmp_path / "out"
    run = run_cli(render_args(str(out)))
    figures["exit_code"] = run.code
    problems = one_error_line(run, "interrupted", code=EXIT_INTERRUPTED)
    assert not problems, few(problems)
    assert not files_in(out), f"files left: {files_in(out)}"
