"""STMMAE's goals over many sets of randomized flights: per set, pooled, and a set's spread.

Each goal of ``scripts/validate_stmmae_random.py`` that is a rate (single faults isolated,
overlapping pairs both isolated, stuck vs oscillating right) is judged on one set of 40 + 40
flights. A set is a sample: even if the bank's true rate were above a goal, some sets would fall
below it. For the seed offsets given (each one set, the same flights, seeds and scoring as
``validate_stmmae_random.py --seed-offset N``; default configuration), this prints

* one row per set: singles isolated, pairs both isolated, kinds right (of all faults), the
  stuck detection delays (median / 95th percentile, a stuck fault never detected counting as
  infinite), wrong-surface detections and detections with no fault active;
* the stuck delays over all sets, from the onset and once the fault is visible (the command
  at least 2 deg from the stuck position);
* the pooled rate of each rate goal with its 95 % Wilson interval;
* the share of sets expected to miss each goal if the true rate were the pooled one (binomial,
  one set's count of flights or faults), beside the share that did.

    .venv/bin/python scripts/stmmae_goal_spread.py --cache DIR --seed-offset 10000 \\
        --seed-offset 140000 ... [--write]

``--write`` also puts the section into ``docs/validation.md`` (between
``<!-- stmmae-spread:begin -->`` and ``<!-- stmmae-spread:end -->``).

What it does not show: the sets are independent draws of the same generator, so the pooled
rate is that generator's rate; another population of flights (other airframes, schedules or
faults) has its own.
"""

from __future__ import annotations

import functools
import math
import multiprocessing
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parent))

import validate_stmmae_random as vr  # noqa: E402

from estimators import stmmae  # noqa: E402
from estimators.simulators.uav_scenarios import random_scenario  # noqa: E402

Z95 = float(stats.norm.ppf(0.975))


@dataclass
class SetResult:
    """One set's counts (``offset``: its seed offset)."""

    offset: int
    singles: int
    singles_ok: int
    pairs: int
    pairs_ok: int
    faults: int
    kinds_ok: int
    stuck_delays: list[float]
    stuck_visible: list[float]  # the same, counted once the fault is visible (``hidden_s``)
    wrong: int
    no_fault: int
    twins_both: int  # spans with both halves of a split surface in fault
    twins_one: int  # of which only one half had a fault


def run_set(offset: int, flights: int, cache: Path | None) -> SetResult:
    """Score one set's single and pair flights as ``validate_stmmae_random.py`` does."""
    recs = [
        vr.run_flight(random_scenario(vr.SEED_BASE[cat] + offset + i, cat), None, cache)
        for cat in ("single", "pair")
        for i in range(flights)
    ]
    singles = [r for f in recs if f.scenario.category == "single" for r in f.faults]
    pairs = [f for f in recs if f.scenario.category == "pair"]
    faults = [r for f in recs for r in f.faults]
    return SetResult(
        offset=offset,
        singles=len(singles),
        singles_ok=sum(r.isolated for r in singles),
        pairs=len(pairs),
        pairs_ok=vr.pairs_isolated(pairs),
        faults=len(faults),
        kinds_ok=sum(vr.kind_ok(r) for r in faults),
        stuck_delays=vr.stuck_delays(singles),
        stuck_visible=vr.stuck_delays(singles, visible=True),
        wrong=sum(f.wrong for f in recs),
        no_fault=sum(f.false_alarms for f in recs),
        twins_both=sum(f.twins_both for f in recs),
        twins_one=sum(f.twins_one for f in recs),
    )


def wilson(k: int, n: int) -> tuple[float, float]:
    """95 % Wilson score interval of a proportion ``k / n``."""
    if n == 0:
        return (math.nan, math.nan)
    p = k / n
    den = 1.0 + Z95**2 / n
    mid = (p + Z95**2 / (2 * n)) / den
    half = Z95 * math.sqrt(p * (1 - p) / n + Z95**2 / (4 * n * n)) / den
    return (max(0.0, mid - half), min(1.0, mid + half))


def miss_chance(rate: float, n: int, goal: float) -> float:
    """Probability that a set of ``n`` draws at true ``rate`` shows fewer than ``goal * n``
    successes (the goal missed on that set)."""
    need = math.ceil(goal * n - 1e-9)
    return float(stats.binom.cdf(need - 1, n, rate))


BEGIN = "<!-- stmmae-spread:begin -->"
END = "<!-- stmmae-spread:end -->"


def _pooled_rows(results: list[SetResult], label_suffix: str) -> list[str]:
    """Rows of the pooled table (one per rate goal) over ``results``."""
    rows = []
    goals = (
        ("single faults isolated >= 99 %", vr.GOALS["single"], "singles_ok", "singles"),
        ("overlapping pairs both isolated >= 90 %", vr.GOALS["pair"], "pairs_ok", "pairs"),
        ("stuck vs oscillating right >= 95 %", vr.GOALS["kind"], "kinds_ok", "faults"),
    )
    for label, goal, ok_key, n_key in goals:
        k = sum(getattr(r, ok_key) for r in results)
        n = sum(getattr(r, n_key) for r in results)
        lo, hi = wilson(k, n)
        missed = sum(
            getattr(r, ok_key) < math.ceil(goal * getattr(r, n_key) - 1e-9) for r in results
        )
        expected = miss_chance(k / n, getattr(results[0], n_key), goal) if n else math.nan
        rows.append(
            f"| {label}{label_suffix} | {k}/{n} ({100.0 * k / n:.1f} %) | "
            f"{100 * lo:.1f}-{100 * hi:.1f} % | {missed} of {len(results)} | "
            f"{100.0 * expected:.0f} % |"
        )
    return rows


def report(results: list[SetResult], flights: int, held_out: set[int] | None = None) -> list[str]:
    """The section: one row per set, then the pooled goals and the spread a set shows
    (``held_out``: the offsets of sets drawn after the configuration was last chosen, marked
    and pooled apart as well)."""
    held_out = held_out or set()
    offsets = ", ".join(str(r.offset) for r in results)
    lines = [
        BEGIN,
        "### Randomized flights: the goals over many sets",
        "",
        "Generated by `scripts/stmmae_goal_spread.py --cache DIR --seed-offset N ...` (seed "
        f"offsets {offsets}; each offset one set of {flights} single-fault and {flights} pair "
        "flights, scored as `scripts/validate_stmmae_random.py --seed-offset N` scores them; "
        "default configuration; the fault-free hours are not part of it). The rate goals are "
        "judged on one set; a set is a sample, so even a bank whose true rate is above a goal "
        "misses it on some sets. *Expected share*: the probability that one set misses the "
        "goal if the true rate were the pooled one (binomial over the set's flights or "
        "faults). The sets are draws of one generator: the pooled rate is that generator's, "
        "not that of other flights.",
        "",
        "| set (seed offset) | singles isolated | pairs both isolated | kinds right | "
        "stuck delay median / p95, s | wrong-surface detections | no fault active |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        d = r.stuck_delays
        delays = f"{np.median(d):.2f} / {np.percentile(d, 95):.2f}" if d else "-"
        mark = " (held out)" if r.offset in held_out else ""
        lines.append(
            f"| {r.offset}{mark} | {r.singles_ok}/{r.singles} | {r.pairs_ok}/{r.pairs} | "
            f"{r.kinds_ok}/{r.faults} | {delays} | {r.wrong} | {r.no_fault} |"
        )
    lines += [
        "",
        "| goal | pooled | 95 % interval (Wilson) | sets missing it | expected share of sets "
        "missing it at the pooled rate |",
        "|---|---|---|---|---|",
    ]
    lines += _pooled_rows(results, "")
    kept = [r for r in results if r.offset in held_out]
    if kept and len(kept) < len(results):
        lines += _pooled_rows(kept, f", the {len(kept)} held-out sets")
    d = [v for r in results for v in r.stuck_delays]
    if d:
        goal = vr.GOALS["stuck_p95_s"] + vr.TIME_TOL_S
        late = sum(np.percentile(r.stuck_delays, 95) > goal for r in results if r.stuck_delays)
        v = [x for r in results for x in r.stuck_visible]
        late_v = sum(np.percentile(r.stuck_visible, 95) > goal for r in results if r.stuck_visible)
        lines += [
            "",
            f"Stuck faults >= 2 deg from trim over all sets: {len(d)}, detection delay median "
            f"{np.median(d):.2f} s, 95th percentile {np.percentile(d, 95):.2f} s; sets whose "
            f"own 95th percentile is above 0.5 s: {late} of {len(results)}. Counted once the "
            "fault is visible (from the first command >= 2 deg from the stuck position; "
            "`validate_stmmae_random.py`, *hidden*): 95th percentile "
            f"{np.percentile(v, 95):.2f} s; sets above 0.5 s: {late_v} of {len(results)}.",
        ]
    both = sum(r.twins_both for r in results)
    one = sum(r.twins_one for r in results)
    lines += [
        "",
        f"Both halves of a split surface in fault together (`validate_stmmae_random.py`, *both "
        f"halves*): {both} times over all sets, {one} of them with a fault of only one half "
        f"({100.0 * one / max(both, 1):.0f} %); the status and `twin_in_fault` say so.",
    ]
    lines.append(END)
    return lines


def main() -> int:
    ap = vr.flight_set_parser(
        __doc__.split("\n")[0], "one set each; default 10000", 40, "flights per category and set"
    )
    ap.add_argument(
        "--write", action="store_true", help="also write the section into docs/validation.md"
    )
    ap.add_argument(
        "--held-out",
        type=int,
        action="append",
        default=[],
        help="a seed offset (also given to --seed-offset) drawn after the configuration was "
        "last chosen: marked, and pooled apart as well (repeatable)",
    )
    ap.add_argument("--jobs", type=int, default=1, help="sets scored in parallel processes")
    args = ap.parse_args()
    offsets = args.seed_offset or [10000]
    stmmae.warm_up()
    score = functools.partial(run_set, flights=args.flights, cache=args.cache)
    with multiprocessing.Pool(max(1, args.jobs)) as pool:
        results = []
        for r in pool.imap(score, offsets):
            results.append(r)
            print(
                f"set {r.offset}: singles {r.singles_ok}/{r.singles}, pairs "
                f"{r.pairs_ok}/{r.pairs}, kinds {r.kinds_ok}/{r.faults}",
                flush=True,
            )
    section = "\n".join(report(results, args.flights, set(args.held_out) & set(offsets)))
    print(section)
    if args.write:
        vr.write_section(section, BEGIN, END, after="<!-- stmmae-random:end -->")
    return 0


if __name__ == "__main__":
    sys.exit(main())
