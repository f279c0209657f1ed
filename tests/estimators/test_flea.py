"""FLEA reader, and the FAKF on real FLEA runs (skipped when the data folder is absent)."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest

from estimators import fakf
from estimators.base import Batch
from estimators.flea import STAND_VOLTAGE_RAILS_V, FleaRun, driven_motor, list_runs, read_flea_run


def test_driven_motor() -> None:
    assert driven_motor("Nominal") == "Y"
    assert driven_motor("Position") == "Y"
    assert driven_motor("Jam") == "X"
    assert driven_motor("Spall") == "X"
    with pytest.raises(ValueError):
        driven_motor("Broken")


def _row(stamp: str, values: list[str]) -> str:
    return "\t".join([stamp, *values])


def test_reader_on_a_written_file(tmp_path: Path) -> None:
    cols = [f"{c:.1f}" for c in range(1, 20)]
    rows = []
    for k, stamp in enumerate(
        [
            "2010-09-03_23:59:59.98000_-0700",
            "2010-09-03_23:59:59.99000_-0700",
            "2010-09-04_00:00:00.00000_-0700",
        ]
    ):
        vals = list(cols)
        vals[6] = f"{10.0 + k}"  # col 7: motor X current
        vals[9] = "NaN" if k == 1 else f"{-5.0 - k}"  # col 10: motor X voltage
        rows.append(_row(stamp, vals))
    path = tmp_path / "BatchProfile_sine13_2010_09_03_23_59_59_Jam_Low.data.gz"
    with gzip.open(path, "wt") as fh:
        fh.write("\n".join(rows) + "\n")
    run = read_flea_run(path)
    assert run.name == "BatchProfile_sine13_2010_09_03_23_59_59_Jam_Low"
    assert (run.scenario, run.motor) == ("Jam", "X")
    np.testing.assert_allclose(run.t_s, [0.0, 0.01, 0.02], atol=1e-9)  # across midnight
    # 23:59:59.98 at UTC-7 is 06:59:59.98 UTC on 2010-09-04
    assert run.t0_epoch_s == pytest.approx(1283583599.98, abs=1e-6)
    np.testing.assert_array_equal(run.current_a, [10.0, 11.0, 12.0])
    np.testing.assert_array_equal(run.voltage_v, [-5.0, np.nan, -7.0])
    np.testing.assert_array_equal(run.load_lbs, [6.0, 6.0, 6.0])
    np.testing.assert_array_equal(run.motor_temperature_c, [13.0, 13.0, 13.0])  # col 13: motor X


def test_reader_refuses_a_short_row(tmp_path: Path) -> None:
    path = tmp_path / "BatchProfile_sine11_2010_09_03_09_51_40_Nominal_Low.data.gz"
    with gzip.open(path, "wt") as fh:
        fh.write("2010-09-03_09:51:41.00000_-0700\t1.0\t2.0\n")
    with pytest.raises(ValueError, match="20 columns"):
        read_flea_run(path)


@pytest.mark.flea
def test_index_and_runs_agree(flea_path: Path) -> None:
    entries = list_runs(flea_path)
    assert len(entries) >= 70
    for entry in entries[::9]:
        run = read_flea_run(entry.path)
        assert len(run) == entry.n_samples
        assert run.scenario == entry.scenario
        assert run.motor == entry.active_motor
        assert np.mean(run.load_lbs) == pytest.approx(entry.mean_measured_load, abs=0.01)
        assert run.t_s[0] == 0.0
        np.testing.assert_allclose(np.diff(run.t_s), 0.01, atol=1e-4)
        assert np.all(np.isfinite(run.current_a)) and np.all(np.isfinite(run.voltage_v))


@pytest.mark.flea
@pytest.mark.parametrize("scenario", ["Nominal", "Jam", "Spall"])
def test_fakf_on_real_runs_beats_the_model_only_estimate(flea_path: Path, scenario: str) -> None:
    entry = next(e for e in list_runs(flea_path) if e.scenario == scenario)
    run = read_flea_run(entry.path)
    config = fakf.parse_config({})
    _, out = fakf.step(
        config,
        fakf.initial_state(config),
        Batch(t_s=run.t_s, channels={"current": run.current_a, "voltage": run.voltage_v}),
    )
    assert out.events[0].kind == "identified"
    assert out.events[0].detail["max_pole_modulus"] < 1.0
    est, mod = out.samples["voltage_estimate"], out.samples["voltage_model"]
    valid = np.isfinite(est)
    assert valid.sum() == len(run) - 1000
    mae_fakf = np.mean(np.abs(est[valid] - run.voltage_v[valid]))
    mae_model = np.mean(np.abs(mod[valid] - run.voltage_v[valid]))
    # the README's first figure: model-only MAE 4-10 V, FAKF 40-60 % lower
    assert 3.0 < mae_model < 12.0
    assert mae_fakf < 0.65 * mae_model


def _feed(config: fakf.FakfConfig, run: FleaRun, batch_samples: int) -> tuple[list, list, dict]:
    """A run fed in batches of ``batch_samples``, the last one closing the run."""
    state = fakf.initial_state(config)
    health, events, est = [], [], []
    n = len(run)
    for lo in range(0, n, batch_samples):
        hi = min(lo + batch_samples, n)
        batch = Batch(
            t_s=run.t_s[lo:hi],
            channels={"current": run.current_a[lo:hi], "voltage": run.voltage_v[lo:hi]},
            end_of_run=hi == n,
        )
        state, out = fakf.step(config, state, batch)
        health.extend(out.health)
        events.extend(out.events)
        est.append(out.samples["voltage_estimate"])
    return health, events, {"voltage_estimate": np.concatenate(est)}


@pytest.mark.flea
def test_flea_trapezoid_jam_run_stays_within_the_stand_rails(flea_path: Path) -> None:
    entry = next(
        e
        for e in list_runs(flea_path)
        if e.path.name.startswith("BatchProfile_trap22_2010_09_03_16_01_40_Jam")
    )
    run = read_flea_run(entry.path)
    lo, hi = STAND_VOLTAGE_RAILS_V
    railed = fakf.parse_config({"voltage_rail_low_v": lo, "voltage_rail_high_v": hi})
    health, events, s = _feed(railed, run, 700)
    est = s["voltage_estimate"][np.isfinite(s["voltage_estimate"])]
    assert est.min() >= lo and est.max() <= hi
    assert sum(h.indicators["censored_samples"] for h in health) > 0
    # every sample of the closed run is in one window
    assert sum(h.n_samples for h in health) == len(run)
    # the first window after identification loses to persistence and the model is replaced
    assert "reidentified" in [e.kind for e in events]
    # without rails the estimate of this run goes far past the clip level
    _, _, s_plain = _feed(fakf.parse_config({}), run, 700)
    assert np.nanmax(np.abs(s_plain["voltage_estimate"])) > 30.0


@pytest.mark.flea
def test_flea_run_split_like_a_replay_gives_the_one_batch_windows(flea_path: Path) -> None:
    entry = next(e for e in list_runs(flea_path) if e.profile_shape == "sine")
    run = read_flea_run(entry.path)
    lo, hi = STAND_VOLTAGE_RAILS_V
    config = fakf.parse_config({"voltage_rail_low_v": lo, "voltage_rail_high_v": hi})
    one = _feed(config, run, len(run))
    split = _feed(config, run, 700)
    assert one[0] == split[0] and one[1] == split[1]
    np.testing.assert_array_equal(one[2]["voltage_estimate"], split[2]["voltage_estimate"])
    assert sum(h.n_samples for h in one[0]) == len(run)
    assert one[0][-1].n_samples == len(run) % 1000
