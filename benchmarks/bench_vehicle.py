"""Benchmark of the simulated MAVLink vehicle (not a test): boot time, idle CPU, memory,
capacity at real time and in lockstep.

Run from the repository root::

    python benchmarks/bench_vehicle.py [--quick] [--out DIR]

Measures (medians where repeated):

1. boot to first heartbeat: ``fimnav vehicle --mavlink udpout:127.0.0.1:P`` spawned, time
   until its first HEARTBEAT datagram reaches a socket bound at P (includes interpreter start
   and imports); and the same inside an already running interpreter;
2. CPU and resident memory of one process hosting N vehicles (N = 1, 10, 50), disarmed on the
   ground ("idle") and hovering ("flying", pointmass physics at 50 Hz), default telemetry
   (~18 messages/s per vehicle) to a UDP sink, from /proc over a 10 s window;
3. real-time capacity: N hovering vehicles in one process; real time holds while the sink
   receives >= 95 % of the expected LOCAL_POSITION_NED frames (4 Hz per vehicle) and the
   process uses < 90 % of one core;
4. lockstep: wall time of one tick (dt = 1 s: 50 physics steps + position report) per vehicle,
   in process, hence the vehicles one core can step at one tick per second.

Prints a JSON summary and writes PNG figures into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
ENV = dict(os.environ, MAVLINK20="1", PYTHONUNBUFFERED="1")
TICKS_PER_S = os.sysconf("SC_CLK_TCK")
PAGE = os.sysconf("SC_PAGE_SIZE")


def sink_socket() -> tuple[socket.socket, int]:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
    s.bind(("127.0.0.1", 0))
    return s, int(s.getsockname()[1])


#: Bootstrap that registers ``planner`` as a bare namespace (its submodules import on demand)
#: instead of running planner/__init__.py, which eagerly imports scipy and the whole core.
#: Used only to quantify what a lazy planner/__init__ would save.
LAZY_PLANNER = (
    "import sys, types; m = types.ModuleType('planner'); m.__path__ = [sys.argv.pop(1)]; "
    "sys.modules['planner'] = m; from missions.cli.main import main; sys.exit(main(sys.argv[1:]))"
)


def spawn(args: list[str], lazy_planner: bool = False) -> subprocess.Popen[bytes]:
    head = ["-c", LAZY_PLANNER, str(ROOT / "planner")] if lazy_planner else ["-m", "missions.cli.main"]
    return subprocess.Popen(
        [sys.executable, *head, "vehicle", *args],
        cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True,
    )


def stop(p: subprocess.Popen[bytes]) -> None:
    try:
        os.killpg(p.pid, 15)
    except ProcessLookupError:
        pass
    try:
        p.wait(5)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, 9)
        p.wait(5)


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS_PER_S


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def is_heartbeat(d: bytes) -> bool:
    return len(d) > 10 and d[0] == 0xFD and int.from_bytes(d[7:10], "little") == 0


def is_local_position(d: bytes) -> bool:
    return len(d) > 10 and d[0] == 0xFD and int.from_bytes(d[7:10], "little") == 32


def boot_to_heartbeat(runs: int, lazy_planner: bool = False) -> dict[str, float]:
    times = []
    cpu = []
    rss = []
    for _ in range(runs):
        s, port = sink_socket()
        s.settimeout(30)
        t0 = time.perf_counter()
        p = spawn(["--mavlink", f"udpout:127.0.0.1:{port}"], lazy_planner)
        try:
            while True:
                data, _ = s.recvfrom(65535)
                if is_heartbeat(data):
                    times.append(time.perf_counter() - t0)
                    cpu.append(cpu_s(p.pid))  # CPU the process used to get there (imports included)
                    rss.append(rss_mb(p.pid))
                    break
        finally:
            stop(p)
            s.close()
    if lazy_planner:
        return {"process_cpu_median_s": statistics.median(cpu), "process_median_s": statistics.median(times),
                "rss_mb_median": statistics.median(rss), "runs": runs}
    # in process: build + first loop iteration (imports already done)
    from vehicle_sim.clock import RealTimeClock
    from vehicle_sim.config import VehicleConfig
    from vehicle_sim.host import VehicleHost, build_vehicle

    inproc = []
    for _ in range(runs):
        s, port = sink_socket()
        s.settimeout(5)
        t0 = time.perf_counter()
        v = build_vehicle(VehicleConfig(), f"udpout:127.0.0.1:{port}")
        host = VehicleHost([v], RealTimeClock())
        host.start()
        while not is_heartbeat(s.recvfrom(65535)[0]):
            pass
        inproc.append(time.perf_counter() - t0)
        host.close()
        s.close()
    return {
        "process_cpu_median_s": statistics.median(cpu),
        "process_median_s": statistics.median(times),
        "rss_mb_median": statistics.median(rss),
        "process_max_s": max(times),
        "in_process_median_s": statistics.median(inproc),
        "runs": runs,
    }


def drain(s: socket.socket, counter: dict[str, int]) -> None:
    s.setblocking(False)
    while True:
        try:
            d = s.recv(65535)
        except BlockingIOError:
            return
        counter["frames"] += 1
        if is_local_position(d):
            counter["lpn"] += 1


class Sink:
    """A thread counting the frames received on a UDP socket (blocking reads, no polling)."""

    def __init__(self) -> None:
        import threading

        self.sock, self.port = sink_socket()
        self.sock.settimeout(0.2)
        self.counter = {"frames": 0, "lpn": 0}
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                d = self.sock.recv(65535)
            except (TimeoutError, OSError):
                continue
            self.counter["frames"] += 1
            if is_local_position(d):
                self.counter["lpn"] += 1

    def reset(self) -> dict[str, int]:
        old, self.counter = self.counter, {"frames": 0, "lpn": 0}
        return old

    def close(self) -> None:
        self._stop.set()
        self._t.join(2)
        self.sock.close()


def process_load(n: int, airborne: bool, window_s: float) -> dict[str, Any]:
    sink = Sink()
    args = []
    for _ in range(n):
        args += ["--mavlink", f"udpout:127.0.0.1:{sink.port}"]
    args += ["--count", str(n), "--profile", "pointmass"]
    if airborne:
        args += ["--airborne", "--start", "0,0,10"]
    p = spawn(args)
    try:
        deadline = time.monotonic() + 60.0  # warm-up: imports, sockets, first streams
        while sink.counter["lpn"] < 8 * n:
            time.sleep(0.1)
            if p.poll() is not None:
                raise RuntimeError(p.stderr.read().decode() if p.stderr else "vehicle process died")
            if time.monotonic() > deadline:
                raise RuntimeError(f"{n} vehicles did not stream within 60 s")
        sink.reset()
        c0, t0 = cpu_s(p.pid), time.monotonic()
        time.sleep(window_s)
        c1, t1 = cpu_s(p.pid), time.monotonic()
        counter = sink.reset()
        rss = rss_mb(p.pid)
    finally:
        stop(p)
        sink.close()
    wall = t1 - t0
    cpu_frac = (c1 - c0) / wall
    expected_lpn = 4.0 * n * wall
    return {
        "n": n,
        "airborne": airborne,
        "cpu_core_fraction": cpu_frac,
        "cpu_pct_per_vehicle": 100.0 * cpu_frac / n,
        "rss_mb": rss,
        "frames_per_s": counter["frames"] / wall,
        "lpn_delivered_fraction": counter["lpn"] / expected_lpn,
        "real_time": counter["lpn"] >= 0.95 * expected_lpn and cpu_frac < 0.9,
    }


def lockstep_cost(n: int, ticks: int) -> dict[str, float]:
    from vehicle_sim.config import VehicleConfig
    from vehicle_sim.host import build_vehicle

    s, port = sink_socket()
    vs = [
        build_vehicle(VehicleConfig(sysid=i + 1, airborne=True, start_enu_m=(2.0 * i, 0.0, 10.0)), f"udpout:127.0.0.1:{port}")
        for i in range(n)
    ]
    counter = {"frames": 0, "lpn": 0}
    per_tick = []
    per_tick_cpu = []
    for k in range(1, ticks + 1):
        t0, c0 = time.perf_counter(), time.thread_time()
        for v in vs:
            v.advance_to(float(k), report_position=True)
        per_tick.append(time.perf_counter() - t0)
        per_tick_cpu.append(time.thread_time() - c0)
        drain(s, counter)
    for v in vs:
        v.link.close()
    s.close()
    med = statistics.median(per_tick)
    cpu = statistics.median(per_tick_cpu)
    return {
        "n": n,
        "tick_s_median": med,
        "tick_cpu_s_median": cpu,
        "per_vehicle_tick_cpu_ms": 1000 * cpu / n,
        "vehicles_per_core_at_1_tick_per_s": n / cpu,
    }


def figures(out: Path, loads: list[dict[str, Any]], capacity: list[dict[str, Any]], lock: list[dict[str, float]]) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    paths = []
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for airborne, style in ((False, "o-"), (True, "s--")):
        rows = [r for r in loads + capacity if r["airborne"] == airborne]
        rows.sort(key=lambda r: r["n"])
        label = "hovering" if airborne else "idle (ground)"
        ax[0].plot([r["n"] for r in rows], [100 * r["cpu_core_fraction"] for r in rows], style, label=label)
        ax[1].plot([r["n"] for r in rows], [r["rss_mb"] for r in rows], style, label=label)
        late = [r for r in rows if not r["real_time"]]
        if late:
            ax[0].plot([r["n"] for r in late], [100 * r["cpu_core_fraction"] for r in late], "rx", ms=12,
                       label="real time not held" if airborne else None)
    ax[0].axhline(90, color="grey", lw=0.8)
    ax[0].set(xlabel="vehicles in one process", ylabel="CPU (% of one core)", xscale="log", title="CPU, real time x1")
    ax[1].set(xlabel="vehicles in one process", ylabel="resident memory (MB)", xscale="log", title="RSS")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend()
    fig.tight_layout()
    p = out / "vehicle_sim_cpu_rss.png"
    fig.savefig(p, dpi=120)
    paths.append(str(p))
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.plot([r["n"] for r in lock], [1000 * r["tick_s_median"] for r in lock], "o-", label="wall")
    ax.plot([r["n"] for r in lock], [1000 * r["tick_cpu_s_median"] for r in lock], "s--", label="CPU")
    ax.legend()
    ax.set(xlabel="vehicles", ylabel="time of one lockstep tick (ms)", title="lockstep, dt = 1 s, 50 Hz physics")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    p = out / "vehicle_sim_lockstep.png"
    fig.savefig(p, dpi=120)
    paths.append(str(p))
    plt.close("all")
    return paths


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer runs, shorter windows")
    ap.add_argument("--out", default="/tmp/fimnav-bench-vehicle", help="directory of the figures")
    args = ap.parse_args()
    runs, window = (3, 5.0) if args.quick else (7, 10.0)
    result: dict[str, Any] = {
        "machine_cpus": os.cpu_count(),
        "python": sys.version.split()[0],
        "load_average_at_start": os.getloadavg(),
    }
    result["boot"] = boot_to_heartbeat(runs)
    print(json.dumps(result["boot"]), flush=True)
    result["boot_lazy_planner"] = boot_to_heartbeat(runs, lazy_planner=True)
    print(json.dumps(result["boot_lazy_planner"]), flush=True)
    loads = []
    for n in (1, 10, 50):
        for airborne in (False, True):
            r = process_load(n, airborne, window)
            print(json.dumps(r), flush=True)
            loads.append(r)
    result["loads"] = loads
    capacity = []
    for n in (100, 200, 255) if not args.quick else (100, 200):  # 255: one MAVLink system id each
        r = process_load(n, True, window)
        print(json.dumps(r), flush=True)
        capacity.append(r)
        if not r["real_time"]:
            break
    result["capacity"] = capacity
    ok = [r["n"] for r in loads + capacity if r["airborne"] and r["real_time"]]
    result["max_real_time_vehicles_per_process_measured"] = max(ok) if ok else 0
    hover = [r for r in loads + capacity if r["airborne"] and r["n"] >= 50]
    if hover:  # CPU-cost projection, insensitive to other jobs stealing the cores
        per = statistics.median(r["cpu_core_fraction"] / r["n"] for r in hover)
        result["projected_real_time_vehicles_per_core"] = int(0.9 / per)
    lock = [lockstep_cost(n, 10 if args.quick else 20) for n in (1, 10, 50, 100)]
    for r in lock:
        print(json.dumps(r), flush=True)
    result["lockstep"] = lock
    result["figures"] = figures(Path(args.out), loads, capacity, lock)
    result["load_average_at_end"] = os.getloadavg()
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
