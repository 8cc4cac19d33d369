"""torchbrdf.parallel: the thread count from affinity, the cgroup quota and the load (fake files, calls)."""

import os

import pytest

from torchbrdf import parallel


def _cgroup(tmp_path, proc: str, files: dict[str, str]):
    """A fake cgroup mount under ``tmp_path/cg`` and a fake ``/proc/self/cgroup``."""
    root = tmp_path / "cg"
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    root.mkdir(parents=True, exist_ok=True)
    pc = tmp_path / "proc_cgroup"
    pc.write_text(proc)
    return str(root), str(pc)


def test_cgroup_v2_quota_of_own_group_and_ancestors(tmp_path):
    root, pc = _cgroup(tmp_path, "0::/user/job\n", {
        "cpu.max": "max 100000\n",
        "user/cpu.max": "300000 100000\n",  # an ancestor's 3 CPUs
        "user/job/cpu.max": "150000 100000\n",  # the process's own 1.5 CPUs
    })
    assert parallel.cgroup_cpu_limit(root, pc) == pytest.approx(1.5)
    # 1.5 CPUs rounds up to 2 threads, then the affinity caps it
    assert parallel.available_cpus(root, pc) == min(2, len(os.sched_getaffinity(0)))


def test_cgroup_v2_unlimited_and_missing(tmp_path):
    root, pc = _cgroup(tmp_path, "0::/\n", {"cpu.max": "max 100000\n"})
    assert parallel.cgroup_cpu_limit(root, pc) is None
    root, pc = _cgroup(tmp_path / "b", "0::/\n", {})
    assert parallel.cgroup_cpu_limit(root, pc) is None
    assert parallel.available_cpus(root, pc) == len(os.sched_getaffinity(0))


def test_cgroup_v1_quota(tmp_path):
    root, pc = _cgroup(tmp_path, "3:cpuset:/\n1:cpu,cpuacct:/docker/abc\n", {
        "cpu,cpuacct/docker/abc/cpu.cfs_quota_us": "50000\n",
        "cpu,cpuacct/docker/abc/cpu.cfs_period_us": "100000\n",
        "cpu,cpuacct/cpu.cfs_quota_us": "-1\n",
        "cpu,cpuacct/cpu.cfs_period_us": "100000\n",
    })
    assert parallel.cgroup_cpu_limit(root, pc) == pytest.approx(0.5)
    assert parallel.available_cpus(root, pc) == 1  # never below one


def test_affinity_caps_the_count(monkeypatch, tmp_path):
    root, pc = _cgroup(tmp_path, "0::/\n", {"cpu.max": "800000 100000\n"})  # 8 CPUs of quota
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2})
    assert parallel.available_cpus(root, pc) == 3


def _no_steal():
    return 0.0


def test_default_threads_subtracts_other_processes_load():
    def load(x):
        return lambda: (x, 0.0, 0.0)

    # quiet 2-CPU machine: our own running thread is the whole load
    assert parallel.default_threads(cpus=2, loadavg=load(1.0), own_load=1.0, steal=_no_steal) == 2
    # one busy process beside us: one thread
    assert parallel.default_threads(cpus=2, loadavg=load(2.0), own_load=1.0, steal=_no_steal) == 1
    # heavily loaded: never below one
    assert parallel.default_threads(cpus=2, loadavg=load(40.0), own_load=1.0, steal=_no_steal) == 1
    # 16 CPUs, 5 others busy: 11
    assert parallel.default_threads(cpus=16, loadavg=load(6.0), own_load=1.0, steal=_no_steal) == 11
    # never above the available CPUs, and load_aware=False ignores the load
    assert parallel.default_threads(cpus=4, loadavg=load(0.0), own_load=1.0, steal=_no_steal) == 4
    assert parallel.default_threads(False, cpus=2, loadavg=load(40.0)) == 2


def test_default_threads_without_a_load_average():
    def none():
        raise OSError("no load average")

    assert parallel.default_threads(cpus=3, loadavg=none, steal=_no_steal) == 3


def _stat(user: int, idle: int, steal: int, cpus: int = 2) -> str:
    """A /proc/stat text: the aggregate line (user nice system idle iowait irq softirq steal guest
    guest_nice) and ``cpus`` per-CPU lines."""
    lines = [f"cpu  {user} 0 0 {idle} 0 0 0 {steal} 0 0"]
    lines += [f"cpu{k} 1 0 0 1 0 0 0 0 0 0" for k in range(cpus)]
    return "\n".join(lines + ["intr 1 2 3", "ctxt 100", "procs_running 3"]) + "\n"


def test_steal_between_counts_cpus_of_stolen_time():
    # 2 vCPUs, over the window: 100 ticks user, 100 idle, 200 stolen: half of all time → 1 CPU
    assert parallel.steal_between(_stat(0, 0, 0), _stat(100, 100, 200)) == pytest.approx(1.0)
    # quiet host
    assert parallel.steal_between(_stat(5, 5, 7), _stat(105, 105, 7)) == 0.0
    # 4 vCPUs, a quarter stolen → 1 CPU
    assert parallel.steal_between(_stat(0, 0, 0, 4), _stat(150, 150, 100, 4)) == pytest.approx(1.0)
    # no time passed, no steal column (an old kernel), not a stat file
    assert parallel.steal_between(_stat(1, 1, 1), _stat(1, 1, 1)) is None
    assert parallel.steal_between("cpu  1 2 3 4\ncpu0 1 2 3 4\n", "cpu  2 3 4 5\ncpu0 2 3 4 5\n") is None
    assert parallel.steal_between("hello", "world") is None


def test_stolen_cpus_reads_the_file_twice_across_a_sleep(tmp_path):
    stat = tmp_path / "stat"
    stat.write_text(_stat(1000, 1000, 0))
    waits = []

    def sleep(seconds):  # the window passes: the host took 60 of the 200 ticks
        waits.append(seconds)
        stat.write_text(_stat(1070, 1070, 60))

    assert parallel.stolen_cpus(0.25, str(stat), sleep) == pytest.approx(2 * 60 / 200)
    assert waits == [0.25]
    assert parallel.stolen_cpus(0.1, str(tmp_path / "missing"), sleep) is None


def test_default_threads_subtracts_stolen_cpus():
    def quiet():
        return (1.0, 0.0, 0.0)  # our own thread only

    # a 2-vCPU machine whose host takes half its time: one thread, as beside one busy process
    assert parallel.default_threads(cpus=2, loadavg=quiet, own_load=1.0, steal=lambda: 1.0) == 1
    # a little steal rounds away; no reading (None) counts as none
    assert parallel.default_threads(cpus=2, loadavg=quiet, own_load=1.0, steal=lambda: 0.3) == 2
    assert parallel.default_threads(cpus=2, loadavg=quiet, own_load=1.0, steal=lambda: None) == 2
    # steal and other processes add up; never below one
    assert parallel.default_threads(cpus=8, loadavg=lambda: (3.0, 0, 0), own_load=1.0, steal=lambda: 2.0) == 4
    assert parallel.default_threads(cpus=2, loadavg=quiet, own_load=1.0, steal=lambda: 5.0) == 1

    # load_aware=False reads nothing
    def boom():
        raise AssertionError("steal read with load_aware=False")

    assert parallel.default_threads(False, cpus=2, steal=boom) == 2


def test_default_threads_real_machine_is_in_range():
    n = parallel.default_threads()
    assert 1 <= n <= parallel.available_cpus()


def test_thread_bench_passes_the_cli_its_thread_choice(monkeypatch):
    from torchbrdf.bench import threads

    cmd = ["python", "-m", "training.recover_svbrdf", "--demo"]
    assert threads._with_threads(cmd, "torch", False) == cmd
    assert threads._with_threads(cmd, "1", True) == cmd + ["--threads", "1"]
    monkeypatch.setattr(parallel, "available_cpus", lambda *a, **k: 4)
    monkeypatch.setattr(os, "getloadavg", lambda: (3.0, 0.0, 0.0))
    assert threads._with_threads(cmd, "auto", True) == cmd + ["--threads", "1"]  # 3 others busy of 4
