"""The byte form of vector states (``estimators.base.dump_vector_state``)."""

from __future__ import annotations

import base64
import json

import numpy as np
import pytest

from estimators.base import EstimatorError, StateVersionError, dump_vector_state, load_vector_state

VALUES = np.array([0.0, -0.0, 1.0 / 3.0, -2.5e-310, 1.7e308, np.nan, np.inf, -np.inf, 1.7e9 + 0.01])


def test_vector_round_trips_bit_for_bit() -> None:
    blob = dump_vector_state("fakf", 3, 1.7e9 + 0.123, VALUES)
    t_last, vec = load_vector_state(blob, "fakf", 3, "a FAKF")
    assert t_last == 1.7e9 + 0.123
    assert vec.tobytes() == VALUES.astype("<f8").tobytes()  # -0.0, NaN and the subnormal included
    assert not vec.flags.writeable
    # Written as base64 of the little-endian float64 bytes (a seventh of a float.hex list's cost).
    assert base64.b64decode(json.loads(blob)["vector64"]) == VALUES.astype("<f8").tobytes()


def test_states_written_as_hex_lists_read_the_same() -> None:
    """States stored before the base64 form: the vector as ``float.hex`` strings."""
    old = json.dumps({"version": 3, "kind": "fakf", "t_last_s": (2.0).hex(),
                      "vector": [float(v).hex() for v in VALUES]}).encode()
    t_old, v_old = load_vector_state(old, "fakf", 3, "a FAKF")
    t_new, v_new = load_vector_state(dump_vector_state("fakf", 3, 2.0, VALUES), "fakf", 3, "a FAKF")
    assert t_old == t_new == 2.0
    assert v_old.tobytes() == v_new.tobytes()


@pytest.mark.parametrize("vector64", ["not base64!", "AAAA", 12])
def test_a_malformed_vector_is_refused(vector64: object) -> None:
    blob = json.dumps({"version": 3, "kind": "fakf", "t_last_s": (0.0).hex(), "vector64": vector64}).encode()
    with pytest.raises(EstimatorError, match="not a FAKF state"):
        load_vector_state(blob, "fakf", 3, "a FAKF")


def test_another_version_or_kind_is_refused() -> None:
    blob = dump_vector_state("fakf", 3, 0.0, VALUES)
    with pytest.raises(StateVersionError):
        load_vector_state(blob, "fakf", 4, "a FAKF")
    with pytest.raises(EstimatorError, match="kind"):
        load_vector_state(blob, "stmmae", 3, "an STMMAE")
