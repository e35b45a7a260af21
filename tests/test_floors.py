"""The accuracy floor of the default training (``scripts/bench_floors.py``): on every system of
the floor suite, the KNODE estimators of a model trained with the default recipe
(``ln.train(run, system)``, nothing passed) score at most the reference code's held-out MSE plus
its seed-to-seed spread, as stored in ``docs/figures/floors.json``. The cartpole's first case is
the demo's runs (seeds 0/1): there the floor is the reference's own MSE, with no margin beyond
float32's rounding."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
import bench_floors  # noqa: E402
import figures  # noqa: E402

pytestmark = pytest.mark.slow


def _floors() -> dict:
    return figures.load("floors")["figures"]


@pytest.mark.parametrize("name", list(bench_floors.SYSTEMS))
def test_default_training_keeps_the_floor(name, tmp_path):
    import learnest_codegen as ln

    stored = _floors()
    floor, nominal, true = (stored[k][name] for k in ("floors", "references", "references"))
    nominal, true = nominal["nominal"], true["true"]
    system = ln.get_system(bench_floors.system_path(name, tmp_path))
    cases = stored["cases"]
    got = {est: [] for est in bench_floors.ESTIMATORS}
    for seed in range(cases):
        run = ln.simulate(system, 2 * seed)
        settings = replace(ln.DEFAULT_TRAINING, seed=2 * seed)  # the demo's rule: the run's seed
        model = ln.train(run, system, settings, progress=False)
        model.save(tmp_path / f"model_{seed}")
        scores = bench_floors.score(str(tmp_path / f"model_{seed}"), system, seed, tmp_path / "compiled")
        for est, value in scores.items():
            got[est].append(value)
    for est, values in got.items():
        ref = floor[est]["mse"]
        mean = float(np.mean(values))
        assert mean <= ref["mean"] + ref["std"], (
            f"{name} KNODE-{est.upper()}: mean held-out MSE {mean:.4e} over {cases} cases above the floor "
            f"{ref['mean']:.4e} + spread {ref['std']:.1e} (per case {values} against {ref['per_case']})")
        if name == "cartpole":  # the demo's runs: the reference's own figure, no margin
            closed = bench_floors.gap_closed(values[0], nominal[est]["per_case"][0], true[est]["per_case"][0])
            # float32 training ends within float32's rounding of the float64 reference's weights:
            # the MSE to 1e-4 relative (measured: 4e-6)
            assert values[0] <= ref["per_case"][0] * (1 + 1e-4), (
                f"the demo's KNODE-{est.upper()}: MSE {values[0]:.4e} ({100 * closed:.2f} % of the gap) "
                f"above the reference's {ref['per_case'][0]:.4e}")

