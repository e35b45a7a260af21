"""Real Crazyflie flights, leave one trajectory type out: per state group and reference window.

Runs the quadrotor study (``learnest_codegen.experiments.quadrotor``) on the NanoBench flights
(``$LEARNEST_DATA`` or ``../shared/data``; ``--data``), protocol ``leave-type-out`` (the 9
circles tested on a model trained on the 8 figure-eights, and the reverse):

* the recommended configuration (``bias_lag_prior``: the fitted prior with states for the
  accelerometer's offset and lag) with the system's noise, KNODE-UKF and KNODE-MHE-RTI, each
  against its nominal estimator as built (which is also "tuned the same way": neither is);
  ``bias_lag`` (no fitted prior), ``bias_prior`` (no lag) and ``linear_prior`` (no sensor
  states) the same way;
* the same models with their noise (and lag) chosen on the training flights
  (``--tune-noise``), against the nominal estimators as built and tuned the same way
  (``linear_prior``: UKF only);
* the physics variants and controls with the UKF, tuned: ``bias`` (the offsets alone, nothing
  fitted), ``bias_thrust_prior`` and ``bias_thrust_prior_axes`` (thrust per battery voltage,
  motor lag and drag rows fitted), ``bias_linear`` (a net on top of ``bias_prior``);
* what limits the long windows: per flight, the velocity change a perfect estimate would make
  (the central-difference velocity itself, scored against each window), and the Vicon noise
  under the position "errors".

Every figure is per test flight and state group (position, velocity, acceleration) and a
normalised overall (each group's MSE over the nominal's), at the references
``sg_0.5s``..``sg_3s`` and ``cd_0.1s``; the onboard EKF's velocity beside. Results are kept in
``--out`` (default ``build/bench/flights``) and reused while the code and data are unchanged.
"""

from __future__ import annotations

from pathlib import Path

import figures
import numpy as np

MINUTES = 120
ORDER = 60
OUT = figures.ROOT / "build" / "bench" / "flights"
RECOMMENDED, RECOMMENDED_TAG = "bias_lag_prior", "untuned"
COMPARED = ("bias_lag", "bias_prior")  # run like the recommended one: both estimators, tuned and not
VARIANTS = ("linear_prior", "bias", "bias_thrust_prior", "bias_thrust_prior_axes", "bias_linear")
REFERENCES = ("cd_0.1s", "sg_0.5s", "sg_1s", "sg_1.5s", "sg_3s")
GROUPS = ("p", "v", "a", "overall")
NAMES = {"p": "position", "v": "velocity", "a": "acceleration", "overall": "overall (normalised)"}


def add_arguments(parser) -> None:
    parser.add_argument("--data", default=None,
                        help="data root (default: $LEARNEST_DATA or ../shared/data)")
    parser.add_argument("--out", type=Path, default=OUT, help="the studies' folder (results reused)")
    parser.add_argument("--tuned", default=",".join((RECOMMENDED, *COMPARED)),
                        help="comma-separated features tuned with both estimators (the recommended one "
                             "always; each takes about half an hour a fold on 2 cores)")
    parser.add_argument("--variants", default=",".join(VARIANTS),
                        help="comma-separated features run with the tuned UKF beside the recommended one")


def _paired(p) -> dict:
    return {"mean": p.mean, "median": p.median, "better": p.improved, "flights": p.n,
            "worst": p.worst, "worst_flight": p.worst_flight}


def _tunings(record: dict) -> dict:
    keep = ("label", "process_scale", "measurement_scale", "measurement_scales", "groups", "criterion",
            "prediction_mse", "rejected_share", "gate_widened", "edge", "parameters", "parameter_criteria")
    out = {est: {k: r[k] for k in keep if k in r} for est, r in record.items() if est != "nominal"}
    for est, r in record.get("nominal", {}).items():
        out[f"nominal {est}"] = {k: r[k] for k in keep if k in r}
    return out


def _summary(s) -> dict:
    per_flight = {case: {m: {"by_reference": v.get("by_reference", {}), "rejected": v.get("rejected"),
                             "rejected_share": v.get("rejected_share")} for m, v in methods.items()}
                  for case, methods in s.per_case.items()}
    return {"by_reference": {pair: {ref: {g: _paired(p) for g, p in row.items()} for ref, row in refs.items()}
                             for pair, refs in s.by_reference.items()},
            "onboard_velocity": {k: {ref: _paired(p) for ref, p in refs.items()}
                                 for k, refs in s.onboard.items()},
            "overall_mse": {k: _paired(groups["all"]) for k, groups in s.paired.items()},
            "per_flight": per_flight,
            "tunings": {fold: _tunings(record) for fold, record in s.tunings.items()},
            "trainings": {fold: {"prior_params": t.get("prior_params"), "net_kept": t.get("net_kept")}
                          for fold, t in s.trainings.items()}}


def _limits(summary: dict, flights: dict) -> dict:
    """Per nominal estimator and reference: the velocity change of the central-difference
    velocity itself (a perfect estimate, up to its 1e-6 error) against that estimator."""
    out = {}
    nominal_labels = {m for c in summary["per_flight"].values() for m in c if not m.startswith("KNODE")}
    for label in sorted(nominal_labels - {"onboard EKF"}):
        out[label] = {}
        for ref in REFERENCES[1:]:
            changes = []
            for name, methods in summary["per_flight"].items():
                cd, sg = flights[name].references["cd_0.1s"][:, 3:6], flights[name].references[ref][:, 3:6]
                ok = np.isfinite(cd).all(axis=1)
                floor = float(np.mean((cd[ok] - sg[ok]) ** 2))
                changes.append(100 * (1 - floor / methods[label]["by_reference"][ref]["v"]))
            out[label][ref] = {"mean": float(np.mean(changes)), "min": float(np.min(changes)),
                               "max": float(np.max(changes))}
    return out


def _vicon_noise(flights: dict) -> dict:
    """Per flight, the Vicon position noise [mm]: the residual of a local cubic fit over 9
    samples, corrected for the fit's own share."""
    from scipy.signal import savgol_filter

    centre = savgol_filter(np.eye(9)[4], 9, 3)[4]
    out = {}
    for name, f in flights.items():
        p = f.run.y[:, :3]
        r = (p - savgol_filter(p, 9, 3, axis=0))[10:-10]
        out[name] = float(1e3 * np.sqrt(np.mean(r ** 2) / (1 - centre)))
    return out


def _facts(flights: dict, study: dict) -> dict:
    """The figures the page's prose quotes: the central-difference velocity's error (against a
    quartic Savitzky-Golay fit over 0.31 s), the accelerometer's world-frame offsets (its mean
    difference from the Vicon acceleration, a cubic fit over 0.31 s), the acceleration's share
    of the paper's overall MSE (UKF as built, sg_1.5s) and the smallest velocity MSE of an
    estimator against cd_0.1s."""
    from scipy.signal import savgol_filter

    cd_err, offsets, share = [], [], []
    for name, methods in study["per_flight"].items():
        f = flights[name]
        p = f.run.y[:, :3]
        cd = f.references["cd_0.1s"][:, 3:6]
        ok = np.isfinite(cd).all(axis=1)
        quartic = savgol_filter(p, 31, 4, deriv=1, delta=f.timing.dt, axis=0)
        cd_err.append(float(np.mean((cd[ok] - quartic[ok]) ** 2)))
        vicon_acc = savgol_filter(p, 31, 3, deriv=2, delta=f.timing.dt, axis=0)
        offsets.append(np.mean(f.run.y[:, 3:] - vicon_acc, axis=0))
        g = methods["UKF"]["by_reference"]["sg_1.5s"]
        share.append(g["a"] / (g["p"] + g["v"] + g["a"]))
    offsets = np.array(offsets)
    v_min = min(m["by_reference"]["cd_0.1s"]["v"] for c in study["per_flight"].values()
                for k, m in c.items() if k != "onboard EKF")
    return {"cd_error_min": min(cd_err), "cd_error_max": max(cd_err),
            "offset_x_min": float(np.min(np.abs(offsets[:, 0]))),
            "offset_x_max": float(np.max(np.abs(offsets[:, 0]))),
            "offset_y_max": float(np.max(np.abs(offsets[:, 1]))),
            "acceleration_share_min": 100 * min(share), "acceleration_share_max": 100 * max(share),
            "velocity_mse_min": v_min}


def measure(args) -> tuple[dict, dict]:
    from learnest_codegen.experiments import quadrotor as fs
    from learnest_codegen.recordings import crazyflie, data_root

    root = data_root(args.data)
    if root is None:
        raise SystemExit("no NanoBench flights: pass --data or set $LEARNEST_DATA")
    findings, skipped = [], {}
    cases = fs.flight_cases(root, findings=findings, skipped=skipped)
    cond = figures.conditions(
        model="per fold, the KNODE model of each features trained on the other trajectory type's flights",
        run=f"{len(cases)} NanoBench flights, leave-type-out", protocol="leave-type-out",
        settings="StudySettings() with the estimators named; --tune-noise where 'tuned'")
    out = Path(args.out)
    both = ("ukf", "mhe_rti")
    studies = {}
    tuned_features = dict.fromkeys([RECOMMENDED, *(f for f in args.tuned.split(",") if f)])
    runs = [*(("tuned", f, both, True) for f in tuned_features),
            *(("untuned", f, both, False) for f in (RECOMMENDED, *COMPARED, "linear_prior")),
            *(("tuned", f, ("ukf",), True) for f in args.variants.split(",") if f)]
    for tag, features, estimators, tune in runs:
        settings = fs.StudySettings(estimators=estimators, tune_noise=tune)
        (summary,) = fs.run_study(cases, out / tag, features=[features], settings=settings,
                                  protocol="leave-type-out", skipped=skipped, findings=findings)
        studies[f"{features}/{tag}"] = _summary(summary)
    flights = {f.name: f for f in (crazyflie.read_flight(p) for p in crazyflie.list_flights(root))}
    rec, tuned = studies[f"{RECOMMENDED}/{RECOMMENDED_TAG}"], studies[f"{RECOMMENDED}/tuned"]
    limits = _limits(tuned, flights)
    figs = {"recommended": RECOMMENDED, "recommended_tag": RECOMMENDED_TAG, "headline": _slugs(rec, limits),
            "tuned_headline": _slugs(tuned, limits), "studies": studies, "limits": limits,
            "vicon_noise_mm": _vicon_noise({n: flights[n] for n in rec["per_flight"]}),
            "facts": _facts(flights, tuned),
            "findings": [f.to_json() for f in findings], "skipped": skipped,
            "references": {k: v for k, v in crazyflie.REFERENCES.items()}}
    return figs, cond


def _slug(text: str) -> str:
    """``"KNODE-MHE-RTI vs MHE-RTI (tuned)"`` -> ``"mhe_rti_vs_tuned"``, ``"sg_1.5s"`` -> ``"sg15"``."""
    if text.startswith("sg_") or text.startswith("cd_"):
        return text[:2] if text.startswith("cd") else "sg" + text[3:-1].replace(".", "")
    knode, _, nominal = text.partition(" vs ")
    est = knode.removeprefix("KNODE-").lower().replace("-", "_")
    return f"{est}_vs_{'tuned' if nominal else 'built'}" if knode.startswith("KNODE") else \
        text.lower().replace("-", "_").replace(" (tuned)", "_tuned").replace(" ", "_")


def _slugs(study: dict, limits: dict) -> dict:
    """The recommended study's figures under plain keys, for the pages' inline values."""
    out = {_slug(pair): {_slug(ref): row for ref, row in refs.items()}
           for pair, refs in study["by_reference"].items()}
    out["onboard"] = {_slug(k).removesuffix("_vs_built"): {_slug(r): v for r, v in refs.items()}
                      for k, refs in study["onboard_velocity"].items()}
    out["limits"] = {_slug(k): {_slug(r): v for r, v in refs.items()} for k, refs in limits.items()}
    return out


# --- views ------------------------------------------------------------------------------------------


def _cell(p: dict | None) -> str:
    if not p:
        return "-"
    return f"{p['mean']:+.1f} % ({p['better']}/{p['flights']}, worst {p['worst']:+.1f} %)"


def _methods(pair: str) -> tuple[str, str]:
    """The KNODE and the nominal method a pair key compares (``"KNODE-UKF"``: against ``"UKF"``)."""
    knode, _, nominal = pair.partition(" vs ")
    return knode, nominal or knode.removeprefix("KNODE-")


def _inside_noise(study: dict, pair: str, ref: str, noise_mm: dict) -> list[str]:
    """The flights on which either method of ``pair`` follows the Vicon position closer than the
    Vicon noise: there the position reference is the measurement the estimator took in, so a
    ratio of two such deviations ranks round-off and tuning, not accuracy."""
    inside = []
    for flight, methods in study.get("per_flight", {}).items():
        for m in _methods(pair):
            mse = methods.get(m, {}).get("by_reference", {}).get(ref, {}).get("p")
            if mse is not None and flight in noise_mm and 1e3 * np.sqrt(mse) < noise_mm[flight]:
                inside.append(flight)
                break
    return inside


def _state_table(study: dict, pair: str, noise_mm: dict) -> list[str]:
    """References by state group for one pair. A position cell (and the normalised overall, which
    contains it) is not a percentage where a method's position deviation lies inside the Vicon
    noise on some flight (see the Position table)."""
    rows = study["by_reference"].get(pair, {})
    lines = ["| reference | " + " | ".join(NAMES[g] for g in GROUPS) + " |",
             "|---" * (len(GROUPS) + 1) + "|"]
    for ref in REFERENCES:
        if ref not in rows:
            continue
        inside = _inside_noise(study, pair, ref, noise_mm)
        cells = []
        for g in GROUPS:
            if inside and g in ("p", "overall") and rows[ref].get(g):
                n = rows[ref][g]["flights"]
                cells.append(f"inside the Vicon noise on {len(inside)}/{n}")
            else:
                cells.append(_cell(rows[ref].get(g)))
        lines.append(f"| {ref} | " + " | ".join(cells) + " |")
    return lines


def _pairs(data: dict, study: dict) -> str:
    out = []
    for pair in study["by_reference"]:
        knode, nominal = _methods(pair)
        title = f"{knode} against {nominal if ' vs ' in pair else nominal + ' as built'}"
        out += [f"**{title}**", "", *_state_table(study, pair, data["figures"]["vicon_noise_mm"]), ""]
    return "\n".join(out).rstrip()


def _recommended(data: dict) -> dict:
    figs = data["figures"]
    return figs["studies"][f"{figs['recommended']}/{figs['recommended_tag']}"]


def render_headline(data: dict) -> str:
    """The recommended configuration: each KNODE estimator against its nominal estimator, per
    reference and state group."""
    return _pairs(data, _recommended(data))


def render_tuned(data: dict) -> str:
    """The recommended model with its noise and lag tuned: against the nominal estimators as
    built and tuned the same way."""
    return _pairs(data, data["figures"]["studies"][f"{data['figures']['recommended']}/tuned"])


def render_untuned_models(data: dict) -> str:
    """Every model with the system's noise, against the nominal estimators as built: velocity
    at every reference (mean, flights better), the worst flight of position and acceleration
    over the references, and the normalised overall's lowest mean."""
    head = ["model", "estimator", *(f"velocity {r}" for r in REFERENCES), "position worst",
            "acceleration worst", "overall lowest mean"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for key, study in data["figures"]["studies"].items():
        features, tag = key.split("/")
        if tag != "untuned":
            continue
        for pair, refs in study["by_reference"].items():
            cells = [f"{refs[r]['v']['mean']:+.1f} % ({refs[r]['v']['better']}/{refs[r]['v']['flights']})"
                     for r in REFERENCES]
            worst = {g: min(refs[r][g]["worst"] for r in REFERENCES if g in refs[r]) for g in ("p", "a")}
            lowest = min(refs[r]["overall"]["mean"] for r in REFERENCES)
            lines.append(f"| {features} | {pair.removeprefix('KNODE-')} | " + " | ".join(cells)
                         + f" | {worst['p']:+.1f} % | {worst['a']:+.1f} % | {lowest:+.1f} % |")
    return "\n".join(lines)


def render_onboard(data: dict) -> str:
    study = _recommended(data)
    labels = list(study["onboard_velocity"])
    lines = ["| reference | " + " | ".join(f"{k} velocity vs onboard EKF" for k in labels) + " |",
             "|---" * (len(labels) + 1) + "|"]
    for ref in REFERENCES:
        cells = [_cell(study["onboard_velocity"][k].get(ref)) for k in labels]
        lines.append(f"| {ref} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


NOT_MEASURED = "Not measured by this run of the benchmark (`{command}`): {what}."


def render_variants(data: dict) -> str:
    """Every tuned features' KNODE-UKF against the UKF tuned the same way: velocity at each
    reference, and acceleration and the normalised overall at 1 s."""
    studies = data["figures"]["studies"]
    variants = [k for k in studies
                if k.endswith("/tuned") and k.split("/")[0] not in (RECOMMENDED, *COMPARED)]
    if not variants:
        return NOT_MEASURED.format(command=data["command"], what="no variant was run (`--variants`)")
    pair = "KNODE-UKF vs UKF (tuned)"
    head = ["features", *(f"velocity {r}" for r in REFERENCES), "acceleration sg_1s", "overall sg_1s"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for key, study in studies.items():
        features, tag = key.split("/")
        if tag != "tuned" or pair not in study["by_reference"]:
            continue
        refs = study["by_reference"][pair]
        cells = [f"{refs[r]['v']['mean']:+.1f} % ({refs[r]['v']['better']}/{refs[r]['v']['flights']})"
                 for r in REFERENCES]
        cells += [f"{refs['sg_1s'][g]['mean']:+.1f} % (worst {refs['sg_1s'][g]['worst']:+.1f} %)"
                  for g in ("a", "overall")]
        lines.append(f"| {features} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def render_limits(data: dict) -> str:
    """The velocity change a perfect estimate would make against each nominal estimator."""
    limits = data["figures"]["limits"]
    lines = ["| against | " + " | ".join(REFERENCES[1:]) + " |", "|---" * len(REFERENCES) + "|"]
    for label, refs in limits.items():
        cells = [f"{refs[r]['mean']:+.1f} % ({refs[r]['min']:+.1f} to {refs[r]['max']:+.1f} %)"
                 for r in REFERENCES[1:]]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def render_tunings(data: dict) -> str:
    study = data["figures"]["studies"][f"{data['figures']['recommended']}/tuned"]
    lines = ["| fold | estimator | process | position | accelerometer | accelerometer lag | criterion | "
             "gate rejects | on the edge |", "|---|---|---|---|---|---|---|---|---|"]
    for fold, ests in study["tunings"].items():
        for est, r in ests.items():
            scales = [r["measurement_scale"] * s for s in r["measurement_scales"]]
            lag = r.get("parameters", {}).get("tau_acc")
            edge = ", ".join("/".join(g) for g in r["edge"]) or "no"
            lines.append(f"| {fold} | {'KNODE ' + est if not est.startswith('nominal') else est} | "
                         f"x{r['process_scale']:g} | x{scales[0]:.3g} | x{scales[1]:.3g} | "
                         f"{'-' if lag is None else f'{1000 * lag:.0f} ms'} | {r['criterion']:.3f} | "
                         f"{100 * r['rejected_share']:.2f} % | {edge} |")
    return "\n".join(lines)


def render_per_flight(data: dict) -> str:
    """Per test flight: velocity MSE against the central differences and acceleration MSE
    against the 1 s fit, each estimator of the recommended tuned study, and the onboard EKF."""
    study = _recommended(data)
    flights = study["per_flight"]
    methods = [m for m in next(iter(flights.values())) if m != "onboard EKF"] + ["onboard EKF"]
    lines = ["| flight | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for name, ms in flights.items():
        cells = []
        for m in methods:
            refs = ms[m]["by_reference"]
            v, a = refs["cd_0.1s"]["v"], refs["sg_1s"].get("a")
            cells.append(f"{v:.2e}" + (f"; {a:.3f}" if a is not None and m != "onboard EKF" else ""))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def render_checks(data: dict) -> str:
    from learnest_codegen.recordings.checks import Finding

    found = data["figures"]["findings"]
    return "\n".join(f"- {Finding(**f).line()}" for f in found) or "- nothing found"


def render_position(data: dict) -> str:
    """Per test flight: the Vicon position noise (std) and each estimator's position RMS
    deviation from the Vicon position, which is the position reference itself."""
    figs = data["figures"]
    study = figs["studies"][f"{figs['recommended']}/tuned"]
    flights = study["per_flight"]
    methods = [m for m in next(iter(flights.values())) if m != "onboard EKF"]
    lines = ["| flight | Vicon noise [mm] | " + " | ".join(f"{m} [mm]" for m in methods) + " |",
             "|---" * (len(methods) + 2) + "|"]
    for name, ms in flights.items():
        cells = [f"{1e3 * np.sqrt(ms[m]['by_reference']['cd_0.1s']['p']):.3f}" for m in methods]
        lines.append(f"| {name} | {figs['vicon_noise_mm'][name]:.3f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def render_every_tuning(data: dict) -> str:
    """The per-state table of every tuned model against its nominal estimator tuned the same way."""
    out = []
    measured = [k.split("/")[0] for k in data["figures"]["studies"] if k.endswith("/tuned")]
    missing = [f for f in COMPARED if f not in measured]
    if missing:
        what = f"{', '.join(missing)} tuned (`--tuned`)"
        out += [NOT_MEASURED.format(command=data["command"], what=what), ""]
    for key, study in data["figures"]["studies"].items():
        features, tag = key.split("/")
        if tag != "tuned":
            continue
        for pair in study["by_reference"]:
            if " vs " in pair:
                out += [f"**{features}: {pair}**", "",
                        *_state_table(study, pair, data["figures"]["vicon_noise_mm"]), ""]
    return "\n".join(out).rstrip()
