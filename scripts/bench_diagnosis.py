"""`learnest diagnose`: self-test with both estimators, the pendulum rig, DART, detection limits.

    python scripts/bench.py diagnosis                         # every part (about 2 h on 2 cores)
    python scripts/bench.py diagnosis --parts limits,dart     # these parts; the others are kept

Parts (each records its own date, commit and load under ``measured``):

* ``selftest`` - every case of ``learnest diagnose --selftest`` with the C MHE and UKF (the
  default estimators): the verdict, the effects found against the truth, each estimator's
  corrected held-out MSE against the level the data support; the pendulum rig's cases are also
  run on the true states (``twin_truth``).
* ``dart`` - the four DART recordings pooled, default settings (``learnest diagnose --format dart``);
  their folder is ``--dart``, else ``dart/`` under the data root (``$LEARNEST_DATA``, then
  ``../shared/data``); without recordings the part is skipped (a kept measurement stays).
* ``limits`` - how large an effect must be to be named through the pre-training observer: each
  kind injected alone into the cartpole at the self-test's strength and at halvings of it (the
  smallest strength from which on it is named by name or alias), a force gain and offset
  together, and the rig's input delay with two encoders, on two swing-ups pooled and on one.
"""

from __future__ import annotations

import dataclasses
import time

import figures

MINUTES = 120
ORDER = 60
PARTS = ("selftest", "dart", "limits")

# effect of the cartpole's library, the self-test's strength of it (halved down to 1/32)
LIMIT_KINDS = (("mass(pdot via m_c)", 0.5), ("viscous_friction(pdot via F)", 2.0),
               ("coulomb_friction(pdot via F)", 1.0), ("quadratic_drag(pdot via F)", 1.0),
               ("viscous_friction(alphadot)", 0.2), ("actuator_gain(pdot via F)", -0.2),
               ("actuator_offset(pdot via F)", 0.3), ("dead_zone(pdot via F)", 1.0),
               ("input_delay(pdot via F)", 0.032), ("actuator_lag(pdot via F)", 0.04))
FACTORS = (1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125)
PAIRS = ((-0.2, 0.3), (-0.1, 0.15), (-0.05, 0.075), (-0.025, 0.0375))  # force gain, offset [N]
RIG_DELAYS_MS = (0.5, 1.0, 1.5, 2.0, 3.0, 5.0)
RIG_ENCODERS = (5e-4, 2e-3)  # [rad]
RIG_RUNS = (2, 1)  # swing-ups of 15 s: pooled, and one run fitted on its first 70 %


def add_arguments(parser) -> None:
    parser.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated, of {', '.join(PARTS)}")
    parser.add_argument("--dart", default=None,
                        help="the DART recordings' folder (default: dart/ under $LEARNEST_DATA or "
                             "../shared/data)")


def _dart_folder(given: str | None):
    """The folder of the DART recordings: ``given``, else ``dart/`` under the data root; ``None``
    when there are no recordings."""
    from learnest_codegen.recordings import dart, data_root

    if given is not None:
        return given
    files = dart.list_recordings(data_root())
    return None if not files else str(files[0].parent)


def _stamp(start: float, load: float) -> dict:
    import os

    cond = figures.conditions()
    return {"date": cond["date"], "commit": cond["commit"], "load_1min": load,
            "load_1min_at_end": round(os.getloadavg()[0], 2),
            "wall_seconds": round(time.perf_counter() - start)}


def _timed(fn, *args) -> dict:
    import os

    start, load = time.perf_counter(), round(os.getloadavg()[0], 2)
    out = fn(*args)
    return {**out, "measured": _stamp(start, load)}


def measure(args) -> tuple[dict, dict]:
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        raise SystemExit(f"unknown parts {unknown}; choose from {', '.join(PARTS)}")
    try:
        kept = figures.load("diagnosis")["figures"]
    except FileNotFoundError:
        kept = {}
    redone = set(parts) | ({"twin_truth"} if "selftest" in parts else set())
    out = {k: v for k, v in kept.items() if k not in redone}
    if "selftest" in parts:
        out["selftest"] = _timed(_selftest)
        out["twin_truth"] = _timed(_twin_truth)
    folder = _dart_folder(args.dart) if "dart" in parts else args.dart
    if "dart" in parts and folder is None:
        print("bench diagnosis: no DART recordings (pass --dart or set $LEARNEST_DATA): part dart skipped",
              flush=True)
    elif "dart" in parts:
        out["dart"] = _timed(_dart, folder)
    if "limits" in parts:
        out["limits"] = _timed(_limits)
    cond = figures.conditions(
        model="the prior of each system (no KNODE model): diagnose corrects it with effects of its library",
        run="self-test: simulated runs, seeds 1, 2, ... per case; dart: the four DART recordings "
            f"({'dart/ of the data root' if args.dart is None else args.dart}); limits: the cartpole "
            "(10 s at 500 Hz, seed 1) and the pendulum rig "
            "(2 runs of 15 s pooled, and 1 run)",
        settings="DiagnosisSettings() (estimators mhe and ukf, C backend) unless a part says otherwise",
        parts={k: v.get("measured") for k, v in out.items()})
    return out, cond


# -- the parts -------------------------------------------------------------------------------------
def _selftest() -> dict:
    from learnest_codegen.diagnosis import DiagnosisSettings
    from learnest_codegen.diagnosis.selftest import run_selftest
    from learnest_codegen.diagnosis.selftest_cases import CASES

    rows = run_selftest(CASES, settings=DiagnosisSettings(), progress=True)
    return {"rows": rows, **_summary(rows)}


def _twin_truth() -> dict:
    from learnest_codegen.diagnosis import DiagnosisSettings
    from learnest_codegen.diagnosis.selftest import run_selftest
    from learnest_codegen.diagnosis.selftest_cases import CASES

    cases = [dataclasses.replace(c, source="truth", label=c.label.replace("(observer)", "(true states)"))
             for c in CASES if c.system == "pendulum_rig"]
    rows = run_selftest(cases, settings=DiagnosisSettings(), progress=True)
    return {"rows": rows, **_summary(rows)}


def _summary(rows: list[dict]) -> dict:
    explained_above = [r["case"] for r in rows if r["verdict"] == "explained" and any(
        (e.get("above_supported") or 0.0) > 0.2 for e in r.get("estimator_errors", {}).values())]
    errors = [r["param_error"] for r in rows if r["param_error"] is not None]
    return {"cases": len(rows), "right": sum(r["pass"] for r in rows),
            "explained": sum(r["verdict"] == "explained" for r in rows),
            "explained_above_supported": explained_above,
            "worst_param_error": max(errors) if errors else None,
            "rejected_by_an_estimator": [r["case"] for r in rows if "rejected" in
                                         r.get("estimator_verdicts", {}).values()]}


def _dart(folder: str) -> dict:
    import tempfile

    from learnest_codegen.diagnosis import DiagnosisSettings, diagnose, load_recordings

    system, found = load_recordings(None, folder, "dart")
    with tempfile.TemporaryDirectory() as work:
        r = diagnose(system, found, settings=DiagnosisSettings(), work_dir=work, progress=True).report
    return {"runs": r["runs"], "verdict": r["verdict"], "verdict_reason": r["verdict_reason"],
            "closed": r["heldout_gap_closed"], "explained_in_sample": r["explained_in_sample"],
            "effects": [{"name": e["name"], "params": e["params"], "derived": e.get("derived", {})}
                        for e in r["effects"]],
            "consistency": [{"effect": c["effect"], "consistent": c["consistent"], "per_run": c["per_run"]}
                            for c in r["consistency"]],
            "blocked": [b["effect"] for b in r["selection"]["blocked"]],
            "estimators": {n: {k: r["shrink"][n].get(k) for k in ("before", "after", "supported",
                                                                   "above_supported", "verdict")}
                           for n in ("mhe", "ukf") if n in r["shrink"]}}


def _named(row: dict) -> bool:
    return row["match"] in ("exact", "alias")


def _limits() -> dict:
    from learnest_codegen.diagnosis import DiagnosisSettings
    from learnest_codegen.diagnosis.selftest import run_case
    from learnest_codegen.diagnosis.selftest_cases import Case

    quick = DiagnosisSettings(estimators=())
    kinds = []
    for name, base in LIMIT_KINDS:
        sweep = []
        for f in FACTORS:
            case = Case("cartpole", f"{name} x{f:g} (observer)", ((name, base * f),), source="observer")
            row = run_case(case, quick)
            sweep.append({"value": base * f, "named": _named(row), "found": row["found"],
                          "param_error": row["param_error"], "verdict": row["verdict"]})
            print(f"    {name} {base * f:.4g}: {'named' if _named(row) else 'not named'} ({row['found']})",
                  flush=True)
        kinds.append({"effect": name, "base": base, "sweep": sweep, "limit": _limit(sweep)})
    pairs = []
    for gain, offset in PAIRS:
        case = Case("cartpole", f"gain {gain:g} & offset {offset:g} N (observer)",
                    (("actuator_gain(pdot via F)", gain), ("actuator_offset(pdot via F)", offset)),
                    source="observer")
        row = run_case(case, quick)
        pairs.append({"gain": gain, "offset": offset, "found": row["found"], "match": row["match"],
                      "verdict": row["verdict"], "param_error": row["param_error"]})
    return {"system": "cartpole, [p, alpha] measured, rts observer", "kinds": kinds, "gain_offset": pairs,
            "rig_delay": _rig_delays()}


def _limit(sweep: list[dict]) -> float | None:
    """The smallest strength from which on every larger one is named (``None``: not even the largest)."""
    limit = None
    for s in sweep:  # largest first
        if not s["named"]:
            break
        limit = s["value"]
    return limit


def _rig_delays() -> list[dict]:
    from learnest_codegen.diagnosis import DiagnosisSettings, diagnose
    from learnest_codegen.diagnosis.selftest import _late_run
    from learnest_codegen.diagnosis.selftest_systems import pendulum_rig

    out = []
    for n_runs, encoder in ((n, e) for n in RIG_RUNS for e in RIG_ENCODERS):
        sweep = []
        for ms in RIG_DELAYS_MS:
            truth = pendulum_rig(ms * 1e-3, encoder)
            runs = [_late_run(truth, seed, None, ms * 1e-3) for seed in range(1, n_runs + 1)]
            diagnosed = dataclasses.replace(truth, true_dynamics=None, true_params=truth.params)
            r = diagnose(diagnosed, runs, settings=DiagnosisSettings(source="observer", estimators=())).report
            found = next((e["params"]["delay"] for e in r["effects"] if e["kind"] == "input_delay"), None)
            sweep.append({"delay_ms": ms, "found_ms": None if found is None else 1e3 * found,
                          "named": found is not None and abs(1e3 * found - ms) <= 1.0,
                          "others": [e["name"] for e in r["effects"] if e["kind"] != "input_delay"]})
            print(f"    rig delay {ms} ms, encoder {encoder * 1e3:g} mrad, {n_runs} run(s): {sweep[-1]}",
                  flush=True)
        limit = None
        for s in reversed(sweep):  # smallest delay from which on every larger one is named within 1 ms
            if not s["named"]:
                break
            limit = s["delay_ms"]
        out.append({"encoder_mrad": encoder * 1e3, "runs": n_runs, "sweep": sweep, "limit_ms": limit})
    return out


# -- views -----------------------------------------------------------------------------------------
def _pct(v, digits=1) -> str:
    return "-" if v is None else f"{100 * v:.{digits}f} %"


def _estimator_cell(r: dict, name: str) -> str:
    e = r.get("estimator_errors", {}).get(name)
    if not e or e.get("after") is None:
        return "-"
    verdict = r.get("estimator_verdicts", {}).get(name, "")
    if e.get("supported") is None:
        return f"{verdict}; {e['after']:.3g} (supported: -)"
    return f"{verdict}; {e['after']:.3g} vs {e['supported']:.3g} ({e['above_supported']:+.0%})"


def render_selftest(data: dict) -> str:
    part = data["figures"]["selftest"]
    lines = ["| case | truth | found | param. error | verdict | MHE: corrected vs supported | "
             "UKF: corrected vs supported | right |", "|---|---|---|---|---|---|---|---|"]
    for r in part["rows"]:
        lines.append(f"| {r['case']} | {r['truth']} | {r['found']} | {_pct(r['param_error'], 2)} | "
                     f"{r['verdict']} | {_estimator_cell(r, 'mhe')} | {_estimator_cell(r, 'ukf')} | "
                     f"{'yes' if r['pass'] else 'NO'} |")
    m = part["measured"]
    lines.append(f"\n{part['right']} of {part['cases']} right; {m['date']}, revision {m['commit']}, "
                 f"{m['wall_seconds'] / 60:.0f} min at load {m['load_1min']}-{m['load_1min_at_end']} on "
                 f"{data['conditions']['machine']['cores']} cores.")
    return "\n".join(lines)


def _rig_rows(rows: list[dict]) -> list[str]:
    out = []
    for r in rows:
        if not r["case"].startswith("pendulum_rig"):
            continue
        got = {}
        for e in r["found_params"]:
            values = {**e["params"], **e["derived"], **{k: v for k, v in e["equivalent"].items()}}
            if e["name"].startswith("mass(qdot via J)"):
                got["J"] = values["J"]
            elif e["name"].startswith("parameter(qdot via mgl)"):
                got["mgl"] = values["mgl"]
            elif "coulomb_friction" in e["name"]:
                got["Coulomb"] = values.get("coulomb_friction(qdot via tau)", values.get("F_c"))
            elif e["name"].startswith("input_delay"):
                got["delay"] = 1e3 * values["delay"]
            else:
                got.setdefault("other", []).append(e["name"])
        label = r["injected"]
        late = label.split("torque ")[1].split(" ms")[0]
        runs = label.split("late, ")[1].split(" swing")[0]

        def fmt(k, f, got=got):
            return "-" if k not in got else format(got[k], f)

        out.append(f"| {late} | {runs} | {fmt('J', '.4f')} | {fmt('mgl', '.3f')} | {fmt('Coulomb', '.4f')} | "
                   f"{fmt('delay', '.2f')} | {', '.join(got.get('other', [])) or '-'} | {r['verdict']} | "
                   f"{_estimator_cell(r, 'mhe')} | {'yes' if r['pass'] else 'NO'} |")
    return out


def render_twin(data: dict) -> str:
    head = ["| torque late [ms] | runs | J [kg m^2] (0.187) | mgl [N m] (3.60) | Coulomb [N m] (0.195) | "
            "delay found [ms] | anything else | verdict | MHE: corrected vs supported | right |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    return "\n".join(head + _rig_rows(data["figures"]["selftest"]["rows"]))


def render_twin_truth(data: dict) -> str:
    head = ["| torque late [ms] | runs | J [kg m^2] (0.187) | mgl [N m] (3.60) | Coulomb [N m] (0.195) | "
            "delay found [ms] | anything else | verdict | MHE: corrected vs supported | right |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    return "\n".join(head + _rig_rows(data["figures"]["twin_truth"]["rows"]))


def render_dart(data: dict) -> str:
    if "dart" not in data["figures"]:
        return "- not measured: no DART recordings were found when the benchmark ran."
    d = data["figures"]["dart"]
    lines = [f"- verdict: **{d['verdict']}**, held-out gap closed {_pct(d['closed'])} ({d['runs']} "
             f"recordings pooled, each held out in turn)"]
    for e in d["effects"]:
        params = ", ".join(f"{k} = {v:.4g}" for k, v in {**e["params"], **e["derived"]}.items())
        lines.append(f"- {e['name']}: {params}")
    for n, e in d["estimators"].items():
        sup = "-" if e.get("supported") is None else f"{e['supported']:.4g} ({e['above_supported']:+.0%})"
        lines.append(f"- {n.upper()}: held-out MSE {e['before']:.4g} -> {e['after']:.4g}, supported {sup}: "
                     f"{e['verdict']}")
    if d["blocked"]:
        lines.append(f"- not entered, their parameters differ between recordings: {', '.join(d['blocked'])}")
    lines.append(f"- why: {d['verdict_reason']}")
    return "\n".join(lines)


def render_limits(data: dict) -> str:
    lim = data["figures"]["limits"]
    lines = ["| effect (cartpole, through the observer) | self-test strength | named from | "
             "named at (strength: fitted) |", "|---|---|---|---|"]
    for k in lim["kinds"]:
        named = ", ".join(f"{s['value']:.3g}" for s in k["sweep"] if s["named"]) or "none"
        limit = "not at the largest" if k["limit"] is None else f"{k['limit']:.3g}"
        lines.append(f"| {k['effect']} | {k['base']:.3g} | {limit} | {named} |")
    lines += ["", "| force gain | force offset [N] | found | match | verdict |", "|---|---|---|---|---|"]
    for p in lim["gain_offset"]:
        lines.append(f"| {p['gain']:g} | {p['offset']:g} | {p['found']} | {p['match']} | {p['verdict']} |")
    lines += ["", "| rig encoder [mrad] | swing-ups | delay named within 1 ms from | "
              "found [ms] at 0.5 / 1 / 1.5 / 2 / 3 / 5 ms |", "|---|---|---|---|"]
    for e in lim["rig_delay"]:
        found = " / ".join("-" if s["found_ms"] is None else f"{s['found_ms']:.2f}" for s in e["sweep"])
        limit = "not at 5 ms" if e["limit_ms"] is None else f"{e['limit_ms']:g} ms"
        runs = e.get("runs", 2)
        runs = f"{runs} (pooled)" if runs > 1 else f"{runs}"
        lines.append(f"| {e['encoder_mrad']:g} | {runs} | {limit} | {found} |")
    m = lim["measured"]
    lines.append(f"\n{m['date']}, revision {m['commit']}, {m['wall_seconds'] / 60:.0f} min at load "
                 f"{m['load_1min']}-{m['load_1min_at_end']}.")
    return "\n".join(lines)


def render_honest(data: dict) -> str:
    part = data["figures"]["selftest"]
    breaches = part["explained_above_supported"]
    return (f"{part['right']} of {part['cases']} cases right; {part['explained']} \"explained\", "
            f"{len(breaches)} of them with an estimator's corrected held-out error more than 20 % above "
            f"what the data support" + (": " + "; ".join(breaches) if breaches else "."))
