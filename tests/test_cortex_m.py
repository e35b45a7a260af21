"""Generated estimators cross-compiled for a Cortex-M4F and run under QEMU (examples/cortex_m).

The firmware loop and the host build of the same loop run over the same simulated test run
(the cartpole, the quadrotor, or a system file); their estimates must agree to 1e-6 relative
per step (the measure of test_ukf.py), in float64 and in float32 (where the QEMU and host
builds both round every operation to float). The firmware starts the estimator from the
tuned defaults of its generated header and builds it from the folder's build fragment.
The host build must in turn be the very library the Python bindings load (CompiledUKF is
checked against FilterPy in test_ukf.py, CompiledEmbeddedMHE against the Ipopt MHE in
test_mhe_gn.py), so the embedded estimator is tied to its reference through two equalities.
Skips when the cross toolchain or QEMU is missing (scripts/setup_and_test.sh installs them).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import load_file

from learnest_codegen import get_system
from learnest_codegen.codegen.emit import c_list
from learnest_codegen.errors import SolverError
from learnest_codegen.estimators.ukf import UKFSettings
from learnest_codegen.export import prior_model
from learnest_codegen.runtime.status import STATUS_NAMES

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "cortex_m"
PARITY_RTOL = 1e-6
STEPS = 300
# Mean |error| of each measured state over the run, in measurement-noise stds: both builds must
# track the truth (the cartpole's earlier bound 0.05 was 5 of its stds).
TRACKING_STDS = 5.0


bc = load_file(EXAMPLE / "build_and_compare.py", "build_and_compare")
_missing = bc.missing_tools()
pytestmark = pytest.mark.skipif(
    bool(_missing), reason=f"{', '.join(_missing)} not found: apt-get install gcc-arm-none-eabi "
                           "libnewlib-arm-none-eabi qemu-system-arm (scripts/setup_and_test.sh does)")


def build_and_run(model, root: Path, steps: int, *, estimator: str = "ukf",
                  precision: str = "float64", machine: str = "mps2-an386"):
    gen = bc.generate(model, root / "gen", steps=steps, estimator=estimator, precision=precision)
    paths = bc.build(gen.directory, root / "build", machine=machine)
    fw = bc.run_qemu(paths["elf"], model.nx, machine=machine)
    return gen, paths, fw, bc.run_host(paths["host"], model.nx)


def check_parity(gen, fw, host, steps: int, system) -> float:
    assert fw.summary["steps"] == host.summary["steps"] == steps
    # 0, or 1 where the innovation gate rejected an output (not an error); the same samples
    assert fw.summary["status"] == host.summary["status"] and fw.summary["status"] >= 0
    # overruns: the steps whose busy ticks exceed the sample period (late steps, each counted,
    # also one that misses no tick); missed_ticks: the sample ticks that passed meanwhile
    period = system.dt * fw.summary["tick_hz"]
    assert fw.summary["overruns"] == int(np.sum(fw.busy_ticks > period))
    assert fw.summary["missed_ticks"] >= 0
    assert np.all(fw.status >= 0) and np.array_equal(fw.status, host.status)
    assert fw.X.shape == (steps, system.nx)
    rel = bc.relative_difference(fw.X, host.X)
    print(f"{gen.estimator} {gen.precision}: QEMU vs host over {steps} steps: max relative "
          f"difference {rel.max():.2e}, {np.all(fw.X == host.X, axis=1).sum()} steps bit-identical")
    assert rel.max() <= PARITY_RTOL
    # Two equally broken builds would agree: the estimates must also track the truth.
    tracking = bc.tracking_error(system, fw.X, gen.X_true)
    assert tracking and max(tracking.values()) < TRACKING_STDS, tracking
    if gen.precision == "float32":  # the printed doubles are widened floats
        assert np.array_equal(fw.X, fw.X.astype(np.float32).astype(np.float64))
    return float(rel.max())


def check_footprint(gen, paths, fw, ram_bytes: int = 32 * 1024) -> None:
    sizes = bc.section_sizes(paths["elf"])
    chain = bc.worst_stack_path(paths["elf"].parent.parent)
    peak = fw.summary["stack_peak_bytes"]
    print(f"flash {sizes['flash']} B, RAM {sizes['ram']} B (workspace {gen.workspace_bytes} B; "
          f"+ stack {sizes['.stack']} B reserved), stack peak {peak} B, deepest static chain "
          f"{chain['bytes']} B: {chain['path']}")
    # The deepest chain of -fstack-usage frames runs main -> the estimator's API (init or
    # step) -> the kit and CasADi's code, so the painted stack's high-water mark must cover it
    # (plus the library routines the .su files do not know) up to its last frame, which a run
    # may use only in part (the float32 chains end in a kit routine whose rarely taken branch,
    # a fallback call or a non-diagonal case, needs the whole frame: the painted peak fell 4 B
    # short of the full chain), and stay inside the reserved stack (an overflow would run into
    # .bss unnoticed).
    assert any(name.startswith(gen.prefix + "_") for name, _ in chain["path"])
    assert chain["bytes"] - chain["path"][-1][1] <= peak < sizes[".stack"]
    # The estimator's workspace is the static buffer in .bss; nothing else is big.
    assert gen.workspace_bytes <= sizes[".bss"] < gen.workspace_bytes + 1024
    # The run data (U, Y as doubles) sits in flash, not RAM.
    assert sizes[".text"] > 8 * gen.U.size + 8 * gen.Y.size
    assert sizes["ram"] < ram_bytes


@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("estimator", ["ukf", "mhe_rti"])
def test_qemu_equals_host_and_library(estimator, precision, tmp_path):
    """The nominal-model estimator on the Cortex-M4F: QEMU equals the host loop to 1e-6, the host
    loop (hex-float run data, rounded by the adapter) is bit-identical to the Python bindings'
    library on the numpy run, and the footprint checks hold."""
    model = prior_model(get_system("cartpole"))
    gen, paths, fw, host = build_and_run(model, tmp_path, STEPS, estimator=estimator,
                                         precision=precision)
    check_parity(gen, fw, host, STEPS, model.system)
    np.testing.assert_array_equal(host.X, bc.host_reference(gen))
    check_footprint(gen, paths, fw)


@pytest.mark.parametrize("estimator, precision", [
    ("mhe_rti", "float32"),
    # the KNODE quadrotor UKF's generated C (one graph through 19 sigma points) takes minutes
    # to compile for two targets
    pytest.param("ukf", "float64", marks=pytest.mark.slow)])
def test_quadrotor_knode_on_the_m4f(estimator, precision, tmp_path):
    """The example is not the cartpole's: the quadrotor's KNODE (9 states, 4 inputs, 6 outputs;
    the default net untrained) runs the same loop, QEMU equal to the host and to the bindings."""
    system = get_system("quadrotor")
    model = bc.untrained_knode(system)
    gen, paths, fw, host = build_and_run(model, tmp_path, 100, estimator=estimator,
                                         precision=precision)
    check_parity(gen, fw, host, 100, system)
    np.testing.assert_array_equal(host.X, bc.host_reference(gen))
    check_footprint(gen, paths, fw, ram_bytes=256 * 1024)


def test_quadrotor_axis_by_axis_on_the_m4f(tmp_path):
    """The nominal quadrotor keeps its three axes apart, so its embedded MHE solves them one by
    one (learnest_gn.h's groups): QEMU equal to the host and to the bindings on that path too."""
    system = get_system("quadrotor")
    model = prior_model(system)
    gen, paths, fw, host = build_and_run(model, tmp_path, 100, estimator="mhe_rti",
                                         precision="float32")
    assert "#define LEARNEST_NCOMP 3" in (gen.directory / f"{gen.prefix}.c").read_text()
    check_parity(gen, fw, host, 100, system)
    np.testing.assert_array_equal(host.X, bc.host_reference(gen))


def test_command_line_with_a_model_of_a_system_file(user_system_file, tmp_path, capsys):
    """A trained model of the README's pendulum (a system file), no ``--system``: the example
    reads the system the model records (as ``learnest-compile``), runs, reports QEMU equal to
    the host in a three-line summary and writes the whole report to its file."""
    import learnest_codegen as ln

    system = ln.get_system(str(user_system_file))
    ln.train(ln.simulate(system, 0, duration=1.0), system, ln.TrainingSettings(epochs=2),
             progress=False).save(tmp_path / "model")
    assert bc.main(["--model", str(tmp_path / "model"), "--steps", "100", "--estimator", "mhe_rti",
                    "--out", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out.splitlines()
    (report,) = (tmp_path / "out").glob("report_my_pendulum_*.json")
    assert len(printed) == 3 and printed[0].startswith("my_pendulum_knode_mhe_rti_n20 (")
    assert printed[2] == f"report: {report}"
    assert json.loads(report.read_text())["max_relative_difference"] <= PARITY_RTOL


def test_command_line_errors_are_one_line(tmp_path, capsys):
    """A model directory that does not exist: exit 1 and one line naming it, no traceback."""
    assert bc.main(["--model", str(tmp_path / "no_model"), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no_model" in err and "Traceback" not in err, err


def _expect_failure(paths, code: int, steps: int) -> None:
    """QEMU and the host both exit 1 after ``steps`` steps, the last printing ``code``."""
    for run in (lambda: bc.run_qemu(paths["elf"], 4), lambda: bc.run_host(paths["host"], 4)):
        with pytest.raises(SolverError, match="exit 1") as failure:
            run()
        if steps:
            assert f"x {steps - 1} {code} " in str(failure.value)
        assert f"summary steps={steps} status={code} " in str(failure.value)


def test_errors_stop_the_firmware_with_their_status(tmp_path):
    """init refuses a covariance that is not positive definite (no step is taken), and a NaN
    measurement fails its step: the loop prints the API's code, stops, and QEMU and the host
    exit non-zero. The covariance is the generated header's tuned default, edited."""
    system = get_system("cartpole")
    gen = bc.generate(prior_model(system), tmp_path / "gen", steps=5)
    header_path = gen.directory / f"{gen.prefix}.h"
    header = header_path.read_text()
    status = (gen.directory / "learnest_status.h").read_text()
    codes = {name: code for code, name in STATUS_NAMES.items()}
    for name in ("NOT_POSITIVE_DEFINITE", "NONFINITE_INPUT"):
        assert f"#define LEARNEST_{name} ({codes[name]})" in status
    P0 = UKFSettings.from_system(system).P0()
    default = f"#define {gen.prefix.upper()}_DEFAULT_P0 {c_list(P0)}"
    assert default in header
    header_path.write_text(header.replace(default, default.replace("{", "{-")))
    _expect_failure(bc.build(gen.directory, tmp_path / "b1"), codes["NOT_POSITIVE_DEFINITE"], 0)

    header_path.write_text(header)
    run_h = (gen.directory / "run_data.h").read_text()
    first_y2 = float(gen.Y[2, 0]).hex()
    assert run_h.count(first_y2) == 1
    guard = "#define RUN_DATA_H\n"
    (gen.directory / "run_data.h").write_text(
        run_h.replace(first_y2, "NAN").replace(guard, guard + "#include <math.h>\n"))
    _expect_failure(bc.build(gen.directory, tmp_path / "b2"), codes["NONFINITE_INPUT"], 3)


@pytest.mark.slow
@pytest.mark.parametrize("machine", list(bc.MACHINES))
@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("estimator", ["ukf", "mhe_rti", "mhe_gn"])
def test_qemu_knode_long_run(estimator, precision, machine, tmp_path):
    """The KNODE model (default net, untrained: the same C as a trained one) over 1000 steps,
    every estimator and precision, on the Cortex-M4F and the Cortex-M7."""
    model = bc.untrained_knode(get_system("cartpole"))
    steps = 1000
    gen, paths, fw, host = build_and_run(model, tmp_path, steps, estimator=estimator,
                                         precision=precision, machine=machine)
    check_parity(gen, fw, host, steps, model.system)
    np.testing.assert_array_equal(host.X, bc.host_reference(gen))
    check_footprint(gen, paths, fw)
