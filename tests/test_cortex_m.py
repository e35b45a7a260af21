"""The generated UKF cross-compiled for a Cortex-M4F and run under QEMU (examples/cortex_m).

The firmware loop and the host build of the same loop run over the same simulated cartpole
test run; their estimates must agree to 1e-6 relative per step (the measure of test_ukf.py).
The host build must in turn be the very library that test_ukf.py checks against FilterPy, so
the embedded filter is tied to the reference through two equalities. Skips when the cross
toolchain or QEMU is missing (scripts/setup_and_test.sh installs them with apt).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from learnest_codegen import get_system
from learnest_codegen.errors import SolverError
from learnest_codegen.estimators.ukf import UKFSettings
from learnest_codegen.export import prior_model
from learnest_codegen.runtime.ukf import CompiledUKF

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "cortex_m"
PARITY_RTOL = 1e-6
STEPS = 500


def _load_example():
    spec = importlib.util.spec_from_file_location("build_and_compare", EXAMPLE / "build_and_compare.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


bc = _load_example()
_missing = bc.missing_tools()
pytestmark = pytest.mark.skipif(
    bool(_missing), reason=f"{', '.join(_missing)} not found: apt-get install gcc-arm-none-eabi "
                           "libnewlib-arm-none-eabi qemu-system-arm (scripts/setup_and_test.sh does)")


def build_and_run(model, root: Path, steps: int, machine: str = "mps2-an386"):
    gen = bc.generate(model, root / "gen", steps=steps)
    paths = bc.build(gen.directory, root / "build", machine=machine)
    fw = bc.run_qemu(paths["elf"], model.nx, machine=machine)
    return gen, paths, fw, bc.run_host(paths["host"], model.nx)


@pytest.fixture(scope="module")
def knode(tmp_path_factory):
    """A KNODE cartpole UKF with the default net untrained: the same C as a trained one."""
    model = bc.untrained_knode(get_system("cartpole"))
    return build_and_run(model, tmp_path_factory.mktemp("cortex_m"), STEPS)


def check_parity(gen, fw, host, steps: int) -> float:
    assert fw.summary["steps"] == host.summary["steps"] == steps
    assert fw.summary["status"] == host.summary["status"] == 0
    assert np.all(fw.status == 0) and fw.X.shape == (steps, 4)
    rel = bc.relative_difference(fw.X, host.X)
    print(f"QEMU vs host over {steps} steps: max relative difference {rel.max():.2e}, "
          f"{np.all(fw.X == host.X, axis=1).sum()} steps bit-identical")
    assert rel.max() <= PARITY_RTOL
    # Two equally broken builds would agree: the estimates must also track the truth.
    assert np.abs(fw.X[:, [0, 2]] - gen.X_true[:, [0, 2]]).mean() < 0.05
    return float(rel.max())


def test_qemu_estimates_equal_host_build(knode):
    gen, _, fw, host = knode
    check_parity(gen, fw, host, STEPS)


def test_host_loop_is_the_compiled_library(knode):
    """The loop with its hex-float run data reproduces CompiledUKF.run on the numpy run."""
    gen, _, _, host = knode
    system = get_system("cartpole")
    X_lib = CompiledUKF(gen.directory).run(gen.U, gen.Y, system.x0)
    np.testing.assert_array_equal(host.X, X_lib)


def test_firmware_footprint_and_stack(knode):
    gen, paths, fw, _ = knode
    sizes = bc.section_sizes(paths["elf"])
    chain = bc.worst_stack_path(paths["elf"].parent.parent)
    peak = fw.summary["stack_peak_bytes"]
    print(f"flash {sizes['flash']} B, RAM {sizes['ram']} B (+ stack {sizes['.stack']} B reserved), "
          f"stack peak {peak} B, deepest static chain {chain['bytes']} B: {chain['path']}")
    # The deepest chain of -fstack-usage frames runs main -> the filter step -> CasADi's code on
    # every sample, so the painted stack's high-water mark must cover it (plus the library
    # routines the .su files do not know), and stay inside the reserved stack (an overflow
    # would run into .bss unnoticed).
    assert any(name.startswith(gen.prefix + "_step") for name, _ in chain["path"])
    assert chain["bytes"] <= peak < sizes[".stack"]
    # The filter's static state lives in .bss: x, P, Q, R and CasADi's work vector at least.
    assert sizes[".bss"] >= 8 * (4 + 3 * 16)
    # The run data (U, Y as doubles) sits in flash, not RAM.
    assert sizes[".text"] > 8 * gen.U.size + 8 * gen.Y.size
    assert sizes["ram"] < 16 * 1024


def test_failing_step_stops_the_firmware_with_its_status(tmp_path):
    """A covariance that is not positive definite fails the first step (Cholesky -> NaN): the
    loop prints the API's error code, stops, and QEMU and the host exit non-zero."""
    system = get_system("cartpole")
    model = prior_model(system)
    gen = bc.generate(model, tmp_path / "gen", steps=5)
    config = (gen.directory / "estimator_config.h").read_text()
    P0 = UKFSettings.from_system(system).P0()
    config = config.replace(bc.c_array("est_P0", P0, (16,)), bc.c_array("est_P0", -P0, (16,)))
    (gen.directory / "estimator_config.h").write_text(config)
    paths = bc.build(gen.directory, tmp_path / "build")
    numeric_error = 4  # <PREFIX>_ERR_NUMERIC in the generated API header
    assert f"#define {gen.prefix.upper()}_ERR_NUMERIC {numeric_error} " in \
        (gen.directory / f"{gen.prefix}_api.h").read_text()
    for run in (lambda: bc.run_qemu(paths["elf"], 4), lambda: bc.run_host(paths["host"], 4)):
        with pytest.raises(SolverError, match="exit 1") as failure:
            run()
        assert f"x 0 {numeric_error} " in str(failure.value)
        assert f"summary steps=1 status={numeric_error} " in str(failure.value)


@pytest.mark.slow
@pytest.mark.parametrize("machine", list(bc.MACHINES))
@pytest.mark.parametrize("kind", ["nominal", "knode"])
def test_qemu_full_test_run(kind, machine, tmp_path):
    """The whole 10 s cartpole test run (5000 steps), on the Cortex-M4F and the Cortex-M7."""
    system = get_system("cartpole")
    model = prior_model(system) if kind == "nominal" else bc.untrained_knode(system)
    steps = int(round(system.duration / system.dt))
    gen, _, fw, host = build_and_run(model, tmp_path, steps, machine)
    check_parity(gen, fw, host, steps)
