"""Validate STMMAE on randomized flights (``estimators/simulators/uav_scenarios.py``); write the
"randomized flights" part of the STMMAE section of ``docs/validation.md`` (between
``<!-- stmmae-random:begin -->`` and ``<!-- stmmae-random:end -->``; the rest is kept).

Three categories, fixed seeds: single faults, two overlapping faults, fault-free flights. Each
flight is simulated, then the bank (default configuration, model linearized at the flight's
airspeed and rate) runs over it in one batch. Scoring (per fault, interval ``[onset, end]``):

* a detection names one surface, or a group of two twin halves ("one of the two",
  ``group_detection``); a detection *covers* a surface when it names it or a group holding it;
* *isolated*: the fault's surface is detected during the interval, the first detection of a
  single surface in the interval names it and no detection before it fails to cover it;
  *strict*: in addition no detection in the interval fails to cover it;
* *delay* (detection): first detection covering the surface after the onset, minus the onset;
  *isolation delay*: first detection naming the surface itself, minus the onset;
* *hidden* (stuck faults): from the onset to the first sample whose command stands at least
  ``MIN_STUCK_OFFSET_DEG`` (2 deg) from the stuck position. Until then the surface is about
  where it is commanded and the data hold no sign of the fault (a surface stuck during a turn
  near the deflection the turn asks for). The goals count from the onset; the report adds the
  delays counted from the end of that span (*delay once visible*: the delay less the hidden
  span, at least 0);
* *re-detections*: further ``fault_detected`` events covering the surface inside the interval
  (a detection cleared and raised again during the fault); a group detection handed to one of
  its halves (its ``fault_cleared`` with ``isolated_as``) is one episode with the detection
  that follows it, whichever half that names (a wrong half counts against *isolated*);
* *kind*: ``fault_kind`` of the episode's ``fault_classified`` (or ``fault_cleared``) event
  against the truth (stuck vs square/sine = oscillating); a fault never named but raised as
  its group takes the kind of the group's first episode in the interval;
* *wrong*: a detection covering no surface with a fault at that time while another fault is
  active (or ended less than 5 s before); *false alarm*: a detection with no fault active or
  ended less than 5 s before;
* *both halves*: a detection of a half while its twin is in fault (its ``twin_in_fault``)
  opens a span with both halves in fault, up to the first clearance of either; *one half
  faulty*: a fault of only one of them is active in that span (or ended less than 5 s before
  it began).

Fault-free flights also report the margins of the detection gates (how often each condition
held alone).

Run: ``.venv/bin/python scripts/validate_stmmae_random.py`` (defaults: 40 single, 40 pair,
5 fault-free flight hours; about 25 min on two shared cores). ``--quick`` runs 6/6/0.2 h and
does not write the document. ``--cache DIR`` keeps the simulated flights (``.npz``, keyed by
category, seed and a digest of the simulator's sources) and reuses them: the estimator costs
about a third of a run, the simulation the rest; ``--simulate-only`` fills the cache.
``--seed-offset N`` draws other flights (every seed base + N); ``--config JSON`` runs a changed
configuration (development; the document then reports that configuration).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimators import stmmae
from estimators.base import Batch, EstimatorEvent
from estimators.models.small_uav import SURFACES, reference_model
from estimators.simulators.uav_closed_loop import SurfaceFault
from estimators.simulators.uav_scenarios import (
    MIN_STUCK_OFFSET_DEG,
    FlightScenario,
    describe,
    random_scenario,
    trim_deflections_deg,
)

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "validation.md"
BEGIN, END = "<!-- stmmae-random:begin -->", "<!-- stmmae-random:end -->"
GRACE_S = 5.0
HIDDEN_REPORT_S = 0.05  # a stuck fault hidden longer than this is counted in the report
# development used seeds < 100; a first run with seeds 1000+/2000+/3000+ led to the evidence
# level of 6 nats (docs/methods-stmmae.md), so the reported run uses fresh seeds
SEED_BASE = {"single": 11000, "pair": 12000, "fault_free": 13000}
# delays are differences of sample times and onsets (floats): a detection 30 samples after an
# onset at 21.5 s is 0.30000000000000071 s; the delay goals compare with this tolerance
TIME_TOL_S = 1e-9
GOALS = {
    "single": 0.99,
    "pair": 0.90,
    "stuck_median_s": 0.3,
    "stuck_p95_s": 0.5,
    "kind": 0.95,
}


@dataclass
class FaultRecord:
    """Outcome for one injected fault."""

    category: str
    seed: int
    surface: str
    kind: str
    offset_deg: float  # stuck: |position - trim|; oscillation: amplitude
    period_s: float | None
    airspeed_m_s: float
    rate_hz: float
    manoeuvre_at_onset: bool
    order: int  # 0: first fault of the flight, 1: second of a pair
    delay_s: float | None = None  # first detection covering the surface
    isolation_delay_s: float | None = None  # first detection naming the surface itself
    isolated: bool = False
    strict: bool = False
    redetections: int = 0
    reported_kind: str | None = None
    hidden_s: float = 0.0  # stuck: onset to the first command >= 2 deg from the position


@dataclass
class FlightRecord:
    """Outcome for one flight."""

    scenario: FlightScenario
    faults: list[FaultRecord] = field(default_factory=list)
    wrong: int = 0
    false_alarms: int = 0
    samples: int = 0
    seconds: float = 0.0
    gate_margins: dict[str, float] = field(default_factory=dict)
    twins_both: int = 0  # spans with both halves of a split surface in fault
    twins_one: int = 0  # of which only one half had a fault


def config_for(sc: FlightScenario, extra: dict[str, Any] | None = None) -> stmmae.StmmaeConfig:
    """The default configuration (plus ``extra``) with the model linearized at the flight's
    airspeed and rate."""
    raw: dict[str, Any] = {"model": reference_model(1.0 / sc.sample_rate_hz, sc.airspeed_m_s)}
    return stmmae.parse_config(raw | (extra or {}))


def _manoeuvre_at(sc: FlightScenario, t_s: float) -> bool:
    return any(m.start_s - 1.0 <= t_s <= m.start_s + m.duration_s + 1.0 for m in sc.manoeuvres)


def _gate_margins(
    config: stmmae.StmmaeConfig, t: np.ndarray, ch: dict[str, np.ndarray], out: Any
) -> dict[str, float]:
    """How often the detection conditions held on a fault-free flight (offline replica of the
    probability and deflection gates; the likelihood-ratio gate is not replicated): runs of at
    least ``hold_s`` with the marginal probability above ``detect_probability``, and of those
    with the smoothed deflection error above ``min_deflection_error_deg`` as well; the largest
    marginal fault probability."""
    hold = config.hold_s
    runs_p = runs_both = 0
    pmax = 0.0
    dt = float(np.median(np.diff(t)))
    a = 1.0 - math.exp(-dt / config.deflection_smoothing_s)
    lim = math.radians(config.deflection_limit_deg)
    min_err = math.radians(config.min_deflection_error_deg)
    surface_inputs = {i.name: i.channel for i in config.model.inputs}
    for s in config.model.surfaces:
        prob = out.samples[f"fault_probability_{s}"]
        pmax = max(pmax, float(np.max(prob)))
        defl = np.clip(out.samples[f"deflection_{s}"], -lim, lim)
        sm = np.empty_like(defl)
        acc = defl[0]
        for k, v in enumerate(defl):
            acc += a * (v - acc)
            sm[k] = acc
        cmd = ch[surface_inputs[s]]
        for cond in (prob > config.detect_probability,):
            both = cond & (np.abs(sm - cmd) > min_err)
            for arr, name in ((cond, "p"), (both, "both")):
                edges = np.flatnonzero(np.diff(np.concatenate([[0], arr.astype(int), [0]])))
                starts, ends = edges[0::2], edges[1::2]
                n_runs = int(np.sum((ends - starts) * dt >= hold))
                if name == "p":
                    runs_p += n_runs
                else:
                    runs_both += n_runs
    return {"runs_probability": runs_p, "runs_probability_and_deflection": runs_both, "pmax": pmax}


def _sources_digest() -> str:
    """Digest of the simulator's source files: a cached flight is reused only if it was
    simulated by the same code."""
    h = hashlib.sha256()
    for mod in ("uav_closed_loop.py", "uav_scenarios.py"):
        h.update((ROOT / "estimators" / "simulators" / mod).read_bytes())
    h.update((ROOT / "estimators" / "models" / "small_uav.py").read_bytes())
    return h.hexdigest()[:16]


def simulate(sc: FlightScenario, cache: Path | None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Simulate one flight, or read it from ``cache`` (a directory of ``.npz`` files keyed by
    category, seed and the simulator's source digest; the simulation is deterministic)."""
    path = None
    if cache is not None:
        path = cache / f"{sc.category}_{sc.seed}_{_sources_digest()}.npz"
        if path.exists():
            with np.load(path) as data:
                return data["t"], {k[3:]: data[k] for k in data.files if k.startswith("ch_")}
    t, ch, _truth = sc.simulate()
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        arrays: dict[str, Any] = {"t": t, **{f"ch_{k}": v for k, v in ch.items()}}
        np.savez(tmp, **arrays)
        tmp.replace(path)
    return t, ch


def judgments(events: list[EstimatorEvent]) -> dict[tuple[str, float | None], EstimatorEvent]:
    """The event each episode's kind was judged in, keyed by ``(component, detected_s)``: its
    ``fault_classified`` event, or its ``fault_cleared`` event when it ended before one (the
    first of them with a kind other than pending)."""
    judged: dict[tuple[str, float | None], EstimatorEvent] = {}
    for e in events:
        if e.kind in ("fault_classified", "fault_cleared") and e.detail["fault_kind"] != "pending":
            judged.setdefault((e.detail["component"], e.detail["detected_s"]), e)
    return judged


def true_kind(kind: str) -> str:
    """The kind the bank should report for a generator's fault kind (stuck, square, sine)."""
    return "stuck" if kind == "stuck" else "oscillating"


def _hidden_s(t: np.ndarray, ch: dict[str, np.ndarray], f: SurfaceFault) -> float:
    """Time from a stuck fault's onset to the first sample of its interval whose command
    stands at least ``MIN_STUCK_OFFSET_DEG`` from the stuck position (the whole interval when
    none does)."""
    cmd = np.degrees(ch["cmd_" + f.surface])
    inside = (t >= f.start_s) & (t <= f.end_s)
    visible = inside & (np.abs(cmd - f.position_deg) >= MIN_STUCK_OFFSET_DEG)
    if not visible.any():
        return f.end_s - f.start_s
    return float(t[visible][0] - f.start_s)


def run_flight(
    sc: FlightScenario, extra: dict[str, Any] | None = None, cache: Path | None = None
) -> FlightRecord:
    """Simulate (or read from ``cache``) and score one flight (``extra``: configuration
    changes)."""
    t, ch = simulate(sc, cache)
    config = config_for(sc, extra)
    t0 = time.perf_counter()
    _, out = stmmae.step(config, stmmae.initial_state(config), Batch(t_s=t, channels=ch))
    rec = FlightRecord(scenario=sc, samples=len(t), seconds=time.perf_counter() - t0)
    events: list[EstimatorEvent] = list(out.events)
    dets = [e for e in events if e.kind == "fault_detected"]

    def covers(e: EstimatorEvent, surface: str) -> bool:
        return surface in e.detail["candidates"]

    judged = judgments(events)
    for e in dets:
        active = [f for f in sc.faults if f.start_s <= e.t_s <= f.end_s + GRACE_S]
        if any(covers(e, f.surface) for f in active):
            continue
        if active:
            rec.wrong += 1
        else:
            rec.false_alarms += 1
    trims = trim_deflections_deg(sc.airspeed_m_s)
    for order, f in enumerate(sc.faults):
        inside = [e for e in dets if f.start_s <= e.t_s <= f.end_s]
        mine = [e for e in inside if e.detail["component"] == f.surface]
        cover = [e for e in inside if covers(e, f.surface)]
        others = [
            e
            for e in inside
            if not covers(e, f.surface)
            and not any(
                covers(e, g.surface) and g.start_s <= e.t_s <= g.end_s + GRACE_S for g in sc.faults
            )
        ]
        fr = FaultRecord(
            category=sc.category,
            seed=sc.seed,
            surface=f.surface,
            kind=f.kind,
            offset_deg=abs(f.position_deg - trims[f.surface])
            if f.kind == "stuck"
            else f.amplitude_deg,
            period_s=None if f.kind == "stuck" else f.period_s,
            airspeed_m_s=sc.airspeed_m_s,
            rate_hz=sc.sample_rate_hz,
            manoeuvre_at_onset=_manoeuvre_at(sc, f.start_s),
            order=order,
        )
        if f.kind == "stuck":
            fr.hidden_s = _hidden_s(t, ch, f)
        if cover:
            fr.delay_s = cover[0].t_s - f.start_s
        if mine:
            fr.isolation_delay_s = mine[0].t_s - f.start_s
            first_other = [e for e in others if e.t_s < mine[0].t_s]
            fr.isolated = not first_other
            fr.strict = not others
            # a group detection handed to a half (``isolated_as``) is one episode with the
            # detection that follows it; a detection covering the surface after a clearance
            # inside the fault is a re-detection
            handed = [
                e
                for e in events
                if e.kind == "fault_cleared"
                and e.detail.get("isolated_as")
                and covers(e, f.surface)
                and f.start_s <= e.t_s <= f.end_s
            ]
            fr.redetections = max(0, len(cover) - 1 - len(handed))
            kind_event = judged.get((f.surface, mine[0].detail["detected_s"]))
            fr.reported_kind = None if kind_event is None else kind_event.detail["fault_kind"]
        elif cover:
            first = cover[0].detail
            kind_event = judged.get((first["component"], first["detected_s"]))
            fr.reported_kind = None if kind_event is None else kind_event.detail["fault_kind"]
        rec.faults.append(fr)
    rec.twins_both, rec.twins_one = both_halves(sc, events, float(t[-1]))
    if sc.category == "fault_free":
        rec.gate_margins = _gate_margins(config, t, ch, out)
    return rec


def both_halves(sc: FlightScenario, events: list[EstimatorEvent], t_end: float) -> tuple[int, int]:
    """Spans with both halves of a split surface in fault (a detection whose
    ``twin_in_fault`` names the other half, up to the first clearance of either, or ``t_end``),
    and how many of them had a fault of only one of the two halves active."""
    both = one = 0
    for i, e in enumerate(events):
        twin = e.detail.get("twin_in_fault")
        if e.kind != "fault_detected" or twin is None:
            continue
        halves = {e.detail["component"], twin}
        s0, s1 = e.t_s, t_end
        for c in events[i + 1 :]:
            if c.kind == "fault_cleared" and c.detail["component"] in halves:
                s1 = c.t_s
                break
        faulty = {f.surface for f in sc.faults if f.start_s < s1 and f.end_s + GRACE_S > s0}
        both += 1
        one += len(halves & faulty) == 1
    return both, one


# ----------------------------------------------------------------------------- report
def write_section(section: str, begin: str, end: str, after: str) -> None:
    """Put ``section`` (which starts with ``begin`` and ends with ``end``) into
    ``docs/validation.md``: in place of the text between the two markers, else after the marker
    ``after``, else at the end."""
    text = DOC.read_text(encoding="utf-8")
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        _, tail = rest.split(end, 1)
        text = head + section + tail
    elif after in text:
        text = text.replace(after, after + "\n\n" + section, 1)
    else:
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    DOC.write_text(text, encoding="utf-8")
    print(f"wrote {DOC}")


def _q(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def _pct(k: int, n: int) -> str:
    return f"{k}/{n} ({100.0 * k / n:.1f} %)" if n else "-"


def _delays(recs: list[FaultRecord], isolation: bool = False) -> str:
    d = [v for r in recs if (v := r.isolation_delay_s if isolation else r.delay_s) is not None]
    if not d:
        return "-"
    return f"{np.median(d):.2f} / {_q(d, 95):.2f} / {max(d):.2f}"


def kind_ok(r: FaultRecord) -> bool:
    """The kind reported for the fault is its true kind."""
    return r.reported_kind == true_kind(r.kind)


def pairs_isolated(pairs: list[FlightRecord]) -> int:
    """Pair flights whose two faults are both isolated."""
    return sum(all(r.isolated for r in f.faults) for f in pairs)


def stuck_delays(recs: list[FaultRecord], visible: bool = False) -> list[float]:
    """Detection delays of the stuck faults among ``recs`` (a fault never detected counts as
    infinite); ``visible``: counted from the end of the fault's hidden span (*hidden*)."""
    return [
        math.inf if r.delay_s is None else max(r.delay_s - (r.hidden_s if visible else 0.0), 0.0)
        for r in recs
        if r.kind == "stuck"
    ]


def _row(label: str, recs: list[FaultRecord]) -> str:
    n = len(recs)
    iso = sum(r.isolated for r in recs)
    strict = sum(r.strict for r in recs)
    judged = [r for r in recs if r.reported_kind is not None]
    return (
        f"| {label} | {n} | {_pct(iso, n)} | {_pct(strict, n)} | {_delays(recs)} | "
        f"{_delays(recs, isolation=True)} | "
        f"{sum(r.redetections for r in recs)} | {_pct(sum(kind_ok(r) for r in judged), len(judged))} |"
    )


HEADER = (
    "| condition | faults | isolated | strict | detection delay median / p95 / max, s "
    "| isolation delay median / p95 / max, s | re-detections "
    "| kind right |\n|---|---|---|---|---|---|---|---|"
)


def _bins(recs: list[FaultRecord], key: Any, edges: list[float], unit: str, name: str) -> list[str]:
    out = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = [r for r in recs if key(r) is not None and lo <= key(r) < hi]
        if sel:
            out.append(_row(f"{name} {lo:g}-{hi:g} {unit}", sel))
    return out


def report(
    flights: list[FlightRecord],
    args: argparse.Namespace,
    wall_s: float,
    ablation: list[FlightRecord],
) -> list[str]:
    singles = [f for f in flights if f.scenario.category == "single"]
    pairs = [f for f in flights if f.scenario.category == "pair"]
    free = [f for f in flights if f.scenario.category == "fault_free"]
    s_recs = [r for f in singles for r in f.faults]
    p_recs = [r for f in pairs for r in f.faults]
    all_recs = s_recs + p_recs
    stuck = [r for r in s_recs if r.kind == "stuck"]
    stuck_d = stuck_delays(s_recs)
    stuck_iso = [math.inf if r.isolation_delay_s is None else r.isolation_delay_s for r in stuck]
    stuck_vis = stuck_delays(s_recs, visible=True)
    hidden = [r for r in stuck if r.hidden_s > HIDDEN_REPORT_S]
    judged = [r for r in all_recs if r.reported_kind is not None]
    pair_ok = pairs_isolated(pairs)
    free_h = sum(f.scenario.duration_s for f in free) / 3600.0
    free_fa = sum(f.false_alarms for f in free)
    single_iso = sum(r.isolated for r in s_recs)
    red_single = sum(r.redetections for r in s_recs)
    all_samples = sum(f.samples for f in flights)
    all_sec = sum(f.seconds for f in flights)

    def met(ok: bool) -> str:
        return "met" if ok else "**NOT met**"

    stuck_med, stuck_p95 = (
        (float(np.median(stuck_d)), _q(stuck_d, 95)) if stuck_d else (math.nan, math.nan)
    )
    kind_rate = sum(kind_ok(r) for r in judged) / max(len(all_recs), 1)
    lines = [
        BEGIN,
        "### Randomized flights",
        "",
        f"Generated by `scripts/validate_stmmae_random.py` (seeds from {SEED_BASE['single']} "
        f"single, {SEED_BASE['pair']} pair, {SEED_BASE['fault_free']} fault-free; the "
        "development of the decision logic used seeds below 100 and 400-2425, a first run on "
        "seeds 1000+, 2000+, 3000+ set the evidence level, a second run used 11000+, 12000+, "
        "13000+; the last eighteen revisions report the same flights, 21000+, 22000+, 23000+ "
        "(`--seed-offset 10000`), some also the untouched 31000+, 32000+, 33000+ "
        "(`--seed-offset 20000`, run once after the report run), and were developed on 61000+, "
        "71000+, then 81000+, 82000+, 83000+, then 91000+, 92000+, 93000+ and 101000+, 102000+, "
        "103000+, one on these and 121000+, 122000+, 123000+ and 131000+, 132000+, "
        "133000+, the eleventh last (group detection) on 151000+, 152000+, 153000+, "
        "161000+, 162000+ and 173000+, the tenth last (the group's onset window, the "
        "model's operating range) on the false alarm of the untouched 33027 and checked on all "
        "of these and the fresh 181000+, 182000+, 183000+, the ninth last (the deeper "
        "lobe for small swings) on 151000+, 152000+, 161000+, 162000+ and checked on these, the "
        "fresh 211000+, 212000+, 213000+ and the sets above, the eighth last (the "
        "sideslip bound of the operating range; second faults on split surfaces raised as their "
        "group; no detection while a fault ends) on the false alarm of 213029, 173000-173011 "
        "and 231000+, 232000+, and checked on 211000+, 212000+, 213000+, 181000+, 182000+, "
        "31000+, 32000+, 151000+, 152000+, 161000+, 162000+ and the fresh 233000+, 253000+, "
        "the seventh last (the angle of attack and rate bounds of the operating range; "
        "the hold of a half while its twin is in fault) on 151000+, 152000+, 181000+, 182000+, "
        "231000+, 232000+, 213000+, 233000+, and checked on the fresh 271000+, 272000+, "
        "291000+, 292000+, 293000+ and the sets above, the sixth last (a detected "
        "group's halves weighed on their filters' summed evidence; the kind history conditioned "
        "on a healthy twin's command) on the two single faults of 271000+ not narrowed to their "
        "half and on 151000+, 152000+, 181000+, 182000+, 231000+, 232000+, and checked on the "
        "fresh 311000+, 312000+ and the sets above, the fifth last (a kind span's end waits for "
        "the detection of a fault whose onset lies inside it) on the kind errors of all the "
        "sets above and checked on them and the fresh 331000+, 332000+, the fourth last (the "
        "deflection gate's variance capped at a filter's prior; no group beside two faults; "
        "kind histories inside the operating range; a settling time back inside it) on "
        "232010, 391008 and the sets above, and checked "
        "on them and the fresh 351000+, 352000+, 371000+, 372000+, 391000+, 392000+, 411000+, "
        "412000+, the third last (a kind for a group never narrowed to its half; its "
        "own scoring rule, the docstring's *kind*) on the group-only second faults of the sets above, and "
        "checked on them and the fresh 431000+, 432000+, 451000+, 452000+, the one before the last (no "
        "change to the decision logic: the stuck delays also counted once the fault is visible, "
        "the docstring's *hidden*, and the sets pooled by `scripts/stmmae_goal_spread.py`) on "
        "all of the sets above and the fresh 471000+, 472000+, 491000+, 492000+, the last one (a "
        "half whose strongest competitor is its twin named at the group's odds before its group "
        "is detected too) on the single faults missed in the sets above and in 511000+ to "
        "871000+ (seed offsets 500000 to 860000) and checked on all of these, their pairs and "
        "the fresh 891000+, 892000+ to 1071000+, 1072000+ (880000 to 1060000): "
        "`docs/methods-stmmae.md`, 'Goals and what was measured'): "
        f"{len(singles)} flights with one fault, {len(pairs)} with two overlapping faults, "
        f"{len(free)} fault-free flights ({free_h:.2f} h). Generator: "
        "`estimators/simulators/uav_scenarios.py` (airspeed 22-32 m/s, 100 Hz or 50 Hz, turns "
        "and climbs, stuck at 2-15 deg from trim, square/sine oscillations of 1.5-8 deg amplitude "
        "and 0.5-4 s period, faults of 10-25 s, the second fault of a pair 2-8 s after the first "
        "and overlapping it by at least 5 s). The bank runs with its default configuration and "
        "the model linearized at the flight's airspeed and rate, one batch per flight. Scoring "
        "rules: the script's docstring.",
        "",
        "| goal | target | measured | |",
        "|---|---|---|---|",
        f"| single faults isolated | >= 99 % | {_pct(single_iso, len(s_recs))} | "
        f"{met(single_iso >= GOALS['single'] * len(s_recs))} |",
        f"| overlapping pairs, both isolated | >= 90 % | {_pct(pair_ok, len(pairs))} | "
        f"{met(pair_ok >= GOALS['pair'] * len(pairs))} |",
        f"| stuck >= 2 deg from trim: median delay | <= 0.3 s | {stuck_med:.2f} s | "
        f"{met(stuck_med <= GOALS['stuck_median_s'] + TIME_TOL_S)} |",
        f"| stuck >= 2 deg from trim: 95th percentile | <= 0.5 s | {stuck_p95:.2f} s | "
        f"{met(stuck_p95 <= GOALS['stuck_p95_s'] + TIME_TOL_S)} |",
        "| stuck >= 2 deg from trim: isolation delay (the half named), median / 95th "
        f"percentile | (no goal) | {float(np.median(stuck_iso)) if stuck_iso else math.nan:.2f} / "
        f"{_q(stuck_iso, 95):.2f} s | |",
        "| stuck >= 2 deg from trim: delay once visible (from the first command >= 2 deg from "
        f"the stuck position; {len(hidden)} of {len(stuck)} hidden for more than "
        f"{HIDDEN_REPORT_S:g} s, longest {max((r.hidden_s for r in stuck), default=0.0):.2f} s), "
        "median / 95th percentile "
        f"| (no goal) | {float(np.median(stuck_vis)) if stuck_vis else math.nan:.2f} / "
        f"{_q(stuck_vis, 95):.2f} s | |",
        f"| stuck vs oscillating right (of all faults) | >= 95 % | "
        f"{_pct(sum(kind_ok(r) for r in judged), len(all_recs))} | "
        f"{met(kind_rate >= GOALS['kind'])} |",
        f"| false alarms, fault-free | 0 in >= 5 h | {free_fa} in {free_h:.2f} h | "
        f"{met(free_fa == 0 and free_h >= 5.0)} |",
        f"| re-detections during a single fault | 0 | {red_single} | {met(red_single == 0)} |",
        "",
        f"Other counts: wrong-surface detections {sum(f.wrong for f in singles)} in the "
        f"single-fault flights and {sum(f.wrong for f in pairs)} in the pair flights; false "
        f"alarms (no fault active) {sum(f.false_alarms for f in singles + pairs)} in the faulty "
        f"flights. Both halves of a split surface in fault together "
        f"{sum(f.twins_both for f in singles + pairs)} times, "
        f"{sum(f.twins_one for f in singles + pairs)} of them with a fault of only one half "
        "(*both halves*; the status then says one of the two may not be in fault). Bank cost: "
        f"{1e6 * all_sec / max(all_samples, 1):.0f} us per sample over "
        f"{all_samples} samples (16 filters with pair hypotheses; shared machine). Wall time "
        f"{wall_s / 60:.0f} min.",
        "",
        "**Single faults by condition** (*isolated*: the first detection of a single surface "
        "in the fault names it, and no detection before it leaves it out; *strict*: no "
        "detection during the fault leaves it out; *detection delay*: the first detection "
        "naming the surface or its group of twin halves; *isolation delay*: the first naming "
        "the surface; delays over detected faults; *kind right* over faults whose kind was "
        "judged).",
        "",
        HEADER,
        _row("all single faults", s_recs),
    ]
    for s in SURFACES:
        for kinds, label in ((("stuck",), "stuck"), (("square", "sine"), "oscillating")):
            sel = [r for r in s_recs if r.surface == s and r.kind in kinds]
            if sel:
                lines.append(_row(f"{s} {label}", sel))
    lines += _bins(stuck, lambda r: r.offset_deg, [2, 5, 10, 15.01], "deg", "stuck, offset")
    osc = [r for r in s_recs if r.kind != "stuck"]
    lines += _bins(osc, lambda r: r.period_s, [0.5, 1.0, 2.0, 4.01], "s", "oscillation, period")
    lines += _bins(
        osc, lambda r: r.offset_deg, [1.5, 3.0, 5.0, 8.01], "deg", "oscillation, amplitude"
    )
    lines += _bins(s_recs, lambda r: r.airspeed_m_s, [22, 25, 28, 32.01], "m/s", "airspeed")
    for rate in (100.0, 50.0):
        sel = [r for r in s_recs if r.rate_hz == rate]
        if sel:
            lines.append(_row(f"{rate:g} Hz", sel))
    for flag, label in ((True, "manoeuvre at onset"), (False, "no manoeuvre at onset")):
        sel = [r for r in s_recs if r.manoeuvre_at_onset == flag]
        if sel:
            lines.append(_row(label, sel))
    lines += [
        "",
        "**Overlapping pairs** (first and second fault of each flight).",
        "",
        HEADER,
        _row("first fault", [r for r in p_recs if r.order == 0]),
        _row("second fault", [r for r in p_recs if r.order == 1]),
        _row(
            "second fault, same pair of halves (both ailerons or both elevators)",
            [
                r
                for f in pairs
                for r in f.faults[1:]
                if r.surface.split("_")[0] == f.faults[0].surface.split("_")[0]
            ],
        ),
        "",
    ]
    if ablation:
        a_recs = [r for f in ablation for r in f.faults]
        a_ok = sum(all(r.isolated for r in f.faults) for f in ablation)
        lines += [
            "Same pair flights with `pair_hypotheses: false` (the seed's bank of one filter per "
            f"surface): both isolated in {_pct(a_ok, len(ablation))} (with pairs: "
            f"{_pct(pair_ok, len(pairs))}); wrong-surface detections "
            f"{sum(f.wrong for f in ablation)} (with pairs: {sum(f.wrong for f in pairs)}).",
            "",
            HEADER,
            _row("first fault, no pair hypotheses", [r for r in a_recs if r.order == 0]),
            _row("second fault, no pair hypotheses", [r for r in a_recs if r.order == 1]),
            "",
        ]
    if free:
        margins = [f.gate_margins for f in free]
        lines += [
            "**Fault-free flights**: "
            f"{len(free)} x {free[0].scenario.duration_s:g} s, {free_fa} false alarms. Margins: "
            "largest marginal fault probability "
            f"{max(m['pmax'] for m in margins):.3f}; runs of at least `hold_s` with a surface's "
            f"fault probability above `detect_probability`: "
            f"{int(sum(m['runs_probability'] for m in margins))} "
            f"(in {sum(m['runs_probability'] > 0 for m in margins)} flights), of which the "
            "smoothed deflection error was also above `min_deflection_error_deg` (the fixed "
            "part of the deflection gate; its part in posterior standard deviations is not "
            "replicated here): "
            f"{int(sum(m['runs_probability_and_deflection'] for m in margins))}; the "
            "likelihood-ratio condition is the third gate.",
            "",
        ]
    missed = [r for r in all_recs if not r.isolated]
    if missed:
        lines += [
            "Faults not isolated (flight seed: fault; delay of the first detection covering it, "
            "of its own detection):",
            "",
        ]
        for f in flights:
            for r, fault in zip(f.faults, f.scenario.faults, strict=True):
                if not r.isolated:
                    d = "; ".join(
                        "never" if x is None else f"{x:.2f} s"
                        for x in (r.delay_s, r.isolation_delay_s)
                    )
                    lines.append(
                        f"* {f.scenario.category} {f.scenario.seed}: {describe(fault)}; {d}"
                    )
        lines.append("")
    wrong_kind = [r for r in judged if not kind_ok(r)]
    if wrong_kind:
        lines.append(
            "Kind wrong: "
            + "; ".join(
                f"{r.category} {r.seed} {r.surface} {r.kind} reported {r.reported_kind}"
                for r in wrong_kind
            )
        )
        lines.append("")
    lines.append(END)
    return lines


def flight_set_parser(
    description: str, offsets_help: str, flights: int, flights_help: str
) -> argparse.ArgumentParser:
    """The arguments of the scripts that read this script's flights: ``--cache`` (the directory
    of simulated flights), ``--seed-offset`` (repeatable) and ``--flights`` (per category and
    offset)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--cache", type=Path, default=None, help="directory of simulated flights")
    ap.add_argument(
        "--seed-offset",
        type=int,
        action="append",
        default=None,
        help=f"a seed offset of validate_stmmae_random.py (repeatable; {offsets_help})",
    )
    ap.add_argument("--flights", type=int, default=flights, help=flights_help)
    return ap


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--singles", type=int, default=40)
    ap.add_argument("--pairs", type=int, default=40)
    ap.add_argument("--fault-free-hours", type=float, default=5.0)
    ap.add_argument("--quick", action="store_true", help="6/6/0.2 h, no document written")
    ap.add_argument("--no-write", action="store_true", help="print, do not write the document")
    ap.add_argument(
        "--no-ablation", action="store_true", help="skip the pair flights without pair hypotheses"
    )
    ap.add_argument(
        "--cache", type=Path, default=None, help="directory of simulated flights to reuse"
    )
    ap.add_argument(
        "--simulate-only",
        action="store_true",
        help="fill --cache with the plan's flights, then stop",
    )
    ap.add_argument(
        "--seed-offset",
        type=int,
        default=0,
        help="added to every seed base (another draw of flights; the document names the seeds)",
    )
    ap.add_argument(
        "--config",
        type=json.loads,
        default={},
        help="configuration changes as a JSON object (the document then names them)",
    )
    args = ap.parse_args()
    if args.seed_offset:
        for key in SEED_BASE:
            SEED_BASE[key] += args.seed_offset
    if args.quick:
        args.singles, args.pairs, args.fault_free_hours = 6, 6, 0.2
    stmmae.warm_up()
    t0 = time.perf_counter()
    plan: list[FlightScenario] = [
        random_scenario(SEED_BASE["single"] + i, "single") for i in range(args.singles)
    ] + [random_scenario(SEED_BASE["pair"] + i, "pair") for i in range(args.pairs)]
    n_free = int(math.ceil(args.fault_free_hours * 3600.0 / 600.0 - 1e-9))
    plan += [random_scenario(SEED_BASE["fault_free"] + i, "fault_free") for i in range(n_free)]
    if args.simulate_only:
        for sc in plan:
            simulate(sc, args.cache)
        return 0
    flights = []
    for i, sc in enumerate(plan):
        rec = run_flight(sc, args.config or None, args.cache)
        flights.append(rec)
        marks = ", ".join(
            f"{r.surface} {r.kind} {'-' if r.delay_s is None else f'{r.delay_s:.2f}'}"
            f"{'' if r.isolated else ' NOT ISOLATED'} {r.reported_kind}"
            for r in rec.faults
        )
        print(
            f"[{i + 1}/{len(plan)}] {sc.category} {sc.seed}: {marks} wrong {rec.wrong} "
            f"fa {rec.false_alarms}",
            flush=True,
        )
    ablation = []
    if not args.no_ablation:
        for sc in plan:
            if sc.category == "pair":
                rec = run_flight(sc, {**args.config, "pair_hypotheses": False}, args.cache)
                ablation.append(rec)
                print(f"[ablation] pair {sc.seed}: wrong {rec.wrong}", flush=True)
    lines = report(flights, args, time.perf_counter() - t0, ablation)
    section = "\n".join(lines)
    print(section)
    if args.quick or args.no_write:
        return 0
    write_section(section, BEGIN, END, after="<!-- stmmae:end -->")
    return 0


if __name__ == "__main__":
    sys.exit(main())
