"""Instructions per sample of the deterioration EKF's compiled kernel, counted by callgrind.

The machine's timings are noisy (shared, 2 cores); instruction counts are not. Run:

    valgrind --tool=callgrind --instr-atstart=no --callgrind-out-file=/tmp/dekf.cg \
        .venv/bin/python bench/dekf_instructions.py ['{"noise_adaptation": false}']
    .venv/bin/python bench/dekf_instructions.py --report /tmp/dekf.cg

The bench's drive (300 s at 1 kHz, m = 0.0005, seed 1) is loaded, the defaults (alpha0 = 10, no
prognosis; the optional JSON argument overrides settings) run over its first 30,000 samples (the
plant-calibration segment), then the instrumentation is switched on (``callgrind_control -i
on``) for the kernel over the next 20,000 samples only; ``--report`` prints the count per
sample from callgrind's output file (the count includes the call from Python, a few
instructions per sample).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

from estimators import deterioration_ekf as de
from estimators.kernels import dekf_kernels as kern
from estimators.simulators.friction_drive import simulate_friction_drive

WARM = 30_000
COUNTED = 20_000


def report(path: str) -> None:
    """Instructions per counted sample from a callgrind output file."""
    with open(path) as f:
        for line in f:
            if line.startswith("totals:"):
                total = int(line.split()[1])
                print(f"{total / COUNTED:.1f} instructions per sample ({total} over {COUNTED})")
                return
    raise SystemExit(f"no totals in {path}")


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--report":
        report(sys.argv[2])
        return
    extra = json.loads(sys.argv[1]) if len(sys.argv) > 1 else {}
    n = WARM + COUNTED
    t, ch, _ = simulate_friction_drive(300.0, 1000.0, m=0.0005, seed=1)
    config = de.parse_config({"alpha0": 10.0, "rul_every_s": None, **extra})
    cfg = config.kernel_vector
    st = de.initial_state(config).vector.copy()
    cur, w1, w2 = ch["current"], ch["motor_speed"], ch["wheel_speed"]
    kern.ekf_batch(cfg, st, t[:WARM], cur[:WARM], w1[:WARM], w2[:WARM])
    part = [a[WARM:n].copy() for a in (t, cur, w1, w2)]
    pid = str(os.getpid())
    subprocess.run(["callgrind_control", "-i", "on", pid], check=True, capture_output=True)
    kern.ekf_batch(cfg, st, *part)
    subprocess.run(["callgrind_control", "-i", "off", pid], check=True, capture_output=True)


if __name__ == "__main__":
    main()
