"""The CPU backend's table reads (guiding.llvm_gathers): both builds render the same bits, each compiles what it
reports, and without Dr.Jit's private symbols every function falls back to LLVM's own choice."""

import numpy as np
import pytest

from guiding import llvm_gathers, provenance


def test_gather_instructions_and_scalar_loads_render_the_same_bits(cornell):
    """Table reads compiled into gather instructions or into scalar loads (use_hardware_gathers; on
    a CPU with AVX-512, or without AVX2, both builds are LLVM's own) give bit-identical passes, the guide's learning
    between them included."""
    from guiding.render.driver import PassDriver, pass_seed
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.guides.methods import make_guide

    images = {}
    with llvm_gathers.llvm_target_kept():
        for hardware in (True, False):
            assert llvm_gathers.use_hardware_gathers(hardware) == llvm_gathers.gathers_in_use()
            driver = PassDriver(cornell, GuidedPathIntegrator(guide=make_guide("ours")))
            driver.prepare()
            images[hardware] = [np.array(driver.run(pass_seed(3, index), 2).image) for index in range(3)]
    for with_gathers, with_loads in zip(images[True], images[False]):
        assert np.any(with_gathers > 0)
        np.testing.assert_array_equal(with_gathers, with_loads)


def test_each_build_compiles_the_table_reads_it_reports(capfd):
    """A kernel's table read is a gather instruction exactly where ``use_hardware_gathers`` reports one: in the gather
    build and not in the scalar-load build where the CPU has the choice, in both builds with AVX-512, in neither
    without AVX2 (Dr.Jit's disassembly of a kernel new to its cache; x86 only: elsewhere the report is None)."""
    import random

    import drjit as dr
    import mitsuba as mi

    from guiding.bench.kernel_size import parse_disassembly

    level = dr.log_level()
    with llvm_gathers.llvm_target_kept():
        for hardware in (True, False):
            reported = llvm_gathers.use_hardware_gathers(hardware)
            assert reported == hardware or not llvm_gathers.gathers_choosable()
            table = dr.arange(mi.Float, 1000)
            dr.eval(table)
            # A literal in the reading kernel: a kernel no cache holds, so that it is compiled (and disassembled).
            read = dr.gather(mi.Float, table, dr.arange(mi.UInt32, 100) * 7 % 1000) * random.uniform(1, 2)
            capfd.readouterr()
            dr.set_log_level(dr.LogLevel.Trace)
            try:
                dr.eval(read)
            finally:
                dr.set_log_level(level)
            log = capfd.readouterr()
            modules = parse_disassembly(log.out + log.err)
            assert modules, "the kernel was not compiled (found in a cache?)"
            if reported is not None:
                assert (sum(count for module in modules for _, count in module) > 0) == reported


def test_bad_hardware_gathers_setting_names_the_choices(monkeypatch):
    monkeypatch.setenv(llvm_gathers.HARDWARE_GATHERS_ENV, "yes")
    with pytest.raises(llvm_gathers.GathersError, match="must be 0 or 1"):
        llvm_gathers.use_hardware_gathers()


def test_without_drjits_target_symbols_every_function_falls_back_to_llvms_choice(monkeypatch, cornell):
    """Another Dr.Jit build without the mangled symbols (or an LLVM backend not started): nothing is changed or
    raised, every report is None ("LLVM decides"), the provenance says so, and a render runs as Dr.Jit compiles it."""
    from guiding.guides.methods import make_guide
    from guiding.render.driver import PassDriver, pass_seed
    from guiding.render.integrator import GuidedPathIntegrator

    monkeypatch.setattr(llvm_gathers, "_target_functions", lambda: None)
    assert llvm_gathers.use_hardware_gathers(True) is None
    assert llvm_gathers.use_hardware_gathers(False) is None
    assert llvm_gathers.gathers_in_use() is None and not llvm_gathers.gathers_choosable()
    with llvm_gathers.llvm_target_kept():
        pass
    assert llvm_gathers.LLVM_DECIDES in provenance.device_name("llvm_ad_rgb")
    driver = PassDriver(cornell, GuidedPathIntegrator(guide=make_guide("ours")))
    driver.prepare()
    assert np.any(np.array(driver.run(pass_seed(3, 0), 2).image) > 0)


def test_an_llvm_backend_without_a_target_yet_is_left_alone(monkeypatch):
    """Before Dr.Jit's LLVM backend has started, its target CPU is empty: no target is set (it would be ignored)."""
    calls = []
    functions = (lambda: b"", lambda: b"+avx2", lambda: 8, lambda *args: calls.append(args))
    monkeypatch.setattr(llvm_gathers, "_target_functions", lambda: functions)
    assert llvm_gathers.use_hardware_gathers(True) is None and calls == []
