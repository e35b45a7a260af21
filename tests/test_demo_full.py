"""The full-scale demo (paper settings): KNODE estimators must beat the nominal ones widely.

Slow (about 6 minutes on 2 cores): run with ``pytest -m slow``.
"""

from __future__ import annotations

import pytest

from learnest_codegen import get_system
from learnest_codegen.experiments.demo import run_demo


@pytest.mark.slow
def test_full_demo_knode_beats_nominal(tmp_path):
    report = run_demo(get_system("cartpole"), tmp_path, python_mhe=False)
    mse = {(row["method"], row["backend"]): row["mse"] for row in report.rows}
    # measured: KNODE-MHE 199x, KNODE-UKF 487x better; true dynamics 270x and 1472x
    assert mse["MHE", "C"] / mse["KNODE-MHE", "C"] > 25
    assert mse["UKF", "C"] / mse["KNODE-UKF", "C"] > 25
    assert mse["MHE (true dynamics)", "C"] < mse["KNODE-MHE", "C"]
    assert mse["UKF (true dynamics)", "C"] < mse["KNODE-UKF", "C"]
    assert mse["KNODE-UKF", "python"] == pytest.approx(mse["KNODE-UKF", "C"], rel=1e-9)
    assert mse["EKF", "C"] / mse["KNODE-EKF", "C"] > 25
    assert mse["EKF (true dynamics)", "C"] < mse["KNODE-EKF", "C"]
    assert mse["KNODE-EKF", "python"] == pytest.approx(mse["KNODE-EKF", "C"], rel=1e-9)
