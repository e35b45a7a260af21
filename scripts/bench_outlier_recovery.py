"""Outlier recovery of every estimator: bursts of finite garbage injected into a clean test run.

For each estimator and backend (Python reference, compiled C) the clean simulated run is
estimated once, then once per burst: ``length`` consecutive samples (from ``BURST_START``) whose
every output is replaced by ``+-size`` (random sign). Reported per burst:

- ``samples_to_recover``: samples after the burst's last one until the estimate stays, for the
  rest of the run, within ``TOLERANCE`` of the clean run's estimate, per state, in units of the
  clean run's RMS error of that state (``|x - x_clean|_i <= TOLERANCE * rms_i``);
- ``max_error_after``: the largest of those normalised deviations from ``RECOVERY_BUDGET``
  samples after the burst to the end (so ``<= TOLERANCE`` means recovered in budget);
- ``errors``: steps that raised (an error status of the C), and ``rejected``: samples with a
  rejected output.

Input bursts (``u_rows``, every estimator, Python and compiled in each precision): the same
lengths and sizes written into the input ``u`` instead (every component ``+-size``), once with
the system's ``input_limits`` (the cartpole's +-50 N: 1e3 and 1e6 are replaced by the held
input, 1e1 is plausible and used) and once without any limits (only the recovery repairs the
state; the compiled estimators are then built from settings without limits). Besides the two figures above
they report ``samples_to_band``: samples after the burst until the error to the truth stays
within the clean run's band (``|e|_i <= |e_clean|_i + rms_i``) -- after a wrong input an
estimator can come back *closer* to the truth than the clean run and still differ from it.

The clean run is also estimated with the gate off: ``clean`` reports the MSE with the gate on
and off and the clean samples the gate rejected. The benchmark (``python scripts/bench.py
outlier_recovery``) runs the cartpole and the ground robot, the compiled estimators in float64
and float32. ``main`` is the same study with its own options, written to ``--out``::

    python scripts/bench_outlier_recovery.py --systems cartpole --precisions float64 float32
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from learnest_codegen import get_system
from learnest_codegen.compilation import (
    ESTIMATORS,
    compile_estimators,
    estimator_dir,
    estimator_kind,
    estimator_settings,
)
from learnest_codegen.errors import SolverError
from learnest_codegen.estimators.gate import GateSettings
from learnest_codegen.export import prior_model
from learnest_codegen.simulation import simulate

MINUTES = 30
ORDER = 50
BURST_START = 150
LENGTHS = (1, 3, 10)
SIZES = (1e1, 1e3, 1e6)
TOLERANCE = 1.0      # deviation from the clean estimate, in clean-run RMS errors per state
RECOVERY_BUDGET = 60  # samples after the burst by which every estimator must be back
def estimator_backends() -> dict[str, tuple[str, ...]]:
    """Estimator -> backends, from the estimator table: the Python reference where it has its
    own (mhe_gn's is the Ipopt MHE's, the same problem; mhe_rti has none) and the C."""
    return {name: kind.backends for name, kind in ESTIMATORS.items()}


def clean_run(system_name: str, samples: int, seed: int = 1):
    system = get_system(system_name)
    return system, simulate(system, seed=seed, duration=samples * system.dt)


def inject_u(U: np.ndarray, length: int, size: float, seed: int = 0) -> np.ndarray:
    """``U`` with the inputs applied before samples ``BURST_START + 1 ..`` (``U[BURST_START]``
    on, ``length`` of them) replaced by ``+-size``."""
    Ub = U.copy()
    signs = np.random.default_rng(seed).choice([-1.0, 1.0], size=(length, U.shape[1]))
    Ub[BURST_START:BURST_START + length] = size * signs
    return Ub


def inject(Y: np.ndarray, length: int, size: float, seed: int = 0) -> np.ndarray:
    """``Y`` with samples ``BURST_START .. BURST_START + length - 1`` replaced by ``+-size``."""
    Yb = Y.copy()
    signs = np.random.default_rng(seed).choice([-1.0, 1.0], size=(length, Y.shape[1]))
    Yb[BURST_START:BURST_START + length] = size * signs
    return Yb


class Estimators:
    """Builds (once) and makes the estimators of one system's nominal model."""

    def __init__(self, system, build_dir: Path):
        self.system, self.model = system, prior_model(system)
        self.build_dir = Path(build_dir)
        self._built: set[tuple[str, str, bool]] = set()

    def make(self, estimator: str, backend: str, gate: GateSettings | None = None,
             limits: bool = True, precision: str = "float64"):
        kind = estimator_kind(estimator)
        settings = kind.default_settings(self.model)
        if not limits:
            settings = dataclasses.replace(settings, input_limits=None)
        if backend == "python":
            if gate is not None:
                settings = dataclasses.replace(settings, gate=gate)
            return (kind.python or estimator_kind("mhe").python)(self.model, settings)
        # the C's input limits are compiled in: a build without them has its own folder
        out = self.build_dir if limits else self.build_dir / "no_input_limits"
        if (estimator, precision, limits) not in self._built:
            free = replace(estimator_settings(estimator, self.model, precision=precision),
                           input_limits=None)
            compile_estimators(self.model, out, model_hash="nominal", estimators=(estimator,),
                               precision=precision, settings=None if limits else {estimator: free})
            self._built.add((estimator, precision, limits))
        est = kind.compiled(estimator_dir(out, self.model, estimator, precision))
        if gate is not None:
            est.settings = dataclasses.replace(est.settings, gate=gate)
        return est


def estimate(est, U: np.ndarray, Y: np.ndarray, x0) -> tuple[np.ndarray, np.ndarray, int]:
    """Step through a run; ``(X_hat, rejected (T,) bool, steps that raised)``."""
    est.reset(x0)
    X = np.empty((len(Y), len(x0)))
    rejected = np.zeros(len(Y), dtype=bool)
    errors = 0
    for k in range(len(Y)):
        u = U[max(k - 1, 0)]  # run()'s convention: sample 0 uses U[0] (only in h)
        try:
            X[k] = est.step(u, Y[k])
            rejected[k] = bool(est.last_status & 1)
        except SolverError:
            errors += 1
            X[k] = est.x
    return X, rejected, errors


def back_in_band(X: np.ndarray, X_clean: np.ndarray, X_true: np.ndarray, length: int) -> int:
    """Samples after the burst until ``|x - x_true|_i <= |x_clean - x_true|_i + rms_i`` for
    good (``rms`` the clean run's RMS error per state); ``len(X)`` if never."""
    end = BURST_START + length
    e, e_clean = np.abs(X - X_true), np.abs(X_clean - X_true)
    rms = np.sqrt(np.mean(e_clean ** 2, axis=0))
    outside = np.flatnonzero(np.any(e[end:] > e_clean[end:] + rms, axis=1))
    return 0 if outside.size == 0 else int(outside[-1]) + 1


def recovery(X: np.ndarray, X_clean: np.ndarray, rms: np.ndarray, length: int) -> tuple[int, float]:
    """``(samples_to_recover, max_error_after)`` of a burst run against the clean estimate."""
    end = BURST_START + length
    deviation = (np.abs(X - X_clean) / rms).max(axis=1)
    outside = np.flatnonzero(deviation[end:] > TOLERANCE)
    to_recover = 0 if outside.size == 0 else int(outside[-1]) + 1
    return to_recover, float(deviation[end + RECOVERY_BUDGET:].max())


def input_rows(system_name: str, run, makers: "Estimators", estimator: str, backend: str,
               precision: str, X_clean: np.ndarray, rms: np.ndarray, lengths=LENGTHS,
               sizes=SIZES, without_limits: bool = True) -> list[dict]:
    """The input-burst rows of one estimator, with the input limits and (Python always, the
    compiled ones with ``without_limits``: a second build) without them."""
    rows = []
    for limits in ((True, False) if backend == "python" or without_limits else (True,)):
        est = makers.make(estimator, backend, limits=limits, precision=precision)
        for length in lengths:
            for size in sizes:
                X, rejected, errors = estimate(est, inject_u(run.u, length, size), run.y,
                                               makers.system.x0)
                to_recover, after = recovery(X, X_clean, rms, length)
                rows.append({"system": system_name, "estimator": estimator, "backend": backend,
                             "precision": precision, "limits": limits, "burst": length, "size": size,
                             "inputs_replaced": int(est.input_rejections),
                             "samples_to_recover": to_recover, "max_error_after": after,
                             "samples_to_band": back_in_band(X, X_clean, run.x, length),
                             "errors": errors, "rejected": int(rejected.sum())})
    return rows


def table(system_name: str, build_dir: Path, *, samples: int = 400, lengths=LENGTHS, sizes=SIZES,
          backends=None, inputs: bool = True, precisions=("float64",),
          c_without_limits: bool = True) -> dict:
    """The recovery table of one system (see the module docstring)."""
    system, run = clean_run(system_name, samples)
    makers = Estimators(system, build_dir)
    rows, clean, u_rows = [], [], []
    for estimator, kinds in (backends or estimator_backends()).items():
        for backend, precision in ((b, p) for b in kinds
                                   for p in (("float64",) if b == "python" else
                                             [p for p in precisions
                                              if p in estimator_kind(estimator).precisions])):
            start = time.process_time()
            est = makers.make(estimator, backend, precision=precision)
            X_clean, rej_clean, err_clean = estimate(est, run.u, run.y, system.x0)
            X_off, _, _ = estimate(makers.make(estimator, backend, GateSettings(threshold=0),
                                               precision=precision), run.u, run.y, system.x0)
            rms = np.sqrt(np.mean((X_clean - run.x) ** 2, axis=0))
            clean.append({"estimator": estimator, "backend": backend, "precision": precision,
                          "samples": samples,
                          "mse_gate_on": float(np.mean((X_clean - run.x) ** 2)),
                          "mse_gate_off": float(np.mean((X_off - run.x) ** 2)),
                          "clean_samples_rejected": int(rej_clean.sum()), "errors": err_clean,
                          "rms_error": rms.tolist()})
            for length in lengths:
                for size in sizes:
                    X, rejected, errors = estimate(est, run.u, inject(run.y, length, size), system.x0)
                    to_recover, after = recovery(X, X_clean, rms, length)
                    rows.append({"system": system_name, "estimator": estimator, "backend": backend,
                                 "precision": precision, "burst": length, "size": size,
                                 "samples_to_recover": to_recover,
                                 "max_error_after": after, "errors": errors,
                                 "rejected": int(rejected.sum()),
                                 "samples_to_band": back_in_band(X, X_clean, run.x, length)})
            if inputs:
                u_rows += input_rows(system_name, run, makers, estimator, backend, precision,
                                     X_clean, rms, lengths, sizes, c_without_limits)
            clean[-1]["cpu_seconds"] = round(time.process_time() - start, 2)
    return {"system": system_name, "tolerance": TOLERANCE, "budget": RECOVERY_BUDGET,
            "burst_start": BURST_START, "clean": clean, "rows": rows, "u_rows": u_rows}


def markdown(result: dict) -> str:
    lines = ["| system | estimator | backend | burst | size | rejected | samples to recover | "
             "max error after | samples to band | errors |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in result["rows"]:
        lines.append(f"| {r['system']} | {r['estimator']} | {_backend(r)} | {r['burst']} | "
                     f"{r['size']:.0e} | {r['rejected']} | {r['samples_to_recover']} | "
                     f"{r['max_error_after']:.2f} | {r['samples_to_band']} | {r['errors']} |")
    if result.get("u_rows"):
        lines += ["", "| system | estimator | backend | input limits | burst | size | inputs replaced | "
                  "outputs rejected | samples to recover | max error after | samples to band | "
                  "errors |",
                  "| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
        for r in result["u_rows"]:
            lines.append(f"| {r['system']} | {r['estimator']} | {_backend(r)} | "
                         f"{'yes' if r['limits'] else 'no'} | "
                         f"{r['burst']} | {r['size']:.0e} | {r['inputs_replaced']} | {r['rejected']} | "
                         f"{r['samples_to_recover']} | {r['max_error_after']:.2f} | "
                         f"{r['samples_to_band']} | {r['errors']} |")
    return "\n".join(lines)


def _backend(row: dict) -> str:
    precision = row.get("precision", "float64")
    return row["backend"] if precision == "float64" else f"{row['backend']} {precision}"


def add_arguments(parser) -> None:
    parser.add_argument("--systems", nargs="+", default=["cartpole", "ground_robot"])
    parser.add_argument("--samples", type=int, default=400)
    parser.add_argument("--precisions", nargs="+", default=["float64", "float32"],
                        choices=["float64", "float32"], help="of the compiled estimators")


def measure(args) -> tuple[dict, dict]:
    import figures

    cond = figures.conditions(
        model="each system's nominal model (the prior)",
        run=f"each system's simulated run seed 1, the first {args.samples} samples; bursts from sample "
            f"{BURST_START} of {', '.join(map(str, LENGTHS))} samples of "
            + ", ".join(f"+-{s:g}" for s in SIZES),
        systems=list(args.systems), precisions=list(args.precisions))
    build = figures.ROOT / "build" / "bench" / "outlier_recovery"
    return {"tables": [table(name, build, samples=args.samples, precisions=tuple(args.precisions))
                       for name in args.systems]}, cond


def _table(data: dict, system: str) -> dict:
    return next(t for t in data["figures"]["tables"] if t["system"] == system)


def _cell(rows: list[dict]) -> str:
    """Samples to recover / to be back in the band, the worst of ``rows``, and what happened."""
    worst = max(rows, key=lambda r: (r["samples_to_recover"], r["samples_to_band"]))
    text = f"{worst['samples_to_recover']} / {worst['samples_to_band']}"
    if any(r.get("inputs_replaced") for r in rows) and all(r.get("inputs_replaced") == r["burst"]
                                                          for r in rows):
        text += " (replaced)"
    rejected, errors = max(r["rejected"] for r in rows), max(r["errors"] for r in rows)
    text += f", {rejected} rejected" if rejected and not errors else ""
    text += f", {rejected} rejected, {errors} failed" if errors else ""
    return text


def render_inputs(data: dict) -> str:
    """Wrong inputs on the cartpole: with and without the system's input limits."""
    t = _table(data, "cartpole")
    lines = ["| estimator | build | input limits | burst | 1e1: to recover / in band | 1e3 | 1e6 |",
             "| --- | --- | --- | ---: | --- | --- | --- |"]
    groups = {}
    for r in t["u_rows"]:
        groups.setdefault((r["estimator"], _backend(r), r["limits"]), []).append(r)
    for (estimator, backend, limits), rows in groups.items():
        bursts = [(b,) for b in LENGTHS] if not limits else [LENGTHS]
        for burst in bursts:
            mine = [r for r in rows if r["burst"] in burst]
            cells = [_cell([r for r in mine if r["size"] == size]) for size in SIZES]
            lines.append(f"| {estimator} | {backend} | {'yes' if limits else 'none'} | "
                         f"{', '.join(map(str, burst))} | " + " | ".join(cells) + " |")
    never = t["clean"][0]["samples"] - t["burst_start"] - 1
    return ("\n".join(lines) + f"\n\n{never}: not within the run. " + render_conditions(data))


def render_conditions(data: dict) -> str:
    c = data["conditions"]
    return (f"Measured by `{data['command']}` on {c['date']}: {c['model']}; {c['run']}. \"To recover\": "
            f"samples until the estimate stays within {TOLERANCE:g} clean RMS error of the clean estimate; "
            "\"in band\": until its error stays within the clean run's error band plus one RMS.")


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--systems", nargs="+", default=["cartpole", "ground_robot"])
    parser.add_argument("--samples", type=int, default=400)
    parser.add_argument("--build-dir", type=Path, default=Path("build/outlier_recovery"))
    parser.add_argument("--out", type=Path, default=Path("bench_outlier_recovery.json"))
    parser.add_argument("--precisions", nargs="+", default=["float64", "float32"],
                        choices=["float64", "float32"], help="of the compiled estimators")
    parser.add_argument("--c-with-limits-only", action="store_true",
                        help="input bursts of the compiled estimators with the system's limits "
                             "only (no second build without them)")
    args = parser.parse_args(argv)
    results = [table(name, args.build_dir, samples=args.samples, precisions=tuple(args.precisions),
                     c_without_limits=not args.c_with_limits_only) for name in args.systems]
    out = {"tables": results}
    args.out.write_text(json.dumps(out, indent=1))
    for r in results:
        print(markdown(r))
        for c in r["clean"]:
            print(c)
    return out


if __name__ == "__main__":
    main()
