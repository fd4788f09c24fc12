"""setuptools' build of fimnav (its metadata is in pyproject.toml), with one step more.

A wheel built on this machine (what ``pip install .`` does) carries the compiled kernels built
ahead of time for this machine's CPU (``planner/__pycache__/aot``, :mod:`planner.aot`), so that
the first command after the install compiles nothing: the build that a first ``fimnav launch``,
``fimnav plan`` or study would do (about a minute on two cores) happens in the install instead.
A module is keyed by the sources, numba's, numpy's and Python's versions and the CPU: installed
on another machine, or beside other versions, it is not used and the first command builds its
own, as it does when this step could not build (no C compiler: the install still succeeds).

``FIMNAV_AOT=0`` skips the step (and turns the modules off at run time). An editable install
(``pip install -e .``) skips it too: its kernels are built where its sources are, on first use.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py
from setuptools.dist import Distribution

#: What the build's child process runs (the package being built on its path).
_BUILD = "import planner.aot_build as b; raise SystemExit(b.build_for_install())"


class BuildPyWithKernels(build_py):
    """``build_py``, then the kernels' extension modules into the built ``planner`` package."""

    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False) or os.environ.get("FIMNAV_AOT", "1").strip() == "0":
            return
        build_lib = Path(self.build_lib).resolve()
        # The package being built first on the path (pip's build environment, which brings numba,
        # passes its own through PYTHONPATH: kept after it), run from its directory.
        path = os.pathsep.join(p for p in (str(build_lib), os.environ.get("PYTHONPATH")) if p)
        print("building the compiled kernels for this machine (about a minute on two cores)", file=sys.stderr, flush=True)
        with tempfile.TemporaryDirectory() as numba_cache:  # what numba caches meanwhile stays out of the wheel
            # and so does the bytecode of the modules the build imports from the built package
            env = dict(
                os.environ,
                PYTHONPATH=path,
                FIMNAV_AOT_DIR=str(build_lib / "planner" / "__pycache__" / "aot"),
                NUMBA_CACHE_DIR=numba_cache,
                PYTHONDONTWRITEBYTECODE="1",
            )
            done = subprocess.run([sys.executable, "-c", _BUILD], env=env, cwd=build_lib, check=False)
        if done.returncode != 0:
            print("the compiled kernels were not built into the package: the first command builds them", file=sys.stderr)


class MachineDistribution(Distribution):
    """A wheel with kernels built for a machine is not pure Python: tagged with the platform."""

    def has_ext_modules(self) -> bool:
        return True


setup(cmdclass={"build_py": BuildPyWithKernels}, distclass=MachineDistribution)
