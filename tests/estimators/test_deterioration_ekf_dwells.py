"""Deterioration EKF: the stream's dwell record of a random two-level load (the mean dwells
over the whole history instead of the ring's 30 s), its stationarity check, its independence
of the batch split and the version-4 state upgrade. Seeds differ from the validation
scripts' (20000+ and 0..)."""

from __future__ import annotations

import math

import numpy as np

from estimators import deterioration_ekf as de
from estimators import rul
from estimators.base import Batch
from estimators.kernels import dekf_kernels as kern
from estimators.simulators import friction_drive_scenarios as fs
from tests.estimators.conftest import upgraded_dekf_state

BIN_S = 0.02
RING_BINS = 1500  # 30 s


def _telegraph_bins(
    rng: np.random.Generator,
    duration_s: float,
    mean_dwell: tuple[float, float] | list[tuple[float, float, float]],
) -> np.ndarray:
    """Bin means (20 ms) of a telegraph between 0 A and 20 A with exponential dwells; a list
    of (t_from, mean_low, mean_high) changes the means at t_from."""
    laws = [(0.0, *mean_dwell)] if isinstance(mean_dwell, tuple) else mean_dwell
    edges = [0.0]
    level = [bool(rng.integers(2))]
    while edges[-1] < duration_s:
        law = [w for w in laws if w[0] <= edges[-1]][-1]
        edges.append(edges[-1] + rng.exponential(law[2] if level[-1] else law[1]))
        level.append(not level[-1])
    sub = 20
    fine = (np.arange(round(duration_s / BIN_S) * sub) + 0.5) * (BIN_S / sub)
    idx = np.searchsorted(np.array(edges), fine, side="right") - 1
    return np.where(np.array(level)[idx], 20.0, 0.0).reshape(-1, sub).mean(axis=1)


def _feed(
    currents: np.ndarray, every_bins: int, memory_s: float = 3600.0
) -> list[tuple[rul.DwellRecord, np.ndarray]]:
    """The record after each ring of RING_BINS bins ending every ``every_bins`` bins."""
    rec = rul.DwellRecord()
    out = []
    durations = np.full(RING_BINS, BIN_S)
    for end in range(RING_BINS, currents.shape[0] + 1, every_bins):
        ring = currents[end - RING_BINS : end]
        rec = rul.update_dwell_record(rec, durations, ring, end * BIN_S, 0.05, memory_s)
        out.append((rec, ring))
    return out


def test_record_knows_the_mean_cycle_far_better_than_the_ring() -> None:
    """Over 16 telegraphs (mean dwells 0.8 s and 1.2 s, 400 s each, rings of 30 s every 10 s),
    the record's mean cycle at the end is within its own sampling error of the truth and its
    error is under half the ring's alone; the ring's sampling error is honest too."""
    rng = np.random.default_rng(73_001)
    durations = np.full(RING_BINS, BIN_S)
    rec_err, ring_err, rec_z, ring_z = [], [], [], []
    for _ in range(16):
        cur = _telegraph_bins(rng, 400.0, (0.8, 1.2))
        rec, ring = _feed(cur, 500)[-1]
        with_rec = rul.dwell_load(durations, ring, 16, 0.05, rec)
        alone = rul.dwell_load(durations, ring, 16, 0.05)
        assert with_rec is not None and alone is not None
        assert with_rec.source == "record" and alone.source == "ring"
        for dl, err, z in ((with_rec, rec_err, rec_z), (alone, ring_err, ring_z)):
            e = math.log(dl.cycle_mean_s / 2.0)
            err.append(e)
            z.append(e / math.sqrt(dl.estimate_rel_var))
        assert with_rec.dwells[0] > 150  # switches out of the low level over ~400 s
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
    assert rms(rec_err) < 0.5 * rms(ring_err)
    assert rms(rec_err) < 0.08
    assert 0.5 < rms(rec_z) < 1.6
    assert rms(ring_z) < 2.0


def test_record_counts_each_bin_once_whatever_the_ring_overlap() -> None:
    """Rings every 2 s (overlapping by 28 s) and every 30 s (abutting) count the same
    switches and time at each level as one pass over the whole signal; rings every 45 s
    (gaps of 15 s) count only what the rings saw, the run across each gap censored."""
    rng = np.random.default_rng(73_002)
    cur = _telegraph_bins(rng, 300.0, (0.5, 1.0))
    whole = rul.record_dwells(
        rul.DwellRecord(), np.full(cur.shape[0], BIN_S), rul.bin_levels(np.full(cur.shape[0], BIN_S), cur, 0.05)[2],  # type: ignore[index]
        cur.shape[0] * BIN_S, math.inf,
    )  # fmt: skip
    for every in (100, 1500):
        rec = _feed(cur, every, memory_s=math.inf)[-1][0]
        np.testing.assert_allclose(rec.exposure_s, whole.exposure_s, rtol=1e-9)
        np.testing.assert_allclose(rec.switches, whole.switches)
        # the first ring's first run is censored in both; the rest agree
        np.testing.assert_allclose(rec.n, whole.n)
    gappy = _feed(cur, 2250, memory_s=math.inf)[-1][0]
    seen = sum(gappy.exposure_s)
    assert abs(seen - 30.0 * len(range(RING_BINS, cur.shape[0] + 1, 2250))) < 0.1
    assert gappy.n[0] < gappy.switches[0] and gappy.n[1] < gappy.switches[1]


def test_record_restarts_when_the_load_changes() -> None:
    """A telegraph whose mean dwells go from 0.4 s to 2 s at 300 s: the stationarity check
    restarts the record, whose mean cycle is then the new load's (4 s), not a mix of both
    (without the check it stays near the time-weighted mix, about 2 s)."""
    rng = np.random.default_rng(73_003)
    cur = _telegraph_bins(rng, 700.0, [(0.0, 0.4, 0.4), (300.0, 2.0, 2.0)])
    before = _feed(cur[:15_000], 500)[-1][0]
    assert before.restarts == 0.0
    rec, ring = _feed(cur, 500)[-1]
    assert rec.restarts >= 1.0
    mu = rec.mean_dwell(0) + rec.mean_dwell(1)
    assert 3.0 < mu < 5.5
    # the same feed without the check: the record mixes both loads
    durations = np.full(RING_BINS, BIN_S)
    mixed = rul.DwellRecord()
    for end in range(RING_BINS, cur.shape[0] + 1, 500):
        ring = cur[end - RING_BINS : end]
        share = rul.bin_levels(durations, ring, 0.05)[2]  # type: ignore[index]
        mixed = rul.record_dwells(mixed, durations, share, end * BIN_S, 3600.0)
    assert mixed.mean_dwell(0) + mixed.mean_dwell(1) < 2.8


def _telegraph_drive(
    seed: int, duration_s: float
) -> tuple[fs.Drive, np.ndarray, dict[str, np.ndarray]]:
    drive = fs.draw_drive(seed, rate_hz=100.0, load="telegraph", mismatch=False, skew=False)
    t, ch, _ = fs.telemetry(drive, duration_s)
    return drive, t, ch


def _config(drive: fs.Drive, record: bool = True) -> de.DekfConfig:
    load = {
        "kind": "observed",
        "bin_samples": 2,
        "bins": RING_BINS,
        "model": "dwells",
        "dwell_record": record,
    }
    return de.parse_config(
        {"alpha0": drive.alpha0, "rul_every_s": 10.0, "rul_trajectories": 50, "rul_load": load}
    )


def test_prognosis_uses_the_record_and_is_batch_split_invariant() -> None:
    """On a 100 Hz telegraph drive the prognoses after the first use the record (reported
    as the source, with more switches than the ring holds and a smaller sampling error than
    the ring's alone), and splitting the stream into batches at arbitrary samples gives the
    same prognoses and the same state."""
    drive, t, ch = _telegraph_drive(73_004, 95.0)
    cfg = _config(drive)
    state, out = de.step(cfg, de.initial_state(cfg), Batch(t_s=t, channels=ch))
    last = out.rul[-1].assumption["dwells"]
    assert isinstance(last, dict) and last["source"] == "record"
    _, alone = de.step(
        _config(drive, False), de.initial_state(_config(drive, False)), Batch(t_s=t, channels=ch)
    )
    ring_only = alone.rul[-1].assumption["dwells"]
    assert isinstance(ring_only, dict) and ring_only["source"] == "ring"
    assert sum(last["observed"].values()) > 1.5 * sum(ring_only["observed"].values())
    assert last["estimate_rel_std"] < 0.8 * ring_only["estimate_rel_std"]
    split_state = de.initial_state(cfg)
    split_rul = []
    for a, b in ((0, 1234), (1234, 4321), (4321, 7777), (7777, t.shape[0])):
        split_state, o = de.step(
            cfg, split_state, Batch(t_s=t[a:b], channels={k: v[a:b] for k, v in ch.items()})
        )
        split_rul.extend(o.rul)
    assert [(e.t_s, e.q50_s, e.q05_s) for e in split_rul] == [
        (e.t_s, e.q50_s, e.q05_s) for e in out.rul
    ]
    np.testing.assert_array_equal(
        split_state.vector[kern.ST_DW_T : kern.ST_RING], state.vector[kern.ST_DW_T : kern.ST_RING]
    )


def test_version_4_state_loads_and_steps() -> None:
    """Bytes dumped by the version-4 code (an observed dwell load, 40 s of a telegraph drive)
    load, upgrade to version 5 with the dwell record empty (the ring and the rest
    unchanged), and step on: the next prognosis starts the record from the ring."""
    state = upgraded_dekf_state(4)
    drive, t, ch = _telegraph_drive(73_005, 60.0)
    cfg = _config(drive)
    assert state.vector.shape[0] == kern.ST_BASE_LEN + 2 * RING_BINS
    assert np.isnan(state.vector[kern.ST_DW_T : kern.ST_DW_RUN + 1]).all()
    assert (state.vector[kern.ST_DW_EXPO : kern.ST_HIST_W] == 0.0).all()
    assert state.vector[kern.ST_OB_FILLED] == RING_BINS
    keep = t > state.t_last_s
    new_state, out = de.step(
        cfg, state, Batch(t_s=t[keep], channels={k: v[keep] for k, v in ch.items()})
    )
    assert out.rul and new_state.vector[kern.ST_DW_T] > state.t_last_s
    assert sum(new_state.vector[kern.ST_DW_SWITCH : kern.ST_DW_SWITCH + 2]) > 0.0


def test_record_shape_gives_the_wear_of_the_dwell_distribution() -> None:
    """At equal mean, the wear depends on the dwells' spread (regular dwells wear faster than
    exponential ones). Over 8 telegraphs (exponential dwells of mean 1 s, 300 s each), the
    time to failure of the period built with the record's histogram is within 6 % of that of
    the stratified true law on average, closer than with the ring's 30 s shape (scaled to the
    same mean), whose few dwells miss the long tail and shorten the life."""
    from estimators.simulators.friction_drive import FrictionDriveParams

    rng = np.random.default_rng(73_006)
    plant = FrictionDriveParams().as_array()
    durations = np.full(RING_BINS, BIN_S)
    x = np.array([[0.0, 0.0, 8.0, 0.005]])
    ell_f = math.log(5.0)
    pairs = 16
    q = (np.arange(pairs) + 0.5) / pairs
    ex = -np.log(1.0 - q)
    law_d = np.empty(2 * pairs)
    law_d[0::2] = ex[np.argsort(np.mod(np.arange(pairs) * 0.6180339887498949, 1.0))]
    law_d[1::2] = ex
    law_c = np.tile([0.0, 20.0], pairs)
    t_law = kern.rul_times(plant, law_d, law_c, x, ell_f, 1e7, 0.01, 0.25)[0]
    rec_err, ring_err = [], []
    for _ in range(8):
        cur = _telegraph_bins(rng, 300.0, (1.0, 1.0))
        rec, ring = _feed(cur, 500)[-1]
        with_rec = rul.dwell_load(durations, ring, pairs, 0.05, rec)
        assert with_rec is not None and with_rec.source == "record"
        # the ring's shape at the record's mean dwells: what the record replaces
        no_hist = rul.DwellRecord(**{**rec.__dict__, "hist": ((0.0,) * 40, (0.0,) * 40)})
        ring_shape = rul.dwell_load(durations, ring, pairs, 0.05, no_hist)
        assert ring_shape is not None
        for dl, err in ((with_rec, rec_err), (ring_shape, ring_err)):
            # both at the true mean cycle, so that only the shape differs
            d = dl.durations_s * (2.0 / dl.cycle_mean_s)
            t = kern.rul_times(plant, d, dl.currents_a, x, ell_f, 1e7, 0.01, 0.25)[0]
            err.append(t / t_law - 1.0)
    assert abs(np.mean(rec_err)) < 0.06
    assert np.mean(ring_err) < np.mean(rec_err) - 0.03
