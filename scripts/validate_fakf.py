"""Validate the FAKF on the NASA FLEA runs and on the EMA simulator; write the FAKF section of
``docs/validation.md`` (between ``<!-- fakf:begin -->`` and ``<!-- fakf:end -->``; the rest of
the file is kept).

Run: ``.venv/bin/python scripts/validate_fakf.py`` (``FLEETHEALTH_FLEA_DIR`` points elsewhere).
"""

from __future__ import annotations

import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from estimators import fakf
from estimators.base import Batch, HealthWindow
from estimators.flea import flea_dir, list_runs, read_flea_run
from estimators.simulators.ema_motor import simulate_ema

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "validation.md"
BEGIN, END = "<!-- fakf:begin -->", "<!-- fakf:end -->"
PAPER = {  # seed Tables 2 and 3: (MAE FAKF, MAE model, RMSE FAKF, RMSE model)
    "-40 lbs": (3.4361, 6.2292, 5.1754, 8.0186),
    "+40 lbs": (3.7047, 6.5225, 5.1613, 8.4893),
}
INDICATORS = ("nis_mean", "innovation_rms_ratio", "nis_in_bounds", "coef_drift", "model_mae")


def run_stream(config: fakf.FakfConfig, t, current, voltage):
    state = fakf.initial_state(config)
    _, out = fakf.step(config, state, Batch(t, {"current": current, "voltage": voltage}))
    return out


def errors(x: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    d = x[mask] - ref[mask]
    return float(np.mean(np.abs(d))), float(np.sqrt(np.mean(d**2)))


def fmt(v: float | None, spec: str = ".2f") -> str:
    return "-" if v is None else format(v, spec)


def flea_section(config: fakf.FakfConfig) -> list[str]:
    lines: list[str] = []
    per_run = []
    windows: dict[tuple[str, str], list[HealthWindow]] = defaultdict(list)
    position_rows = []
    for entry in list_runs():
        run = read_flea_run(entry.path)
        out = run_stream(config, run.t_s, run.current_a, run.voltage_v)
        ev = out.events[0] if out.events else None
        if entry.scenario == "Position":
            statuses = [h.status for h in out.health]
            position_rows.append(
                (run.name, [e.kind for e in out.events], ev.detail if ev else {}, statuses)
            )
            continue
        if ev is None or ev.kind != "identified":
            per_run.append((entry, run, None, ev))
            continue
        est = out.samples["voltage_estimate"]
        mask = np.isfinite(est) & np.isfinite(run.voltage_v)
        prior = run.voltage_v - out.samples["innovation"]
        res = {
            "fakf": errors(est, run.voltage_v, mask),
            "model": errors(out.samples["voltage_model"], run.voltage_v, mask),
            "prior": errors(prior, run.voltage_v, mask),
            "n": int(mask.sum()),
            "pole": ev.detail["max_pole_modulus"],
            "resid": ev.detail["residual_rms"],
        }
        per_run.append((entry, run, res, ev))
        for h in out.health[1:]:  # window 0 is the identification window
            windows[(entry.scenario, entry.profile_shape)].append(h)

    n_id = config.identification_samples
    lines += [
        "### FLEA runs (real data, 100 Hz)",
        "",
        f"Data: `{flea_dir()}` (74 runs listed in `index.csv`). Each run is fed as one stream "
        f"with the default configuration: identification on the first {n_id} samples "
        f"(10 s, about the first third of a 30 s run), then filtering of the rest; "
        f"`q = r = auto` (half the identification residual variance each); health windows of "
        f"{config.health_window_samples} samples. Driven motor: Y for Nominal, X for Jam/Spall.",
        "",
        "Columns: MAE / RMSE in volts against the **measured** voltage over the filtered part. "
        "*FAKF* = posterior (the paper's metric, Tables 2-3); *prior* = one-step-ahead "
        "prediction made before V_k is seen (honest metric); *model* = model-only estimate "
        "(eq. 15 driven by current alone).",
        "",
        "| run | scen. | load lbs | max pole | resid RMS | FAKF MAE | FAKF RMSE | prior MAE "
        "| prior RMSE | model MAE | model RMSE |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    agg: dict[str, list[dict]] = defaultdict(list)
    failed = []
    for entry, run, res, ev in per_run:
        short = run.name.removeprefix("BatchProfile_").removesuffix("_Low")
        if res is None:
            reason = ev.detail.get("reason") if ev else "no event"
            failed.append((short, reason))
            lines.append(
                f"| {short} | {entry.scenario} | {entry.mean_measured_load:.1f} | "
                f"identification failed: {reason} ||||||||"
            )
            continue
        agg[entry.scenario].append(res)
        agg["all"].append(res)
        lines.append(
            f"| {short} | {entry.scenario} | {entry.mean_measured_load:.1f} | {res['pole']:.3f} "
            f"| {res['resid']:.2f} | {res['fakf'][0]:.2f} | {res['fakf'][1]:.2f} "
            f"| {res['prior'][0]:.2f} | {res['prior'][1]:.2f} | {res['model'][0]:.2f} "
            f"| {res['model'][1]:.2f} |"
        )
    lines += [
        "",
        "Aggregated by scenario (median over runs; model-only errors have a long tail when the "
        "identified poles are close to the unit circle, hence medians):",
        "",
        "| group | runs | FAKF MAE | FAKF RMSE | prior MAE | prior RMSE | model MAE "
        "| model RMSE | FAKF MAE vs model |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for group in ("Nominal", "Jam", "Spall", "all"):
        rs = agg[group]
        if not rs:
            continue

        def med(key: str, i: int, rs=rs) -> float:
            return float(np.median([r[key][i] for r in rs]))

        red = 100.0 * (1.0 - med("fakf", 0) / med("model", 0))
        lines.append(
            f"| {group} | {len(rs)} | {med('fakf', 0):.2f} | {med('fakf', 1):.2f} "
            f"| {med('prior', 0):.2f} | {med('prior', 1):.2f} | {med('model', 0):.2f} "
            f"| {med('model', 1):.2f} | -{red:.0f} % |"
        )
    for label, (mf, mm, rf, rm) in PAPER.items():
        lines.append(
            f"| seed paper, {label} (1 kHz, one Jam run) | 1 | {mf:.4f} | {rf:.4f} | - | - "
            f"| {mm:.4f} | {rm:.4f} | -{100 * (1 - mf / mm):.1f} % |"
        )
    lines += [
        "",
        "The last column is the relative change of the median MAE, 1 - FAKF/model. For the "
        "paper the same formula gives -44.8 % and -43.2 %; the paper's text quotes -55.2 % and "
        "-56.8 %, which are the ratios FAKF/model (3.4361/6.2292 = 0.552, 3.7047/6.5225 = "
        "0.568), not reductions (likewise for RMSE: ratios 0.645 and 0.608).",
    ]
    if failed:
        lines += [
            "",
            f"{len(failed)} run(s) had their first identification refused and were "
            "re-identified on the next 1000 samples, leaving too little to score: "
            + "; ".join(f"{n} ({r})" for n, r in failed)
            + ".",
        ]
    all_rs = agg["all"]
    lines += [
        "",
        "**What (a), the paper's metric, shows and does not.** The posterior is scored against "
        "the very measurement it has just been pulled toward: with r -> 0 the estimate equals "
        'the measurement and this "error" is zero, with r -> infinity it is the model-only '
        "error. So a lower posterior MAE than model-only is guaranteed by construction for any "
        "r between, and on its own says nothing about how close the estimate is to the true "
        "voltage. Here the FAKF posterior MAE is "
        f"{np.median([r['fakf'][0] for r in all_rs]):.2f} V against "
        f"{np.median([r['model'][0] for r in all_rs]):.2f} V model-only (medians), the same "
        "order and reduction as the paper's Tables 2-3, for that reason as much as any other.",
        "",
        "**(b), the one-step-ahead prior**, is a fair test of the model: it predicts V_k from "
        "the current and the past voltages without seeing V_k. Its median MAE is "
        f"{np.median([r['prior'][0] for r in all_rs]):.2f} V, better than model-only "
        f"({np.median([r['model'][0] for r in all_rs]):.2f} V) because it is corrected by past "
        "measurements every step, but about the size of the identification residual: at "
        "100 Hz the second-order current-to-voltage model explains only part of the measured "
        "voltage (residual RMS 3-7 V on a +-25 V signal).",
        "",
    ]
    # health indicators
    lines += [
        "### Health indicators by scenario (FLEA)",
        "",
        "Complete health windows after identification (windows 2-3 of each 30 s run, more for "
        "the 2-minute runs). Median [min - max] over windows; status counts with the default "
        "thresholds.",
        "",
        "| scenario | profile | windows | nis_mean | innovation_rms_ratio | nis_in_bounds "
        "| coef_drift | model_mae V | ok / watch / alert |",
        "|---|---|---:|---|---|---|---|---|---|",
    ]
    for scen in ("Nominal", "Jam", "Spall"):
        for shape in ("sine", "trap"):
            hs = windows.get((scen, shape), [])
            if not hs:
                continue
            cells = []
            for name in INDICATORS:
                vals = [h.indicators[name] for h in hs if h.indicators[name] is not None]
                if not vals:
                    cells.append("-")
                    continue
                cells.append(f"{np.median(vals):.2f} [{np.min(vals):.2f} - {np.max(vals):.2f}]")
            counts = [sum(h.status == s for h in hs) for s in ("ok", "watch", "alert")]
            lines.append(
                f"| {scen} | {shape} | {len(hs)} | "
                + " | ".join(cells)
                + " | "
                + " / ".join(map(str, counts))
                + " |"
            )
    lines += [
        "",
        "**What separates the scenarios.** On the sine profiles no indicator separates Nominal "
        "from Jam or Spall: NIS near 1, innovation ratio near 1, and coefficient drift of a "
        "few percent in all three. On the trapezoid profiles all indicators rise in every "
        "scenario, because the first 10 s of a trapezoid run (used for identification) do not "
        "excite the model like the rest; the Jam trapezoid runs reach the highest NIS and "
        "drift (the two -21 lbs Jam runs most), but Nominal trapezoid runs with -40 lbs and "
        "Spall runs overlap them. Two confounders stand in the way of a fault claim: the "
        "driven motor differs (Y in Nominal runs, X in Jam/Spall) and the profile shape "
        "changes the indicators more than the fault does. The indicators are therefore "
        "consistency monitors of the voltage model (they react strongly to a changed plant, "
        "see the tests), not a jam/spall classifier on these 30 s runs.",
        "",
    ]
    if position_rows:
        lines += [
            "### Position runs (sensor-fault runs, shown apart)",
            "",
            "Motor Y voltage stays pinned negative in these runs; they are not voltage-model "
            "data. What the estimator reports on them:",
            "",
            "| run | events | first event detail | window statuses |",
            "|---|---|---|---|",
        ]
        for name, kinds, detail, statuses in position_rows:
            short = name.removeprefix("BatchProfile_").removesuffix("_Low")
            d = detail.get("reason") or (
                f"max pole {fmt(detail.get('max_pole_modulus'), '.4f')}, "
                f"resid {fmt(detail.get('residual_rms'))} V"
            )
            lines.append(f"| {short} | {', '.join(kinds)} | {d} | {', '.join(statuses)} |")
        lines.append("")
    return lines


def simulator_section() -> list[str]:
    lines = [
        "### Simulator (known true voltage)",
        "",
        "`simulate_ema(duration_s=30, sample_rate_hz=1000, load_lbs=+-40, seed)`, sine profile, "
        "interference: Gaussian 1 V, spikes 5/s of 4-12 V, 2 V tone at 60 Hz. Identification "
        "on the first 2000 samples, `q = r = auto`. RMSE in volts against the **true** "
        "armature voltage over the filtered part:",
        "",
        "| load lbs | seed | raw measurement | model-only | FAKF prior | FAKF posterior |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    config = fakf.parse_config({"identification_samples": 2000, "health_window_samples": 2000})
    rows = []
    for load in (-40.0, 40.0):
        for seed in range(4):
            run = simulate_ema(load_lbs=load, seed=seed)
            out = run_stream(config, run.t_s, run.current_a, run.voltage_measured_v)
            est = out.samples["voltage_estimate"]
            mask = np.isfinite(est)
            prior = run.voltage_measured_v - out.samples["innovation"]
            vals = [
                errors(x, run.voltage_true_v, mask)[1]
                for x in (run.voltage_measured_v, out.samples["voltage_model"], prior, est)
            ]
            rows.append(vals)
            lines.append(f"| {load:+.0f} | {seed} | " + " | ".join(f"{v:.3f}" for v in vals) + " |")
    mean = np.mean(rows, axis=0)
    lines += [
        "| mean | | " + " | ".join(f"**{v:.3f}**" for v in mean) + " |",
        "",
        f"Against the true voltage the FAKF posterior is {100 * (1 - mean[3] / mean[0]):.0f} % "
        f"better than the raw measurement and {100 * (1 - mean[3] / mean[1]):.0f} % better "
        "than the model-only estimate. The model-only estimate is poor because the current-"
        "only model has no term for the constant load torque and its identified poles sit "
        "near z = 1 (the back-emf integrates the current), so it drifts. With the automatic "
        "equal split of q and r the one-step prior is about as good as the posterior: the "
        "split is a neutral default, not the optimum for this noise mix.",
        "",
    ]
    return lines


def main() -> int:
    config = fakf.parse_config({})
    fakf.warm_up()
    lines = [BEGIN, "## FAKF", "", "Generated by `scripts/validate_fakf.py`.", ""]
    if (flea_dir() / "index.csv").is_file():
        lines += flea_section(config)
    else:
        lines += [f"FLEA data not found at `{flea_dir()}`: FLEA tables skipped.", ""]
    lines += simulator_section()
    lines.append(END)
    section = "\n".join(lines)
    text = DOC.read_text(encoding="utf-8") if DOC.exists() else "# Validation\n\n"
    if BEGIN in text and END in text:
        head, rest = text.split(BEGIN, 1)
        _, tail = rest.split(END, 1)
        text = head + section + tail
    else:
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    DOC.parent.mkdir(parents=True, exist_ok=True)
    DOC.write_text(text, encoding="utf-8")
    print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
