"""Recordings checked before they are used: duplicates counted once, faulty spans cut and said.

The faulty recordings are made in a temporary folder from the shared NanoBench flights (the
tests skip when those are absent); the checks' helpers are tested on closed forms.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from learnest_codegen.errors import DataError
from learnest_codegen.experiments import quadrotor as fs
from learnest_codegen.recordings import checks, data_root
from learnest_codegen.recordings import crazyflie as nb

CLEAN = "B2_circle_slow_rep2"  # 34.6 s airborne, no finding
OTHER = "B3_figure8_slow_rep1"


def _nanobench():
    root = data_root()
    if root is None or not (root / "nanobench").is_dir() or not nb.list_flights(root):
        pytest.skip("NanoBench flights not found (../shared/data/nanobench or $LEARNEST_DATA)")
    return root / "nanobench"


def _copy(src_dir, name, folder, as_name=None):
    as_name = as_name or name
    shutil.copy(src_dir / f"{name}.csv", folder / f"{as_name}.csv")
    meta = src_dir / f"{name}_metadata.yaml"
    if meta.exists():
        shutil.copy(meta, folder / f"{as_name}_metadata.yaml")
    return folder / f"{as_name}.csv"


def _rewrite(src, dst, change):
    """``src`` with its columns changed by ``change(columns, t)`` (``t`` from 0), as ``dst``."""
    header = src.read_text().splitlines()[0].split(",")
    columns = nb.read_table(src)
    change(columns, columns["t"] - columns["t"][0])
    table = np.column_stack([columns[h] for h in header])
    np.savetxt(dst, table, delimiter=",", header=",".join(header), comments="", fmt="%.9f")
    return dst


# --- helpers, on closed forms ------------------------------------------------------------------------


def test_runs_and_the_longest_run():
    mask = np.array([0, 1, 1, 0, 1, 1, 1, 0, 1], bool)
    assert checks.runs_of(mask) == [(1, 2), (4, 6), (8, 8)]
    assert checks.longest_run(mask) == (4, 6)
    assert checks.longest_run(np.zeros(4, bool)) is None
    np.testing.assert_array_equal(checks.grow(mask, 1, 0), [1, 1, 1, 1, 1, 1, 1, 1, 1])
    np.testing.assert_array_equal(checks.grow(np.array([0, 0, 1, 0, 0, 0], bool), 1, 2), [0, 1, 1, 1, 1, 0])


@pytest.mark.parametrize("hinge, slope", [(300, 0.01), (1234, 0.002), (5, 0.5)])
def test_drift_onset_is_the_hinge_of_a_noiseless_ramp(hinge, slope):
    """A constant followed by a ramp: the least-squares hinge is exact without noise."""
    k = np.arange(2000, dtype=float)
    d = 0.3 + slope * np.maximum(0.0, k - hinge)
    assert checks.drift_onset(d, 1999, 1999) == hinge
    assert checks.drift_onset(d, 1999, 1999 - hinge + 50) == hinge  # a shorter look back


def test_drift_onset_through_noise():
    """Noise of 0.2 on a ramp of 0.01 per sample (2 units over 200 samples, the fault
    threshold's size): the hinge within 20 samples (0.2 s at 100 Hz) on 20 seeds."""
    k = np.arange(2000, dtype=float)
    d = 0.3 + 0.01 * np.maximum(0.0, k - 1500)
    for seed in range(20):
        noisy = d + 0.2 * np.random.default_rng(seed).normal(size=k.size)
        assert abs(checks.drift_onset(noisy, 1999, 1999) - 1500) <= 20, seed


def test_duplicates_keep_the_first_name():
    a, b = np.arange(6.0).reshape(3, 2), np.ones((3, 2))
    keys = {"x": checks.content_key([a]), "y": checks.content_key([b]),
            "x_copy": checks.content_key([a.copy()])}
    assert checks.duplicates(keys) == {"x_copy": "x"}
    assert checks.content_key([a]) != checks.content_key([a.reshape(2, 3)])  # the shape counts
    (finding,) = checks.duplicate_findings(keys)
    assert (finding.recording, finding.action) == ("x_copy", "counted once")


# --- the shared flights ---------------------------------------------------------------------------------


def test_the_clean_flights_raise_no_finding_and_the_brown_out_is_cut():
    """On the 17 NanoBench flights the checks find nothing but B2_circle_medium_rep3's brown-out
    (motor values up to 1.9e6, the accelerometer at > 100 m/s^2 from 31.1 s), which ends the
    flight 1 s before the accelerometer's drift begins."""
    found = {}
    for path in nb.list_flights(_nanobench()):
        f = nb.read_flight(path)
        found[f.name] = f
    faulty = {n: f for n, f in found.items() if f.findings}
    assert set(faulty) <= {"B2_circle_medium_rep3"}
    if faulty:
        f = faulty["B2_circle_medium_rep3"]
        checks_found = {x.check: x for x in f.findings}
        assert set(checks_found) == {"inputs", "accelerometer"}
        onset = checks_found["accelerometer"].start_s
        assert 30.5 < onset < 31.4
        end_s = f.trimmed[1] * f.timing.dt
        assert end_s == pytest.approx(onset - 1.0, abs=0.02) and f.truncated
        assert "kept" in checks_found["inputs"].note


@pytest.mark.parametrize("peak_g, start_s", [(2.0, 15.0), (39.0, 25.0)])
def test_a_drifting_accelerometer_is_cut_before_the_drift(tmp_path, capsys, peak_g, start_s):
    """A copy of a clean flight whose x accelerometer climbs steadily from ``start_s`` to
    ``peak_g`` at the end of the log (the motion capture unchanged) ends before the drift
    begins: the hinge fit dates its onset within 0.5 s (0.25 s early on a steep one, from the
    0.5 s mean the check reads), the flight ends 1 s before that, and
    the finding is on stderr and in the report."""
    src = _copy(_nanobench(), CLEAN, tmp_path)
    clean = nb.read_flight(src)

    def drift(c, t):
        c["imu_acc_x"] = c["imu_acc_x"] + peak_g * np.clip((t - start_s) / (t[-1] - start_s), 0, None)

    path = _rewrite(src, tmp_path / "drifting.csv", drift)
    findings: list = []
    (case,) = fs.flight_cases(path, findings=findings)
    (finding,) = findings
    assert finding.check == "accelerometer" and finding.action == "cut"
    # the 0.5 s mean the check reads starts a steep drift's ramp up to 0.25 s early
    assert start_s - 0.3 <= finding.start_s <= start_s + 0.5
    assert case.run.t[-1] + clean.trimmed[0] * clean.timing.dt <= start_s  # nothing of the drift kept
    assert case.run.t[-1] > start_s - 2.0 - clean.trimmed[0] * clean.timing.dt  # but the rest is
    assert "warning: drifting: accelerometer" in capsys.readouterr().err
    from learnest_codegen.experiments.quadrotor_report import markdown

    assert finding.line() in markdown([], findings=[finding.to_json()])


def test_a_folder_with_a_duplicate_and_a_drifting_accelerometer(tmp_path, capsys):
    """The acceptance: a folder holding two flights, a copy of one under another name and a
    flight with a drifting accelerometer is read with the copy counted once and the fault cut,
    both said on stderr."""
    src_dir = _nanobench()
    folder = tmp_path / "flights"
    folder.mkdir()
    _copy(src_dir, CLEAN, folder)
    _copy(src_dir, OTHER, folder)
    _copy(src_dir, CLEAN, folder, "Z9_renamed_copy")

    def drift(c, t):
        c["imu_acc_y"] = c["imu_acc_y"] - 2.0 * np.clip((t - 12.0) / 10.0, 0, None)

    _rewrite(src_dir / f"{OTHER}.csv", folder / "B3_figure8_drifting.csv", drift)
    findings, skipped = [], {}
    cases = fs.flight_cases(folder, findings=findings, skipped=skipped)
    assert sorted(c.name for c in cases) == sorted([CLEAN, OTHER, "B3_figure8_drifting"])
    by_check = {f.check: f for f in findings}
    assert by_check["duplicate"].recording == "Z9_renamed_copy" and CLEAN in by_check["duplicate"].detail
    assert by_check["accelerometer"].recording == "B3_figure8_drifting"
    drifting = next(c for c in cases if c.name == "B3_figure8_drifting")
    assert len(drifting.run) < len(next(c for c in cases if c.name == OTHER).run)
    err = capsys.readouterr().err
    assert "Z9_renamed_copy: duplicate" in err and "B3_figure8_drifting: accelerometer" in err


def test_motor_values_out_of_range_and_a_dropout_are_cut(tmp_path):
    """Motor PWM above 65535 for 0.5 s and 0.3 s without rows: each span is cut (a dropout with
    1.5 s either side, where the references fit across it) and the longest clean stretch kept."""
    src = _copy(_nanobench(), CLEAN, tmp_path)
    clean = nb.read_flight(src)
    t0 = clean.trimmed[0] * clean.timing.dt

    def motors(c, t):
        span = (t > t0 + 25.0) & (t < t0 + 25.5)
        c["motor_motor_m2"][span] = 70000.0

    flight = nb.read_flight(_rewrite(src, tmp_path / "motors.csv", motors))
    (finding,) = flight.findings
    assert finding.check == "inputs" and "motor_motor_m2" in finding.detail
    assert flight.trimmed[0] == clean.trimmed[0]
    assert t0 + 24.9 < flight.trimmed[1] * flight.timing.dt < t0 + 25.0

    header = src.read_text().splitlines()
    t = nb.read_table(src)["t"]
    rel = t - t[0]
    keep = [0] + [i + 1 for i in range(len(rel)) if not (t0 + 8.0 < rel[i] < t0 + 8.3)]
    (tmp_path / "dropout.csv").write_text("\n".join(header[i] for i in keep) + "\n")
    flight = nb.read_flight(tmp_path / "dropout.csv")
    (finding,) = flight.findings
    assert finding.check == "dropout" and "no data for" in finding.detail
    assert flight.trimmed[0] * flight.timing.dt > t0 + 8.3 + 1.5 - 0.02  # the longer part, after it
    with pytest.raises(DataError, match="left once the faulty spans are cut"):
        nb.read_flight(tmp_path / "dropout.csv", min_flight_s=40.0)
