"""How many CPU threads this process should use: the CPUs it may run on, not the CPUs the machine has.

``torch.get_num_threads()`` defaults to the machine's physical cores. A process limited by its
CPU affinity (``taskset``, a batch scheduler) or by a container's cgroup CPU quota then runs
more OpenMP threads than it has CPUs, and every synchronisation between its small operations
waits for a thread that is not running. On a machine that other processes keep busy the same
happens with the CPUs they use.

* :func:`available_cpus`: the CPUs this process may use, from the affinity mask and the cgroup
  v2 (``cpu.max``) or v1 (``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``) quota;
* :func:`stolen_cpus`: the CPUs' worth of time a hypervisor gave other machines over a short
  window (the ``steal`` column of ``/proc/stat``): on a virtual machine whose host is
  oversubscribed a vCPU is descheduled for whole milliseconds, and an OpenMP barrier waits
  for it just as for a thread another process holds;
* :func:`default_threads`: that count, optionally less the 1-minute load of the other
  processes and the stolen CPUs (``load_aware``), at least 1.

Typical use, when the user did not choose a thread count::

    torch.set_num_threads(torchbrdf.parallel.default_threads())
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable

__all__ = ["available_cpus", "cgroup_cpu_limit", "default_threads", "stolen_cpus", "steal_between",
           "CGROUP_ROOT", "PROC_STAT", "STEAL_WINDOW"]

#: Where the cgroup file systems are mounted (the process's own cgroup is read from /proc/self/cgroup).
CGROUP_ROOT = "/sys/fs/cgroup"
#: The kernel's CPU time counters (the aggregate ``cpu`` line and one ``cpuN`` line per CPU).
PROC_STAT = "/proc/stat"
#: Seconds between the two readings of :data:`PROC_STAT` in :func:`stolen_cpus`: the steal of an
#: oversubscribed host comes in bursts of milliseconds, so a tenth of a second averages tens of them.
STEAL_WINDOW = 0.1


def _read(path: str) -> str | None:
    try:
        with open(path, encoding="ascii") as fh:
            return fh.read().strip()
    except (OSError, UnicodeDecodeError):
        return None


def _own_cgroup_dirs(root: str, proc_cgroup: str) -> list[str]:
    """The directories holding this process's CPU controller files, innermost first.

    cgroup v2: ``0::/path`` in ``/proc/self/cgroup``; v1: ``N:cpu,cpuacct:/path``. Inside a
    container the path is usually ``/`` (the namespace root), so the root itself is tried last.
    """
    dirs: list[str] = []
    text = _read(proc_cgroup) or ""
    for line in text.splitlines():
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, path = parts
        ctl = controllers.split(",") if controllers else []
        rel = path.lstrip("/")
        if not controllers:  # v2 unified hierarchy
            base = root
        elif "cpu" in ctl:
            base = next((os.path.join(root, d) for d in (controllers, "cpu,cpuacct", "cpu")
                         if os.path.isdir(os.path.join(root, d))), os.path.join(root, "cpu"))
        else:
            continue
        # a limit set on any ancestor applies too: walk up to the hierarchy's root
        while True:
            dirs.append(os.path.join(base, rel) if rel else base)
            if not rel:
                break
            rel = os.path.dirname(rel)
    for d in (root, os.path.join(root, "cpu"), os.path.join(root, "cpu,cpuacct")):
        if d not in dirs:
            dirs.append(d)
    return dirs


def _quota_in(d: str) -> float | None:
    """The CPU quota (in CPUs) set in cgroup directory ``d``, or None when unlimited/absent."""
    v2 = _read(os.path.join(d, "cpu.max"))
    if v2 is not None:  # "max 100000" or "150000 100000"
        parts = v2.split()
        if len(parts) >= 1 and parts[0] != "max":
            try:
                quota, period = float(parts[0]), float(parts[1]) if len(parts) > 1 else 100000.0
            except ValueError:
                return None
            return quota / period if quota > 0 and period > 0 else None
        return None
    q, p = _read(os.path.join(d, "cpu.cfs_quota_us")), _read(os.path.join(d, "cpu.cfs_period_us"))
    if q is None or p is None:
        return None
    try:
        quota, period = float(q), float(p)
    except ValueError:
        return None
    return quota / period if quota > 0 and period > 0 else None  # -1: unlimited


def cgroup_cpu_limit(root: str = CGROUP_ROOT, proc_cgroup: str = "/proc/self/cgroup") -> float | None:
    """The tightest cgroup CPU quota over this process's cgroup and its ancestors, in CPUs.

    Reads cgroup v2 ``cpu.max`` (``"QUOTA PERIOD"`` or ``"max PERIOD"``) or v1
    ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us`` (quota ``-1``: unlimited). Returns a float
    (``1.5`` = one and a half CPUs' time per period) or None when no quota is set or nothing
    can be read. ``root`` / ``proc_cgroup``: where to read (tests point them at fake files).
    """
    limits = [q for q in (_quota_in(d) for d in _own_cgroup_dirs(root, proc_cgroup)) if q is not None]
    return min(limits) if limits else None


def _affinity_count() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        return os.cpu_count() or 1


def available_cpus(root: str = CGROUP_ROOT, proc_cgroup: str = "/proc/self/cgroup") -> int:
    """The number of CPUs this process may use, at least 1.

    The CPUs of its affinity mask (``os.sched_getaffinity``; ``os.cpu_count()`` where that does
    not exist), capped by the cgroup CPU quota (:func:`cgroup_cpu_limit`, rounded up: a quota of
    1.5 CPUs keeps two threads busy 75 % of the time rather than one thread all the time).
    """
    n = _affinity_count()
    quota = cgroup_cpu_limit(root, proc_cgroup)
    if quota is not None:
        n = min(n, max(1, math.ceil(quota - 1e-9)))
    return max(1, n)


def _own_load() -> float:
    """CPUs this process is using now (1-min load counts its running threads too): its own
    threads that are running, read from ``/proc/self/task/*/stat`` (state ``R``)."""
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return 1.0
    running = 0
    for t in tasks:
        stat = _read(f"/proc/self/task/{t}/stat")
        if stat and ") R " in stat:
            running += 1
    return float(max(running, 1))


def _cpu_times(text: str) -> tuple[list[int], int] | None:
    """The aggregate ``cpu`` line's counters and the number of ``cpuN`` lines of a ``/proc/stat`` text."""
    total: list[int] | None = None
    n_cpu = 0
    for line in text.splitlines():
        name, _, rest = line.partition(" ")
        if name == "cpu":
            try:
                total = [int(x) for x in rest.split()]
            except ValueError:
                return None
        elif name.startswith("cpu") and name[3:].isdigit():
            n_cpu += 1
    return (total, n_cpu) if total is not None and n_cpu else None


def steal_between(before: str, after: str) -> float | None:
    """The CPUs' worth of stolen time between two ``/proc/stat`` texts, or None.

    ``steal`` (the 8th counter of the aggregate ``cpu`` line: time a vCPU was ready but the
    hypervisor ran something else) over all eight time counters (user … steal; ``guest`` is
    part of ``user``), times the CPU count: ``1.0`` on a 2-vCPU machine means half of every
    vCPU's time went to other machines. None when either text lacks the counters (no steal
    column before Linux 2.6.11, not Linux) or no time passed.
    """
    a, b = _cpu_times(before), _cpu_times(after)
    if a is None or b is None or len(a[0]) < 8 or len(b[0]) < 8:
        return None
    delta = [y - x for x, y in zip(a[0][:8], b[0][:8])]
    total = sum(delta)
    if total <= 0:
        return None
    return max(0.0, delta[7] / total) * b[1]


def stolen_cpus(window: float = STEAL_WINDOW, stat: str = PROC_STAT,
                sleep: Callable[[float], object] = time.sleep) -> float | None:
    """The CPUs' worth of time the hypervisor gave to other machines over ``window`` seconds.

    Reads ``stat`` (:data:`PROC_STAT`), sleeps ``window`` seconds (a sleep: no spinning) and
    reads it again (:func:`steal_between`). 0 on bare metal or a quiet host; None where the
    file or its steal counter is missing. ``stat`` / ``sleep``: tests point them at fake files.
    """
    before = _read(stat)
    if before is None:
        return None
    sleep(window)
    after = _read(stat)
    return None if after is None else steal_between(before, after)


def default_threads(load_aware: bool = True, *, cpus: int | None = None,
                    loadavg: Callable[[], tuple[float, float, float]] | None = None,
                    own_load: float | None = None, steal: Callable[[], float | None] | None = None) -> int:
    """The thread count for this process's CPU work, at least 1.

    :func:`available_cpus`, and with ``load_aware`` less the 1-minute load average of the other
    processes (``os.getloadavg()[0]`` minus this process's own running threads) and less the
    CPUs the hypervisor is stealing now (:func:`stolen_cpus`, over :data:`STEAL_WINDOW`),
    rounded to the nearest CPU: beside one busy process on 2 CPUs this gives 1 thread, and so
    does a 2-vCPU virtual machine whose host takes half its time, so no OpenMP barrier waits for
    a thread the scheduler (or the hypervisor) has parked. The load average counts every
    runnable task of the machine, which inside a container with a quota may include other
    containers' work; the result is still at most :func:`available_cpus`.

    Args:
        load_aware: subtract the other processes' load and the stolen CPUs (False: the
            available CPUs, nothing read, no wait).
        cpus: the available CPUs (default :func:`available_cpus`).
        loadavg: replaces ``os.getloadavg`` (tests).
        own_load: this process's own share of the load (default: its running threads).
        steal: replaces :func:`stolen_cpus` (tests; None from it counts as no steal).

    Returns:
        An int in ``[1, cpus]``.
    """
    n = available_cpus() if cpus is None else int(cpus)
    n = max(1, n)
    if not load_aware:
        return n
    stolen = (steal or stolen_cpus)() or 0.0
    try:
        one_min = float((loadavg or os.getloadavg)()[0])
    except (AttributeError, OSError):  # no load average on this platform
        one_min = None
    others = 0.0 if one_min is None else max(0.0, one_min - (_own_load() if own_load is None else float(own_load)))
    return int(min(n, max(1, math.floor(n - others - stolen + 0.5))))
