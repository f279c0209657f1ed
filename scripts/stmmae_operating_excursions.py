"""How far fault-free flights go from the trim in the quantities STMMAE's operating range bounds.

For the randomized fault-free flights of ``scripts/validate_stmmae_random.py`` (same generator,
seeds and cache), the bank runs with its default configuration (the model at the flight's
airspeed) in batches of 0.1 s; after each, the measurements the model's ``operating_range``
bounds, as the bank has smoothed them (``StateParts.operating``), are compared with the middle
of their range (the trim airspeed, zero sideslip, the trim angle of attack, zero rates). Prints,
per measurement, the largest smoothed excursion over all flights (deg, deg/s or m/s) against the
bound's half-width, and the share of samples outside the range from the health windows
(``outside_operating_range_fraction``, complete windows). The bounds of
``estimators/models/small_uav.py`` were set between these excursions and the departures from
controlled flight (``docs/methods-stmmae.md``, "Operating range").

    .venv/bin/python scripts/stmmae_operating_excursions.py --cache DIR     # the I and J sets
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import validate_stmmae_random as vr  # noqa: E402

from estimators import stmmae  # noqa: E402
from estimators.base import Batch  # noqa: E402
from estimators.simulators.uav_scenarios import random_scenario  # noqa: E402

ANGLES = {"beta", "alpha", "p", "q", "r"}  # radians (or rad/s) in the model, printed in degrees
BATCH_S = 0.1  # the smoothed values are read after each batch (the time constant is 10 s)


def main() -> int:
    ap = vr.flight_set_parser(
        __doc__.split("\n")[0],
        "default 200000 and 220000",
        30,
        "fault-free flights per offset",
    )
    args = ap.parse_args()
    offsets = args.seed_offset or [200000, 220000]
    worst: dict[str, float] = {}
    half: dict[str, float] = {}
    outside = windowed = 0.0
    seconds = 0.0
    for off in offsets:
        for i in range(args.flights):
            sc = random_scenario(vr.SEED_BASE["fault_free"] + off + i, "fault_free")
            t, ch = vr.simulate(sc, args.cache)
            config = vr.config_for(sc)
            seconds += float(t[-1] - t[0])
            bounded = [
                (k, m.name, config.model.operating_range[m.name])
                for k, m in enumerate(config.model.measurements)
                if m.name in config.model.operating_range
            ]
            state = stmmae.initial_state(config)
            step = max(1, int(round(BATCH_S * sc.sample_rate_hz)))
            for lo in range(0, len(t), step):
                batch = Batch(
                    t_s=t[lo : lo + step], channels={c: v[lo : lo + step] for c, v in ch.items()}
                )
                state, out = stmmae.step(config, state, batch)
                smoothed = stmmae.state_parts(config, state).operating
                for k, name, (low, high) in bounded:
                    scale = math.degrees(1.0) if name in ANGLES else 1.0
                    dev = abs(float(smoothed[k]) - 0.5 * (low + high)) * scale
                    worst[name] = max(worst.get(name, 0.0), dev)
                    half[name] = 0.5 * (high - low) * scale
                for w in out.health:
                    n = config.health_window_samples
                    outside += w.indicators["outside_operating_range_fraction"] * n
                    windowed += n
            print(f"  {sc.seed}: {len(t)} samples", file=sys.stderr, flush=True)
    print(f"{len(offsets) * args.flights} fault-free flights, {seconds / 3600.0:.2f} h")
    print(f"samples outside the operating range: {100.0 * outside / max(windowed, 1.0):.3f} %")
    print("| measurement | largest smoothed excursion | bound (half-width) |")
    print("|---|---|---|")
    for name, dev in worst.items():
        unit = "deg/s" if name in {"p", "q", "r"} else ("deg" if name in ANGLES else "m/s")
        print(f"| {name} | {dev:.2f} {unit} | {half[name]:.2f} {unit} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
