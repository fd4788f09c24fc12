"""Pinned numerics (:mod:`missions.runtime.numerics`): the machine check on synthetic CPU flags,
``FIMNAV_NUMERICS`` as a command reads it (its errors one line, exit 2), and a real process
pinned by ``fimnav``'s entry point, asked what numba, numpy and both OpenBLAS libraries chose."""

from __future__ import annotations

import ctypes
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from missions.runtime.numerics import (
    NUMERICS_VARIABLE,
    PINNED,
    REQUIRED_FLAGS,
    apply_requested,
    cpu_flags,
    is_pinned,
    numerics_identity,
    why_not_pinnable,
)

ROOT = Path(__file__).resolve().parents[2]
HASWELL = frozenset({"fpu", "sse2", "avx", "avx2", "fma", "f16c", "bmi1", "bmi2", "movbe", "popcnt", "abm"})

#: fimnav's entry point on a command, then what each library chose: numba's target CPU, numpy's
#: AVX-512 dispatch, and the kernel family of numpy's and scipy's OpenBLAS (their own answer,
#: ``openblas_get_corename``).
SCRIPT = """
import contextlib, ctypes, io, json, os, pathlib, sys
from missions.cli.main import main
with contextlib.redirect_stdout(io.StringIO()):
    status = main(["missions", "list"])
import numpy, scipy
from numba.core import config
from numpy._core._multiarray_umath import __cpu_features__ as features

def corename(package, symbol):
    lib = next((pathlib.Path(package.__file__).parent.parent / (package.__name__ + ".libs")).glob("libscipy_openblas*.so"))
    get = getattr(ctypes.CDLL(str(lib)), symbol)
    get.restype = ctypes.c_char_p
    return get().decode()

print(json.dumps({
    "status": status,
    "numba_cpu": config.CPU_NAME,
    "numba_features": config.CPU_FEATURES,
    "numpy_avx512": bool(features.get("X86_V4") or features.get("AVX512_SKX")),
    "numpy_openblas": corename(numpy, "scipy_openblas_get_corename64_"),
    "scipy_openblas": corename(scipy, "scipy_openblas_get_corename"),
}))
"""

_NOT_PINNABLE = why_not_pinnable()


def run_command(extra: dict[str, str]) -> dict[str, object]:
    env = {k: v for k, v in os.environ.items() if k not in PINNED and k != NUMERICS_VARIABLE}
    env.update(extra, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    result: dict[str, object] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


def test_the_machine_check_reads_the_flags_it_needs(tmp_path: Path) -> None:
    assert why_not_pinnable(HASWELL, "x86_64") is None
    assert why_not_pinnable(HASWELL | {"avx512f"}, "AMD64") is None
    reason = why_not_pinnable(HASWELL - {"avx2", "fma"}, "x86_64")
    assert reason is not None and "avx2 fma" in reason and "\n" not in reason
    reason = why_not_pinnable(HASWELL, "aarch64")
    assert reason is not None and "aarch64" in reason
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: GenuineIntel\nflags\t\t: fpu sse2 avx avx2\n\nprocessor\t: 1\nflags\t\t: fpu\n")
    assert cpu_flags(info) == {"fpu", "sse2", "avx", "avx2"}
    assert cpu_flags(tmp_path / "absent") == frozenset()
    assert REQUIRED_FLAGS <= HASWELL


def test_the_identity_tells_pinned_from_each_cpu_kind(tmp_path: Path) -> None:
    """What a cluster compares (missions.study.cluster.environment): pinned whatever the CPU,
    else the CPU's model and flags, so that two kinds differ and one kind matches itself."""
    a, b = tmp_path / "a", tmp_path / "b"
    a.write_text("processor\t: 0\nmodel name\t: CPU One\nflags\t\t: fpu avx avx2\n")
    b.write_text("processor\t: 0\nmodel name\t: CPU One\nflags\t\t: fpu avx avx2 avx512f\n")
    assert numerics_identity(dict(PINNED), a) == numerics_identity(dict(PINNED), b) == "pinned"
    host_a, host_b = numerics_identity({}, a), numerics_identity({}, b)
    assert host_a.startswith("host: CPU One, flags ") and host_a != host_b
    assert numerics_identity({}, a) == host_a
    assert numerics_identity({**PINNED, "OPENBLAS_CORETYPE": "Zen"}, a) == host_a  # half pinned is not pinned
    assert numerics_identity({}, tmp_path / "absent").startswith("host: ")


def test_the_variable_is_read_as_documented() -> None:
    for unset in ({}, {NUMERICS_VARIABLE: "host"}, {NUMERICS_VARIABLE: " "}):
        environ = dict(unset)
        assert apply_requested(environ) is None
        assert environ == unset  # nothing pinned
    environ = {NUMERICS_VARIABLE: "fast"}
    problem = apply_requested(environ)
    assert problem is not None and NUMERICS_VARIABLE in problem and "'fast'" in problem and "portable" in problem
    assert environ == {NUMERICS_VARIABLE: "fast"}
    environ = {NUMERICS_VARIABLE: "portable", "NUMBA_CPU_NAME": "znver4"}
    problem = apply_requested(environ)
    if _NOT_PINNABLE is None:
        assert problem is None and is_pinned(environ)
    else:
        assert problem == f"{NUMERICS_VARIABLE}=portable: {_NOT_PINNABLE}" and environ["NUMBA_CPU_NAME"] == "znver4"


def test_a_bad_value_stops_a_command_with_one_line() -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT), **{NUMERICS_VARIABLE: "fast"})
    out = subprocess.run([sys.executable, "-m", "missions", "check", "paper/joint"], env=env, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    assert out.stdout == "" and out.stderr.count("\n") == 1 and NUMERICS_VARIABLE in out.stderr and "Traceback" not in out.stderr


@pytest.mark.skipif(_NOT_PINNABLE is not None, reason=_NOT_PINNABLE or "")
@pytest.mark.skipif(not Path("/proc/cpuinfo").exists(), reason="reads the CPU's flags in /proc/cpuinfo (Linux)")
def test_a_pinned_command_loads_every_library_pinned() -> None:
    pinned = run_command({NUMERICS_VARIABLE: "portable"})
    assert pinned == {
        "status": 0,
        "numba_cpu": "haswell",
        "numba_features": "",
        "numpy_avx512": False,
        "numpy_openblas": "Haswell",
        "scipy_openblas": "Haswell",
    }
    # The default leaves each library its own choice (on an AVX-512 machine numpy dispatches to
    # its AVX-512 loops there, which the pin turned off above).
    host = run_command({})
    assert host["status"] == 0 and host["numba_cpu"] is None and host["numba_features"] is None
    flags = cpu_flags()
    assert host["numpy_avx512"] == (
        "avx512f" in flags and "avx512bw" in flags and "avx512vl" in flags and "avx512dq" in flags and "avx512cd" in flags
    )


def test_the_suite_runs_pinned() -> None:
    """tests/__init__.py pins this process before numpy loads (or says why it cannot)."""
    from numba.core import config

    from tests import UNPINNED

    if UNPINNED is None:
        assert is_pinned(os.environ) and config.CPU_NAME == "haswell"
        get = ctypes.CDLL(
            str(next((Path(__import__("numpy").__file__).parent.parent / "numpy.libs").glob("libscipy_openblas*.so")))
        ).scipy_openblas_get_corename64_
        get.restype = ctypes.c_char_p
        assert get().decode() == "Haswell"
    elif os.environ.get(NUMERICS_VARIABLE) == "host":
        assert not is_pinned(os.environ) and config.CPU_NAME is None and NUMERICS_VARIABLE in UNPINNED
    else:
        assert why_not_pinnable() == UNPINNED
