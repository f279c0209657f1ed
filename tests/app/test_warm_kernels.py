"""No request pays a compile: after start-up warm-up, applying batches adds no kernel signature."""

from __future__ import annotations

import importlib
import pkgutil

from numba.core.registry import CPUDispatcher

import estimators.kernels
from tests.app.conftest import Api
from tests.conftest import make_series


def _signatures() -> dict[str, int]:
    out: dict[str, int] = {}
    for info in pkgutil.iter_modules(estimators.kernels.__path__):
        mod = importlib.import_module(f"estimators.kernels.{info.name}")
        for name, obj in vars(mod).items():
            if isinstance(obj, CPUDispatcher):
                out[f"{info.name}.{name}"] = len(obj.signatures)
    return out


def test_applying_batches_compiles_nothing_new(api: Api) -> None:
    assert api.app.state.kernels_warm.wait(120)
    before = _signatures()
    assert any(before.values()), "warm-up compiled no kernel"
    api.setup_actuator()
    s = make_series(1500, seed=3)
    s.voltage[700:705] = float("nan")
    for k, (a, b) in enumerate([(0, 1), (1, 900), (900, 1500)]):
        r = api.send_arrow("N1", "ema1", f"w{k}", s.t_s[a:b], {"current": s.current[a:b], "voltage": s.voltage[a:b]})
        assert r.status_code == 202
    assert api.health()["last_applied_seq"] == 3
    assert _signatures() == before


def test_each_fakf_kernel_is_compiled_for_one_signature() -> None:
    """numba compiles a kernel once per distinct argument types, and a constant integer
    argument (an offset such as 0 or a layout index) is typed as its own literal: the kernels
    take views of their blocks instead, so the whole-array entry (``identify_arx``), the warm-up
    and the streaming kernel all use one compiled version of each."""
    from app.kernels import warm_kind
    from estimators import fakf
    from estimators.kernels import fakf_kernels

    warm_kind("fakf")
    s = make_series(600, seed=8)
    fakf.identify_arx(s.current, s.voltage)
    counts = {
        name: len(obj.signatures)
        for name, obj in vars(fakf_kernels).items()
        if isinstance(obj, CPUDispatcher) and obj.signatures
    }
    assert counts and all(n == 1 for n in counts.values()), counts
