"""Faults of the fused kernels' build cache (torchbrdf/kernels/build.py): each leaves ``principled`` working.

Every test gets a fresh cache folder (``$TORCHBRDF_CACHE_DIR``) and fresh in-process state, and
forces the fused path at a small lane count. The kernels are compiled once per test run into a
"golden" folder and copied in where a test only needs a cached kernel.
"""

import hashlib
import importlib
import os
import shutil
import subprocess
import sys
import textwrap
import time
import warnings

import pytest
import torch

import torchbrdf
from torchbrdf.kernels import build, fused

P = importlib.import_module("torchbrdf.brdf.principled")

pytestmark = pytest.mark.skipif(not build.available(), reason="no C compiler: the fused path is unavailable")

N = 256


def _inputs():
    g = torch.Generator().manual_seed(3)
    up = torch.tensor([0.0, 0.0, 1.2])
    l = torch.nn.functional.normalize(torch.rand(N, 3, generator=g) - 0.5 + up, dim=-1)
    v = torch.nn.functional.normalize(torch.rand(N, 3, generator=g) - 0.5 + up, dim=-1)
    n = torch.nn.functional.normalize(torch.rand(N, 3, generator=g) * 0.2 - 0.1 + up, dim=-1)
    return dict(l=l, v=v, n=n, base_color=torch.rand(N, 3, generator=g),
                roughness=torch.rand(N, 1, generator=g) * 0.8 + 0.1, metallic=0.3)


def _run(fast: bool):
    """Run ``principled`` forward + backward (w.r.t. base_color, roughness): (out, grads, grad_fn name)."""
    old = P.fast_path_enabled()
    P.set_fast_path(fast)
    try:
        ins = _inputs()
        for k in ("base_color", "roughness"):
            ins[k].requires_grad_(True)
        out = torchbrdf.principled(**ins)
        name = out.grad_fn.name()
        out.backward(torch.ones_like(out))
        return out.detach(), (ins["base_color"].grad, ins["roughness"].grad), name
    finally:
        P.set_fast_path(old)


def _check_principled(expect_fused: bool | None = None):
    """Check that ``principled`` works and equals eager; returns whether the fused kernels ran."""
    of, gf, name = _run(True)
    # The operator falls back to the eager formula inside itself when no kernel loads, so
    # whether a kernel ran is whether a kernel library is loaded, not the grad_fn's name.
    ran_fused = bool(fused._libs)
    oe, ge, _ = _run(False)
    torch.testing.assert_close(of, oe, rtol=1e-6, atol=1e-7)
    for a, b in zip(gf, ge):
        torch.testing.assert_close(a, b, rtol=2e-6, atol=1e-6)
    if expect_fused is not None:
        assert ran_fused == expect_fused, name
    return ran_fused


def _fresh_state(monkeypatch):
    monkeypatch.setattr(build, "_state", build._State())
    monkeypatch.setattr(fused, "_libs", {})
    monkeypatch.setattr(fused, "_failed", set())


def _kernels(d):
    return sorted(f for f in os.listdir(d) if f.endswith(".so"))


@pytest.fixture(scope="session")
def golden(tmp_path_factory):
    """A cache folder holding this test's kernels, built once."""
    root = tmp_path_factory.mktemp("golden") / "cache"
    mp = pytest.MonkeyPatch()
    try:
        mp.setenv("TORCHBRDF_CACHE_DIR", str(root))
        _fresh_state(mp)
        assert _check_principled(expect_fused=True)
    finally:
        mp.undo()
    return root


@pytest.fixture
def cache(tmp_path, monkeypatch, recwarn):
    """A fresh, empty cache root in ``$TORCHBRDF_CACHE_DIR`` and fresh in-process state."""
    root = tmp_path / "cache"
    monkeypatch.setenv("TORCHBRDF_CACHE_DIR", str(root))
    _fresh_state(monkeypatch)
    warnings.simplefilter("always")
    return root


def _prefill(root, golden):
    shutil.copytree(golden, root)


def _our_warnings(recwarn):
    return [w for w in recwarn.list if "torchbrdf" in str(w.message)]


def _mapped():
    with open("/proc/self/maps") as fh:
        return {line.split()[-1] for line in fh if ".so" in line}


# --- layout -----------------------------------------------------------------------------------

def test_cache_is_private_atomic_and_validated(cache, recwarn):
    assert _check_principled(expect_fused=True)
    kd = cache / "kernels"
    assert build.kernel_cache_dir() == str(kd)
    for d in (cache, kd):
        st = os.stat(d)
        assert st.st_mode & 0o777 == 0o700 and st.st_uid == os.getuid()
    sos = _kernels(kd)
    assert len(sos) == 2  # forward and backward
    for so in sos:
        size, digest = open(kd / (so + ".sha256")).read().split()
        data = (kd / so).read_bytes()
        assert int(size) == len(data) and digest == hashlib.sha256(data).hexdigest()
        assert any(str(kd / so) == p for p in _mapped())
    assert not [f for f in os.listdir(kd) if f.startswith(".tmp-")]  # no temporaries left
    assert not _our_warnings(recwarn)


def test_one_cache_variable_for_kernels_and_demo_capture(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCHBRDF_CACHE_DIR", str(tmp_path / "c"))
    assert build.cache_root() == str(tmp_path / "c")
    assert build.kernel_cache_dir() == str(tmp_path / "c" / "kernels")
    monkeypatch.delenv("TORCHBRDF_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert build.cache_root() == str(tmp_path / "xdg" / "torchbrdf")


@pytest.mark.parametrize("home", ["", "relative/home"])
def test_empty_or_relative_home_is_not_taken_relative_to_the_current_folder(monkeypatch, tmp_path, home):
    import pwd

    monkeypatch.delenv("TORCHBRDF_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", "")
    monkeypatch.setenv("HOME", home)
    monkeypatch.chdir("/")
    expected = os.path.join(pwd.getpwuid(os.getuid()).pw_dir, ".cache", "torchbrdf")
    assert build.cache_root() == os.path.abspath(expected) != "/.cache/torchbrdf"


# --- unusable folders: a private per-process folder, never a shared one ------------------------

def test_unwritable_cache_dir_builds_in_a_private_folder(cache, tmp_path, monkeypatch, recwarn):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("TORCHBRDF_CACHE_DIR", str(blocker / "cache"))  # cannot be created, even by root
    assert _check_principled(expect_fused=True)
    assert _check_principled(expect_fused=True)
    ws = _our_warnings(recwarn)
    assert len(ws) == 1 and "private folder" in str(ws[0].message)
    priv = build._state.private_dir
    st = os.stat(priv)
    assert st.st_mode & 0o777 == 0o700 and st.st_uid == os.getuid()
    assert os.path.basename(priv) != "torchbrdf-kernels"  # unique, not the old shared name
    assert any(p.startswith(priv + os.sep) for p in _mapped())


def _plant(root, golden):
    """A cache whose kernels are garbage with matching sidecars (code another user could plant)."""
    _prefill(root, golden)
    kd = root / "kernels"
    for so in _kernels(kd):
        data = b"\x7fELF planted by someone else" * 100
        (kd / so).write_bytes(data)
        (kd / (so + ".sha256")).write_text(f"{len(data)} {hashlib.sha256(data).hexdigest()}\n")
    return kd


def _untouched(kd, before):
    after = {f: (kd / f).read_bytes() for f in os.listdir(kd)}
    assert after == before
    assert not any(p.startswith(str(kd)) for p in _mapped())


def test_foreign_owned_cache_dir_is_refused(cache, golden, monkeypatch, recwarn):
    kd = _plant(cache, golden)
    before = {f: (kd / f).read_bytes() for f in os.listdir(kd)}
    if os.getuid() == 0:
        os.chown(cache, 4242, 4242)  # root can make it really foreign
    else:
        uid = os.getuid()
        monkeypatch.setattr(os, "getuid", lambda: uid + 1)
    assert _check_principled(expect_fused=True)
    ws = _our_warnings(recwarn)
    assert len(ws) == 1 and "owned by uid" in str(ws[0].message)
    _untouched(kd, before)


@pytest.mark.parametrize("which", ["root", "kernels"])
def test_group_or_world_writable_cache_dir_is_refused(cache, golden, recwarn, which):
    kd = _plant(cache, golden)
    before = {f: (kd / f).read_bytes() for f in os.listdir(kd)}
    os.chmod(cache if which == "root" else kd, 0o777)
    assert _check_principled(expect_fused=True)
    ws = _our_warnings(recwarn)
    assert len(ws) == 1 and "writable by the group or others" in str(ws[0].message)
    _untouched(kd, before)


# --- damaged cached kernels: validated before dlopen, rebuilt once ------------------------------

@pytest.mark.parametrize("damage", ["truncated", "zero_bytes", "garbage"])
def test_damaged_cached_kernel_is_rebuilt(cache, golden, recwarn, damage):
    _prefill(cache, golden)
    kd = cache / "kernels"
    bad = {}
    for so in _kernels(kd):
        data = (kd / so).read_bytes()
        bad[so] = {"truncated": data[: len(data) // 2], "zero_bytes": b"",
                   "garbage": os.urandom(len(data))}[damage]
        (kd / so).write_bytes(bad[so])
    assert _check_principled(expect_fused=True)
    for so in bad:  # rebuilt in place
        assert (kd / so).read_bytes() != bad[so] and build._valid(str(kd / so))
    assert not _our_warnings(recwarn)


def test_truncated_kernel_with_forged_sidecar_does_not_crash(cache, golden):
    """A truncated .so that passes the checksum must still never reach dlopen (SIGBUS)."""
    _prefill(cache, golden)
    kd = cache / "kernels"
    for so in _kernels(kd):
        data = (kd / so).read_bytes()[:6000]
        (kd / so).write_bytes(data)
        (kd / (so + ".sha256")).write_text(f"{len(data)} {hashlib.sha256(data).hexdigest()}\n")
    # in a child process: if the loader touched the file, the SIGBUS would kill pytest itself
    script = textwrap.dedent(f"""
        import sys, warnings
        sys.path.insert(0, {os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))!r})
        warnings.filterwarnings("error", message="torchbrdf")
        from tests.kernels.test_kernel_cache import _check_principled
        assert _check_principled(expect_fused=True)
    """)
    env = dict(os.environ, TORCHBRDF_CACHE_DIR=str(cache), OMP_NUM_THREADS="1")
    res = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, (res.returncode, res.stderr[-3000:])
    for so in _kernels(kd):
        assert build._valid(str(kd / so))


def test_valid_elf_without_the_kernel_is_rebuilt_once(cache, golden, tmp_path, recwarn):
    """A well-formed library that loads but lacks the kernel symbol (a stale or foreign file)."""
    _prefill(cache, golden)
    kd = cache / "kernels"
    src = tmp_path / "other.c"
    src.write_text("int not_a_kernel(void) { return 1; }\n")
    other = tmp_path / "other.so"
    subprocess.run([build._compiler(), "-shared", "-fPIC", str(src), "-o", str(other)], check=True)
    for so in _kernels(kd):
        shutil.copy(other, kd / so)
        data = other.read_bytes()
        (kd / (so + ".sha256")).write_text(f"{len(data)} {hashlib.sha256(data).hexdigest()}\n")
    assert _check_principled(expect_fused=True)
    assert not _our_warnings(recwarn)


def test_kernel_that_never_loads_runs_eager_with_one_warning(cache, golden, monkeypatch, recwarn):
    _prefill(cache, golden)
    builds = []
    real_compile = build._compile

    def counting_compile(*a):
        builds.append(a[1])
        return real_compile(*a)

    def broken_dlopen(so, symbols):
        raise OSError(f"{so}: cannot load")

    monkeypatch.setattr(build, "_compile", counting_compile)
    monkeypatch.setattr(build, "_dlopen", broken_dlopen)
    assert not _check_principled(expect_fused=False)
    assert not _check_principled(expect_fused=False)
    # Each kernel that fails to load (the forward's cached file, then the backward's, which the
    # operator's autograd still asks for) is rebuilt once; then eager, no more builds.
    assert len(builds) == 2 and len({b.rsplit("_", 1)[0] for b in builds}) == 2
    assert len(_our_warnings(recwarn)) == 1


# --- OSError while building: eager, one warning, no exception ---------------------------------

@pytest.mark.parametrize("err", [OSError(28, "No space left on device"), PermissionError(13, "Read-only")])
def test_oserror_while_building_runs_eager_with_one_warning(cache, monkeypatch, recwarn, err):
    def failing(*a):
        raise err

    monkeypatch.setattr(build, "_compile", failing)
    assert not _check_principled(expect_fused=False)
    assert not _check_principled(expect_fused=False)
    ws = _our_warnings(recwarn)
    assert len(ws) == 1 and "using eager" in str(ws[0].message)


@pytest.mark.skipif(os.getuid() == 0, reason="root writes into read-only folders")
def test_read_only_cache_dir_runs_eager_with_one_warning(cache, recwarn):
    (cache / "kernels").mkdir(parents=True, mode=0o700)
    os.chmod(cache / "kernels", 0o500)
    try:
        assert not _check_principled(expect_fused=False)
    finally:
        os.chmod(cache / "kernels", 0o700)
    assert len(_our_warnings(recwarn)) == 1


def test_compiler_failure_runs_eager_with_one_warning(cache, monkeypatch, recwarn, tmp_path):
    fake = tmp_path / "cc"
    fake.write_text("#!/bin/sh\necho 'cc: fatal error: no space left' >&2\nexit 1\n")
    fake.chmod(0o755)
    monkeypatch.setenv("CC", str(fake))
    assert not _check_principled(expect_fused=False)
    assert not _check_principled(expect_fused=False)
    ws = _our_warnings(recwarn)
    assert len(ws) == 1 and "building a fused kernel failed" in str(ws[0].message)
    assert not [f for f in os.listdir(cache / "kernels") if not f.endswith(".lock")]


# --- concurrency ------------------------------------------------------------------------------

def test_two_processes_compiling_at_once(cache):
    """Two fresh processes build the same kernels into one empty cache at the same moment."""
    go = cache.parent / "go"
    script = textwrap.dedent(f"""
        import os, sys, time, warnings
        sys.path.insert(0, {os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))!r})
        warnings.filterwarnings("error", message="torchbrdf")
        from tests.kernels.test_kernel_cache import _check_principled
        open(sys.argv[1], "w").close()
        while not os.path.exists({str(go)!r}):
            time.sleep(0.01)
        assert _check_principled(expect_fused=True)
    """)
    env = dict(os.environ, TORCHBRDF_CACHE_DIR=str(cache), OMP_NUM_THREADS="1")
    ready = [cache.parent / f"ready{k}" for k in range(2)]
    procs = [subprocess.Popen([sys.executable, "-c", script, str(r)], env=env, stderr=subprocess.PIPE,
                              text=True) for r in ready]
    t0 = time.time()
    while not all(r.exists() for r in ready) and time.time() - t0 < 300:
        time.sleep(0.05)
    go.touch()
    for p in procs:
        _, err = p.communicate(timeout=600)
        assert p.returncode == 0, err[-3000:]
    kd = cache / "kernels"
    sos = _kernels(kd)
    assert len(sos) == 2
    assert all(build._valid(str(kd / so)) for so in sos)
    assert not [f for f in os.listdir(kd) if f.startswith(".tmp-")]
    # and this process loads what they built
    assert _check_principled(expect_fused=True)
