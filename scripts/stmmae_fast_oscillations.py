"""How fast an oscillating fault STMMAE still detects, names and classifies, per surface.

One simulated flight per case (25 m/s, 100 Hz, noise seed 1, ``simulate_flight(27.0, ...)``):
a sine and a square wave of +-5 deg about 0 deg on one surface from 10 to 25 s, for periods of
0.3, 0.5, 0.75 and 1.0 s. Prints one Markdown row per surface and period: what was detected
(the group of both halves, the surface itself, another surface), when, and the kind reported.
The table in ``docs/methods-stmmae.md`` ("Fault kind and stuck position") comes from this
script.

    .venv/bin/python scripts/stmmae_fast_oscillations.py [--config JSON]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimators import stmmae  # noqa: E402
from estimators.base import Batch  # noqa: E402
from estimators.simulators.uav_closed_loop import SurfaceFault, simulate_flight  # noqa: E402

SURFACES = ("aileron_right", "elevator_left", "rudder")
PERIODS_S = (0.3, 0.5, 0.75, 1.0)
START_S, END_S = 10.0, 25.0


def outcome(config: stmmae.StmmaeConfig, surface: str, kind: str, period_s: float) -> str:
    """What the bank reports for one oscillating fault: each detection during the fault as
    ``component delay-from-onset``, and the kind classified for the surface itself."""
    fault = SurfaceFault(
        surface, START_S, END_S, kind, center_deg=0.0, amplitude_deg=5.0, period_s=period_s
    )
    t, ch, _ = simulate_flight(27.0, faults=(fault,), seed=1)
    _, out = stmmae.step(config, stmmae.initial_state(config), Batch(t_s=t, channels=ch))
    parts = [
        f"{e.detail['component']} {e.t_s - START_S:.2f} s"
        for e in out.events
        if e.kind == "fault_detected" and START_S <= e.t_s <= END_S
    ]
    kinds = {
        e.detail["fault_kind"]
        for e in out.events
        if e.kind in ("fault_classified", "fault_cleared")
        and e.detail["component"] == surface
        and e.detail["fault_kind"] != "pending"
    }
    detected = ", ".join(parts) if parts else "not detected"
    return f"{detected}" + (f"; kind {'/'.join(sorted(kinds))}" if kinds else "")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", type=json.loads, default={}, help="configuration changes (JSON)")
    args = ap.parse_args()
    config = stmmae.parse_config(args.config)
    print("| surface | period | sine | square |")
    print("|---|---|---|---|")
    for surface in SURFACES:
        for period in PERIODS_S:
            sine = outcome(config, surface, "sine", period)
            square = outcome(config, surface, "square", period)
            print(f"| `{surface}` | {period} s | {sine} | {square} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
