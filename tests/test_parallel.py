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


def test_default_threads_subtracts_other_processes_load():
    def load(x):
        return lambda: (x, 0.0, 0.0)

    # quiet 2-CPU machine: our own running thread is the whole load
    assert parallel.default_threads(cpus=2, loadavg=load(1.0), own_load=1.0) == 2
    # one busy process beside us: one thread
    assert parallel.default_threads(cpus=2, loadavg=load(2.0), own_load=1.0) == 1
    # heavily loaded: never below one
    assert parallel.default_threads(cpus=2, loadavg=load(40.0), own_load=1.0) == 1
    # 16 CPUs, 5 others busy: 11
    assert parallel.default_threads(cpus=16, loadavg=load(6.0), own_load=1.0) == 11
    # never above the available CPUs, and load_aware=False ignores the load
    assert parallel.default_threads(cpus=4, loadavg=load(0.0), own_load=1.0) == 4
    assert parallel.default_threads(False, cpus=2, loadavg=load(40.0)) == 2


def test_default_threads_without_a_load_average():
    def none():
        raise OSError("no load average")

    assert parallel.default_threads(cpus=3, loadavg=none) == 3


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
