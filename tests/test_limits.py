"""Every option's range lives in one table (``runtime/limits.py``): the settings classes and the
command line check it, and its C rendering (what the generated C's argument checks test) agrees
with Python on the edges, NaN and the infinities, compiled by gcc."""

from __future__ import annotations

import math
import subprocess

import pytest
from click.testing import CliRunner

from learnest_codegen import get_system
from learnest_codegen.errors import SettingsError
from learnest_codegen.estimators.gate import GateSettings
from learnest_codegen.estimators.mhe_gn import GaussNewtonSettings
from learnest_codegen.estimators.mhe_problem import MHESettings
from learnest_codegen.estimators.ukf import UKFSettings
from learnest_codegen.runtime.limits import C_INT_MAX, LIMITS, check_option


def _probes(limit):
    """Values on and around each end, the off values, NaN, the infinities and the C int edges."""
    values = {limit.low, limit.high, 0.0, -1.0, math.nan, math.inf, -math.inf, *limit.off}
    for end in (limit.low, limit.high):
        values |= {end * (1 - 1e-9) - 1e-300, end * (1 + 1e-9) + 1e-300}
    if limit.integer:
        values = {v for v in values if math.isfinite(v) and v == int(v)} | {limit.low - 1, limit.high + 1}
    return sorted(values, key=lambda v: (math.isnan(v), v))


def test_the_c_rendering_agrees_with_python(tmp_path):
    """Each Limit's c_condition, compiled, says in/out exactly where Limit.contains does."""
    lines, expected = [], []
    for limit in LIMITS.values():
        ctype = "long long" if limit.integer else "double"
        for value in _probes(limit):
            literal = (repr(int(value)) + "LL") if limit.integer else \
                ("NAN" if math.isnan(value) else ("INFINITY" if value == math.inf else
                                                  ("-INFINITY" if value == -math.inf else repr(value))))
            test = limit.c_condition("x")
            lines.append(f"  {{ {ctype} x = {literal}; printf(\"%d\\n\", {test} ? 1 : 0); }}")
            expected.append(int(limit.contains(value)))
    source = tmp_path / "limits.c"
    source.write_text("#include <math.h>\n#include <stdio.h>\nint main(void) {\n" + "\n".join(lines) +
                      "\n  return 0;\n}\n")
    subprocess.run(["gcc", "-std=c99", "-O0", str(source), "-o", str(tmp_path / "limits"), "-lm"],
                   check=True)
    got = [int(v) for v in subprocess.run([str(tmp_path / "limits")], capture_output=True, text=True,
                                          check=True).stdout.split()]
    assert got == expected


def test_integer_options_fit_a_c_int_and_types_are_checked():
    for limit in LIMITS.values():
        if limit.integer:
            assert 1 <= limit.low <= limit.high <= C_INT_MAX, limit.name
    assert check_option("run_length", C_INT_MAX, "T") == C_INT_MAX
    for bad in (C_INT_MAX + 1, 2**32 + 10, 20.0, True, "20", None):
        with pytest.raises(SettingsError, match="must be an integer in"):
            check_option("horizon", bad, "MHESettings.horizon")


@pytest.mark.parametrize("make, field", [
    (lambda: GaussNewtonSettings(tolerance=1e300), "tolerance"),  # no step was taken: MSE 36-47x
    (lambda: GaussNewtonSettings(tolerance=1e-300), "tolerance"),
    (lambda: GaussNewtonSettings(tolerance=1e-10, precision="float32"), "tolerance"),
    (lambda: GaussNewtonSettings(max_iterations=10**9), "max_iterations"),  # hours per step
    (lambda: GaussNewtonSettings(max_iterations=2**32 + 3), "max_iterations"),  # reached C as 3
    (lambda: GateSettings(recover_after=2**32 + 10), "recover_after"),  # reached C as 10
    (lambda: GateSettings(inflation=1e300), "inflation"),  # above the cap: never applied
    (lambda: GateSettings(threshold=1e-3), "threshold"),
    (lambda: GateSettings(threshold=math.nan), "threshold"),
    (lambda: MHESettings.from_system(get_system("cartpole"), horizon=10**7), "horizon"),
    (lambda: MHESettings.from_system(get_system("cartpole"), process_std=(1e200, 1, 1, 1)), "process_std"),
    (lambda: UKFSettings.from_system(get_system("cartpole"), alpha=2.0), "alpha"),
    (lambda: UKFSettings.from_system(get_system("cartpole"), measurement_std=(1e-200, 0.01)),
     "measurement_std"),
])
def test_settings_outside_their_range_are_one_line(make, field):
    with pytest.raises(SettingsError, match=field) as info:
        make()
    assert "\n" not in str(info.value)


def test_the_defaults_and_the_off_values_are_in_range():
    assert GateSettings(threshold=0).threshold == math.inf == GateSettings(threshold=math.inf).threshold
    assert GateSettings(threshold=1e12, recover_after=10**6, inflation=100).enabled
    GaussNewtonSettings(max_iterations=1000, tolerance=1e-14)
    GaussNewtonSettings(precision="float32", tolerance=1e-6)
    MHESettings.from_system(get_system("cartpole"), horizon=1000)


@pytest.mark.parametrize("option, value", [("--gate-recover-after", "4294967306"),
                                           ("--gate-recover-after", "0"),
                                           ("--gate-inflation", "1e300"), ("--gate-inflation", "nan"),
                                           ("--gate-threshold", "nan"), ("--gate-threshold", "1e-300"),
                                           ("--gate-threshold", "-1")])
def test_the_command_line_names_the_option(option, value, tmp_path):
    from learnest_codegen.cli import cli

    result = CliRunner().invoke(cli, ["estimate", "--data", __file__, "--estimator", "ukf", "--out",
                                      str(tmp_path / "e.csv"), option, value])
    assert result.exit_code == 2 and f"Invalid value for '{option}'" in result.output, result.output
