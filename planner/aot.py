"""The compiled kernels built ahead of time into extension modules, loaded without numba's compiler.

numba compiles the kernels (:mod:`planner.kernels`, :mod:`planner.estimator.kernels.update`,
:mod:`planner.sim_kernels`) on first use and caches them, but loading a cached kernel still
starts numba's compiler in the process (its registries, its typing, the link of each kernel):
about a second of every command that plans or estimates. Here the same kernel functions are
compiled once by numba's ahead-of-time compiler (``numba.pycc``, :mod:`planner.aot_build`) into
one extension module per group, for the machine's own CPU and its features, exactly as numba's
JIT compiles them (the same machine code choices: a run is bit-identical either way), with the
argument types of :mod:`planner.aot_signatures` (written by
:mod:`missions.study.kernel_signatures`). A kernel module then binds its entry kernels to the
module's functions at import (:func:`bind`): a call goes straight to the compiled code. An
argument of another type than the recorded one (a caller off the common path) goes to the JIT
kernel, which compiles or loads that version as before.

An extension module is keyed by everything its code depends on: the source of the kernel module
and of the ``planner`` modules it imports, numba's, numpy's and Python's versions (the module is
compiled against numpy's C interface), the CPU name and
features numba compiles for (``NUMBA_CPU_NAME``, ``NUMBA_CPU_FEATURES`` or the host's). An edit
of the source, an upgrade or another CPU (a home directory shared by a cluster's nodes) finds no
module and builds its own. They live in ``$FIMNAV_AOT_DIR`` when that variable is set, else in
``$NUMBA_CACHE_DIR/fimnav-aot`` when that one is, else in ``planner/__pycache__/aot`` of the
installed package when it can be written, else in ``$XDG_CACHE_HOME/fimnav/aot``
(``~/.cache/fimnav/aot``). A wheel built on the machine that installs it (``pip install .``)
carries its modules in that package directory already (``setup.py``,
:func:`planner.aot_build.build_for_install`): the first command builds nothing. A module is
marked used when it is loaded (its modification time, renewed at most once a day); a build
removes its group's modules of other keys that were not used for 30 days
(:func:`planner.aot_build.remove_unused_modules`), so edits and upgrades do not pile them up,
while the modules of other CPUs still in use in a shared directory stay.

The build needs a C compiler (numba.pycc compiles a small C wrapper) and, on Python 3.12 or
later, setuptools; without them :func:`planner.aot_build.build` raises
:class:`planner.aot_build.BuildError`, the reason is recorded (:func:`failed`) and the kernels
are the JIT's, as before. ``FIMNAV_AOT=0`` turns the extension modules off (the JIT kernels
only: for a debugger, or to compare).
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import importlib.machinery
import importlib.util
import os
import re
import sys
import time
from collections.abc import Callable, MutableMapping
from pathlib import Path
from types import ModuleType
from typing import Any

#: The groups of entry kernels, each built into one extension module: group → (kernel module,
#: its entry kernels built ahead of time). The planning group takes most of the build.
GROUPS: dict[str, tuple[str, tuple[str, ...]]] = {
    "planning": (
        "planner.kernels",
        ("plan_batch", "policy_batch", "small_batch", "distances_batch", "fim_batch", "invert_batch"),
    ),
    "estimator": ("planner.estimator.kernels.update", ("update_batch",)),
    "simulator": (
        "planner.sim_kernels",
        (
            "line_of_sight",
            "hop_counts",
            "update_saved_steps",
            "gather_view",
            "gather_new_records",
            "nearest_peer_distance",
            "same_views",
            "position_error_bounds",
        ),
    ),
}

#: The groups whose kernels call LAPACK (the estimator's ``eigh`` and ``eigvalsh``): loading one
#: loads scipy's LAPACK bindings too (:func:`preload_lapack`).
LAPACK_GROUPS: frozenset[str] = frozenset({"estimator"})

_PLANNER = Path(__file__).resolve().parent
_IMPORT = re.compile(r"^\s*(?:from\s+(planner[\w.]*)\s+import\s+([\w\s,()]+)|import\s+(planner[\w.]*))", re.MULTILINE)


def enabled() -> bool:
    """Whether the extension modules are used (``FIMNAV_AOT`` is not ``0``)."""
    return os.environ.get("FIMNAV_AOT", "1").strip() != "0"


def _module_file(name: str) -> Path | None:
    """The source file of ``planner`` module ``name`` (a package's ``__init__.py``), or None."""
    parts = name.split(".")[1:]
    base = _PLANNER.joinpath(*parts)
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def sources(module: str) -> list[Path]:
    """The source files a kernel module's compiled code depends on: its own and those of the
    ``planner`` modules it imports, transitively (read from its import statements, without
    importing anything), sorted."""
    seen: dict[Path, None] = {}
    todo = [module]
    while todo:
        name = todo.pop()
        # Neither the package's __init__ nor this module (the binding) is compiled code.
        path = _module_file(name) if name not in ("planner", __name__) else None
        if path is None or path in seen:
            continue
        seen[path] = None
        for m in _IMPORT.finditer(path.read_text(encoding="utf-8")):
            if m.group(3):
                todo.append(m.group(3))
                continue
            todo.append(m.group(1))
            # a name imported may be a submodule
            todo.extend(f"{m.group(1)}.{imported}" for imported in re.split(r"[\s,()]+", m.group(2)) if imported.isidentifier())
    return sorted(seen)


def jit_cpu() -> tuple[str, str]:
    """The CPU name and features numba's JIT compiles for (its environment variables, else the
    host's)."""
    from numba.core import codegen, config

    settings: Any = config  # set from the environment at numba's import
    name = settings.CPU_NAME or codegen.ll.get_host_cpu_name()
    features = settings.CPU_FEATURES if settings.CPU_FEATURES is not None else codegen.get_host_cpu_features()
    return str(name), str(features)


@functools.cache
def key(group: str) -> str:
    """The key of ``group``'s extension module: a digest of its sources (:func:`sources`),
    numba's, numpy's and Python's versions and the CPU (:func:`jit_cpu`). Computed once per process (the
    kernels a process runs are the sources it imported)."""
    import numba
    import numpy

    module = GROUPS[group][0]
    h = hashlib.sha256()
    for part in (group, numba.__version__, numpy.__version__, sys.version, *jit_cpu(), repr(GROUPS[group][1])):
        h.update(part.encode())
        h.update(b"\0")
    for path in [*sources(module), _PLANNER / "aot.py", _PLANNER / "aot_signatures.py"]:
        h.update(path.relative_to(_PLANNER).as_posix().encode())
        h.update(b"\0")
        h.update(path.read_bytes())
    return h.hexdigest()[:20]


def directory() -> Path:
    """Where the extension modules are kept (see the module's documentation): the package's
    own ``__pycache__/aot`` when it exists or can be made and is writable."""
    chosen = os.environ.get("FIMNAV_AOT_DIR")
    if chosen:
        return Path(chosen)
    cache = os.environ.get("NUMBA_CACHE_DIR")
    if cache:
        return Path(cache) / "fimnav-aot"
    local = _PLANNER / "__pycache__" / "aot"
    nearest = next(p for p in (local, local.parent, _PLANNER) if p.exists())
    if nearest.is_dir() and os.access(nearest, os.W_OK):
        return local
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "fimnav" / "aot"


def module_name(group: str) -> str:
    """The extension module's name (its file is this name and the platform's suffix)."""
    return f"fimnav_aot_{group}_{key(group)}"


def path(group: str) -> Path:
    """The extension module's file for the current sources, CPU and versions."""
    return directory() / (module_name(group) + importlib.machinery.EXTENSION_SUFFIXES[0])


def load(group: str) -> ModuleType | None:
    """``group``'s extension module, or None when it is turned off, not built, or cannot be
    loaded."""
    if not enabled():
        return None
    try:
        name = module_name(group)
        if name in sys.modules:
            return sys.modules[name]
        file = path(group)
        if not file.is_file():
            return None
        spec = importlib.util.spec_from_file_location(name, file)
        if spec is None or spec.loader is None:
            return None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except Exception:  # a damaged or foreign file: the JIT kernels
        return None
    sys.modules[name] = module
    mark_used(file)
    if group in LAPACK_GROUPS:
        preload_lapack()
    return module


#: The module of scipy's LAPACK bindings that numba's LAPACK helpers look their functions up in.
LAPACK_MODULE: str = "scipy.linalg.cython_lapack"


def preload_lapack() -> bool:
    """Load scipy's LAPACK bindings (:data:`LAPACK_MODULE`, which a built kernel's ``eigh`` and
    ``eigvalsh`` reach through numba's helpers: they import it by name at their first call)
    from its file, without running ``scipy.linalg``'s package (about 0.2 s of a command's start
    that the kernels do not use: it imports scipy's whole linear algebra, numpy's test tools and
    unittest). The import system then finds it loaded: ``import scipy.linalg.cython_lapack`` and
    ``from scipy.linalg import cython_lapack`` give the same module, also after a later ``import
    scipy.linalg`` (whose package then has no ``cython_lapack`` attribute of its own: reach the
    module by one of those imports). Returns whether it is loaded (True at once when it is
    already); nothing is done (False) where scipy.linalg is imported without it or scipy's file
    is not where scipy keeps it, and the helpers then import it the usual way.
    """
    if LAPACK_MODULE in sys.modules:
        return True
    if "scipy.linalg" in sys.modules:
        return False
    try:
        scipy = importlib.util.find_spec("scipy")
        if scipy is None or not scipy.submodule_search_locations:
            return False
        file = Path(next(iter(scipy.submodule_search_locations))) / "linalg" / ("cython_lapack" + importlib.machinery.EXTENSION_SUFFIXES[0])
        spec = importlib.util.spec_from_file_location(LAPACK_MODULE, file) if file.is_file() else None
        if spec is None or spec.loader is None:
            return False
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except Exception:  # another layout of scipy: imported the usual way when first used
        return False
    sys.modules[LAPACK_MODULE] = module
    return True


#: A module not loaded for this long (seconds) is removed by the next build in its directory
#: (:func:`planner.aot_build.build`): one of earlier sources or versions, left by an edit or an
#: upgrade. A module in use has its modification time renewed at most once a day (:func:`mark_used`).
UNUSED_MODULE_S: float = 30 * 86400.0
#: How old (seconds) a loaded module's modification time may be before :func:`mark_used` renews it.
USE_MARK_S: float = 86400.0


def mark_used(file: Path) -> None:
    """Record that ``file`` (an extension module) was loaded now: its modification time is set to
    now when it is more than :data:`USE_MARK_S` old (a directory that cannot be written is left
    as it is). Modules of other CPUs sharing a directory (the nodes of a cluster on one install)
    keep their own mark and are not removed while their nodes use them."""
    try:
        if time.time() - file.stat().st_mtime > USE_MARK_S:
            os.utime(file)
    except OSError:
        pass


class Entry:
    """An entry kernel bound to its ahead-of-time version: a call whose arguments are of the
    recorded types (``accepts``, checked before the call: the compiled function itself does not
    check them) runs the compiled function, any other the JIT kernel ``jit``, which compiles
    or loads a version for them as numba does. The check runs once per combination of argument
    types, which later calls recognise by numba's own type fingerprints of their arguments (its
    dispatcher's fast path, in C)."""

    def __init__(self, compiled: Callable[..., Any], jit: Any, accepts: Callable[[tuple[Any, ...]], bool]) -> None:
        from numba._dispatcher import compute_fingerprint

        self.compiled = compiled
        self.jit = jit
        self.accepts = accepts
        self.__name__ = getattr(jit, "__name__", "kernel")
        self.__doc__ = getattr(jit, "__doc__", None)
        self.py_func = getattr(jit, "py_func", None)
        self._fingerprint = compute_fingerprint
        self._accepted: set[tuple[Any, ...]] = set()

    def _key(self, args: tuple[Any, ...]) -> tuple[Any, ...] | None:
        """The types of ``args`` as numba's fingerprints (a value without one by its Python
        type); None when an array has none (then every call is checked in full)."""
        key: list[Any] = []
        for a in args:
            try:
                key.append(self._fingerprint(a))
            except Exception:  # no fingerprint: an unusual array (checked in full), or another kind of value
                if hasattr(a, "__array_interface__") or isinstance(a, tuple):
                    return None
                key.append(type(a))
        return tuple(key)

    def __call__(self, *args: Any) -> Any:
        key = self._key(args)
        if key is not None and key in self._accepted:
            return self.compiled(*args)
        if self.accepts(args):
            if key is not None:
                self._accepted.add(key)
            return self.compiled(*args)
        return self.jit(*args)


@functools.cache
def checker(t: Any) -> Callable[[Any], bool]:
    """A check that a Python value is of numba type ``t`` as numba's ``typeof`` would type it
    (for the kinds of :func:`expression`): an array of that dtype, dimension, layout, aligned and
    writeable unless ``t`` is read-only; a tuple of that length whose items check; a bool, an
    integer or a float of that width (Python's own or numpy's). One check per type (numba's
    types are interned), made on first use.

    Raises:
        ValueError: a kind of type the signatures do not use.
    """
    import numpy as np
    from numba.core import types as nbtypes

    if isinstance(t, nbtypes.Array):
        dtype, ndim, layout, writeable = np.dtype(str(t.dtype) if str(t.dtype) != "bool" else "bool"), t.ndim, t.layout, t.mutable

        def array(x: Any) -> bool:
            if type(x) is not np.ndarray or x.dtype != dtype or x.ndim != ndim or not x.flags.aligned:
                return False
            if (layout == "C" and not x.flags.c_contiguous) or (layout == "F" and not x.flags.f_contiguous):
                return False
            return bool(x.flags.writeable or not writeable)

        return array
    if isinstance(t, nbtypes.BaseTuple):
        items = [checker(x) for x in t.types]  # type: ignore[attr-defined]

        def tuple_(x: Any) -> bool:
            return type(x) is tuple and len(x) == len(items) and all(c(v) for c, v in zip(items, x))

        return tuple_
    if isinstance(t, nbtypes.Boolean):
        return lambda x: type(x) in (bool, np.bool_)
    if isinstance(t, nbtypes.Integer):
        exact = np.dtype(str(t)).type
        return lambda x: type(x) is exact or (type(x) is int and str(t) == "int64")
    if isinstance(t, nbtypes.Float):
        exact = np.dtype(str(t)).type
        return lambda x: type(x) is exact or (type(x) is float and str(t) == "float64")
    raise ValueError(f"no check for numba type {t!r}")


def parse_signature(text: str) -> Any:
    """A recorded signature (:mod:`planner.aot_signatures`, the text of
    :func:`signature_expression`) as numba's signature."""
    from numba.core import types as nbtypes
    from numba.core.typing import signature

    namespace = {name: getattr(nbtypes, name) for name in dir(nbtypes) if not name.startswith("_")} | {"signature": signature}
    return eval(text, {"__builtins__": {}}, namespace)  # our own, fixed text


def _accepts(text: str) -> Callable[[tuple[Any, ...]], bool]:
    """The argument check of a recorded signature (:mod:`planner.aot_signatures`)."""
    checks = [checker(a) for a in parse_signature(text).args]

    def accepts(args: tuple[Any, ...]) -> bool:
        return len(args) == len(checks) and all(c(a) for c, a in zip(checks, args))

    return accepts


def jit_kernel(kernel: Any) -> Any:
    """The JIT dispatcher behind ``kernel`` (itself when it is not bound)."""
    return kernel.jit if isinstance(kernel, Entry) else kernel


def bind(group: str, namespace: MutableMapping[str, Any]) -> bool:
    """Bind the entry kernels of ``group`` in ``namespace`` (the kernel module's globals) to its
    extension module when there is one; returns whether they are bound. Called by each kernel
    module at its import, and again by :func:`bind_built` once a build is done. A kernel bound to
    this very module already keeps its binding (and the argument types it has accepted), and a
    name that holds neither a JIT kernel nor a binding (a caller's stand-in) is left as it is."""
    module = load(group)
    if module is None:
        return False
    from planner.aot_signatures import SIGNATURES

    for name in GROUPS[group][1]:
        compiled = getattr(module, name, None)
        if compiled is None or name not in namespace:
            continue
        current = namespace[name]
        if isinstance(current, Entry) and current.compiled is compiled:
            continue
        if not isinstance(current, Entry) and not hasattr(current, "py_func"):
            continue
        namespace[name] = Entry(compiled, jit_kernel(current), _accepts(SIGNATURES[name]))
    return True


def bind_built() -> None:
    """Bind every group whose kernel module is imported already (after a build)."""
    for group, (module, _) in GROUPS.items():
        if module in sys.modules:
            bind(group, vars(sys.modules[module]))


def missing() -> list[str]:
    """The groups with no extension module for the current sources (all of them when the
    modules are turned off: then nothing is built either)."""
    return [g for g in GROUPS if not enabled() or not path(g).is_file()]


def expression(t: Any) -> str:
    """A numba type as the Python expression that makes it in the namespace of
    ``numba.core.types`` (the text of :mod:`planner.aot_signatures`).

    Raises:
        ValueError: a kind of type the signatures do not use.
    """
    from numba.core import types as nbtypes

    if isinstance(t, nbtypes.Array):
        ro = ", readonly=True" if not t.mutable else ""
        return f"Array({expression(t.dtype)}, {t.ndim}, {t.layout!r}{ro})"
    if isinstance(t, nbtypes.UniTuple):
        return f"UniTuple({expression(t.dtype)}, {t.count})"
    if isinstance(t, nbtypes.Tuple):
        return "Tuple((" + "".join(expression(x) + ", " for x in t.types) + "))"
    if isinstance(t, (nbtypes.Boolean, nbtypes.Integer, nbtypes.Float)):
        return str(t) if str(t) != "bool" else "boolean"
    raise ValueError(f"no expression for numba type {t!r}")


def signature_expression(sig: Any) -> str:
    """A numba signature as an expression (:func:`expression`): ``none(arg, ...)``-style calls
    of the return type, or ``signature(...)`` when the return type is not callable."""
    args = ", ".join(expression(a) for a in sig.args)
    ret = sig.return_type
    from numba.core import types as nbtypes

    if isinstance(ret, nbtypes.NoneType):
        return f"none({args})"
    return f"signature({expression(ret)}, {args})"


def failure_file(group: str) -> Path:
    """Where a failed build of ``group`` leaves its reason (same key as the module)."""
    return directory() / (module_name(group) + ".failed")


def failed() -> dict[str, str]:
    """The groups whose build failed for the current sources, CPU and versions, with the
    reason: they are the JIT's (a new key, e.g. after an upgrade, tries again; so does
    :func:`planner.aot_build.build_or_record` when called directly, as ``fimnav compile`` does)."""
    out = {}
    for group in GROUPS:
        try:
            out[group] = failure_file(group).read_text(encoding="utf-8").strip()
        except OSError:
            continue
    return out


def forget_failure(group: str) -> None:
    """Forget that ``group``'s build failed (the next :func:`planner.warm.compile_aside` tries
    again)."""
    try:
        failure_file(group).unlink(missing_ok=True)
    except OSError:
        pass


__all__ = [
    "GROUPS",
    "LAPACK_GROUPS",
    "LAPACK_MODULE",
    "UNUSED_MODULE_S",
    "USE_MARK_S",
    "Entry",
    "bind",
    "bind_built",
    "checker",
    "directory",
    "enabled",
    "expression",
    "failed",
    "failure_file",
    "forget_failure",
    "jit_cpu",
    "jit_kernel",
    "key",
    "load",
    "mark_used",
    "missing",
    "parse_signature",
    "path",
    "preload_lapack",
    "signature_expression",
    "sources",
]
