"""Start ``fimnav`` child processes from a fork server that has already imported them, and the
child's side of the launcher's contract: a child of a launcher stops when its launcher dies.

A planner process spends about 0.45 s of CPU importing numpy, pydantic, pymavlink and zenoh
before it does anything; the launcher starts N of them at once on a 2-core machine (10 drones:
~2 s of wall time, 100 drones: ~20 s). :class:`ForkServer` uses the standard library's
``multiprocessing`` fork server (``forkserver`` start method): one server process imports
:data:`PRELOAD` once, and each child is forked from it, already imported. Each child is
still a separate operating-system process, in its own session and process group (as with
``subprocess.Popen(start_new_session=True)``), with stdin from /dev/null and stdout and stderr
in its log file, and its process title set to the command line it runs (``setproctitle``:
``ps`` and ``/proc/PID/cmdline`` show ``python -m missions plan ...``).

:class:`ForkedProcess` gives the launcher the part of ``subprocess.Popen`` it uses (``pid``,
``poll``, ``wait``, ``returncode``); exit statuses follow Popen's convention (−N: killed by
signal N).

**Dying with the launcher.** Children run in their own sessions, so neither a hang-up of the
launcher's terminal nor the launcher's own death reaches them. The launcher therefore holds the
only write end of a pipe (the *watchdog pipe*) whose read end every child inherits, named by
the environment variable :data:`LAUNCHER_FD_ENV` (a forked child gets it from
:meth:`ForkServer.spawn`). :func:`watch_launcher`, called first thing by ``fimnav plan`` and
``fimnav vehicle``, starts a thread that reads the pipe: end of file means every copy of the
write end is closed, i.e. the launcher is gone (SIGKILL, a crash, or the end of its run); the
child then sends itself SIGTERM (its usual clean stop) and exits by force after
:data:`ORPHAN_GRACE_S` if that did not end it. On Linux the child also asks for SIGTERM when its
parent process dies (``prctl(PR_SET_PDEATHSIG)``); a forked child's parent is the fork server,
which ends with the launcher (its children close their copies of the server's "alive" pipe).
A process started by hand has no such variable and is not watched.

**The launcher's code.** A child must import the very ``missions`` package the launcher imported,
not one it happens to find first (``python -m`` and ``-c`` put the working directory in front
of ``sys.path``: a clone's source would shadow an installed copy). :func:`same_code_environment`
gives a child the launcher's ``sys.path`` and no working-directory entry; the fork server is
started with it too (``multiprocessing`` passes it the launcher's ``sys.path`` but its
``main`` does not use it).
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import multiprocessing
import multiprocessing.forkserver
import multiprocessing.resource_tracker
import os
import runpy
import signal
import stat
import subprocess
import sys
import threading
from collections.abc import Callable, Mapping, MutableMapping, Sequence
from multiprocessing import reduction
from pathlib import Path
from typing import Any

log = logging.getLogger("fimnav.child")

#: Modules the fork server imports once: everything ``fimnav plan`` needs before it flies.
PRELOAD: tuple[str, ...] = (
    "numpy",
    "zenoh",
    "pymavlink.mavutil",
    "missions.format.loader",
    "missions.cli.plan",
    "comms.mavlink_client",
    "comms.session",
    "planner.node",
    "planner.node.warm",  # loads (or, once after an install, compiles) the planning kernels before the fork
    "planner.node.warm_estimator",  # the same for the estimator kernels
)

#: Environment variable of a launcher's child: the file descriptor of the read end of the
#: launcher's watchdog pipe (end of file: the launcher is gone).
LAUNCHER_FD_ENV: str = "FIMNAV_LAUNCHER_FD"

#: Seconds a child whose launcher died gives its own SIGTERM to end it before it exits by force.
ORPHAN_GRACE_S: float = 5.0

#: Signals the fork server (in the launcher's process group) never acts on: a hang-up of the
#: terminal, a Ctrl-C or a SIGTERM to the group are the launcher's to handle (it stops the
#: planners itself, and the server ends with it). Blocked signals are inherited through fork
#: and exec; a forked child unblocks them.
SERVER_BLOCKED_SIGNALS: frozenset[signal.Signals] = frozenset({signal.SIGHUP, signal.SIGINT, signal.SIGTERM})

#: ``prctl`` option: the signal a process receives when its parent dies (linux/prctl.h).
_PR_SET_PDEATHSIG: int = 1


def same_code_environment(base: Mapping[str, str] | None = None) -> dict[str, str]:
    """``base`` (default: this process's environment) for a child of this interpreter that must
    import what this process imports: ``PYTHONPATH`` is this process's ``sys.path`` (relative
    entries made absolute) and ``PYTHONSAFEPATH=1`` keeps ``-m`` and ``-c`` from putting the
    working directory in front of it (Python 3.11+; on 3.10 start the child in a directory
    that holds no module)."""
    env = dict(os.environ if base is None else base)
    env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(os.path.abspath(p) for p in sys.path))
    env["PYTHONSAFEPATH"] = "1"
    return env


def set_parent_death_signal(signum: int = signal.SIGTERM) -> bool:
    """Linux: have the kernel send ``signum`` to this process when its parent dies (it fires
    when the parent *thread* that forked it ends). Returns whether it is set (False elsewhere)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return int(libc.prctl(_PR_SET_PDEATHSIG, int(signum), 0, 0, 0)) == 0
    except (OSError, AttributeError):
        return False


def _await_launcher_exit(fd: int, grace_s: float) -> None:
    """Watchdog thread: block on the pipe until end of file, then stop this process."""
    try:
        while os.read(fd, 512):
            pass  # the launcher never writes; anything read is ignored
    except OSError as exc:
        log.warning("launcher watchdog: cannot read its pipe (fd %d: %s); not watching", fd, exc)
        return
    log.warning("the launcher is gone (its watchdog pipe closed): stopping")
    os.kill(os.getpid(), signal.SIGTERM)
    # The clean stop ends the process; this thread, a daemon, normally never wakes again.
    threading.Event().wait(grace_s)
    log.error("still running %g s after the launcher died: exiting by force", grace_s)
    os._exit(128 + signal.SIGTERM)


def watch_launcher(environ: MutableMapping[str, str] | None = None, grace_s: float = ORPHAN_GRACE_S) -> bool:
    """In a launcher's child: stop this process when the launcher dies (module doc).

    Reads and removes :data:`LAUNCHER_FD_ENV` (so that nothing this process starts inherits it).
    Returns False, and does nothing, when the variable is absent (a process started by hand) or
    does not name a pipe (a warning is logged).
    """
    env = os.environ if environ is None else environ
    text = env.pop(LAUNCHER_FD_ENV, None)
    if text is None:
        return False
    try:
        fd = int(text)
        is_pipe = stat.S_ISFIFO(os.fstat(fd).st_mode)
    except (ValueError, OSError):
        is_pipe = False
    if not is_pipe:
        log.warning("%s=%r: expected the file descriptor of the launcher's pipe, found none; not watching the launcher", LAUNCHER_FD_ENV, text)
        return False
    os.set_inheritable(fd, False)
    set_parent_death_signal(signal.SIGTERM)
    threading.Thread(target=_await_launcher_exit, args=(fd, grace_s), name="launcher-watchdog", daemon=True).start()
    return True


def _rebuild_fd(dup: Any) -> int:
    """Fork-server child: the descriptor number of an fd sent along with the process."""
    return int(dup.detach())


class _InheritedFd:
    """A file descriptor passed to a fork-server child (``multiprocessing`` sends it over the
    server's socket while it pickles the process; the child gets its own copy)."""

    def __init__(self, fd: int) -> None:
        self.fd = fd

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return _rebuild_fd, (reduction.DupFd(self.fd),)


def _leave_fork_server() -> None:
    """Fork-server child: close this process's copy of the server's "alive" pipe, so the server
    ends with the launcher rather than with its last child (its own end of file), and unblock
    the signals the server blocks."""
    server = getattr(multiprocessing.forkserver, "_forkserver", None)
    alive = getattr(server, "_forkserver_alive_fd", None)
    if server is not None and isinstance(alive, int):
        try:
            os.close(alive)
        except OSError:
            pass  # already closed: nothing holds the server up
        server._forkserver_alive_fd = None
    signal.pthread_sigmask(signal.SIG_UNBLOCK, SERVER_BLOCKED_SIGNALS)


def _run_cli(argv: list[str], log_path: str, title: str, launcher_fd: int | None = None, truncate: bool = False, cwd: str | None = None) -> None:
    """Fork-server child: become ``python -m missions ARGV`` with its output in ``log_path``
    (truncated first if ``truncate``, else appended to), in directory ``cwd``, watching the
    launcher through ``launcher_fd``."""
    os.setsid()  # own session and process group: the launcher signals the group
    flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | (os.O_TRUNC if truncate else 0)
    fd = os.open(log_path, flags, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    for stream in (sys.stdout, sys.stderr):
        if stream is not None and hasattr(stream, "reconfigure"):
            stream.reconfigure(write_through=True, line_buffering=True)
    # A process started by the launcher with Popen gets the default dispositions.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGHUP, signal.SIG_DFL)
    _leave_fork_server()
    if cwd is not None:
        os.chdir(cwd)
    if launcher_fd is not None:
        os.environ[LAUNCHER_FD_ENV] = str(launcher_fd)
    import setproctitle

    setproctitle.setproctitle(title)
    # The fimnav program by its name, as a spawned child runs it (``python -m missions``): the
    # launch layer starts commands, it does not import the command line.
    sys.argv = ["fimnav", *argv]
    runpy.run_module("missions", run_name="__main__", alter_sys=True)


class ForkedProcess:
    """``subprocess.Popen``'s ``pid``, ``poll``, ``wait`` and ``returncode`` for a fork-server
    child (the launcher is not its parent: its exit status comes through the fork server)."""

    def __init__(self, process: Any, args: Sequence[str]) -> None:
        self._p = process
        self.args = list(args)
        self.pid: int = process.pid

    @property
    def returncode(self) -> int | None:
        return self._p.exitcode

    def poll(self) -> int | None:
        """The exit status, or None while it runs."""
        return self._p.exitcode

    def wait(self, timeout: float | None = None) -> int:
        """Wait for the exit (at most ``timeout`` s); ``subprocess.TimeoutExpired`` after it."""
        self._p.join(timeout)
        code = self._p.exitcode
        if code is None:
            raise subprocess.TimeoutExpired(self.args, timeout if timeout is not None else 0.0)
        return int(code)


class ForkServer:
    """Starts ``python -m missions ARGS`` children from a pre-imported fork server.

    :meth:`warm_up` starts the server (it imports :data:`PRELOAD` while the caller does other
    work); :meth:`spawn` forks one child. :meth:`close` ends the server and waits for it
    (the launcher does, once its children are stopped); otherwise it ends with the process that
    created it.
    """

    def __init__(self, python: str = sys.executable) -> None:
        self.ctx = multiprocessing.get_context("forkserver")
        self.python = python
        self.ctx.set_forkserver_preload(list(PRELOAD))
        #: Whether :meth:`wait_ready` saw the server done with its preload.
        self.ready = False

    def warm_up(self, cwd: Path | None = None) -> None:
        """Start the fork server now (it imports the preload in the background), with
        :data:`SERVER_BLOCKED_SIGNALS` blocked in it (and in ``multiprocessing``'s resource
        tracker, started with it), importing this process's code (:func:`same_code_environment`;
        on Python 3.10 started in ``cwd``, a directory that holds no module). ``multiprocessing``
        starts it with this process's environment and working directory, which are set for
        the few milliseconds that takes (call it before other threads depend on them)."""
        env = same_code_environment({})
        saved = {name: os.environ.get(name) for name in env}
        start_in = cwd if sys.version_info < (3, 11) else None
        old_cwd = os.getcwd() if start_in is not None else None
        old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, SERVER_BLOCKED_SIGNALS)
        try:
            os.environ.update(env)
            if start_in is not None:
                os.chdir(start_in)
            multiprocessing.forkserver.ensure_running()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
            if old_cwd is not None:
                os.chdir(old_cwd)
            for name, value in saved.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value

    def wait_ready(
        self,
        timeout_s: float = 120.0,
        notice: Callable[[str], None] | None = None,
        notice_after_s: float = 3.0,
        stop: Callable[[], bool] | None = None,
    ) -> bool:
        """Wait until the fork server has imported :data:`PRELOAD` (it forks a child only then):
        fork a child that exits at once and wait for it. The planners' start time (real time)
        is fixed after this, as the preload loads the compiled planning step (seconds, and
        once after an install the time to compile it). ``notice``: told once, in one line, when
        the wait passes ``notice_after_s`` seconds (the kernels being compiled). ``stop``:
        polled every 0.1 s; once true the wait ends at once and returns False (Ctrl-C during
        the first compile: :meth:`close` then ends the server without waiting for its
        preload). True once the server is ready."""
        # (Process.start itself blocks until the server forks, after its preload: a timer
        # tells, and the start runs in a thread so that a stop need not wait for it.)
        timer = None
        if notice is not None:
            timer = threading.Timer(
                notice_after_s,
                notice,
                ("compiling the planning and estimation kernels: once after an install, "
                 "about a minute on two cores (later launches load them at once; `fimnav compile` does it beforehand)",),
            )  # fmt: skip
            timer.daemon = True
            timer.start()
        child = self.ctx.Process(target=int)
        failed: list[BaseException] = []

        def start() -> None:
            try:
                child.start()
            except BaseException as exc:  # raised below, in the caller's thread; a server ended by close() is no error
                failed.append(exc)

        starter = threading.Thread(target=start, name="fork-server-ready", daemon=True)
        try:
            starter.start()
            # The preload takes what it takes (a first compile on a slow machine: minutes);
            # only the forked child's exit is bounded by timeout_s.
            while starter.is_alive():
                if stop is not None and stop():
                    return False
                starter.join(0.1)
            if failed:
                raise failed[0]
            child.join(timeout_s)
        finally:
            if timer is not None:
                timer.cancel()
        self.ready = True
        return True

    def close(self) -> None:
        """End the fork server and multiprocessing's resource tracker (started with it) and wait
        for them to exit (after the children are stopped).
        Without this it ends on its own once this process has exited, a fraction of a second
        later, so a launch that had returned still left it running for that moment."""
        server = getattr(multiprocessing.forkserver, "_forkserver", None)
        tracker = getattr(multiprocessing.resource_tracker, "_resource_tracker", None)
        # A server still in its preload (a launch stopped during the first compile) would only
        # notice the end of its pipe once the preload is done: it is killed (it has forked no
        # planner yet; numba writes its cache files whole or not at all), and its compiling
        # children (planner.warm) end when it does.
        pid = getattr(server, "_forkserver_pid", None)
        if not self.ready and pid is not None:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        # The server first: its children hold the resource tracker too.
        for owner, pid_attr in ((server, "_forkserver_pid"), (tracker, "_pid")):
            stop = getattr(owner, "_stop", None)
            if callable(stop) and getattr(owner, pid_attr, None) is not None:
                with contextlib.suppress(OSError):  # already gone: nothing to wait for
                    stop()

    def spawn(
        self, args: Sequence[str], log_path: Path, launcher_fd: int | None = None, truncate: bool = False, cwd: Path | None = None
    ) -> ForkedProcess:
        """Fork ``python -m missions ARGS`` with stdout/stderr in ``log_path`` (truncated first
        if ``truncate``, else appended to), in directory ``cwd`` (default: the server's), given
        the read end ``launcher_fd`` of the launcher's watchdog pipe (:func:`watch_launcher`)."""
        title = " ".join([self.python, "-m", "missions", *args])
        inherited = _InheritedFd(launcher_fd) if launcher_fd is not None else None
        p = self.ctx.Process(
            target=_run_cli, args=(list(args), str(log_path), title, inherited, truncate, str(cwd) if cwd is not None else None), daemon=True
        )
        p.start()
        return ForkedProcess(p, [self.python, "-m", "missions", *args])
