"""Real sensor streams: every estimator on the cartpole with a dropout, a slow output and a wrong start.

Per estimator (and backend), on the demo's test run (seed 1, the whole 10 s) with the demo's
trained KNODE model (``bench_demo.model_dir()``; ``--model`` takes any model directory,
``nominal`` or ``true``):

- ``clean``: every output at every sample, started at the system's ``x0``;
- ``dropout_<output>``: that output missing for 0.25 s (from 4 s on);
- ``quarter_<output>``: that output present at every fourth sample only;
- ``wrong_start``: the clean run started 3 standard deviations off (``x0 + 3 initial_std``
  with alternating signs) with ``P0 = diag(initial_std**2)`` (what ``--P0 initial`` gives);
  ``wrong_start_default_P0`` the same start with the estimator's own ``P0``.

Reported per case: the MSE and its ratio to the clean run's (and, for the dropout and slow
cases, the ratio when every sample that lacks an output is skipped instead of stepped with the
output missing), the outputs the gate rejected, errors, and for the wrong starts
``converged_s``: the time from which the error of every state stays within the clean run's band
(``|e_k,i| <= |e_clean,k,i| + rms_clean,i``) to the end, and the rejections after 1 s.
Criteria (``TARGETS``): dropout MSE at most 1.3x clean, a quarter rate within 2x and finite, a
wrong start back in the band within 1 s with no rejection after.

Backends: ``python`` (the references) and ``c`` (the compiled libraries, in each of
``--precisions`` they are built in: the Ipopt MHE is float64 only).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import figures
import numpy as np

import learnest_codegen as ln
from learnest_codegen.compilation import ESTIMATORS, estimator_kind
from learnest_codegen.errors import SolverError
from learnest_codegen.estimators.contract import takes_missing_outputs

MINUTES = 40
ORDER = 40
BUILD = figures.ROOT / "build" / "bench" / "streams"
DROPOUT_START_S, DROPOUT_S, SLOW_EVERY = 4.0, 0.25, 4
#: estimator -> backends that have it (mhe_gn's Python reference is the Ipopt MHE: the same
#: problem; mhe_rti has none).
def estimator_backends() -> dict[str, tuple[str, ...]]:
    """Estimator -> backends, from the estimator table: the Python reference where it has its
    own (mhe_gn's is the Ipopt MHE's, the same problem; mhe_rti has none) and the C."""
    return {name: kind.backends for name, kind in ESTIMATORS.items()}
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
    for name, kinds in estimator_backends().items():
        if estimators and name not in estimators:
            continue
        for backend, precision in ((b, p) for b in kinds if b in backends
                                   for p in (("float64",) if b == "python" else
                                             [p for p in precisions
                                              if p in estimator_kind(name).precisions])):
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


def add_arguments(parser) -> None:
    parser.add_argument("--model", default=None,
                        help="model directory, 'nominal' or 'true' (default: the demo's trained model)")
    parser.add_argument("--backends", nargs="+", default=["python", "c"], choices=["python", "c"])
    parser.add_argument("--estimators", nargs="+", default=None, choices=list(ESTIMATORS))
    parser.add_argument("--precisions", nargs="+", default=["float64", "float32"],
                        choices=["float64", "float32"], help="of the compiled estimators")


def measure(args) -> tuple[dict, dict]:
    import bench_demo

    model = args.model or str(bench_demo.model_dir())
    described = (f"the demo's trained KNODE cartpole ({Path(model).relative_to(figures.ROOT)})"
                 if not args.model else model)
    cond = figures.conditions(model=described, model_hash=bench_demo.model_hash(model),
                              run="cartpole seed 1 (the demo's test run), 5000 samples",
                              settings="each estimator's defaults; backends " + ", ".join(args.backends)
                              + "; compiled precisions " + ", ".join(args.precisions))
    result = bench(model, tuple(args.backends), BUILD, args.estimators, tuple(args.precisions))
    result["model"] = described
    return result, cond


# -- views -------------------------------------------------------------------------------------

def _ratio(r: dict, key: str) -> str:
    v = r.get(key)
    return "" if v is None else (f"{v:.3g}" if v < 1e4 else f"{v:.1e}")


def _rows(data: dict, backends) -> list[dict]:
    return [r for r in data["figures"]["rows"] if r["backend"].split()[0] in backends]


def render_cases(data: dict) -> str:
    """The references (Python) case by case."""
    lines = ["| estimator | case | MSE | × clean | × clean, skipping samples with a missing output | "
             "outputs rejected | back in the clean band |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in _rows(data, ("python",)):
        conv = r.get("converged_s", "")
        conv = "never" if "converged_s" in r and conv is None else (f"{conv:.2f} s" if conv != "" else "")
        lines.append(f"| {r['estimator'].upper() if r['estimator'] in ('ukf', 'mhe') else r['estimator']} | "
                     f"{CASE_LABELS.get(r['case'], r['case'])} | {r['mse']:.3e} | "
                     f"{_ratio(r, 'mse_ratio') if r['case'] != 'clean' else '1'} | "
                     f"{_ratio(r, 'mse_ratio_dropping_samples')} | "
                     f"{r['rejected']} | {conv} |")
    return "\n".join(lines) + "\n\n" + render_conditions(data)


def render_compiled(data: dict) -> str:
    """The compiled builds, one line each."""
    def get(rows, case):
        return next(r for r in rows if r["case"] == case)

    head = ("| estimator | build | clean MSE | p / alpha missing 0.25 s (× clean) | p / alpha at 1/4 rate "
            "(× clean) | 3 sigma off, `P0 = initial`: in band / rejected | own `P0`: in band / rejected "
            "(after 1 s) | errors | criteria met |")
    lines = [head, "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    rows = _rows(data, ("c",))
    verdict = data["figures"]["verdict"]
    for name in dict.fromkeys(r["estimator"] for r in rows):  # the order measured
        for backend in dict.fromkeys(r["backend"] for r in rows if r["estimator"] == name):
            mine = [r for r in rows if (r["estimator"], r["backend"]) == (name, backend)]
            c, w, d = get(mine, "clean"), get(mine, "wrong_start"), get(mine, "wrong_start_default_P0")
            met = [v["met"] for v in verdict if (v["estimator"], v["backend"]) == (name, backend)]
            build = "C " + (backend.split()[1] if " " in backend else "float64")
            lines.append(
                f"| {name} | {build} | {c['mse']:.3e} | {get(mine, 'dropout_p')['mse_ratio']:.2f} / "
                f"{get(mine, 'dropout_alpha')['mse_ratio']:.2f} | "
                f"{get(mine, 'quarter_p')['mse_ratio']:.2f} / "
                f"{get(mine, 'quarter_alpha')['mse_ratio']:.2f} | {_seconds(w)} / {w['rejected']} | "
                f"{_seconds(d)} / {d['rejected']} ({d['rejected_after_1s']}) | "
                f"{sum(r['errors'] for r in mine)} | {sum(met)} of {len(met)} |")
    return "\n".join(lines) + "\n\n" + render_conditions(data)


def _seconds(r: dict) -> str:
    return "never" if r["converged_s"] is None else f"{r['converged_s']:.2f} s"


CASE_LABELS = {"clean": "clean", "dropout_p": "p missing 0.25 s", "dropout_alpha": "alpha missing 0.25 s",
               "quarter_p": "p at 1/4 rate", "quarter_alpha": "alpha at 1/4 rate",
               "wrong_start": "start 3 sigma off, `P0 = initial`",
               "wrong_start_default_P0": "start 3 sigma off, own `P0`"}


def render_conditions(data: dict) -> str:
    c, f = data["conditions"], data["figures"]
    return (f"Measured by `{data['command']}` on {c['date']}: {f['model']}; {c['run']}; "
            f"dropout {f['dropout']['length_s']} s from {f['dropout']['start_s']} s, slow outputs every "
            f"{f['slow_every']}th sample.")


if __name__ == "__main__":
    import sys

    import bench

    sys.exit(bench.main(["streams", *sys.argv[1:]]))
