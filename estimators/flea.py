"""Reader for the NASA FLEA low-rate runs (100 Hz test-stand files).

A run file is gzip-compressed, tab-separated text without a header, 20 columns (see
``columns.txt`` beside the data): 0 time stamp ``2010-09-03_09:51:41.01000_-0700``, 6 measured
load, 7-9 motor X/Y/Z current, 10-12 motor X/Y/Z voltage, ...; ``NaN`` marks an empty cell.

The driven motor depends on the scenario: X (current col. 7, voltage col. 10) for Jam and Spall
runs, Y (cols. 8, 11) for Nominal and Position runs.
"""

from __future__ import annotations

import csv
import gzip
import os
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

N_COLUMNS = 20
COL_TIME = 0
COL_MEASURED_LOAD = 6
CURRENT_COLUMN = {"X": 7, "Y": 8, "Z": 9}
VOLTAGE_COLUMN = {"X": 10, "Y": 11, "Z": 12}
MOTOR_TEMPERATURE_COLUMN = {"X": 13, "Y": 14, "Z": 15}
SCENARIOS = ("Nominal", "Jam", "Spall", "Position")
STAND_VOLTAGE_RAILS_V = (-25.0, 23.2)
"""Voltage rails of the FLEA low-rate runs for the FAKF (``voltage_rail_low_v``,
``voltage_rail_high_v``). The measured motor voltage clips near -25.3 / +23.9 V on motor X and
-26.0 / +23.5 V on motor Y, the clipped values scattering by a few tenths of a volt around the
level; the rails sit inside both motors' clip levels, so every clipped sample is censored (a
few unclipped samples within half a volt of the clip are censored with them)."""


@dataclass(frozen=True)
class FleaRun:
    """One FLEA run, driven motor only.

    Attributes:
        name: file name without ``.data.gz``.
        scenario: "Nominal", "Jam", "Spall" or "Position".
        motor: driven motor, "X" or "Y".
        t0_epoch_s: absolute time of the first sample, POSIX seconds (UTC).
        t_s: sample times from the run start, seconds, shape (n,).
        current_a: driven motor current, shape (n,).
        voltage_v: driven motor voltage, shape (n,).
        load_lbs: measured load, shape (n,).
        motor_temperature_c: driven motor temperature (deg C, the likely unit), shape (n,).
    """

    name: str
    scenario: str
    motor: str
    t0_epoch_s: float
    t_s: FloatArray
    current_a: FloatArray
    voltage_v: FloatArray
    load_lbs: FloatArray
    motor_temperature_c: FloatArray

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


@dataclass(frozen=True)
class FleaIndexEntry:
    """One row of ``index.csv``.

    Attributes:
        path: absolute path of the run file.
        scenario: scenario name.
        profile_shape: "sine" or "trap".
        n_samples: rows in the file.
        active_motor: driven motor.
        mean_measured_load: mean of the measured load, lbs.
    """

    path: Path
    scenario: str
    profile_shape: str
    n_samples: int
    active_motor: str
    mean_measured_load: float


def flea_dir() -> Path:
    """The FLEA data folder: ``$FLEETHEALTH_FLEA_DIR`` or ``<repo>/../shared/data/flea``."""
    default = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "flea"
    return Path(os.environ.get("FLEETHEALTH_FLEA_DIR", str(default)))


def driven_motor(scenario: str) -> str:
    """The motor driven in a scenario: "X" for Jam and Spall, "Y" for Nominal and Position."""
    if scenario in ("Jam", "Spall"):
        return "X"
    if scenario in ("Nominal", "Position"):
        return "Y"
    raise ValueError(f"unknown FLEA scenario {scenario!r}; expected one of {SCENARIOS}")


def scenario_from_name(name: str) -> str:
    """The scenario written in a run's file name (``..._<Scenario>_Low``)."""
    for scenario in SCENARIOS:
        if f"_{scenario}_" in name:
            return scenario
    raise ValueError(f"no known scenario in FLEA run name {name!r}")


def _parse_time_s(stamps: list[str]) -> tuple[float, FloatArray]:
    """Time stamps ``YYYY-MM-DD_HH:MM:SS.fffff_+zzzz`` -> (epoch of the first, offsets in s).

    The date and zone part is parsed once per distinct value; the clock part by slicing, which is
    much faster than ``strptime`` on every row.
    """
    day_epoch: dict[tuple[str, str], float] = {}
    first_day: float | None = None
    out = np.empty(len(stamps), dtype=np.float64)
    for i, stamp in enumerate(stamps):
        date, clock, zone = stamp.split("_")
        key = (date, zone)
        base = day_epoch.get(key)
        if base is None:
            base = datetime.strptime(f"{date} {zone}", "%Y-%m-%d %z").timestamp()
            day_epoch[key] = base
        if first_day is None:
            first_day = base
        hours, minutes, seconds = clock.split(":")
        # Offsets from the first day's midnight keep 1e-12 s resolution (epoch values would not).
        out[i] = (base - first_day) + int(hours) * 3600.0 + int(minutes) * 60.0 + float(seconds)
    assert first_day is not None
    t_first = float(out[0])
    return first_day + t_first, out - t_first


def read_flea_run(path: str | os.PathLike[str]) -> FleaRun:
    """Read one run file (``.data.gz`` or plain text) and keep the driven motor's channels.

    Raises:
        ValueError: the file has no rows or a row without 20 columns.
    """
    p = Path(path)
    opener = gzip.open if p.suffix == ".gz" else open
    with opener(p, "rt", encoding="ascii") as fh:
        lines = fh.read().splitlines()
    rows = [line.split("\t") for line in lines if line]
    if not rows:
        raise ValueError(f"{p}: empty FLEA run file")
    for lineno, row in enumerate(rows, start=1):
        if len(row) != N_COLUMNS:
            raise ValueError(f"{p}:{lineno}: expected {N_COLUMNS} columns, got {len(row)}")
    name = p.name.removesuffix(".gz").removesuffix(".data")
    scenario = scenario_from_name(name)
    motor = driven_motor(scenario)
    t0, t_s = _parse_time_s([row[COL_TIME] for row in rows])
    c_i, c_v = CURRENT_COLUMN[motor], VOLTAGE_COLUMN[motor]
    # float() reads "NaN" as nan, so missing cells stay missing samples.
    c_temp = MOTOR_TEMPERATURE_COLUMN[motor]
    values = np.array(
        [(row[c_i], row[c_v], row[COL_MEASURED_LOAD], row[c_temp]) for row in rows],
        dtype=np.float64,
    )
    return FleaRun(
        name=name,
        scenario=scenario,
        motor=motor,
        t0_epoch_s=t0,
        t_s=t_s,
        current_a=np.ascontiguousarray(values[:, 0]),
        voltage_v=np.ascontiguousarray(values[:, 1]),
        load_lbs=np.ascontiguousarray(values[:, 2]),
        motor_temperature_c=np.ascontiguousarray(values[:, 3]),
    )


def list_runs(directory: Path | None = None) -> list[FleaIndexEntry]:
    """The runs listed in ``index.csv`` of the FLEA folder, in file order."""
    base = flea_dir() if directory is None else directory
    entries: list[FleaIndexEntry] = []
    with open(base / "index.csv", newline="", encoding="utf-8") as fh:
        for rec in csv.DictReader(fh):
            entries.append(
                FleaIndexEntry(
                    path=base / rec["path"],
                    scenario=rec["scenario"],
                    profile_shape=rec["profile_shape"],
                    n_samples=int(rec["n_samples"]),
                    active_motor=rec["active_motor"],
                    mean_measured_load=float(rec["mean_measured_load"]),
                )
            )
    return entries
