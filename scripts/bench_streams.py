"""Real sensor streams: every estimator on the cartpole with a dropout, a slow output and a wrong start.

Per estimator (and backend), on the cartpole test run (seed 1, the full 10 s):

- ``clean``: every output at every sample, started at the system's ``x0``;
- ``dropout_<output>``: that output missing for 0.25 s (from 4 s on);
- ``quarter_<output>``: that output present at every fourth sample only;
- ``wrong_start``: the clean run started 3 standard deviations off (``x0 + 3 initial_std``
  with alternating signs) with ``P0 = diag(initial_std**2)`` (what ``--P0 initial`` gives);
  ``wrong_start_default_P0`` the same start with the estimator's own ``P0``.

Reported per case: the MSE and its ratio to the clean run's (and, for the dropout and slow
cases, the ratio with the advice before missing outputs existed: skip every sample that lacks
an output), the outputs the gate rejected,
errors, and for the wrong starts ``converged_s``: the time from which the error of every state
stays within the clean run's band (``|e_k,i| <= |e_clean,k,i| + rms_clean,i``) to the end, and
the rejections after 1 s. Targets (``TARGETS``): dropout MSE at most 1.3x clean, a quarter
rate within 2x and finite, a wrong start back in the band within 1 s with no rejection after.

The model: the cartpole KNODE fixture ``tests/data/model_b12bfa1`` (a net trained for 3
epochs: the KNODE model's structure and cost, quickly; ``--model`` takes any model directory,
``nominal`` or ``true``). Backends: ``python`` (the references) and ``c`` (the compiled
libraries, in each of ``--precisions`` they are built in: the Ipopt MHE is float64 only).
Usage::

    python scripts/bench_streams.py --out bench_streams.json
    python scripts/bench_streams.py --backends c --precisions float64 float32 --out c.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

import learnest_codegen as ln
from learnest_codegen.compilation import estimator_kind
from learnest_codegen.errors import SolverError
from learnest_codegen.estimators.contract import takes_missing_outputs

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MODEL = ROOT / "tests" / "data" / "model_b12bfa1"
DROPOUT_START_S, DROPOUT_S, SLOW_EVERY = 4.0, 0.25, 4
#: estimator -> backends that have it (mhe_gn's Python reference is the Ipopt MHE: the same
#: problem; mhe_rti has none).
BACKENDS = {"ukf": ("python", "c"), "mhe": ("python", "c"), "mhe_gn": ("c",), "mhe_rti": ("c",)}
#: precisions each compiled estimator is generated in
C_PRECISIONS = {"ukf": ("float64", "float32"), "mhe": ("float64",),
                "mhe_gn": ("float64", "float32"), "mhe_rti": ("float64", "float32")}
TARGETS = {"dropout_mse_ratio": 1.3, "quarter_mse_ratio": 2.0, "converged_s": 1.0}


def scenarios(run, system) -> dict[str, tuple[np.ndarray, np.ndarray | None, bool]]:
    """name -> (Y with NaN for missing, x0 (None: the system's), whether to give P0)."""
    out = {"clean": (run.y, None, False)}
    k0 = int(round(DROPOUT_START_S / system.dt))
    n = int(round(DROPOUT_S / system.dt))
    for j, name in enumerate(system.output_names):
        Y = run.y.copy()
        Y[k0:k0 + n, j] = np.nan
        out[f"dropout_{name}"] = (Y, None, False)
        Y = run.y.copy()
        Y[np.arange(len(Y)) % SLOW_EVERY != 0, j] = np.nan
        out[f"quarter_{name}"] = (Y, None, False)
    signs = np.where(np.arange(system.nx) % 2 == 0, 1.0, -1.0)
    x0 = np.asarray(system.x0) + 3.0 * signs * np.asarray(system.noise.initial_std)
    out["wrong_start"] = (run.y, x0, True)
    out["wrong_start_default_P0"] = (run.y, x0, False)
    return out


def estimate(est, run, Y, x0, P0, *, drop: bool = False) -> dict:
    """Step through the run (``run``'s convention), counting rejections and errors.

    ``drop``: the advice before missing outputs existed -- a sample with any output missing is
    not stepped at all (the estimate is held, and the estimator falls a step behind).
    """
    est.reset(x0, P0)
    X = np.empty((len(Y), len(x0)))
    rejected = np.zeros(len(Y), dtype=bool)
    errors = 0
    start = time.process_time()
    for k in range(len(Y)):
        u = run.u[max(k - 1, 0)]  # run()'s convention: sample 0 uses U[0] (only in h)
        if drop and k and np.isnan(Y[k]).any():
            X[k] = est.x
            continue
        try:
            X[k] = est.step(u, Y[k])
            rejected[k] = bool(est.last_status & 1)
        except SolverError:
            errors += 1
            X[k] = est.x
    return {"X": X, "rejected": rejected, "errors": errors,
            "cpu_us_per_step": 1e6 * (time.process_time() - start) / len(Y)}


def converged_after(X, X_clean, x_true, dt) -> float | None:
    """Seconds from which every state's error stays within the clean run's band; None: never."""
    e, e_clean = np.abs(X - x_true), np.abs(X_clean - x_true)
    rms = np.sqrt(np.mean(e_clean ** 2, axis=0))
    outside = np.flatnonzero(np.any(e > e_clean + rms, axis=1))
    if outside.size == 0:
        return 0.0
    if outside[-1] == len(X) - 1:
        return None
    return float((outside[-1] + 1) * dt)


def bench(model_arg: str, backends: tuple[str, ...], build_dir: Path, estimators=None,
          precisions: tuple[str, ...] = ("float64",)) -> dict:
    system = ln.get_system("cartpole")
    run = ln.simulate(system, seed=1)
    resolved = ln.resolve(model_arg, system)
    P0 = ln.pipeline.initial_covariance(system)
    cases = scenarios(run, system)
    rows, skipped = [], []
    for name, kinds in BACKENDS.items():
        if estimators and name not in estimators:
            continue
        for backend, precision in ((b, p) for b in kinds if b in backends
                                   for p in (("float64",) if b == "python" else
                                             [p for p in precisions if p in C_PRECISIONS[name]])):
            kind = estimator_kind(name)
            if not takes_missing_outputs(kind.python if backend == "python" else kind.compiled):
                skipped.append({"estimator": name, "backend": backend, "precision": precision,
                                "reason": "it takes no missing outputs"})
                continue
            est = ln.make_estimator(resolved, name, backend=backend, system=system, out=build_dir,
                                    precision=precision)
            backend = backend if precision == "float64" else f"{backend} {precision}"
            clean = None
            for case, (Y, x0, give_P0) in cases.items():
                start = np.asarray(system.x0) if x0 is None else x0
                r = estimate(est, run, Y, start, P0 if give_P0 else None)
                mse = float(np.mean((r["X"] - run.x) ** 2))
                row = {"estimator": name, "backend": backend, "case": case, "mse": mse,
                       "rejected": int(r["rejected"].sum()), "errors": r["errors"],
                       "missing": int(np.isnan(Y).sum()), "cpu_us_per_step": r["cpu_us_per_step"],
                       "finite": bool(np.all(np.isfinite(r["X"])))}
                if case == "clean":
                    clean = r
                else:
                    row["mse_ratio"] = mse / rows_clean_mse(rows, name, backend)
                if case.startswith(("dropout", "quarter")):
                    dropped = estimate(est, run, Y, start, None, drop=True)["X"]
                    row["mse_ratio_dropping_samples"] = (float(np.mean((dropped - run.x) ** 2))
                                                         / rows_clean_mse(rows, name, backend))
                if case.startswith("wrong_start"):
                    row["converged_s"] = converged_after(r["X"], clean["X"], run.x, system.dt)
                    row["rejected_after_1s"] = int(r["rejected"][int(round(1.0 / system.dt)):].sum())
                rows.append(row)
                print(json.dumps(row), flush=True)
    return {"system": system.name, "model": str(model_arg), "samples": len(run), "dt": system.dt,
            "dropout": {"start_s": DROPOUT_START_S, "length_s": DROPOUT_S},
            "slow_every": SLOW_EVERY, "targets": TARGETS, "rows": rows, "skipped": skipped,
            "verdict": verdicts(rows)}


def rows_clean_mse(rows, name, backend) -> float:
    return next(r["mse"] for r in rows
                if (r["estimator"], r["backend"], r["case"]) == (name, backend, "clean"))


def verdicts(rows) -> list[dict]:
    """Each row against its target (``TARGETS``)."""
    out = []
    for r in rows:
        case = r["case"]
        if case.startswith("dropout"):
            ok = r["mse_ratio"] <= TARGETS["dropout_mse_ratio"]
        elif case.startswith("quarter"):
            ok = r["finite"] and r["mse_ratio"] <= TARGETS["quarter_mse_ratio"]
        elif case == "wrong_start":
            ok = (r["converged_s"] is not None and r["converged_s"] <= TARGETS["converged_s"]
                  and r["rejected_after_1s"] == 0)
        else:
            continue
        out.append({"estimator": r["estimator"], "backend": r["backend"], "case": case, "met": ok})
    return out


def markdown(result: dict) -> str:
    lines = ["| estimator | backend | case | MSE | x clean | x clean, samples skipped | rejected | "
             "converged [s] | errors |", "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in result["rows"]:
        conv = r.get("converged_s", "")
        conv = "never" if "converged_s" in r and conv is None else (f"{conv:.3f}" if conv != "" else "")
        ratio = f"{r['mse_ratio']:.3f}" if "mse_ratio" in r else ""
        before = f"{r['mse_ratio_dropping_samples']:.3g}" if "mse_ratio_dropping_samples" in r else ""
        lines.append(f"| {r['estimator']} | {r['backend']} | {r['case']} | {r['mse']:.4e} | {ratio} | "
                     f"{before} | {r['rejected']} | {conv} | {r['errors']} |")
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=str(DEFAULT_MODEL),
                        help="model directory, 'nominal' or 'true' (default: the KNODE fixture)")
    parser.add_argument("--backends", nargs="+", default=["python", "c"], choices=["python", "c"])
    parser.add_argument("--estimators", nargs="+", default=None, choices=list(BACKENDS))
    parser.add_argument("--precisions", nargs="+", default=["float64", "float32"],
                        choices=["float64", "float32"], help="of the compiled estimators")
    parser.add_argument("--build-dir", type=Path, default=Path("build/bench_streams"))
    parser.add_argument("--out", type=Path, default=Path("bench_streams.json"))
    args = parser.parse_args(argv)
    start = time.time()
    result = bench(args.model, tuple(args.backends), args.build_dir, args.estimators,
                   tuple(args.precisions))
    result.update(machine=platform.platform(), python=platform.python_version(),
                  wall_seconds=round(time.time() - start, 1))
    args.out.write_text(json.dumps(result, indent=1))
    print(markdown(result))
    return result


if __name__ == "__main__":
    main()
