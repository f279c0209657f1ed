"""Validate the STMMAE filter bank on the closed-loop small-UAV simulator; write the STMMAE
section of ``docs/validation.md`` (between ``<!-- stmmae:begin -->`` and ``<!-- stmmae:end -->``;
the rest of the file is kept).

For each fault of a schedule: detection delay (first ``fault_detected`` after the onset naming
the surface or a group of two halves holding it, ``group_detection``) and whether the first
detection of a single surface names the right one, clearance delay (first ``fault_cleared`` of that surface
after the fault's end), the fault kind and stuck position reported at clearance; false alarms
are detections while no fault is active. Several noise seeds per schedule.

Run: ``.venv/bin/python scripts/validate_stmmae.py`` (about a minute on two cores).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estimators import stmmae
from estimators.base import Batch, EstimatorEvent
from estimators.models.small_uav import SURFACES, reference_model
from estimators.simulators.uav_closed_loop import (
    PAPER_FAULT_SCHEDULE,
    FlightTruth,
    SurfaceFault,
    simulate_flight,
)

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "validation.md"
BEGIN, END = "<!-- stmmae:begin -->", "<!-- stmmae:end -->"
METHODS: tuple[tuple[str, dict[str, str]], ...] = (
    ("EMMAE + Gaussian", {"variant": "emmae", "likelihood": "gaussian"}),
    ("EMMAE + Euclidean", {"variant": "emmae", "likelihood": "euclidean"}),
    ("STMMAE (one-sided) + Euclidean", {"variant": "strong_tracking", "likelihood": "euclidean"}),
    (
        "improved STMMAE + Euclidean (seed's method)",
        {"variant": "improved", "likelihood": "euclidean"},
    ),
    ("STMMAE (one-sided) + Gaussian", {"variant": "strong_tracking", "likelihood": "gaussian"}),
    ("improved STMMAE + Gaussian (default)", {"variant": "improved", "likelihood": "gaussian"}),
)
OTHER_SCHEDULE: tuple[SurfaceFault, ...] = (
    SurfaceFault("rudder", 15.0, 35.0, "square", center_deg=0.0, amplitude_deg=4.0, period_s=3.0),
    SurfaceFault("elevator_right", 55.0, 70.0, "stuck", position_deg=-18.0),
    SurfaceFault("aileron_right", 90.0, 110.0, "stuck", position_deg=8.0),
    SurfaceFault(
        "elevator_left", 130.0, 150.0, "sine", center_deg=-4.0, amplitude_deg=5.0, period_s=2.5
    ),
    SurfaceFault(
        "aileron_left", 170.0, 185.0, "square", center_deg=-3.0, amplitude_deg=6.0, period_s=1.5
    ),
    SurfaceFault("rudder", 205.0, 225.0, "stuck", position_deg=3.0),
)
DEFAULT = {"variant": "improved", "likelihood": "gaussian"}
SHORT = {
    "aileron_left": "a1",
    "aileron_right": "a2",
    "elevator_left": "e1",
    "elevator_right": "e2",
    "rudder": "r",
}


@dataclass
class FaultResult:
    """What one method did about one fault in one flight."""

    detect_delay_s: float | None = None
    right_surface: bool | None = None  # None: no detection of a single surface in the fault
    clear_delay_s: float | None = None
    kind: str | None = None
    stuck_position_deg: float | None = None


@dataclass
class FlightResult:
    """One method on one flight."""

    faults: list[FaultResult] = field(default_factory=list)
    false_alarms: int = 0
    wrong_isolations: int = 0
    repeated: int = 0


@dataclass(frozen=True)
class Scenario:
    """A fault schedule flown with several noise seeds."""

    title: str
    schedule: tuple[SurfaceFault, ...]
    duration_s: float
    seeds: tuple[int, ...]
    sample_rate_hz: float = 100.0
    airspeed_m_s: float = 25.0


def score(
    events: list[EstimatorEvent],
    t: np.ndarray,
    truth: FlightTruth,
    schedule: tuple[SurfaceFault, ...],
) -> FlightResult:
    """Detections and clearances matched against the true schedule."""
    res = FlightResult()
    detections = [e for e in events if e.kind == "fault_detected"]
    first_seen: set[int] = set()
    for e in detections:
        k = min(int(np.searchsorted(t, e.t_s)), len(t) - 1)
        faulty = int(truth.faulty_surface[k])
        if faulty < 0:
            res.false_alarms += 1
        elif SURFACES[faulty] not in e.detail["candidates"]:
            res.wrong_isolations += 1
    for i, f in enumerate(schedule):
        fr = FaultResult()
        during = [e for e in detections if f.start_s <= e.t_s < f.end_s]
        covering = [e for e in during if f.surface in e.detail["candidates"]]
        singles = [e for e in during if len(e.detail["candidates"]) == 1]
        if covering:
            fr.detect_delay_s = covering[0].t_s - f.start_s
            first_seen.add(i)
        if singles:
            fr.right_surface = singles[0].detail["component"] == f.surface
            res.repeated += sum(e.detail["component"] == f.surface for e in singles[1:])
        nxt = schedule[i + 1].start_s if i + 1 < len(schedule) else float("inf")
        cleared = [
            e
            for e in events
            if e.kind == "fault_cleared"
            and e.detail["component"] == f.surface
            and f.end_s <= e.t_s < nxt
        ]
        if cleared:
            fr.clear_delay_s = cleared[0].t_s - f.end_s
            fr.kind = cleared[0].detail["fault_kind"]
            fr.stuck_position_deg = cleared[0].detail["stuck_position_deg"]
        res.faults.append(fr)
    return res


def run_method(
    config: stmmae.StmmaeConfig, t: np.ndarray, ch: dict[str, np.ndarray]
) -> tuple[list[EstimatorEvent], float]:
    state = stmmae.initial_state(config)
    t0 = time.perf_counter()
    _, out = stmmae.step(config, state, Batch(t_s=t, channels=ch))
    return list(out.events), time.perf_counter() - t0


def goal_line(results: list[FlightResult]) -> str:
    """The goal check of the default method: every fault isolated, each within 0.5 s, no false
    alarm."""
    delays = [f.detect_delay_s for r in results for f in r.faults]
    isolated = all(
        f.detect_delay_s is not None and f.right_surface for r in results for f in r.faults
    )
    worst = max((d for d in delays if d is not None), default=float("nan"))
    fa = sum(r.false_alarms + r.wrong_isolations for r in results)
    verdict = "met" if isolated and worst <= 0.5 and fa == 0 else "NOT met"
    return (
        f"Goal for the default method (every fault isolated, each within 0.5 s, no false alarm): "
        f"**{verdict}** - every fault isolated: {'yes' if isolated else 'no'}; slowest "
        f"detection {worst:.2f} s; false alarms and wrong isolations: {fa}."
    )


def fmt_delays(values: list[float | None], rights: list[bool | None]) -> str:
    """median [max] of the delays; "miss" counts undetected, "wrong" misisolated flights,
    "group only" those detected as a group of two halves and never isolated."""
    pairs = list(zip(values, rights, strict=True))
    ok = [v for v, r in pairs if v is not None and r]
    n_miss = sum(v is None for v in values)
    n_wrong = sum(v is not None and r is False for v, r in pairs)
    n_group = sum(v is not None and r is None for v, r in pairs)
    text = f"{np.median(ok):.2f} [{max(ok):.2f}]" if ok else "-"
    if n_miss:
        text += f" {n_miss} miss"
    if n_wrong:
        text += f" {n_wrong} wrong"
    if n_group:
        text += f" {n_group} group only"
    return text


def fmt_clear(values: list[float | None]) -> str:
    got = [v for v in values if v is not None]
    text = f"{np.median(got):.1f} [{max(got):.1f}]" if got else "-"
    missing = len(values) - len(got)
    return text + (f" {missing} not cleared" if missing else "")


def scenario_section(sc: Scenario) -> list[str]:
    flights = []
    for seed in sc.seeds:
        t, ch, truth = simulate_flight(
            sc.duration_s,
            sample_rate_hz=sc.sample_rate_hz,
            faults=sc.schedule,
            seed=seed,
            airspeed_m_s=sc.airspeed_m_s,
        )
        flights.append((t, ch, truth))
    model = reference_model(1.0 / sc.sample_rate_hz, sc.airspeed_m_s)
    heads = [f"{SHORT[f.surface]} {f.kind} {f.start_s:g}-{f.end_s:g} s" for f in sc.schedule]
    lines = [
        f"### {sc.title}",
        "",
        f"{len(sc.seeds)} noise seeds ({', '.join(map(str, sc.seeds))}), {sc.duration_s:g} s at "
        f"{sc.sample_rate_hz:g} Hz, trim airspeed {sc.airspeed_m_s:g} m/s, estimator model "
        f"`{model['name']}`. Faults: " + "; ".join(_describe(f) for f in sc.schedule) + ".",
        "",
        "**Detection delay**, s after the onset (the first detection naming the surface or, "
        "with `group_detection`, a group of two halves holding it): median [max] over seeds; "
        "*miss*: not detected during the fault; *wrong*: the first detection of a single surface "
        "named another surface; *group only*: detected as a group of two halves, no half "
        "detected during the fault.",
        "",
        "| method | " + " | ".join(heads) + " | false alarms | wrong isol. | re-detections |",
        "|---|" + "---|" * (len(heads) + 3),
    ]
    clear_rows, kind_rows = [], []
    cost = []
    for label, raw in METHODS:
        config = stmmae.parse_config({"model": model, **raw})
        results = []
        for t, ch, truth in flights:
            events, secs = run_method(config, t, ch)
            cost.append(secs / len(t))
            results.append(score(events, t, truth, sc.schedule))
        cells = []
        for i in range(len(sc.schedule)):
            cells.append(
                fmt_delays(
                    [r.faults[i].detect_delay_s for r in results],
                    [r.faults[i].right_surface for r in results],
                )
            )
        fa = sum(r.false_alarms for r in results)
        wrong = sum(r.wrong_isolations for r in results)
        rep = sum(r.repeated for r in results)
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {fa} | {wrong} | {rep} |")
        if raw == DEFAULT:
            goal = goal_line(results)
        clear_rows.append(
            f"| {label} | "
            + " | ".join(
                fmt_clear([r.faults[i].clear_delay_s for r in results])
                for i in range(len(sc.schedule))
            )
            + " |"
        )
        kinds = []
        for i, f in enumerate(sc.schedule):
            expected = "stuck" if f.kind == "stuck" else "oscillating"
            got = [r.faults[i].kind for r in results if r.faults[i].kind is not None]
            right = sum(k == expected for k in got)
            pos = [
                r.faults[i].stuck_position_deg
                for r in results
                if r.faults[i].stuck_position_deg is not None and f.kind == "stuck"
            ]
            cell = f"{right}/{len(results)}"
            if pos:
                cell += f", {np.mean(pos):+.1f} deg (true {f.position_deg:+g})"
            kinds.append(cell)
        kind_rows.append(f"| {label} | " + " | ".join(kinds) + " |")
    lines += ["", goal]
    lines += [
        "",
        "**Clearance delay**, s after the fault's end (no-fault back and the fault hypothesis "
        "below 0.05 for the hold time): median [max].",
        "",
        "| method | " + " | ".join(heads) + " |",
        "|---|" + "---|" * len(heads),
        *clear_rows,
        "",
        "**Fault kind** reported at clearance (right / flights) and mean stuck position reported "
        "for stuck faults.",
        "",
        "| method | " + " | ".join(heads) + " |",
        "|---|" + "---|" * len(heads),
        *kind_rows,
        "",
        f"Bank cost in this run: {1e6 * float(np.median(cost)):.1f} us per sample (median over "
        "all methods and flights, one `step` per flight; see `bench/bench_stmmae.py`).",
        "",
    ]
    return lines


def _describe(f: SurfaceFault) -> str:
    if f.kind == "stuck":
        what = f"stuck at {f.position_deg:+g} deg"
    else:
        lo, hi = f.center_deg - f.amplitude_deg, f.center_deg + f.amplitude_deg
        what = f"{f.kind} {lo:+g}..{hi:+g} deg, period {f.period_s:g} s"
    return f"{f.surface} {what} ({f.start_s:g}-{f.end_s:g} s)"


def main() -> int:
    stmmae.warm_up()
    scenarios = (
        Scenario(
            "Seed paper's fault sequence (Table 2 setting)",
            PAPER_FAULT_SCHEDULE,
            300.0,
            (0, 1, 2, 3, 4),
        ),
        Scenario(
            "Another schedule (surfaces, positions, waveforms, times)",
            OTHER_SCHEDULE,
            240.0,
            (10, 11, 12),
        ),
        Scenario(
            "Another schedule at 50 Hz and 30 m/s (model re-derived for that trim and rate)",
            OTHER_SCHEDULE,
            240.0,
            (20, 21, 22),
            sample_rate_hz=50.0,
            airspeed_m_s=30.0,
        ),
    )
    lines = [
        BEGIN,
        "## STMMAE (control-surface fault isolation)",
        "",
        "Generated by `scripts/validate_stmmae.py`: closed-loop Aerosonde simulator "
        "(`estimators/simulators/uav_closed_loop.py`), sensor noise of the seed paper, the "
        "bank with default settings except variant and likelihood. Method and choices: "
        "`docs/methods-stmmae.md`.",
        "",
        "Seed paper (Table 2 is not legible in the available text; its prose): the Kalman bank "
        "(EMMAE) needed about 4 s to isolate the left-aileron fault, STMMAE and the improved "
        "STMMAE about 0.4 s, and the no-fault probability returned to 1 about 4 s after the "
        "fault ended (EMMAE).",
        "",
    ]
    for sc in scenarios:
        lines += scenario_section(sc)
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
    print(section)
    print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
