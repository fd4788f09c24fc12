"""The real-flight benchmark reads a pickle from outside the project (untrusted input) with a
restricted unpickler: plain data, naive datetimes and float numpy scalars only; anything that
would call other code is refused before it runs."""

from __future__ import annotations

import datetime as dt
import importlib.util
import io
import os
import pickle
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "real_flight_afar.py"


@pytest.fixture(scope="module")
def afar() -> ModuleType:
    spec = importlib.util.spec_from_file_location("real_flight_afar", BENCH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["real_flight_afar"] = module
    spec.loader.exec_module(module)
    return module


def _read(afar: ModuleType, data: bytes) -> Any:
    return afar.RestrictedUnpickler(io.BytesIO(data)).load()


def test_the_runs_record_shape_is_read(afar: ModuleType) -> None:
    t = dt.datetime(2023, 12, 13, 12, 33, 7, 151042)
    records = [
        {"radio_timestamp": t, "position": [35.7, -78.6, 40.0], "Channel": np.float32(-16.878746), "Quality": np.float64(50.25), "moving": True}
    ]
    back = _read(afar, pickle.dumps(records, protocol=4))
    assert back[0]["radio_timestamp"] == t
    assert back[0]["position"] == [35.7, -78.6, 40.0]
    assert back[0]["Channel"] == pytest.approx(float(np.float32(-16.878746)), abs=0.0)
    assert back[0]["Quality"] == 50.25 and isinstance(back[0]["Quality"], float)


class _Evil:
    def __reduce__(self) -> tuple[Any, tuple[str]]:
        return (os.system, ("touch pwned",))


def test_a_pickle_that_calls_a_function_is_refused(afar: ModuleType, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(pickle.UnpicklingError, match="refused global"):
        _read(afar, pickle.dumps([_Evil()]))
    assert not (tmp_path / "pwned").exists()


def test_arrays_and_other_classes_are_refused(afar: ModuleType) -> None:
    with pytest.raises(pickle.UnpicklingError, match="refused global"):
        _read(afar, pickle.dumps(np.arange(3.0)))
    with pytest.raises(pickle.UnpicklingError, match="refused global"):
        _read(afar, pickle.dumps(dt.timezone.utc))
    with pytest.raises(pickle.UnpicklingError, match="float dtype"):
        _read(afar, pickle.dumps(np.int64(3)))
