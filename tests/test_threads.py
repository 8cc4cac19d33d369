"""Threads that share the machine: the fused kernels run on PyTorch's OpenMP pool; the CLI sleeps, not spins.

Each check runs in a fresh interpreter (thread pools and OpenMP settings are per process).
Timings are in ``python -m torchbrdf.bench.threads`` and docs/fast_path.md, not here.
"""

import os
import subprocess
import sys
import textwrap

import pytest

from torchbrdf.kernels import build

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _python(code: str, env_extra=None, drop=("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OMP_NUM_THREADS")) -> str:
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    env.update(env_extra or {})
    res = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env, capture_output=True,
                         text=True, timeout=600, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-3000:]
    return res.stdout


@pytest.mark.skipif(not build.available() or not os.path.exists("/proc/self/maps"),
                    reason="needs the fused kernels and /proc")
def test_kernels_share_torchs_openmp_runtime_and_thread_count(tmp_path):
    out = _python("""
        import os, torch, torchbrdf
        from torchbrdf.brdf.principled import set_fast_path
        set_fast_path(True)
        torch.set_num_threads(1)
        N = 1 << 16
        l = torch.nn.functional.normalize(torch.rand(N, 3) + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
        def run():
            b = torch.rand(N, 3, requires_grad=True)
            out = torchbrdf.principled(l, l, l, base_color=b, roughness=0.5)
            out.sum().backward()
            assert "PrincipledFunction" in out.grad_fn.name()
        before = len(os.listdir("/proc/self/task"))
        run()
        after = len(os.listdir("/proc/self/task"))
        maps = {x.split()[-1] for x in open("/proc/self/maps") if "/" in x}
        omp = sorted(p for p in maps if "gomp" in os.path.basename(p) or "libomp" in os.path.basename(p)
                     or "iomp5" in os.path.basename(p))
        kernels = [p for p in maps if "principled_" in p]
        print("THREADS", before, after)
        print("OMP", len(omp), omp)
        print("KERNELS", len(kernels))
    """, {"TORCHBRDF_CACHE_DIR": str(tmp_path / "cache")})
    lines = dict(line.split(" ", 1) for line in out.splitlines())
    before, after = map(int, lines["THREADS"].split())
    assert after == before  # torch.set_num_threads(1): the kernels started no threads of their own
    assert lines["OMP"].startswith("1 ")  # one OpenMP runtime in the process: PyTorch's
    assert int(lines["KERNELS"]) == 2


def test_library_import_leaves_the_openmp_environment_alone():
    out = _python("""
        import os, torchbrdf, torchbrdf.recovery.svbrdf
        print(os.environ.get("OMP_WAIT_POLICY"))
    """)
    assert out.strip() == "None"


# Python code that records the OpenMP wait settings at torch's first import into ``seen``.
_SPY_ON_TORCH_IMPORT = """
import os, sys
seen = []

class Spy:  # records the environment at torch's first import
    def find_spec(self, name, path=None, target=None):
        if name == "torch" and not seen:
            seen.append((os.environ.get("OMP_WAIT_POLICY"), os.environ.get("GOMP_SPINCOUNT")))

sys.meta_path.insert(0, Spy())
"""


@pytest.mark.parametrize("how", ["module", "file"])
@pytest.mark.parametrize("user, expect", [(None, ["PASSIVE", "2000"]), ("ACTIVE", ["ACTIVE", "None"])])
def test_recovery_cli_sleeps_instead_of_spinning(user, expect, how):
    """``python -m training.recover_svbrdf`` and ``python training/recover_svbrdf.py`` set a short
    poll, then sleep (OMP_WAIT_POLICY=PASSIVE, GOMP_SPINCOUNT=2000) before torch loads libgomp; a
    policy the user set is kept."""
    run = ("runpy.run_module('training.recover_svbrdf', alter_sys=True)" if how == "module"  # argv[0] as -m sets it
           else "sys.argv[0] = 'training/recover_svbrdf.py'; runpy.run_path(sys.argv[0])")
    out = _python(_SPY_ON_TORCH_IMPORT + f"import runpy\n{run}\nprint(*seen[0])\n",
                  {"OMP_WAIT_POLICY": user} if user else None)
    assert out.split() == expect


@pytest.mark.parametrize("user, expect", [(None, "PASSIVE 2000"), ("ACTIVE", "ACTIVE None")])
def test_console_script_sets_the_wait_before_torch_loads(tmp_path, user, expect):
    """``torchbrdf-recover`` has the policy set when torch is first imported, in one process.

    The script is what pip generates (import the entry point, call it); no restart; a policy the
    user set is kept.
    """
    script = tmp_path / "torchbrdf-recover"
    script.write_text(_SPY_ON_TORCH_IMPORT + textwrap.dedent("""
        from torchbrdf.recovery.svbrdf import cli
        print("POLICY", *seen[0], flush=True)
        cli()
    """))
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    if user:
        env["OMP_WAIT_POLICY"] = user
    res = subprocess.run([sys.executable, str(script), "--help"], env=env, capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert [x for x in res.stdout.splitlines() if x.startswith("POLICY")] == [f"POLICY {expect}"]
    assert "usage:" in res.stdout


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_keep_freed_memory_reuses_freed_blocks_instead_of_fresh_pages():
    """After ``keep_freed_memory``, freed 20 MB blocks are reused.

    Ten passes of three 20 MB temporaries fault in at most about one block's pages (glibc
    without it maps such a block fresh, or trims it from the heap when freed, so reuses
    page-fault it in again: 4 to 21 blocks measured here, varying run to run).
    """
    code = """
        import mmap, resource, torch
        from torchbrdf.recovery.svbrdf import keep_freed_memory
        applied = {call} and keep_freed_memory()
        def touch():  # three 20 MB temporaries alive at once, then freed: a fit's pattern
            xs = [torch.ones(5 << 20) for _ in range(3)]
            del xs
        touch()
        f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(10):
            touch()
        block = (20 << 20) // mmap.PAGESIZE
        print(applied, (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / block)
    """
    on = _python(code.format(call=True)).split()
    if on[0] != "True":
        pytest.skip("mallopt not available (not glibc)")
    off = _python(code.format(call=False)).split()
    if float(off[1]) < 3:
        pytest.skip(f"this libc reuses the blocks without it ({off[1]} blocks faulted)")
    assert float(on[1]) <= 1.5, (on, off)


@pytest.mark.parametrize("limit", [0, -1, 1 << 40, 1.5])
def test_keep_freed_memory_refuses_a_limit_glibc_cannot_take(limit):
    from torchbrdf.recovery.svbrdf import keep_freed_memory

    with pytest.raises(ValueError, match="limit must be an integer in"):
        keep_freed_memory(limit)


def test_a_workloads_time_is_its_seconds_line_else_its_wall_time():
    """``run_timed`` takes a workload's own ``SECONDS`` line, else its wall time.

    Without the line, ``require_seconds`` makes it an error; a failing command raises with its stderr.
    """
    from torchbrdf.bench import threads

    said = [sys.executable, "-c", "print('noise'); print('SECONDS 123.5')"]
    silent = [sys.executable, "-c", "print('no time here')"]
    assert threads.run_timed(said, None, False, require_seconds=True) == 123.5
    assert 0 < threads.run_timed(silent, None, False) < 60
    with pytest.raises(RuntimeError, match="printed no SECONDS line"):
        threads.run_timed(silent, None, False, require_seconds=True)
    with pytest.raises(RuntimeError, match="boom"):
        threads.run_timed([sys.executable, "-c", "raise SystemExit('boom')"], None, False)
    wall, out = threads.run_workload(said, None, False)
    assert out.splitlines() == ["noise", "SECONDS 123.5"] and wall > 0
