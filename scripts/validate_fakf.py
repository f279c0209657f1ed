"""Validate the FAKF on the NASA FLEA runs and on the EMA simulator; write the FAKF section of
``docs/validation.md`` (between ``<!-- fakf:begin -->`` and ``<!-- fakf:end -->``; the rest of
the file is kept).

Run: ``.venv/bin/python scripts/validate_fakf.py`` (``FLEETHEALTH_FLEA_DIR`` points elsewhere).
``--quick`` runs every fourth FLEA run and one simulator seed (for development; the committed
section comes from a full run).
"""

from __future__ import annotations

import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from estimators import fakf
from estimators.base import Batch, HealthWindow
from estimators.flea import (
    STAND_VOLTAGE_RAILS_V,
    FleaIndexEntry,
    FleaRun,
    flea_dir,
    list_runs,
    read_flea_run,
)
from estimators.simulators.ema_motor import simulate_ema

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "validation.md"
BEGIN, END = "<!-- fakf:begin -->", "<!-- fakf:end -->"
PAPER = {  # seed Tables 2 and 3: (MAE FAKF, MAE model, RMSE FAKF, RMSE model)
    "-40 lbs": (3.4361, 6.2292, 5.1754, 8.0186),
    "+40 lbs": (3.7047, 6.5225, 5.1613, 8.4893),
}
INDICATORS = ("nis_mean", "innovation_rms_ratio", "nis_in_bounds", "coef_drift", "model_mae")


QUICK = "--quick" in sys.argv
REPLAY_BATCH = 700  # samples per batch, as the replay tool's --batch-samples in the e2e test


def run_stream(config: fakf.FakfConfig, t, current, voltage, end_of_run: bool = True):
    """One run as one batch; by default the batch closes the run (the replay tool's marker)."""
    state = fakf.initial_state(config)
    _, out = fakf.step(
        config, state, Batch(t, {"current": current, "voltage": voltage}, end_of_run=end_of_run)
    )
    return out


def run_batches(config: fakf.FakfConfig, run: FleaRun, size: int):
    """A run fed in batches of ``size`` samples, the last one closing the run."""
    state = fakf.initial_state(config)
    health: list[HealthWindow] = []
    events = []
    est = []
    n = len(run)
    for lo in range(0, n, size):
        hi = min(lo + size, n)
        state, out = fakf.step(
            config,
            state,
            Batch(
                run.t_s[lo:hi],
                {"current": run.current_a[lo:hi], "voltage": run.voltage_v[lo:hi]},
                end_of_run=hi == n,
            ),
        )
        health.extend(out.health)
        events.extend(out.events)
        est.append(out.samples["voltage_estimate"])
    return health, events, np.concatenate(est)


def flea_entries() -> list[FleaIndexEntry]:
    entries = list_runs()
    return entries[::4] if QUICK else entries


def stand_config(**extra) -> fakf.FakfConfig:
    lo, hi = STAND_VOLTAGE_RAILS_V
    return fakf.parse_config({"voltage_rail_low_v": lo, "voltage_rail_high_v": hi, **extra})


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
    for entry in flea_entries():
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
            if h.n_samples == config.health_window_samples:  # complete windows only
                windows[(entry.scenario, entry.profile_shape)].append(h)

    n_id = config.identification_samples
    lines += [
        "### FLEA runs (real data, 100 Hz)",
        "",
        f"Data: `{flea_dir()}` ({len(list_runs())} runs listed in `index.csv`). Each run is fed "
        f"as one stream, closed at its end, with the default configuration (no voltage rails, "
        f"re-identification on): identification on the first {n_id} samples "
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
        "Complete health windows after identification (the second 10 s of each 30 s run, more "
        "for the 2-minute runs; the shorter closed tail of each run is left out here). Median "
        "[min - max] over windows; status counts with the default thresholds (`unknown`: the "
        "prior lost to persistence in that window).",
        "",
        "| scenario | profile | windows | nis_mean | innovation_rms_ratio | nis_in_bounds "
        "| coef_drift | model_mae V | ok / watch / unknown / alert |",
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
            counts = [sum(h.status == s for h in hs) for s in ("ok", "watch", "unknown", "alert")]
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
        for seed in range(1) if QUICK else range(4):
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


# ----------------------------------------------------------------------------- beyond the seed
def _ratio(h: HealthWindow) -> float | None:
    return h.indicators.get("prior_to_persistence_rms_ratio")


def _scored(h: HealthWindow, config: fakf.FakfConfig) -> bool:
    """A window with a model and enough scored samples for a persistence comparison."""
    return (
        _ratio(h) is not None
        and (h.indicators.get("scored_samples") or 0.0) >= config.min_graded_samples
    )


def _judged(h: HealthWindow, config: fakf.FakfConfig) -> bool:
    """A full window with a model and enough scored samples: the ones the rule compares."""
    return h.n_samples == config.health_window_samples and _scored(h, config)


def beyond_section() -> list[str]:
    lo, hi = STAND_VOLTAGE_RAILS_V
    railed = stand_config()
    railed_off = stand_config(reidentification={"enabled": False})
    plain = fakf.parse_config({})
    limit = 1.0 + railed.reidentification.margin
    rails_rows: dict[str, dict[str, float]] = defaultdict(lambda: defaultdict(float))
    pers: dict[tuple[str, str], dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    cover: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    gain_pole: dict[tuple[str, str], list[tuple[float, float, float, str]]] = defaultdict(list)
    lost_runs: list[str] = []
    for entry in flea_entries():
        run = read_flea_run(entry.path)
        shape = entry.profile_shape
        short = run.name.removeprefix("BatchProfile_").removesuffix("_Low")
        # --- rails: one batch, closed, with and without rails
        out_r = run_stream(railed, run.t_s, run.current_a, run.voltage_v)
        out_p = run_stream(plain, run.t_s, run.current_a, run.voltage_v)
        row = rails_rows[shape]
        est_r = out_r.samples["voltage_estimate"]
        mod_r = out_r.samples["voltage_model"]
        row["runs"] += 1
        row["samples"] += len(run)
        row["censored"] += float(np.sum((run.voltage_v <= lo) | (run.voltage_v >= hi)))
        row["outside"] += float(
            np.sum((est_r < lo) | (est_r > hi)) + np.sum((mod_r < lo) | (mod_r > hi))
        )
        row["max_abs_railed"] = max(row["max_abs_railed"], float(np.nanmax(np.abs(est_r))))
        row["max_abs_plain"] = max(
            row["max_abs_plain"], float(np.nanmax(np.abs(out_p.samples["voltage_estimate"])))
        )
        beyond_plain = np.sum(
            (out_p.samples["voltage_estimate"] < lo) | (out_p.samples["voltage_estimate"] > hi)
        )
        row["beyond_plain"] += float(beyond_plain)
        # --- prior against persistence (rails on), with and without re-identification
        key = (entry.scenario, shape)
        out_off = run_stream(railed_off, run.t_s, run.current_a, run.voltage_v)
        reid_at = {e.t_s: e.kind for e in out_r.events if e.kind.startswith("reident")}
        hs = out_r.health
        for j, h in enumerate(hs):
            if _scored(h, railed) and not _judged(h, railed):
                r = _ratio(h)
                pers[key]["partial"].append(1.0)
                pers[key]["partial_lost"].append(1.0 if r is not None and r > limit else 0.0)
            if not _judged(h, railed):
                continue
            r = _ratio(h)
            assert r is not None
            pers[key]["ratio"].append(r)
            if r <= limit:
                pers[key]["won"].append(1.0)
                continue
            kind = reid_at.get(h.t_end_s)
            pers[key]["lost"].append(1.0)
            if kind == "reidentified":
                pers[key]["reidentified"].append(1.0)
                nxt = next((x for x in hs[j + 1 :] if _scored(x, railed)), None)
                if nxt is not None and _ratio(nxt) is not None:
                    pers[key]["next_ratio"].append(float(_ratio(nxt)))  # type: ignore[arg-type]
            elif kind == "reidentification_failed":
                pers[key]["refused"].append(1.0)
                lost_runs.append(f"{short} (refused)")
            else:
                pers[key]["neither"].append(1.0)
                lost_runs.append(f"{short} (neither)")
        for h in out_off.health:
            if _judged(h, railed_off):
                r = _ratio(h)
                pers[key]["off_lost"].append(1.0 if r is not None and r > limit else 0.0)
        # --- coverage: replay-like batches, closed at the end
        health_b, events_b, est_b = run_batches(railed, run, REPLAY_BATCH)
        c = cover[shape]
        c["runs"] += 1
        c["samples"] += len(run)
        c["in_windows"] += sum(h.n_samples for h in health_b)
        c["complete"] += int(sum(h.n_samples for h in health_b) == len(run))
        same = (
            health_b == list(out_r.health)
            and events_b == list(out_r.events)
            and np.array_equal(est_b, est_r, equal_nan=True)
        )
        c["same_as_one_batch"] += int(same)
        open_out = run_stream(railed, run.t_s, run.current_a, run.voltage_v, end_of_run=False)
        c["unclosed_in_windows"] += sum(h.n_samples for h in open_out.health)
        # --- gain and pole of complete windows after identification
        temp = float(np.nanmean(run.motor_temperature_c))
        for h in out_r.health[1:]:
            g, p = h.indicators.get("static_gain_v_per_a"), h.indicators.get("dominant_pole")
            if h.n_samples == railed.health_window_samples and g is not None and p is not None:
                gain_pole[key].append((g, p, temp, short))

    lines = [
        "### Beyond the seed: rails, persistence, closed runs (FLEA)",
        "",
        f"Configuration: the defaults plus the stand's voltage rails `voltage_rail_low_v = {lo}`, "
        f"`voltage_rail_high_v = {hi}` (`estimators.flea.STAND_VOLTAGE_RAILS_V`: inside the "
        "clip levels of both driven motors, see `docs/methods.md`). The service passes them "
        "the same way, in the actuator's FAKF configuration.",
        "",
        "**Rails.** Estimates (posterior and model-only) outside the rails with rails "
        "configured, against the largest estimate of the same runs without rails:",
        "",
        "| profile | runs | samples | censored samples | estimates outside the rails "
        "| max abs estimate V | without rails: max abs estimate V | without rails: estimates "
        "beyond |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for shape, row in sorted(rails_rows.items()):
        lines.append(
            f"| {shape} | {row['runs']:.0f} | {row['samples']:.0f} | {row['censored']:.0f} "
            f"| **{row['outside']:.0f}** | {row['max_abs_railed']:.1f} "
            f"| {row['max_abs_plain']:.1f} | {row['beyond_plain']:.0f} |"
        )
    total_outside = sum(r["outside"] for r in rails_rows.values())
    lines += [
        "",
        f"No estimate outside the configured rails: {total_outside:.0f} samples outside in "
        "total (the kernel clamps the state after every prediction and update).",
        "",
        "**Prior against persistence.** Judged windows: complete windows with a model and at "
        f"least {railed.min_graded_samples} samples scored by both the one-step prior and "
        "persistence (repeating the last measured sample). A window *loses* when its prior RMS "
        f"exceeds {limit:g} x the persistence RMS; then the model is re-identified on that "
        "window (rule in `docs/methods.md`). *Next* is the ratio of the next window after a "
        "re-identification (the closed tail of a 30 s run, about 1000 samples); *off* counts "
        "the judged windows that lose with re-identification disabled; *tails* are the partial "
        "windows closed by the end of a run (not judged by the rule, graded all the same), "
        "lost / scored.",
        "",
        "| scenario | profile | judged windows | prior/persistence RMS median [min - max] "
        "| won | lost | lost and re-identified | refused | neither | next ratio median "
        "| off: lost | tails: lost / scored |",
        "|---|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    tot = defaultdict(float)
    for (scen, shape), d in sorted(pers.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        ratios = d["ratio"]
        cells = (
            f"{np.median(ratios):.2f} [{np.min(ratios):.2f} - {np.max(ratios):.2f}]"
            if ratios
            else "-"
        )
        nxt = f"{np.median(d['next_ratio']):.2f}" if d["next_ratio"] else "-"
        lines.append(
            f"| {scen} | {shape} | {len(ratios)} | {cells} | {len(d['won'])} | {len(d['lost'])} "
            f"| {len(d['reidentified'])} | {len(d['refused'])} | {len(d['neither'])} | {nxt} "
            f"| {sum(d['off_lost']):.0f} | {sum(d['partial_lost']):.0f} / {len(d['partial'])} |"
        )
        for name in ("won", "lost", "reidentified", "refused", "neither"):
            tot[name] += len(d[name])
        tot["judged"] += len(ratios)
        tot["off_lost"] += sum(d["off_lost"])
        tot["partial"] += len(d["partial"])
        tot["partial_lost"] += sum(d["partial_lost"])
    ok = tot["won"] + tot["reidentified"]
    lines += [
        "",
        f"The prior beats persistence or the model is re-identified in {ok:.0f} of "
        f"{tot['judged']:.0f} judged windows ({tot['won']:.0f} won, {tot['reidentified']:.0f} "
        f"lost and re-identified, {tot['refused']:.0f} refused, {tot['neither']:.0f} neither). "
        f"With re-identification off, {tot['off_lost']:.0f} judged windows lose. Closed tails: "
        f"{tot['partial_lost']:.0f} of {tot['partial']:.0f} lose (graded `unknown`, see the "
        "status rule)." + (f" Refused or neither: {', '.join(lost_runs)}." if lost_runs else ""),
        "",
        "**Closed runs.** Each run fed as the replay tool sends it: batches of "
        f"{REPLAY_BATCH} samples, the last one carrying `end_of_run`:",
        "",
        "| profile | runs | samples | samples in a window | runs fully windowed "
        "| runs equal to the one-batch result | samples in a window without the marker |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for shape, c in sorted(cover.items()):
        lines.append(
            f"| {shape} | {c['runs']} | {c['samples']} | {c['in_windows']} | {c['complete']} "
            f"| {c['same_as_one_batch']} | {c['unclosed_in_windows']} |"
        )
    lines += ["", *idle_gap_lines(railed), ""]
    lines += gain_pole_lines(gain_pole)
    lines.append("")
    return lines


def idle_gap_lines(config: fakf.FakfConfig) -> list[str]:
    """Consecutive runs of one motor sent as one stream in absolute time, no end-of-run marker:
    the idle gap between runs (about a minute) closes each run's last window."""
    idle = 5.0
    cfg = config.model_copy(update={"idle_close_s": idle})
    cfg = fakf.parse_config(fakf.config_to_dict(cfg))
    entries = [e for e in flea_entries() if e.scenario == "Jam" and e.profile_shape == "sine"]
    runs = sorted((read_flea_run(e.path) for e in entries), key=lambda r: r.t0_epoch_s)
    runs = [r for r in runs if r.t0_epoch_s - runs[0].t0_epoch_s < 3 * 3600.0][:6]
    if len(runs) < 2:
        return []
    base = runs[0].t0_epoch_s
    t = np.concatenate([r.t0_epoch_s - base + r.t_s for r in runs])
    cur = np.concatenate([r.current_a for r in runs])
    volt = np.concatenate([r.voltage_v for r in runs])
    out = run_stream(cfg, t, cur, volt, end_of_run=False)
    bounds = [(r.t0_epoch_s - base, r.t0_epoch_s - base + r.t_s[-1]) for r in runs]
    spanning = sum(
        1
        for h in out.health
        if not any(a - 1e-9 <= h.t_start_s and h.t_end_s <= b + 1e-9 for a, b in bounds)
    )
    closed_by_gap = sum(
        1 for h in out.health if h.indicators["closed_by"] == fakf.CLOSED_BY_CODES["idle_gap"]
    )
    in_windows = sum(h.n_samples for h in out.health)
    last_open = len(t) - in_windows
    return [
        f"**Idle gap.** {len(runs)} consecutive Jam sine runs of motor X sent as one stream in "
        f"absolute time without any end-of-run marker, `idle_close_s = {idle:g}` (the runs "
        f"are about a minute apart): {len(out.health)} windows, {closed_by_gap} closed by an "
        f"idle gap, {spanning} spanning two runs; {in_windows} of {len(t)} samples in a "
        f"window, the {last_open} left being the last run's open window (closed by the next "
        "sample after a gap, or by a marker).",
    ]


def gain_pole_lines(
    gain_pole: dict[tuple[str, str], list[tuple[float, float, float, str]]],
) -> list[str]:
    lines = [
        "**Static gain and dominant pole per window** (complete windows after "
        "identification, rails on; median [min - max]; motor temperature: mean of the driven "
        "motor's temperature channel over each run, range over runs):",
        "",
        "| scenario | profile | motor | windows | static gain V/A | dominant pole "
        "| motor temperature degC |",
        "|---|---|---|---:|---|---|---|",
    ]
    for (scen, shape), vals in sorted(gain_pole.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        g = np.array([v[0] for v in vals])
        p = np.array([v[1] for v in vals])
        temp = np.array([v[2] for v in vals])
        motor = "Y" if scen in ("Nominal", "Position") else "X"
        lines.append(
            f"| {scen} | {shape} | {motor} | {len(vals)} "
            f"| {np.median(g):.2f} [{g.min():.2f} - {g.max():.2f}] "
            f"| {np.median(p):.3f} [{p.min():.3f} - {p.max():.3f}] "
            f"| {temp.min():.1f} - {temp.max():.1f} |"
        )
    jam = gain_pole.get(("Jam", "sine"), [])
    spall = gain_pole.get(("Spall", "sine"), [])
    if jam and spall:
        jg = [v[0] for v in jam]
        sg = [v[0] for v in spall]
        s_temp = [v[2] for v in spall]
        cool_jam = [v[0] for v in jam if min(s_temp) - 0.5 <= v[2] <= max(s_temp) + 0.5]
        separated = max(jg) < min(sg) or max(sg) < min(jg)
        jp = [v[1] for v in jam]
        sp = [v[1] for v in spall]
        pole_overlap = not (max(jp) < min(sp) or max(sp) < min(jp))
        lines += [
            "",
            "**What the gain and pole show on FLEA, and what they do not.** On the sine "
            "profile the static gain of the window model "
            + (
                f"separates the two fault scenarios of motor X: Jam windows "
                f"{min(jg):.2f}-{max(jg):.2f} V/A, Spall windows {min(sg):.2f}-{max(sg):.2f} "
                "V/A, no overlap"
                if separated
                else f"does not separate Jam ({min(jg):.2f}-{max(jg):.2f} V/A) from Spall "
                f"({min(sg):.2f}-{max(sg):.2f} V/A)"
            )
            + (
                f"; motor temperature does not explain it (the Jam windows of runs at the "
                f"Spall runs' {min(s_temp):.0f}-{max(s_temp):.0f} degC have "
                f"{min(cool_jam):.2f}-{max(cool_jam):.2f} V/A)"
                if separated and cool_jam
                else ""
            )
            + ". The dominant pole "
            + ("overlaps between them" if pole_overlap else "separates them too")
            + f" (Jam {min(jp):.2f}-{max(jp):.2f}, Spall {min(sp):.2f}-{max(sp):.2f}). What "
            "this does not show: that the gain detects a spall. The Spall runs are "
            f"{len({v[3] for v in spall})} runs recorded in one session after the Jam "
            "sessions, so a change of set-up between sessions (the faulty nut is a part "
            "swapped in) cannot be told from the fault; the Nominal runs drive the other motor "
            "(Y), so no scenario can be compared with a healthy motor X; and on the trapezoid "
            "profile the window models swing between regimes within a run (dominant pole from "
            "negative to positive), so neither indicator separates anything there. They are "
            "reported per window, with history, for trend watching on one actuator under one "
            "profile; no status is derived from them.",
        ]
    return lines


def simulator_beyond_section() -> list[str]:
    """100 Hz simulator runs with a FLEA-like clipping voltage sensor, three profile shapes."""
    clip_lo, clip_hi = -25.3, 23.9
    lo, hi = STAND_VOLTAGE_RAILS_V
    profiles = {
        "sine": {},
        "trapezoid": {},
        "sweep": {"frequency_hz": 0.3, "sweep_end_frequency_hz": 3.0},
    }
    seeds = range(1) if QUICK else range(3)
    lines = [
        "### Simulator at 100 Hz with a clipping voltage sensor",
        "",
        f"`simulate_ema(duration_s=30, sample_rate_hz=100, load_lbs=+-40, seed, "
        f"voltage_clip_low_v={clip_lo}, voltage_clip_high_v={clip_hi})`; sweep: 0.3 to 3 Hz "
        f"over the run. FAKF with rails ({lo}, {hi}) and without (re-identification off "
        "there, as the seed's filter). RMSE in volts against the **true** voltage over the "
        "filtered part; prior/persistence: per judged window, median; outside: estimates "
        "beyond the rails.",
        "",
        "| profile | runs | true V max abs | censored | plain: prior/persistence | plain: max "
        "abs estimate | plain: RMSE | rails: prior/persistence | rails: re-identified "
        "| rails: outside | rails: RMSE | measured RMSE |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    plain = fakf.parse_config({"reidentification": {"enabled": False}})
    railed = stand_config()
    summary: dict[str, dict[str, float]] = {}
    for shape, extra in profiles.items():
        acc: dict[str, list[float]] = defaultdict(list)
        for load in (-40.0, 40.0):
            for seed in seeds:
                sim = simulate_ema(
                    duration_s=30.0,
                    sample_rate_hz=100.0,
                    load_lbs=load,
                    seed=seed,
                    profile=shape,
                    voltage_clip_low_v=clip_lo,
                    voltage_clip_high_v=clip_hi,
                    **extra,
                )
                v = sim.voltage_measured_v
                acc["true_max"].append(float(np.max(np.abs(sim.voltage_true_v))))
                acc["censored"].append(float(np.sum((v <= lo) | (v >= hi))))
                for name, cfg in (("plain", plain), ("rails", railed)):
                    out = run_stream(cfg, sim.t_s, sim.current_a, v)
                    est = out.samples["voltage_estimate"]
                    mask = np.isfinite(est)
                    acc[f"{name}_rmse"].append(errors(est, sim.voltage_true_v, mask)[1])
                    acc[f"{name}_max"].append(float(np.nanmax(np.abs(est))))
                    acc[f"{name}_ratio"] += [
                        float(_ratio(h))  # type: ignore[arg-type]
                        for h in out.health
                        if _judged(h, cfg)
                    ]
                    if name == "rails":
                        acc["reid"].append(float(sum(e.kind == "reidentified" for e in out.events)))
                        mod = out.samples["voltage_model"]
                        acc["outside"].append(
                            float(np.sum((est < lo) | (est > hi)) + np.sum((mod < lo) | (mod > hi)))
                        )
                    else:
                        acc["meas_rmse"].append(errors(v, sim.voltage_true_v, mask)[1])
        lines.append(
            f"| {shape} | {len(acc['reid'])} | {max(acc['true_max']):.1f} "
            f"| {np.mean(acc['censored']):.0f} | {np.median(acc['plain_ratio']):.2f} "
            f"| {max(acc['plain_max']):.1f} | {np.mean(acc['plain_rmse']):.2f} "
            f"| {np.median(acc['rails_ratio']):.2f} | {sum(acc['reid']):.0f} "
            f"| **{sum(acc['outside']):.0f}** | {np.mean(acc['rails_rmse']):.2f} "
            f"| {np.mean(acc['meas_rmse']):.2f} |"
        )
        summary[shape] = {
            "plain_ratio": float(np.median(acc["plain_ratio"])),
            "plain_max": max(acc["plain_max"]),
            "plain_rmse": float(np.mean(acc["plain_rmse"])),
            "rails_ratio": float(np.median(acc["rails_ratio"])),
            "rails_rmse": float(np.mean(acc["rails_rmse"])),
            "meas_rmse": float(np.mean(acc["meas_rmse"])),
            "true_max": max(acc["true_max"]),
        }
    sw, tr = summary["sweep"], summary["trapezoid"]
    lines += [
        "",
        f"The sweep reproduces what was reported on real sweep runs not kept here: without "
        f"rails the prior loses "
        f"to persistence (median ratio {sw['plain_ratio']:.2f}) and the estimate reaches "
        f"{sw['plain_max']:.0f} V while the sensor clips at {clip_lo} / {clip_hi} V. With "
        f"rails and re-identification no estimate leaves the rails, the ratio falls to "
        f"{sw['rails_ratio']:.2f} and the RMSE against the true voltage from "
        f"{sw['plain_rmse']:.2f} to {sw['rails_rmse']:.2f} V; it stays above the raw "
        f"measurement's {sw['meas_rmse']:.2f} V. The trapezoid shows the price of rails "
        f"inside the physical range: the true voltage reaches {tr['true_max']:.0f} V (the "
        "supply) while the estimate is held at the rail, so the RMSE rises from "
        f"{tr['plain_rmse']:.2f} to {tr['rails_rmse']:.2f} V; and at 100 Hz the FAKF is "
        f"worse than the raw measurement on this profile ({tr['plain_rmse']:.2f} against "
        f"{tr['meas_rmse']:.2f} V): a second-order current-to-voltage model sampled at 100 Hz "
        "does not follow the voltage through the dwells and the saturated ramps. The 1 kHz "
        "sine above is where the seed's filter helps.",
        "",
    ]
    return lines


def binding_section() -> list[str]:
    """The service demo's degradation: viscous friction grows 60-fold over 90 s of a 120 s
    stream (100 Hz, 30 s work cycles); re-identification must not hide it."""
    seeds = range(2) if QUICK else range(8)
    on_cfg = fakf.parse_config({})
    off_cfg = fakf.parse_config({"reidentification": {"enabled": False}})
    lines = [
        "### Simulator: a binding ball screw (re-identification must not hide it)",
        "",
        "Four 30 s work cycles at 100 Hz, `simulate_ema(..., damping_nm_s_rad=B)` with B growing "
        "from nominal to 60 x nominal between 30 s and 120 s (the service demo's degradation), "
        "load +-40 lbs by seed; default configuration with and without re-identification. "
        "Last window: status and `innovation_rms_ratio`.",
        "",
        "| seed | re-identifications | last status (on) | ratio (on) | last status (off) "
        "| ratio (off) | prior/persistence of the last window (on / off) |",
        "|---:|---:|---|---:|---|---:|---|",
    ]
    hidden = 0
    ok_anyway = 0
    for seed in seeds:
        ts, cs, vs = [], [], []
        for cycle in range(4):
            severity = min(1.0, max(0.0, (30.0 * cycle - 30.0) / 90.0))
            sim = simulate_ema(
                30.0,
                100.0,
                40.0 if seed % 2 == 0 else -40.0,
                seed * 1_000_003 + cycle,
                damping_nm_s_rad=2.0e-5 * (1.0 + 59.0 * severity),
            )
            ts.append(30.0 * cycle + sim.t_s)
            cs.append(sim.current_a)
            vs.append(sim.voltage_measured_v)
        t, cur, volt = np.concatenate(ts), np.concatenate(cs), np.concatenate(vs)
        on = run_stream(on_cfg, t, cur, volt, end_of_run=False)
        off = run_stream(off_cfg, t, cur, volt, end_of_run=False)
        h_on, h_off = on.health[-1], off.health[-1]
        n_re = sum(e.kind == "reidentified" for e in on.events)
        if h_off.status != "ok" and h_on.status == "ok":
            hidden += 1
        if h_off.status == "ok" and h_on.status == "ok":
            ok_anyway += 1
        lines.append(
            f"| {seed} | {n_re} | {h_on.status} "
            f"| {fmt(h_on.indicators['innovation_rms_ratio'])} | {h_off.status} "
            f"| {fmt(h_off.indicators['innovation_rms_ratio'])} "
            f"| {fmt(_ratio(h_on))} / {fmt(_ratio(h_off))} |"
        )
    lines += [
        "",
        f"Runs where re-identification turned a non-ok status into ok: {hidden} of "
        f"{len(seeds)}. The consistency indicators come from the reference filter (the first "
        "model) once a re-identification has happened, so the ratio is the same with and "
        "without it; the status differs only where the prior lost to persistence without "
        "re-identification (`unknown`, which outranks `watch`). What this does not change: "
        f"the seed filter's own sensitivity; in {ok_anyway} of {len(seeds)} runs the binding "
        "leaves the innovation ratio at or below the 1.5 watch level and the last window "
        "`ok`, with re-identification or without.",
        "",
    ]
    return lines


def main() -> int:
    config = fakf.parse_config({})
    fakf.warm_up()
    lines = [BEGIN, "## FAKF", "", "Generated by `scripts/validate_fakf.py`.", ""]
    if (flea_dir() / "index.csv").is_file():
        lines += flea_section(config)
        lines += beyond_section()
    else:
        lines += [f"FLEA data not found at `{flea_dir()}`: FLEA tables skipped.", ""]
    lines += simulator_section()
    lines += simulator_beyond_section()
    lines += binding_section()
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
