"""The one signal module (missions.runtime.signals), in this process: a stop signal asks a loop
to stop and then ends the command with 128 + its number; an inherited ignored SIGHUP stays
ignored (nohup) while SIGINT and SIGTERM are taken even when ignored; a signal held back while
a pool starts is delivered after. Every signal here is sent while a handler of the test's is
in place (the commands' own exits are checked on real processes: test_montecarlo_signals,
test_vehicle_cli, test_partition, test_launch_lifecycle)."""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from typing import Any

import pytest

from missions.runtime.signals import Interrupted, StopRequest, exit_status, signals_deferred, stop_on_signals


@pytest.fixture
def dispositions() -> Iterator[None]:
    """The test process's stop signals as they were, whatever a test sets."""
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    yield
    for s, h in saved.items():
        signal.signal(s, h)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_a_stop_signal_asks_the_loop_to_stop_then_ends_with_128_plus_it(signum: int, dispositions: None) -> None:
    # As from a terminal: a suite run under nohup (or as a background job) has SIGHUP ignored,
    # which fimnav honours on purpose (test_an_ignored_hangup_stays_ignored_an_ignored_term_does_not).
    signal.signal(signum, signal.SIG_DFL)
    stopped: list[bool] = []
    request = StopRequest(lambda: stopped.append(True))
    before = signal.getsignal(signum)
    with stop_on_signals(request):
        os.kill(os.getpid(), signum)
        os.kill(os.getpid(), signal.SIGTERM)  # a second signal: the first one is the reason
    assert stopped == [True, True] and request.signum == signum
    assert signal.getsignal(signum) == before  # restored
    with pytest.raises(Interrupted) as raised:
        request.raise_if_stopped()
    assert raised.value.exit_code == exit_status(signum) == 128 + signum
    assert str(raised.value) == f"stopped by {signal.Signals(signum).name}"


def test_an_ignored_hangup_stays_ignored_an_ignored_term_does_not(dispositions: None) -> None:
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    request = StopRequest(lambda: None)
    with stop_on_signals(request):
        assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
        os.kill(os.getpid(), signal.SIGHUP)  # ignored: nohup
        assert request.signum is None
        assert signal.getsignal(signal.SIGTERM) not in (signal.SIG_IGN, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGTERM)
    assert request.signum == signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_IGN


def test_a_signal_held_back_while_a_pool_starts_is_delivered_after(dispositions: None) -> None:
    got: list[int] = []

    def handler(signum: int, frame: Any) -> None:
        got.append(signum)

    signal.signal(signal.SIGHUP, handler)
    with signals_deferred():
        os.kill(os.getpid(), signal.SIGHUP)
        os.kill(os.getpid(), signal.SIGHUP)  # held once
        assert got == []
    assert got == [signal.SIGHUP]
    assert signal.getsignal(signal.SIGHUP) is handler
