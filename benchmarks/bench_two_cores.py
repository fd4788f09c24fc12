"""What two processes get from this machine's cores on plain Python (not a timed test): a loop
of 30 million additions in a fresh interpreter, alone, then two copies started at once, taken in
turn (the order swapped every round) for ``--rounds`` rounds.

The ceiling printed is 2 × (median wall of one alone) / (median wall of two at once): 2.00 ×
on two free, independent cores; less where the two cores share what a process runs on (a
virtual machine's two vCPUs on one physical core, a neighbour's load). No fimnav code runs:
it is the bound ``bench_study_scaling.py``'s speed-ups are read against.

Usage::

    python benchmarks/bench_two_cores.py [--rounds 8] [--iterations 30000000]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time


def loop_code(iterations: int) -> str:
    """The work of one process: ``iterations`` additions in a Python loop."""
    return f"s = 0\nfor i in range({int(iterations)}):\n    s += i\n"


def alone(code: str) -> float:
    """Wall seconds of one process running ``code``."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], check=True)
    return time.perf_counter() - t0


def two_at_once(code: str) -> float:
    """Wall seconds until two processes running ``code``, started at once, have both ended."""
    t0 = time.perf_counter()
    started = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(2)]
    if any(p.wait() for p in started):
        raise SystemExit("bench_two_cores: a loop process failed")
    return time.perf_counter() - t0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--iterations", type=int, default=30_000_000)
    args = parser.parse_args()
    code = loop_code(args.iterations)
    one: list[float] = []
    two: list[float] = []
    for r in range(args.rounds):
        if r % 2 == 0:
            one.append(alone(code))
            two.append(two_at_once(code))
        else:
            two.append(two_at_once(code))
            one.append(alone(code))
        print(f"round {r + 1}: alone {one[-1]:.2f} s, two at once {two[-1]:.2f} s", flush=True)
    a, b = statistics.median(one), statistics.median(two)
    print(
        f"\n{args.iterations} additions, {args.rounds} rounds: alone {a:.2f} s [{min(one):.2f}-{max(one):.2f}], two at once {b:.2f} s [{min(two):.2f}-{max(two):.2f}]"
    )
    print(f"this machine's ceiling for two processes (2 x alone / two at once, medians): {2 * a / b:.2f} x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
