"""The flights study's per-state tables (``scripts/bench_flights.py``): a position ratio is shown
only where both estimators' position deviations lie outside the Vicon noise."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import bench_flights  # noqa: E402


def _study(knode_p_mm: float, nominal_p_mm: float) -> dict:
    cell = {"mean": 12.5, "median": 12.5, "better": 2, "flights": 2, "worst": 3.0, "worst_flight": "b"}
    row = {"p": cell, "v": cell, "a": cell, "overall": cell}
    per_flight = {f: {"KNODE-UKF": {"by_reference": {"sg_1s": {"p": (knode_p_mm / 1e3) ** 2}}},
                      "UKF (tuned)": {"by_reference": {"sg_1s": {"p": (nominal_p_mm / 1e3) ** 2}}}}
                  for f in ("a", "b")}
    return {"by_reference": {"KNODE-UKF vs UKF (tuned)": {"sg_1s": row}}, "per_flight": per_flight}


def test_a_position_ratio_inside_the_vicon_noise_is_not_shown():
    noise = {"a": 0.05, "b": 0.05}
    # the nominal copies the measurement (1e-9 mm against 0.05 mm of noise): no ratio
    inside = bench_flights._state_table(_study(0.4, 1e-9), "KNODE-UKF vs UKF (tuned)", noise)[-1]
    cells = [c.strip() for c in inside.strip("|").split("|")]
    assert cells == ["sg_1s", "inside the Vicon noise on 2/2", "+12.5 % (2/2, worst +3.0 %)",
                     "+12.5 % (2/2, worst +3.0 %)", "inside the Vicon noise on 2/2"]
    # both follow it less closely than its noise: every cell is the ratio
    outside = bench_flights._state_table(_study(0.4, 0.6), "KNODE-UKF vs UKF (tuned)", noise)[-1]
    assert outside.count("+12.5 %") == 4 and "inside" not in outside
