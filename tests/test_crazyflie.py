"""The Crazyflie target: ``learnest-compile MODEL --target crazyflie`` writes an out-of-tree
estimator app that the Crazyflie firmware's own build compiles, and its firmware side, replayed
on recorded flights, computes what the Python bindings compute (examples/crazyflie/replay.py).

- The app folder and the CLI's one-line refusals need nothing but the package.
- The host replay (gcc, the firmware tarball's headers, the NanoBench flights) feeds three
  circle flights, from the ground up, to the app's own ``estimator_out_of_tree.c`` compiled
  against the firmware's headers and a stub of its queue. What the app gives its estimator must
  be what the recordings pipeline gives the Python study (float32 rounding of the same
  arithmetic), the estimates must equal the Python bindings' bit for bit on the app's inputs
  (the same C, the same float32 inputs: docs/reports/cortex_m.md), and the replayed estimator's
  velocity error must beat the onboard EKF's logged estimate on each flight.
- Slow: the same replay with the KNODE model; the firmware's build of cf2.bin as it comes and
  with the app (``make cf2_defconfig && make``; flash, RAM and CCM printed before and after) and
  the same replay under QEMU on the Cortex-M4F, compiled with the flags that build used.

The models: the grey-box quadrotor prior (``quadrotor_linear``: ``adot = -k_v v - k_a a``,
fitted by least squares) on two figure-eight flights, and the KNODE model (that prior and the
net, the study's training) on the eight figure-eights, as scripts/bench_crazyflie.py trains it;
the circles they are replayed on are held out (the benchmark replays all 17 flights on models
fitted on the other type).
Skips, with the reason, when gcc, arm-none-eabi-gcc, the firmware tarball, QEMU or the flights
are missing.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import load_file

from learnest_codegen.cli import compile_cmd
from learnest_codegen.codegen import crazyflie
from learnest_codegen.recordings import data_root
from learnest_codegen.toolchain import CFLAGS

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "crazyflie"
TRAINING = ("B3_figure8_medium_rep1", "B3_figure8_slow_rep2")
REPLAYED = ("B2_circle_fast_rep1", "B2_circle_medium_rep3", "B2_circle_slow_rep2")
# The app forms y in float32 from the same float32 pose and accelerometer as the pipeline in
# float64: a rotation of 9.81 acc and a subtraction, a few roundings of numbers below 16.
ACCEL_ROUNDING = 8 * np.spacing(np.float32(16.0))  # [m/s^2]
# u: the motor ratios are rounded to the integers a firmware holds (0.5 of 65535 each).
THRUST_ROUNDING = 0.5 / 65535 + 8 * np.spacing(np.float32(1.0))


rp = load_file(EXAMPLE / "replay.py", "crazyflie_replay")


def invoke(args):
    return CliRunner().invoke(compile_cmd, [str(a) for a in args], catch_exceptions=False)


# -- the app folder --------------------------------------------------------------------------------


def test_the_app_folder_names_its_estimator_and_the_firmware_build(tmp_path):
    r = invoke(["--nominal", "--system", "quadrotor_linear", "--target", "crazyflie", "--out", tmp_path])
    assert r.exit_code == 0, r.output
    estimator = next(p for p in tmp_path.iterdir() if not p.name.endswith("_crazyflie"))
    prefix = estimator.name  # ukf in float32: the target's defaults
    assert prefix.endswith("_ukf_float32")
    app = tmp_path / crazyflie.app_name(prefix)
    assert f"crazyflie app: {app}" in r.output
    makefile = (app / "Makefile").read_text()
    assert "CRAZYFLIE_BASE ?=" in makefile and "include $(CRAZYFLIE_BASE)/tools/make/oot.mk" in makefile
    assert "CONFIG_ESTIMATOR_OOT=y" in (app / "app-config").read_text().splitlines()
    assert f"CONFIG_APP_STACKSIZE={crazyflie.STACK_WORDS}" in (app / "app-config").read_text()
    header = (app / "src" / "learnest_app.h").read_text()
    assert f'#include "{prefix}.h"' in header and f"#define APP_STEP {prefix}_step" in header
    assert "#define APP_SAMPLE_RATE_HZ 100" in header  # the quadrotor's dt = 10 ms
    assert "#define APP_STATE_V 3" in header and "#define APP_OUTPUT_A 3" in header
    # the estimator's C as generated, compiled with the flags it was verified with
    kbuild = (app / "src" / prefix / "Kbuild").read_text()
    assert f"obj-y += {prefix}.o {prefix}_model.o" in kbuild and f"ccflags-y += {' '.join(CFLAGS)}" in kbuild
    for name in (f"{prefix}.c", f"{prefix}_model.c", f"{prefix}.h", "learnest_ukf.h", f"{prefix}.mk"):
        assert (app / "src" / prefix / name).read_bytes() == (estimator / name).read_bytes()
    assert not list(app.rglob("*.so")) and not (app / "src" / prefix / "manifest.json").exists()
    # float32 code computes in float: the firmware builds it with -Wdouble-promotion -Werror
    if shutil.which("gcc"):
        for source in (f"{prefix}.c", f"{prefix}_model.c"):
            subprocess.run(["gcc", *CFLAGS, "-Wdouble-promotion", "-Werror", "-c",
                            str(app / "src" / prefix / source), "-o", str(tmp_path / "x.o")], check=True)
    # again without --force: refused before any work; with --force: replaced whole
    r = invoke(["--nominal", "--system", "quadrotor_linear", "--target", "crazyflie", "--out", tmp_path])
    assert r.exit_code == 1 and "--force" in r.output
    (app / "stale.txt").write_text("x")
    r = invoke(["--nominal", "--system", "quadrotor_linear", "--target", "crazyflie", "--out", tmp_path,
                "--force"])
    assert r.exit_code == 0 and not (app / "stale.txt").exists()


@pytest.mark.parametrize("args, message", [
    (["--system", "cartpole"], "the crazyflie target needs the quadrotor's states"),
    (["--system", "quadrotor", "--estimator", "mhe"], "no Ipopt, no heap"),
    (["--system", "quadrotor", "--precision", "float64"], "needs float32"),
], ids=["not_a_quadrotor", "ipopt", "float64"])
def test_what_a_crazyflie_cannot_run_is_refused_in_one_line(tmp_path, args, message):
    r = invoke(["--nominal", *args, "--target", "crazyflie", "--out", tmp_path])
    assert r.exit_code == 1 and message in r.output and len(r.output.strip().splitlines()) == 1
    assert not list(tmp_path.iterdir())  # refused before anything was written


def test_an_estimator_the_firmware_cannot_hold_is_refused_with_a_horizon_that_fits(tmp_path):
    """The embedded MHE's workspace at its default horizon overflows the firmware's free RAM (its
    link would fail): refused in one line, nothing left behind, and the horizon it proposes
    generates the workspace it names."""
    r = invoke(["--nominal", "--system", "quadrotor_linear", "--estimator", "mhe_rti", "--target",
                "crazyflie", "--out", tmp_path])
    assert r.exit_code == 1 and len(r.output.strip().splitlines()) == 1, r.output
    assert f"{crazyflie.FREE_RAM_BYTES:,} B of RAM" in r.output and "--estimator ukf" in r.output
    workspace = int(re.search(r"needs a ([\d,]+) B workspace", r.output).group(1).replace(",", ""))
    assert workspace + 4 * crazyflie.STACK_WORDS > crazyflie.FREE_RAM_BYTES
    assert not list(tmp_path.iterdir())
    horizon, predicted = re.search(r"--horizon (\d+) or less \(N = \d+ needs ([\d,]+) B\)", r.output).groups()
    r = invoke(["--nominal", "--system", "quadrotor_linear", "--estimator", "mhe_rti", "--horizon", horizon,
                "--target", "crazyflie", "--out", tmp_path])
    assert r.exit_code == 0, r.output
    assert f"workspace {predicted.replace(',', '')} B" in r.output
    # one stage more does not fit
    r = invoke(["--nominal", "--system", "quadrotor_linear", "--estimator", "mhe_rti", "--horizon",
                int(horizon) + 1, "--target", "crazyflie", "--out", tmp_path / "longer" / "app"])
    assert r.exit_code == 1 and "needs a" in r.output
    assert not (tmp_path / "longer").exists()  # the --out folders it would have created are not left


def test_one_estimator_per_app(tmp_path):
    r = invoke(["--nominal", "--system", "quadrotor", "--estimator", "ukf", "--estimator", "mhe_rti",
                "--target", "crazyflie", "--out", tmp_path])
    assert r.exit_code == 2 and "builds one estimator" in r.output


# -- the replay ------------------------------------------------------------------------------------


def _flights_folder() -> Path:
    root = data_root()
    if root is None or not (root / "nanobench").is_dir():
        pytest.skip("NanoBench flights not found (../shared/data/nanobench or $LEARNEST_DATA)")
    return root / "nanobench"


@pytest.fixture(scope="module")
def firmware(tmp_path_factory):
    missing = rp.missing_tools()
    if missing:
        pytest.skip(f"{', '.join(missing)} not found (scripts/setup_tools.sh installs the toolchain)")
    return rp.unpack_firmware(tmp_path_factory.mktemp("firmware"))


@pytest.fixture(scope="module")
def greybox(tmp_path_factory):
    """The grey-box prior fitted on two figure-eights, its estimator folder and its app."""
    from learnest_codegen.experiments.quadrotor import Case, StudySettings, trained_model
    from learnest_codegen.recordings.crazyflie import read_flight

    folder = _flights_folder()
    work = tmp_path_factory.mktemp("greybox")
    train = []
    for name in TRAINING:
        flight = read_flight(folder / f"{name}.csv")
        train.append(Case(flight.name, flight.run, flight.reference, flight.onboard))
    trained_model(train, "linear_prior", work, StudySettings(), work / "model", progress=False)
    r = invoke([work / "model", "--target", "crazyflie", "--out", work / "gen"])
    assert r.exit_code == 0, r.output
    estimator = next(p for p in (work / "gen").iterdir() if not p.name.endswith("_crazyflie"))
    return estimator, work / "gen" / crazyflie.app_name(estimator.name)


@pytest.fixture(scope="module")
def host_replay(firmware, greybox, tmp_path_factory):
    return rp.build_replay(greybox[1], firmware, tmp_path_factory.mktemp("replay"))


def _check_replays(estimator_dir: Path, binary: Path, label: str) -> None:
    """Each of :data:`REPLAYED` through the app's replay ``binary``: the app's samples are the
    pipeline's, its estimates the bindings', its velocity error below the onboard EKF's."""
    from learnest_codegen.pipeline import load_estimator

    estimator = load_estimator(estimator_dir)
    for name in REPLAYED:
        flight = rp.flight_replay(_flights_folder() / f"{name}.csv")
        replay = rp.run_replay(binary, flight.records)
        assert replay.summary["errors"] == 0 and replay.summary["late"] == 0
        assert np.all(replay.status[replay.started] >= 0)
        # the app's measurement and inputs are the recordings pipeline's, to float32 rounding
        assert np.array_equal(replay.valid, np.isfinite(flight.y))
        posed = replay.valid[:, 0]  # with a pose, the app's attitude is the pose's
        err = np.abs(replay.y.astype(float) - flight.y)[posed]
        assert np.all(err[:, :3] <= np.spacing(np.abs(flight.y[posed, :3]).astype(np.float32)))
        assert np.max(err[:, 3:]) <= ACCEL_ROUNDING, np.max(err[:, 3:])
        assert np.max(np.abs(replay.u[posed, :3] - flight.u[posed, :3])) <= THRUST_ROUNDING
        np.testing.assert_array_equal(replay.u[:, 3], flight.u[:, 3].astype(np.float32))
        # the estimates: the bindings' on the app's own samples, to the bit
        X = rp.bindings_estimates(estimator, replay)
        k0 = int(np.argmax(replay.started))
        assert k0 == 0 and np.all(replay.started)  # the log starts on the ground, pose in hand
        np.testing.assert_array_equal(replay.x.astype(float), X)
        # and the bindings' on the pipeline's samples agree to float32 tolerance
        x0 = rp.start_state(replay)[1]
        study = estimator.run(flight.u, flight.y, x0)
        assert np.max(np.abs(study - replay.x)) < 1e-3
        # the velocity error over the airborne part, against Vicon: below the onboard EKF's
        first, last = flight.span
        airborne = slice(first, last + 1)
        v = slice(3, 6)
        ours = np.sqrt(np.mean((replay.x[airborne, v] - flight.reference[:, v]) ** 2))
        ekf = np.sqrt(np.mean((flight.onboard[:, v] - flight.reference[:, v]) ** 2))
        print(f"{label}, {name}: velocity RMS {ours:.4f} m/s, onboard EKF {ekf:.4f} m/s")
        assert ours < ekf


def test_replayed_flights_equal_the_bindings_and_beat_the_onboard_ekf(greybox, host_replay):
    _check_replays(greybox[0], host_replay, "grey-box")


@pytest.fixture(scope="module")
def knode(tmp_path_factory):
    """The KNODE model (the study's training, features ``linear``: the grey-box prior and the net)
    trained on the eight figure-eights, as scripts/bench_crazyflie.py trains it; its estimator
    folder and its app."""
    from learnest_codegen.experiments.quadrotor import StudySettings, flight_cases, trained_model

    _flights_folder()
    work = tmp_path_factory.mktemp("knode")
    train = [c for c in flight_cases(data_root()) if c.name.startswith("B3_figure8")]
    trained = trained_model(train, "linear", work / "study", StudySettings(), work / "model", progress=False)
    print(f"KNODE net kept: {trained.meta.get('net_kept')}")
    r = invoke([work / "model", "--system", "quadrotor_linear", "--target", "crazyflie", "--out",
                work / "gen"])
    assert r.exit_code == 0, r.output
    estimator = next(p for p in (work / "gen").iterdir() if not p.name.endswith("_crazyflie"))
    return estimator, work / "gen" / crazyflie.app_name(estimator.name)


@pytest.mark.slow
def test_the_knode_app_replayed_equals_the_bindings_and_beats_the_onboard_ekf(firmware, knode,
                                                                              tmp_path):
    _check_replays(knode[0], rp.build_replay(knode[1], firmware, tmp_path / "replay"), "KNODE")


def test_the_replay_catches_a_sample_the_app_did_not_take(greybox, host_replay):
    """The equality is not vacuous: a flight whose pose vanishes for a second leaves the
    position missing on exactly those samples and still equals the bindings given them."""
    from learnest_codegen.pipeline import load_estimator

    flight = rp.flight_replay(_flights_folder() / f"{REPLAYED[0]}.csv")
    records = flight.records.copy()
    gap = slice(1000, 1100)
    records[gap, 7] = 0.0  # no pose
    replay = rp.run_replay(host_replay, records)
    assert not replay.valid[gap, 0:3].any() and replay.valid[gap, 3:6].all()
    assert replay.summary["no_position"] == 100
    X = rp.bindings_estimates(load_estimator(greybox[0]), replay)
    np.testing.assert_array_equal(replay.x.astype(float), X)
    untouched = rp.run_replay(host_replay, flight.records)
    assert not np.array_equal(replay.x[1100:], untouched.x[1100:])


# -- the firmware's own build and the Cortex-M4F ---------------------------------------------------


def _sizes(sizes: dict) -> str:
    return ", ".join(f"{r} {sizes[k]['used']:,} of {sizes[k]['total']:,} B ({sizes[k]['free']:,} free)"
                     for k, r in (("flash", "flash"), ("ram", "RAM"), ("ccm", "CCM")))


@pytest.mark.slow
def test_the_firmware_builds_with_the_app_and_runs_it_on_the_m4f(firmware, greybox, host_replay,
                                                                tmp_path):
    before = rp.build_firmware(firmware).sizes.to_json()  # as it comes
    print(f"cf2.bin as it comes: {_sizes(before)}")
    assert before["ram"]["free"] == crazyflie.FREE_RAM_BYTES  # the limit the target refuses by
    build = rp.build_firmware(firmware, greybox[1])
    sizes = build.sizes.to_json()
    print(f"cf2.bin with the grey-box app: {_sizes(sizes)} ({build.seconds:.0f} s)")
    assert build.binary.stat().st_size > 100_000 and build.warnings == ()
    assert sizes["ram"]["free"] >= 8 * 1024  # the app leaves the firmware 8 KB of RAM
    assert rp.path_occurrences(build, firmware, greybox[1]) == 0  # the same wherever checked out
    if rp.missing_tools(qemu=True):
        pytest.skip(f"{rp.QEMU} not found")
    flight = rp.flight_replay(_flights_folder() / f"{REPLAYED[0]}.csv")
    records = flight.records[:600]  # take-off and the first 2.5 s in the air
    elf = rp.build_qemu(greybox[1], firmware, records, tmp_path / "qemu")
    m4f = rp.run_qemu(elf)
    host = rp.run_replay(host_replay, records)
    np.testing.assert_array_equal(m4f.x, host.x)  # float32, no fused multiply-add: to the bit
    np.testing.assert_array_equal(m4f.y, host.y)
    assert m4f.summary["stack_peak_bytes"] < 4 * crazyflie.STACK_WORDS
