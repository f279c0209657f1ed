"""Where STMMAE's fault kind (stuck or oscillating) is wrong on the randomized flights, by context.

For the single-fault and pair flights of ``scripts/validate_stmmae_random.py`` (same generator,
seeds and cache), the bank runs with its default configuration over each flight in one batch.
Every kind the bank judged for a surface in fault (the ``fault_kind`` of its
``fault_classified`` event, or of ``fault_cleared`` when the episode ended first) is compared
with the truth (stuck against square/sine = oscillating). Each judged kind gets one context,
the first that applies, over its span (from the episode's onset to the judgment):

* ``single``: the flight's only fault;
* ``other began in span``: another surface's fault began inside the span (from 0.5 s before
  its onset); a detection of that surface cuts the span only when it comes before the span's
  end (``fault_kind_cut``);
* ``twin in fault``: the surface's twin half was in fault through the span;
* ``other in fault``: another surface was in fault through the span;
* ``alone in a pair flight``: no other fault during the span.

Prints one row per context (judged, wrong: stuck reported oscillating, oscillating reported
stuck) and one line per wrong kind (flight seed, surface, truth, the statistics the kind was
judged on, the other faults).

    .venv/bin/python scripts/stmmae_kind_errors.py --cache DIR --seed-offset 140000 \\
        --seed-offset 170000
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import validate_stmmae_random as vr  # noqa: E402

from estimators import stmmae  # noqa: E402
from estimators.base import Batch  # noqa: E402
from estimators.simulators.uav_closed_loop import SurfaceFault  # noqa: E402
from estimators.simulators.uav_scenarios import random_scenario  # noqa: E402

CONTEXTS = (
    "single",
    "other began in span",
    "twin in fault",
    "other in fault",
    "alone in a pair flight",
)
TWINS = {
    "aileron_left": "aileron_right",
    "aileron_right": "aileron_left",
    "elevator_left": "elevator_right",
    "elevator_right": "elevator_left",
}
MARGIN_S = 0.5  # a fault's effect reaches the other estimates some tenths of a second early


def context(surface: str, faults: tuple[SurfaceFault, ...], t0: float, t1: float) -> str:
    """The context of a kind judged on ``surface`` over the span ``[t0, t1]`` (module doc)."""
    if len(faults) == 1:
        return "single"
    others = [f for f in faults if f.surface != surface]
    if any(t0 <= f.start_s + MARGIN_S and f.start_s - MARGIN_S <= t1 for f in others):
        return "other began in span"
    during = [f for f in others if f.start_s <= t0 and f.end_s >= t0]
    if any(f.surface == TWINS.get(surface) for f in during):
        return "twin in fault"
    if during:
        return "other in fault"
    return "alone in a pair flight"


def main() -> int:
    ap = vr.flight_set_parser(
        __doc__.split("\n")[0], "default 0", 40, "flights per category and offset"
    )
    args = ap.parse_args()
    stmmae.warm_up()
    judged: Counter[str] = Counter()
    wrong: Counter[tuple[str, str]] = Counter()
    lines: list[str] = []
    for off in args.seed_offset or [0]:
        for category in ("single", "pair"):
            for i in range(args.flights):
                sc = random_scenario(vr.SEED_BASE[category] + off + i, category)
                t, ch = vr.simulate(sc, args.cache)
                config = vr.config_for(sc)
                _, out = stmmae.step(
                    config, stmmae.initial_state(config), Batch(t_s=t, channels=ch)
                )
                for e in vr.judgments(list(out.events)).values():
                    d = e.detail
                    truth = [
                        f
                        for f in sc.faults
                        if f.surface == d["component"]
                        and f.start_s - 1.0 <= d["onset_s"] <= f.end_s
                    ]
                    if not truth:
                        continue  # a wrong surface's episode: scored by validate_stmmae_random
                    fault = truth[0]
                    want = vr.true_kind(fault.kind)
                    ctx = context(fault.surface, sc.faults, d["onset_s"], e.t_s)
                    judged[ctx] += 1
                    if d["fault_kind"] == want:
                        continue
                    wrong[(ctx, want)] += 1
                    others = ", ".join(
                        f"{f.surface} {f.kind} {f.start_s:.1f}-{f.end_s:.1f} s"
                        for f in sc.faults
                        if f is not fault
                    )
                    corr = d.get("deflection_autocorrelation_min")
                    swing = d.get("deflection_swing_deg")
                    lines.append(
                        f"{sc.seed} {fault.surface} {fault.kind} ({fault.start_s:.1f} s) reported "
                        f"{d['fault_kind']} at {e.t_s:.1f} s: autocorrelation "
                        f"{float('nan') if corr is None else corr:.2f}, swing "
                        f"{float('nan') if swing is None else swing:.1f} deg; {ctx}"
                        + (f"; {others}" if others else "")
                    )
    print(
        "| context | kinds judged | wrong | stuck reported oscillating | "
        "oscillating reported stuck |"
    )
    print("|---|---|---|---|---|")
    for ctx in CONTEXTS:
        s, o = wrong[(ctx, "stuck")], wrong[(ctx, "oscillating")]
        print(f"| {ctx} | {judged[ctx]} | {s + o} | {s} | {o} |")
    total = sum(judged.values())
    bad = sum(wrong.values())
    print(f"| all | {total} | {bad} | - | - |")
    print()
    for line in lines:
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
