"""How far fault-free flights go from the trim in the quantities STMMAE's operating range bounds.

For the randomized fault-free flights of ``scripts/validate_stmmae_random.py`` (same generator,
seeds and cache), each measurement the model's ``operating_range`` bounds is smoothed as the
bank smooths it (first order, time constant ``operating_range_smoothing_s``, the first valid
value starting it) and compared with the middle of its range (the trim airspeed, zero
sideslip, the trim angle of attack, zero rates). Prints, per measurement, the largest smoothed
excursion over all flights (deg, deg/s or m/s), the bound's half-width, and the share of
samples outside the bound. The bounds of ``estimators/models/small_uav.py`` were set between
these excursions and the departures from controlled flight (``docs/methods-stmmae.md``,
"Operating range").

    .venv/bin/python scripts/stmmae_operating_excursions.py --cache DIR --seed-offset 200000 \\
        --seed-offset 220000        # the I and J sets: 60 flights, 10 h
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import validate_stmmae_random as vr  # noqa: E402

from estimators.simulators.uav_scenarios import random_scenario  # noqa: E402

ANGLES = {"beta", "alpha", "p", "q", "r"}  # radians (or rad/s) in the model, printed in degrees


def smoothed(y: np.ndarray, t: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order smoothing of ``y`` as the bank's operating range does it."""
    out = np.empty_like(y)
    acc = math.nan
    prev_t = math.nan
    for k, (tk, v) in enumerate(zip(t, y, strict=True)):
        if math.isfinite(v):
            if math.isnan(acc):
                acc = float(v)
            else:
                acc += (1.0 - math.exp(-(tk - prev_t) / tau_s)) * (v - acc)
        out[k] = acc
        prev_t = tk
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cache", type=Path, default=None, help="directory of simulated flights")
    ap.add_argument(
        "--seed-offset",
        type=int,
        action="append",
        default=None,
        help="a seed offset of validate_stmmae_random.py (repeatable; default 200000 and 220000)",
    )
    ap.add_argument("--flights", type=int, default=30, help="fault-free flights per offset")
    args = ap.parse_args()
    offsets = args.seed_offset or [200000, 220000]
    worst: dict[str, float] = {}
    half: dict[str, float] = {}
    outside: dict[str, int] = {}
    samples = 0
    seconds = 0.0
    for off in offsets:
        for i in range(args.flights):
            sc = random_scenario(vr.SEED_BASE["fault_free"] + off + i, "fault_free")
            t, ch = vr.simulate(sc, args.cache)
            config = vr.config_for(sc)
            samples += len(t)
            seconds += float(t[-1] - t[0])
            for m in config.model.measurements:
                bounds = config.model.operating_range.get(m.name)
                if bounds is None:
                    continue
                lo, hi = bounds
                mid = 0.5 * (lo + hi)
                sm = smoothed(ch[m.channel], t, config.operating_range_smoothing_s)
                scale = math.degrees(1.0) if m.name in ANGLES else 1.0
                dev = float(np.nanmax(np.abs(sm - mid))) * scale
                worst[m.name] = max(worst.get(m.name, 0.0), dev)
                half[m.name] = 0.5 * (hi - lo) * scale
                outside[m.name] = outside.get(m.name, 0) + int(np.sum((sm < lo) | (sm > hi)))
            print(f"  {sc.seed}: {len(t)} samples", file=sys.stderr, flush=True)
    print(f"{len(offsets) * args.flights} fault-free flights, {seconds / 3600.0:.2f} h")
    print("| measurement | largest smoothed excursion | bound (half-width) | samples outside |")
    print("|---|---|---|---|")
    for name, dev in worst.items():
        unit = "deg/s" if name in {"p", "q", "r"} else ("deg" if name in ANGLES else "m/s")
        print(
            f"| {name} | {dev:.2f} {unit} | {half[name]:.2f} {unit} | "
            f"{100.0 * outside[name] / samples:.3f} % |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
