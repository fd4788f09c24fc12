"""planner.aot: the kernels built ahead of time compute what numba's JIT kernels compute, bit
for bit; an argument of another type goes to the JIT; a build that fails is recorded and its
group is the JIT's; the recorded argument types are those the kernels are called with; the key
of a module follows its sources and the CPU.

Each test builds into its own empty directory (``FIMNAV_AOT_DIR``) in fresh interpreters with
the modules turned on (``FIMNAV_AOT=1``; the rest of the suite runs the JIT kernels). The
simulator group (about 8 s to build) is the one built in the default run; every group, and a
study on them, in the slow run."""

from __future__ import annotations

import importlib.machinery
import os
import subprocess
import sys
import textwrap
import time
import types
from pathlib import Path

import numpy as np
import pytest

from planner import aot
from planner.aot_signatures import SIGNATURES
from tests.support.proc import fimnav

ROOT = Path(__file__).resolve().parents[2]


def run(code: str, aot_dir: Path, on: bool = True, **env: str) -> subprocess.CompletedProcess[str]:
    full = dict(os.environ, PYTHONPATH=str(ROOT), FIMNAV_AOT_DIR=str(aot_dir), FIMNAV_AOT="1" if on else "0", **env)
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=full, text=True, capture_output=True, timeout=600)


#: A short study of the simulator's every kernel (faults on: the late records), its arrays saved.
SIMULATE = """
import sys
import numpy as np
from missions.format.loader import load_mission
from missions.study.simulator import RunSpec, simulate
from planner import sim_kernels
print(type(sim_kernels.gather_view).__name__)
mission = load_mission("paper/heterogeneous", {"comms.faults.loss": 0.2, "comms.faults.extra_delay_steps": 1})
r = simulate(RunSpec(mission, "A", 4, 25))
np.savez(sys.argv[1] if len(sys.argv) > 1 else OUT, positions=r.positions_m, estimates=r.estimates_m, peb=r.peb_m, ages=r.record_ages)
"""


def test_sources_are_the_kernel_modules_and_what_they_import_not_the_binding() -> None:
    names = {g: sorted(p.relative_to(ROOT / "planner").as_posix() for p in aot.sources(m)) for g, (m, _) in aot.GROUPS.items()}
    assert names["planning"] == ["kernels.py"]
    assert names["simulator"] == ["sim_kernels.py"]
    assert names["estimator"] == [
        "estimator/kernels/__init__.py",
        "estimator/kernels/extension.py",
        "estimator/kernels/linalg.py",
        "estimator/kernels/memory.py",
        "estimator/kernels/pseudolinear.py",
        "estimator/kernels/robust.py",
        "estimator/kernels/update.py",
        "estimator/layout.py",
    ]


def test_the_key_follows_the_cpu_numba_compiles_for(tmp_path: Path) -> None:
    code = "from planner import aot; print(aot.key('simulator'), aot.path('simulator').parent)"
    host = run(code, tmp_path)
    generic = run(code, tmp_path, NUMBA_CPU_NAME="generic")
    assert host.returncode == 0 and generic.returncode == 0, host.stderr + generic.stderr
    assert host.stdout.split()[1] == generic.stdout.split()[1] == str(tmp_path)
    assert host.stdout.split()[0] != generic.stdout.split()[0]


def test_every_recorded_signature_reads_back_to_its_own_text() -> None:
    from numba.core import types
    from numba.core.typing import signature

    namespace = {name: getattr(types, name) for name in dir(types) if not name.startswith("_")} | {"signature": signature}
    built = {name for _, names in aot.GROUPS.values() for name in names}
    assert set(SIGNATURES) == built
    for name, text in SIGNATURES.items():
        assert aot.signature_expression(eval(text, {"__builtins__": {}}, namespace)) == text, name


def test_the_recorded_signatures_are_those_the_jit_kernels_are_compiled_for(tmp_path: Path) -> None:
    # A planner's warm-up and a few steps of every paper mission under every policy, read off the
    # JIT kernels: the file in the repository is what they give.
    done = run("from missions.study.kernel_signatures import record; print(record(), end='')", tmp_path, on=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout == (ROOT / "planner" / "aot_signatures.py").read_text()


def test_a_built_group_gives_the_jit_results_bit_for_bit_and_another_type_goes_to_the_jit(tmp_path: Path) -> None:
    # What a killed build left two hours ago goes; what a build running now holds stays.
    stale, fresh = tmp_path / ".build-killed", tmp_path / ".build-running"
    for d in (stale, fresh):
        (d / "sub").mkdir(parents=True)
    os.utime(stale, (time.time() - 7200, time.time() - 7200))
    built = run("import planner.aot_build as a; print(a.build('simulator').name)", tmp_path)
    assert built.returncode == 0, built.stderr
    assert built.stdout.strip().startswith("fimnav_aot_simulator_")
    assert not stale.exists() and fresh.is_dir()
    assert sorted(p.name for p in tmp_path.glob(".build-*")) == [".build-running"]
    with_aot = run(SIMULATE.replace("OUT", repr(str(tmp_path / "aot.npz"))), tmp_path)
    with_jit = run(SIMULATE.replace("OUT", repr(str(tmp_path / "jit.npz"))), tmp_path, on=False)
    assert with_aot.returncode == 0 and with_jit.returncode == 0, with_aot.stderr + with_jit.stderr
    assert with_aot.stdout.split() == ["Entry"]
    assert with_jit.stdout.split() == ["CPUDispatcher"]
    a, b = np.load(tmp_path / "aot.npz"), np.load(tmp_path / "jit.npz")
    for name in ("positions", "estimates", "peb", "ages"):
        assert np.array_equal(a[name], b[name], equal_nan=True), name
    # float32 points are not the recorded type: the JIT kernel runs (and agrees with numpy's).
    other = run(
        """
        import numpy as np
        from planner import geometry, sim_kernels
        rng = np.random.default_rng(3)
        points = rng.uniform(-50, 50, (64, 3)).astype(np.float32)
        source, bmin, bmax = np.zeros(3), np.array([[-10.0, 5.0, 0.0]]), np.array([[10.0, 15.0, 30.0]])
        out = np.empty(64, dtype=bool)
        sim_kernels.line_of_sight(points, source, bmin, bmax, out)
        jit = sim_kernels.line_of_sight.jit
        print(type(sim_kernels.line_of_sight).__name__, [str(s[0]) for s in jit.signatures])
        print(bool(np.array_equal(out, geometry.line_of_sight(points.astype(float), source, bmin, bmax))), int(out.sum()), int((~out).sum()))
        """,
        tmp_path,
    )
    assert other.returncode == 0, other.stderr
    first, second = other.stdout.splitlines()
    assert first == "Entry ['array(float32, 2d, C)']"
    same, clear, blocked = second.split()
    assert same == "True" and int(clear) > 0 and int(blocked) > 0


def test_binding_again_keeps_a_binding_to_the_same_module_and_leaves_a_stand_in(monkeypatch: pytest.MonkeyPatch) -> None:
    """A study's start binds every group again (planner.warm.compile_aside): a kernel already
    bound to the loaded module keeps its binding; a name a caller replaced (a timer) is left;
    a newly built module replaces the old binding, over the same JIT kernel."""
    group = "simulator"
    name = aot.GROUPS[group][1][0]

    def jit(*args: object) -> str:
        return "jit"

    jit.py_func = jit  # type: ignore[attr-defined]  # what marks a JIT kernel

    def built(*args: object) -> str:
        return "built"

    def rebuilt(*args: object) -> str:
        return "rebuilt"

    monkeypatch.setattr(aot, "load", lambda g: types.SimpleNamespace(**{name: built}))
    namespace: dict[str, object] = {name: jit}
    assert aot.bind(group, namespace)
    first = namespace[name]
    assert isinstance(first, aot.Entry) and first.compiled is built and first.jit is jit
    assert aot.bind(group, namespace) and namespace[name] is first

    def stand_in(*args: object) -> None:
        return None

    namespace[name] = stand_in
    assert aot.bind(group, namespace) and namespace[name] is stand_in

    namespace[name] = first
    monkeypatch.setattr(aot, "load", lambda g: types.SimpleNamespace(**{name: rebuilt}))
    assert aot.bind(group, namespace)
    again = namespace[name]
    assert isinstance(again, aot.Entry) and again is not first and again.compiled is rebuilt and again.jit is jit


def test_a_failed_build_is_recorded_and_its_group_is_the_jits(tmp_path: Path) -> None:
    # No C compiler: numba.pycc's wrapper cannot be compiled.
    failed = run("import planner.aot_build as a; a.build_or_record('simulator')", tmp_path, CC="/nonexistent-cc")
    assert failed.returncode == 1
    assert "the simulator kernels could not be built ahead of time" in failed.stderr, failed.stderr
    assert "Traceback" not in failed.stderr
    after = run(
        """
        from planner import aot, sim_kernels
        from planner.warm import missing_groups
        print(sorted(aot.failed()), 'simulator' in missing_groups(), type(sim_kernels.gather_view).__name__)
        """,
        tmp_path,
    )
    assert after.returncode == 0, after.stderr
    assert after.stdout.split() == ["['simulator']", "False", "CPUDispatcher"]


def test_a_damaged_module_is_not_loaded(tmp_path: Path) -> None:
    done = run(
        """
        from planner import aot
        aot.path('simulator').parent.mkdir(parents=True, exist_ok=True)
        aot.path('simulator').write_bytes(b'not an extension module')
        from planner import sim_kernels
        print(aot.load('simulator'), type(sim_kernels.gather_view).__name__)
        """,
        tmp_path,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["None", "CPUDispatcher"]


@pytest.mark.slow
def test_fimnav_compile_builds_every_group_and_a_study_on_them_equals_the_jits(tmp_path: Path) -> None:
    # About a minute on two cores.
    env = dict(os.environ, PYTHONPATH=str(ROOT), FIMNAV_AOT_DIR=str(tmp_path / "aot"), FIMNAV_AOT="1")
    first = subprocess.run(fimnav("compile", "--jobs", "2"), env=env, text=True, capture_output=True, timeout=900)
    assert first.returncode == 0, first.stderr
    assert first.stdout.startswith("compiled the planning, estimator and simulator kernels in 3 processes, up to 2 at once: "), first.stdout
    second = subprocess.run(fimnav("compile"), env=env, text=True, capture_output=True, timeout=300)
    assert second.returncode == 0, second.stderr
    for group in aot.GROUPS:
        assert f"{group} kernels: already built ({tmp_path / 'aot'}), loaded: " in second.stdout, second.stdout
    outs = {}
    for on in ("1", "0"):
        argv = fimnav("montecarlo", "paper/ranging_los", "--trials", "12", "--steps", "60", "--no-figures", "--out", str(tmp_path / on))
        done = subprocess.run(argv, env=dict(env, FIMNAV_AOT=on), text=True, capture_output=True, timeout=600)
        assert done.returncode == 0, done.stderr
        assert "compiling" not in done.stderr, done.stderr
        outs[on] = tmp_path / on / "runs" / "paper_ranging_los_A"
    for name in ("peb.csv", "trajectories.csv", "trajectories.geojson"):
        assert (outs["1"] / name).read_bytes() == (outs["0"] / name).read_bytes(), name


def test_a_build_removes_its_groups_modules_unused_for_30_days_and_a_load_marks_its_own(tmp_path: Path) -> None:
    from planner.aot_build import remove_unused_modules

    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    now = time.time()

    def made(name: str, age_days: float) -> Path:
        f = tmp_path / name
        f.write_bytes(b"")
        os.utime(f, (now - age_days * 86400, now - age_days * 86400))
        return f

    current = aot.module_name("simulator")
    keep_current_old = made(current + suffix, 90)  # the current key's, however old
    keep_current_failed = made(current + ".failed", 90)
    stale = made("fimnav_aot_simulator_0123456789abcdef0123" + suffix, 31)
    stale_failed = made("fimnav_aot_simulator_0123456789abcdef0123.failed", 45)
    recent = made("fimnav_aot_simulator_fedcba9876543210fedc" + suffix, 29)  # another CPU, still in use
    other_group = made("fimnav_aot_planning_0123456789abcdef0123" + suffix, 400)
    removed = remove_unused_modules(tmp_path, "simulator")
    assert sorted(removed) == sorted([stale, stale_failed])
    assert not stale.exists() and not stale_failed.exists()
    assert all(f.exists() for f in (keep_current_old, keep_current_failed, recent, other_group))
    # A load renews a mark older than a day, and leaves a fresh one as it is.
    aot.mark_used(recent)
    assert abs(recent.stat().st_mtime - time.time()) < 60
    fresh = made("fresh" + suffix, 0.5)
    before = fresh.stat().st_mtime
    aot.mark_used(fresh)
    assert fresh.stat().st_mtime == before
    aot.mark_used(tmp_path / "missing")  # no error where there is nothing to mark


def test_the_install_build_leaves_only_the_current_keys_modules_and_no_failure_record(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import planner.warm
    from planner.aot_build import build_for_install

    monkeypatch.setenv("FIMNAV_AOT_DIR", str(tmp_path))
    monkeypatch.setenv("FIMNAV_AOT", "1")
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    built = [aot.path(g) for g in ("planning", "estimator")]
    left = [
        tmp_path / ("fimnav_aot_planning_0123456789abcdef0123" + suffix),  # another key's
        aot.failure_file("simulator"),  # the group that could not be built
        tmp_path / ".build-x1y2z3" / "partial.o",  # a build's scratch
    ]

    def compile_aside(workers: int) -> list[str]:  # what the real build leaves, minus the slow part
        assert workers >= 1
        for f in built + left:
            f.parent.mkdir(parents=True, exist_ok=True)
            f.write_text("the simulator kernels could not be built ahead of time: no C compiler\n" if f.suffix == ".failed" else "")
        return ["planning", "estimator"]

    monkeypatch.setattr(planner.warm, "compile_aside", compile_aside)
    assert build_for_install() == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f.name for f in built)
    assert "the simulator kernels could not be built ahead of time: no C compiler" in capsys.readouterr().err
    # Every group built: 0, and the built modules stay.
    monkeypatch.setattr(planner.warm, "compile_aside", lambda workers: [])
    assert build_for_install() == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f.name for f in built)


@pytest.mark.slow
def test_the_packages_build_carries_this_machines_kernel_modules_and_nothing_numba_cached(tmp_path: Path) -> None:
    # About a minute on two cores: setup.py's build_py (what `pip install .` runs to make its
    # wheel) builds every group into the built package.
    listed = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout.split(b"\0")
    src = tmp_path / "src"
    for name in (n.decode() for n in listed if n):
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        (src / name).write_bytes((ROOT / name).read_bytes())
    env = {k: v for k, v in os.environ.items() if k not in ("FIMNAV_AOT_DIR", "FIMNAV_AOT", "NUMBA_CACHE_DIR", "PYTHONPATH")}
    built = tmp_path / "lib"
    done = subprocess.run(
        [sys.executable, "setup.py", "build_py", "--build-lib", str(built)], cwd=src, env=env, text=True, capture_output=True, timeout=900
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "building the compiled kernels for this machine" in done.stderr
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    # The same sources, numba, numpy, Python and CPU here: the keys this process computes.
    cached = sorted(p.relative_to(built).as_posix() for p in built.rglob("*") if "__pycache__" in p.parts and p.is_file())
    assert cached == sorted(f"planner/__pycache__/aot/{aot.module_name(g)}{suffix}" for g in aot.GROUPS)
    # An editable install's build (setuptools sets build_py's editable_mode) skips the step: its
    # kernels are built where its sources are.
    as_editable = """
        import sys
        from setuptools.command.build_py import build_py
        plain = build_py.initialize_options
        def initialize_options(self):
            plain(self)
            self.editable_mode = True
        build_py.initialize_options = initialize_options
        sys.argv = ["setup.py", "build_py", "--build-lib", sys.argv[1]]
        exec(open("setup.py").read())
    """
    editable = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(as_editable), str(tmp_path / "editable")],
        cwd=src,
        env=env,
        text=True,
        capture_output=True,
        timeout=300,
    )
    assert editable.returncode == 0, editable.stderr
    assert "building the compiled kernels" not in editable.stderr, editable.stderr
    assert not list((tmp_path / "editable").rglob("*.so"))


def test_lapacks_bindings_are_loaded_without_scipy_linalgs_package(tmp_path: Path) -> None:
    done = run(
        """
        import sys
        from planner import aot
        first = aot.preload_lapack()
        alone = "scipy.linalg" not in sys.modules
        import scipy.linalg.cython_lapack as lapack  # what numba's LAPACK helpers import
        same = lapack is sys.modules[aot.LAPACK_MODULE] and "dsyevd" in lapack.__pyx_capi__
        import numpy as np
        import scipy.linalg
        w = scipy.linalg.eigh(np.array([[2.0, 1.0], [1.0, 2.0]]), eigvals_only=True)
        from scipy.linalg import cython_lapack
        print(first, alone, same, aot.preload_lapack(), np.allclose(w, [1.0, 3.0]), cython_lapack is lapack)
        """,
        tmp_path,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["True"] * 6
    # scipy.linalg imported first: its own import of the bindings is the one used.
    late = run(
        "import sys, scipy.linalg; from planner import aot; print(aot.preload_lapack(), scipy.linalg.cython_lapack is sys.modules[aot.LAPACK_MODULE])",
        tmp_path,
    )
    assert late.returncode == 0, late.stderr
    assert late.stdout.split() == ["True", "True"]
