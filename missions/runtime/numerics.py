"""Reproducible floating point across x86-64 machines: one instruction set for every library
that rounds differently by CPU.

A run's numbers depend on the machine's CPU in their last bits, through three libraries that
choose code by CPU when they load:

* numba compiles fimnav's kernels for the host CPU (``NUMBA_CPU_NAME``, ``NUMBA_CPU_FEATURES``),
  and the range memory's sums are vectorised with reassociation
  (:mod:`planner.estimator.kernels.memory`): their order follows the vector width (4 doubles
  with AVX2, 8 with AVX-512 on CPUs whose compiler model prefers 512-bit vectors);
* OpenBLAS, under numpy and scipy (the estimator's eigen-decompositions through LAPACK), picks
  its kernels by CPU (``OPENBLAS_CORETYPE``);
* numpy dispatches its own loops (logarithms, ``atan2``, ``pow``) to AVX-512 versions where the
  CPU has them (``NPY_DISABLE_CPU_FEATURES``); they differ from the AVX2 ones by an ulp on a few
  per cent of arguments.

A study is deterministic on one machine whatever its number of workers. Across machines, one
step's estimates of bearing and joint swarms agree to about 1e-12 m, and their runs part only
after the safety filter or a keep-out first decides differently; ranging runs part within a few
steps: a range-only estimate from coplanar drones has two mirror-image solutions, and the last
bits decide which one an early step takes. Their statistics agree; a rare event such as a
keep-out crossing may come or go. :func:`pin_numerics` sets the
three libraries to one configuration that every x86-64 CPU with AVX2 and FMA runs the same way
(Intel since 2013, AMD since 2015): numba's ``haswell`` target, OpenBLAS's Haswell kernels, numpy
without its AVX-512 loops. The test suite runs pinned (``tests/__init__.py``), so that its
recorded references hold on any such machine; ``FIMNAV_NUMERICS=portable fimnav ...`` runs a
command pinned (:func:`missions.cli.main.main`), so that two machines of a cluster compute the
same trials bit for bit (its Dask workers need the same variables, docs/studies.md).

The libraries read these variables once, when they load: set them before numpy, scipy and
numba are imported. Nothing here imports them.
"""

from __future__ import annotations

import hashlib
import platform
from collections.abc import Mapping, MutableMapping
from pathlib import Path

#: The variable that asks a ``fimnav`` command for pinned numerics (value ``portable``).
NUMERICS_VARIABLE = "FIMNAV_NUMERICS"

#: numpy's names of its AVX-512 dispatch targets: numpy 2.4's feature groups and the older
#: releases' single features (numpy ignores a name it does not dispatch to).
NUMPY_AVX512 = "X86_V4 AVX512_ICL AVX512_SPR AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL"

#: What :func:`pin_numerics` sets: numba's target CPU (its features are that CPU's, hence the
#: empty feature string), OpenBLAS's kernel family and numpy's disabled dispatch targets.
PINNED: dict[str, str] = {
    "NUMBA_CPU_NAME": "haswell",
    "NUMBA_CPU_FEATURES": "",
    "OPENBLAS_CORETYPE": "Haswell",
    "NPY_DISABLE_CPU_FEATURES": NUMPY_AVX512,
}

#: The CPU flags (``/proc/cpuinfo``) of numba's ``haswell`` target: the pinned kernels use them
#: (``abm`` is Linux's name for ``lzcnt``).
REQUIRED_FLAGS = frozenset({"avx", "avx2", "fma", "f16c", "bmi1", "bmi2", "movbe", "popcnt", "abm"})


def _cpuinfo(cpuinfo: Path) -> dict[str, str]:
    """The first processor's fields in ``cpuinfo`` (Linux); empty where the file is absent."""
    try:
        text = cpuinfo.read_text(encoding="ascii", errors="replace")
    except OSError:
        return {}
    fields: dict[str, str] = {}
    for line in text.splitlines():
        if not line.strip():
            break  # the first processor's block ends
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    return fields


def cpu_flags(cpuinfo: Path = Path("/proc/cpuinfo")) -> frozenset[str]:
    """The first processor's flags in ``cpuinfo`` (Linux); empty where the file is absent or
    has none."""
    return frozenset(_cpuinfo(cpuinfo).get("flags", "").split())


def numerics_identity(environ: Mapping[str, str], cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """What sets a process's last bits besides its code and library versions: ``pinned`` where
    ``environ`` holds :data:`PINNED`, else ``host:`` the CPU's model and a digest of its flags
    (``cpuinfo``; the machine's architecture where the file is absent). Two processes of equal
    identity, code and libraries compute the same bits (:func:`missions.study.cluster.environment`)."""
    if is_pinned(environ):
        return "pinned"
    fields = _cpuinfo(cpuinfo)
    flags = fields.get("flags", "").split()
    model = fields.get("model name") or platform.machine() or "unknown CPU"
    digest = hashlib.sha256(" ".join(sorted(set(flags))).encode()).hexdigest()[:8] if flags else "no flags"
    return f"host: {model}, flags {digest}"


def why_not_pinnable(flags: frozenset[str] | None = None, machine: str | None = None) -> str | None:
    """``None`` where this machine runs the pinned configuration (an x86-64 CPU with AVX2 and
    FMA, read from Linux's ``/proc/cpuinfo``), else a one-line reason."""
    machine = machine or platform.machine()
    if machine.lower() not in ("x86_64", "amd64"):
        return f"pinned numerics need an x86-64 CPU with AVX2 and FMA; this machine is {machine}"
    flags = cpu_flags() if flags is None else flags
    missing = sorted(REQUIRED_FLAGS - flags)
    if missing:
        return f"pinned numerics need an x86-64 CPU with AVX2 and FMA; /proc/cpuinfo lacks {' '.join(missing)}"
    return None


def pin_numerics(environ: MutableMapping[str, str]) -> str | None:
    """Set :data:`PINNED` in ``environ`` (``os.environ``) where this machine can run it; return
    ``None`` then, else the reason it cannot (``environ`` unchanged). Values already set are
    replaced: a half-pinned configuration is no configuration. Has an effect on libraries loaded
    after the call only (and on the processes started with ``environ``)."""
    reason = why_not_pinnable()
    if reason is None:
        environ.update(PINNED)
    return reason


def pin_unless_host(environ: MutableMapping[str, str]) -> str | None:
    """:func:`pin_numerics`, unless :data:`NUMERICS_VARIABLE` is ``host`` (the test suite's and
    ``docs/regenerate.py``'s default is pinned): ``None`` where pinned, else why not."""
    if environ.get(NUMERICS_VARIABLE, "").strip() == "host":
        return f"{NUMERICS_VARIABLE}=host: this run uses the machine's own numerics"
    return pin_numerics(environ)


def is_pinned(environ: Mapping[str, str]) -> bool:
    """Whether ``environ`` holds every value of :data:`PINNED`."""
    return all(environ.get(name) == value for name, value in PINNED.items())


def apply_requested(environ: MutableMapping[str, str]) -> str | None:
    """Pin ``environ`` where :data:`NUMERICS_VARIABLE` asks for it (``portable``; ``host`` or
    unset: the libraries' own choices). Returns ``None``, or a one-line error naming the
    variable: an unknown value, or ``portable`` on a machine that cannot run it."""
    value = environ.get(NUMERICS_VARIABLE, "").strip()
    if value in ("", "host"):
        return None
    if value != "portable":
        return f"{NUMERICS_VARIABLE}={value!r}: expected 'portable' (one configuration on every x86-64 CPU with AVX2 and FMA) or 'host'"
    reason = pin_numerics(environ)
    return None if reason is None else f"{NUMERICS_VARIABLE}=portable: {reason}"
