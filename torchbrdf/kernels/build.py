"""Build, cache and load generated C kernels, safely, like a library should.

One call does it all: :func:`load_kernel` ``(source, name, symbols) -> ctypes.CDLL | None``.
``None`` means "run eager": every failure (no compiler, a build error, a read-only or full
disk, a cached file that will not load) ends there with at most one warning per kind of
failure and process, never with an exception or a crash.

The guarantees (the same as ``torch.utils.cpp_extension`` gives, or stronger):

* **Compiler discovery**: ``$CC``, else ``gcc``, else ``cc`` on ``PATH``; its version is part
  of the cache key, with the flags, the machine's CPU flags and the OpenMP runtime.
* **A per-user cache**: ``$TORCHBRDF_CACHE_DIR`` (the one cache variable of torchbrdf; default
  ``$XDG_CACHE_HOME/torchbrdf`` or ``~/.cache/torchbrdf``), kernels in its ``kernels/``
  folder. Folders are created 0700; a folder owned by another user, or writable by the group
  or others, is refused (another user could plant code there), and so is a cached file with
  those properties. There is no shared fallback: when the cache cannot be used, the kernels are
  built in a private ``tempfile.mkdtemp()`` folder for this process (removed at exit), with
  one warning.
* **Atomic, durable writes**: the compiler writes a uniquely named temporary file in the cache
  folder; it is fsync'd, renamed into place, and then a sidecar ``<so>.sha256`` holding its
  size and SHA-256 is written the same way; finally the folder is fsync'd.
* **Validated loads**: before ``dlopen`` the ``.so`` must match its sidecar and be a
  well-formed ELF file whose loadable segments lie inside the file. A truncated library would
  otherwise be mapped and kill the interpreter with SIGBUS when touched.
* **Concurrent builds**: processes building the same kernel serialise on an ``flock`` of
  ``<so>.lock`` (released by the kernel if a process dies) and the second one finds the first
  one's result; the unique temporary names plus ``os.replace`` keep even lock-less
  filesystems safe.
* **Rebuild once**: a cached kernel that fails validation or ``dlopen`` is rebuilt once; if
  that fails too, eager runs (one warning).

OpenMP: kernels are compiled with ``-fopenmp`` and linked against the OpenMP runtime that
PyTorch itself has loaded (found in ``/proc/self/maps``), so they run on PyTorch's intra-op
thread pool, with its thread count (:func:`torch.set_num_threads`) and its wait policy,
instead of a second pool that would spin against PyTorch's. See ``docs/fast_path.md``.
"""

from __future__ import annotations

import atexit
import ctypes
import errno
import hashlib
import os
import re
import shutil
import stat
import struct
import subprocess
import tempfile
import threading
import warnings
from collections.abc import Sequence
from typing import Any

from torchbrdf.io import CACHE_ENV, cache_root, fsync_dir  # re-exported: the kernels' cache lives there

__all__ = ["load_kernel", "cache_root", "kernel_cache_dir", "available", "CACHE_ENV", "CFLAGS"]

# -ffp-contract=off: no FMA contraction, so float results round exactly like ATen's ops.
# -fno-math-errno/-fno-trapping-math: lets sqrt and the selects vectorise (IEEE results kept).
# The -fno-* passes below would otherwise thread jumps through the clamps of the backward and
# leave boolean selects that gcc 12 cannot vectorise.
# --param=vect-epilogues-nomask=0: the lane loop's few leftover lanes run scalar instead of in a
# second, narrower vectorised copy of the loop body (less to compile; the blocks of 512 lanes
# leave no leftover but the last block's).
CFLAGS = ["-O3", "-march=native", "-fopenmp", "-ffp-contract=off", "-fno-math-errno",
          "-fno-trapping-math", "-fno-tree-dominator-opts", "-fno-thread-jumps", "-fno-tree-pre",
          "-fno-code-hoisting", "--param=vect-epilogues-nomask=0", "-fPIC", "-std=c11"]


class _State:
    """Process-wide state (one object, so tests can swap in a fresh one)."""

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.loaded: dict[str, ctypes.CDLL] = {}  # file name -> CDLL
        self.failed: set[str] = set()  # so names that failed twice: eager from now on
        self.warned: set[str] = set()
        self.compiler_checked = False
        self.compiler: str | None = None
        self.compiler_id: str | None = None
        self.private_dir: str | None = None
        self.omp: tuple[str | None] | None = None


_state = _State()


def _warn_once(kind: str, msg: str) -> None:
    if kind in _state.warned:
        return
    _state.warned.add(kind)
    warnings.warn(f"torchbrdf: {msg}", RuntimeWarning, stacklevel=4)


# ---------------------------------------------------------------------------------------------
# Where: the per-user cache
# ---------------------------------------------------------------------------------------------


def kernel_cache_dir() -> str:
    """Folder of the compiled kernels: ``<cache_root()>/kernels``."""
    return os.path.join(cache_root(), "kernels")


def _check_private(path: str, is_dir: bool) -> str | None:
    """Why ``path`` may not be trusted (another owner, writable by others), or None."""
    st = os.stat(path)
    if is_dir and not stat.S_ISDIR(st.st_mode):
        return "is not a directory"
    if hasattr(os, "getuid") and st.st_uid != os.getuid():
        return f"is owned by uid {st.st_uid}, not by this user (uid {os.getuid()})"
    if st.st_mode & 0o022:
        return f"is writable by the group or others (mode {stat.S_IMODE(st.st_mode):o})"
    return None


def _private_dir(path: str) -> None:
    """Create ``path`` (0700, parents as needed) or check an existing one; raises OSError."""
    if not os.path.isdir(path):
        os.makedirs(path, mode=0o700, exist_ok=True)
    why = _check_private(path, True)
    if why:
        raise PermissionError(errno.EPERM, f"unsafe cache folder: {why}", path)


def _kernel_dir() -> str | None:
    """A folder only this user can write to, for the kernels; None when there is none."""
    root, d = cache_root(), kernel_cache_dir()
    try:
        _private_dir(root)
        _private_dir(d)
        return d
    except OSError as e:
        reason = e
    with _state.lock:
        if _state.private_dir is None:
            try:
                _state.private_dir = tempfile.mkdtemp(prefix="torchbrdf-kernels-")  # 0700, unique
                atexit.register(shutil.rmtree, _state.private_dir, True)
            except OSError as e2:
                _warn_once("nodir", f"no usable folder for the fused kernels ({reason}; {e2}); using eager")
                return None
            _warn_once("cachedir", f"cannot use the kernel cache {d!r} ({reason}); building the fused "
                                   f"kernels in the private folder {_state.private_dir!r} for this process "
                                   f"(set ${CACHE_ENV} to a folder of your own)")
        return _state.private_dir


# ---------------------------------------------------------------------------------------------
# With what: compiler, flags, OpenMP runtime
# ---------------------------------------------------------------------------------------------

def _compiler() -> str | None:
    """Path of the C compiler (``$CC``, ``gcc`` or ``cc``), or None."""
    if not _state.compiler_checked:
        # Under the lock, and marked checked only once found: a thread that arrives while
        # another one looks must wait for the answer, not read "no compiler" (and run eager).
        with _state.lock:
            if not _state.compiler_checked:
                cc = os.environ.get("CC") or "gcc"
                _state.compiler = shutil.which(cc) or shutil.which("gcc") or shutil.which("cc")
                _state.compiler_checked = True
    return _state.compiler


def _compiler_id() -> str:
    """Compiler path and version: part of the cache key (an upgraded gcc rebuilds)."""
    if _state.compiler_id is None:
        cc = _compiler()
        if cc is None:  # only reached after available() found one; keeps the key well-defined
            return "no compiler"
        try:
            v = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=60).stdout
            _state.compiler_id = f"{cc} {v.splitlines()[0] if v else ''}"
        except (OSError, subprocess.SubprocessError):
            _state.compiler_id = str(cc)
    return _state.compiler_id


def available() -> bool:
    """True when kernels can be built here: a POSIX system with a C compiler on ``PATH``."""
    return os.name == "posix" and _compiler() is not None


def _machine_tag() -> str:
    """Hash of the CPU flags (kernels are built with ``-march=native``)."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("flags"):
                    return hashlib.sha1(line.encode()).hexdigest()[:8]
    except OSError:
        pass
    import platform

    return platform.machine() or "generic"


_OMP_RE = re.compile(r"/lib(gomp|iomp5|omp)[-.][^/]*\.so[^/]*$|/lib(gomp|iomp5|omp)\.so[^/]*$")


def _openmp_runtime() -> str | None:
    """Path of the OpenMP runtime PyTorch has loaded in this process (None if none is seen).

    Linking the kernels against this very file makes the dynamic loader reuse the loaded copy
    (same soname), so kernels and PyTorch share one runtime, one thread pool, one thread count.
    """
    if _state.omp is None:
        import torch  # noqa: F401  (loads PyTorch's OpenMP runtime)

        found = None
        try:
            with open("/proc/self/maps") as fh:
                paths = {line.split()[-1] for line in fh if "/" in line}
            torch_dir = os.path.dirname(os.path.dirname(torch.__file__))
            cands = sorted(p for p in paths if _OMP_RE.search(p))
            # prefer the copy shipped with torch (torch/lib or torch.libs)
            pref = [p for p in cands if p.startswith(torch_dir)]
            found = next(iter(pref or cands), None)
        except OSError:
            found = None
        _state.omp = (found,)
    return _state.omp[0]


# ---------------------------------------------------------------------------------------------
# Validation before dlopen
# ---------------------------------------------------------------------------------------------

def _sha256(path: str) -> tuple[int, str]:
    h = hashlib.sha256()
    size = 0
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
            size += len(block)
    return size, h.hexdigest()


def _elf_ok(path: str) -> bool:
    """Whether ``path`` is a complete ELF shared object.

    Header, program and section tables and every loadable segment must lie inside the file: a
    truncated one would SIGBUS when the loader touches it.
    """
    size = os.path.getsize(path)
    with open(path, "rb") as fh:
        head = fh.read(64)
        if len(head) < 52 or head[:4] != b"\x7fELF" or head[4] not in (1, 2) or head[5] not in (1, 2):
            return False
        end = "<" if head[5] == 1 else ">"
        if head[4] == 2:  # 64-bit
            if len(head) < 64:
                return False
            etype, = struct.unpack_from(end + "H", head, 16)
            phoff, shoff = struct.unpack_from(end + "QQ", head, 32)
            phentsize, phnum, shentsize, shnum = struct.unpack_from(end + "HHHH", head, 54)
            ph_fmt, off_i, filesz_i = end + "IIQQQQQQ", 2, 5
        else:
            etype, = struct.unpack_from(end + "H", head, 16)
            phoff, shoff = struct.unpack_from(end + "II", head, 28)
            phentsize, phnum, shentsize, shnum = struct.unpack_from(end + "HHHH", head, 42)
            ph_fmt, off_i, filesz_i = end + "IIIIIIII", 1, 4
        if etype != 3 or phnum == 0:  # ET_DYN
            return False
        if phoff + phnum * phentsize > size or shoff + shnum * shentsize > size:
            return False
        if phentsize < struct.calcsize(ph_fmt):
            return False
        fh.seek(phoff)
        table = fh.read(phnum * phentsize)
    for k in range(phnum):
        ph = struct.unpack_from(ph_fmt, table, k * phentsize)
        if ph[0] == 1 and ph[off_i] + ph[filesz_i] > size:  # PT_LOAD beyond the end of the file
            return False
    return True


def _valid(so: str) -> bool:
    """``so`` and its sidecar exist, belong to this user, match, and ``so`` is a whole ELF file."""
    meta = so + ".sha256"
    try:
        if _check_private(so, False) or _check_private(meta, False):
            return False
        with open(meta) as fh:
            want = fh.read().split()
        size, digest = _sha256(so)
        return want == [str(size), digest] and _elf_ok(so)
    except (OSError, ValueError, struct.error):
        return False


# ---------------------------------------------------------------------------------------------
# Build
# ---------------------------------------------------------------------------------------------

def _write_atomic(path: str, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path), prefix=".tmp-", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _compile(source: str, so: str, cflags) -> str | None:
    """Compile ``source`` into ``so`` atomically; returns the compiler's error text or None."""
    d = os.path.dirname(so)
    fd, cpath = tempfile.mkstemp(dir=d, prefix=".tmp-", suffix=".c")
    base = cpath[:-2]
    obj, tmp_so = base + ".o", base + ".so"
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(source)
        cc = _compiler()
        if cc is None:  # only reached after available() found one
            return "no C compiler found"
        omp = _openmp_runtime() if "-fopenmp" in cflags else None
        plain = [cc, *cflags, "-shared", cpath, "-o", tmp_so, "-lm"]
        if omp:
            # compile with OpenMP, link against PyTorch's runtime (no -fopenmp at link: no -lgomp);
            # -z defs: a runtime lacking gcc's GOMP_* entry points fails here, not at dlopen
            res = subprocess.run([cc, *cflags, "-c", cpath, "-o", obj], capture_output=True, text=True)
            if res.returncode != 0:
                return (res.stderr or res.stdout)[-2000:]
            res = subprocess.run([cc, "-shared", "-fPIC", "-Wl,-z,defs", obj, omp, "-o", tmp_so, "-lm"],
                                 capture_output=True, text=True)
            if res.returncode != 0:  # then the compiler's own OpenMP runtime
                res = subprocess.run(plain, capture_output=True, text=True)
        else:
            res = subprocess.run(plain, capture_output=True, text=True)
        if res.returncode != 0:
            return (res.stderr or res.stdout)[-2000:]
        with open(tmp_so, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp_so, 0o700)
        size, digest = _sha256(tmp_so)
        os.replace(tmp_so, so)
        # the sidecar is written after the .so: it only ever vouches for a whole file
        _write_atomic(so + ".sha256", f"{size} {digest}\n".encode())
        fsync_dir(d)
        return None
    finally:
        for p in (cpath, obj, tmp_so):
            try:
                os.unlink(p)
            except OSError:
                pass


class _FileLock:
    """``flock`` on ``path`` (released by the kernel if the process dies); no-op without fcntl."""

    def __init__(self, path: str):
        self.path, self.fd = path, None

    def __enter__(self):
        try:
            import fcntl
        except ImportError:  # pragma: no cover - not POSIX
            return self
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        fcntl.flock(self.fd, fcntl.LOCK_EX)
        return self

    def __exit__(self, *exc):
        if self.fd is not None:
            os.close(self.fd)  # closing releases the flock
        return False


def _remove(so: str) -> None:
    for p in (so + ".sha256", so):
        try:
            os.unlink(p)
        except FileNotFoundError:
            pass


def _dlopen(so: str, symbols):
    """``ctypes.CDLL(so)`` with ``symbols`` (name -> (argtypes, restype)) resolved and typed."""
    cdll = ctypes.CDLL(so)
    try:
        for sym, (argtypes, restype) in (symbols or {}).items():
            fn = getattr(cdll, sym)  # AttributeError when missing
            fn.argtypes = list(argtypes)
            fn.restype = restype
    except AttributeError:
        # unload it: glibc would hand back this very object for the rebuilt file at this path
        import _ctypes

        _ctypes.dlclose(cdll._handle)
        raise
    return cdll


def load_kernel(source: str, name: str, symbols: dict[str, tuple[Sequence[Any], Any]] | None = None,
                cflags: Sequence[str] | None = None) -> ctypes.CDLL | None:
    """Build (once per machine), cache and load the C ``source``.

    Args:
        source: complete C translation unit.
        name: a short file-name prefix, e.g. ``"principled_fwd"`` (letters, digits, ``_``).
        symbols: dict ``{symbol: (argtypes, restype)}`` to check and type on the result.
        cflags: compiler flags (default :data:`CFLAGS`; ``-shared`` is added).

    Returns:
        The ``ctypes.CDLL``, or None when it cannot be built or loaded here (then run eager;
        a warning has been issued once).
    """
    if not re.fullmatch(r"[A-Za-z0-9_]+", name):
        raise ValueError(f"name: expected letters, digits and '_', got {name!r}")
    if not available():
        return None
    flags = list(CFLAGS if cflags is None else cflags)
    try:
        key = "\0".join([source, " ".join(flags), _machine_tag(), _compiler_id(),
                         str(_openmp_runtime() if "-fopenmp" in flags else None)])
        tag = hashlib.sha256(key.encode()).hexdigest()[:24]
        fname = f"{name}_{tag}.so"
        with _state.lock:
            lib = _state.loaded.get(fname)
            if lib is not None:
                return lib
            if fname in _state.failed:
                return None
            d = _kernel_dir()
            if d is None:
                return None
            so = os.path.join(d, fname)
            lib = _build_and_load(source, so, symbols, flags)
            if lib is None:
                _state.failed.add(fname)
            else:
                _state.loaded[fname] = lib
            return lib
    except OSError as e:  # read-only folder, full disk, ...: eager, one warning
        _warn_once("oserror", f"cannot build or load the fused kernels ({e}); using eager")
        return None


def _build_and_load(source, so, symbols, cflags):
    built = False
    for attempt in range(2):  # the cached file, then one rebuild
        if not _valid(so):
            with _FileLock(so + ".lock"):
                if not _valid(so):  # nobody built it while we waited
                    _remove(so)
                    err = _compile(source, so, cflags)
                    built = True
                    if err is not None:
                        _warn_once("build", f"building a fused kernel failed; using eager.\n{err}")
                        return None
        try:
            return _dlopen(so, symbols)
        except (OSError, AttributeError) as e:
            if attempt == 1 or built:
                _warn_once("load", f"cannot load the fused kernel {so!r} ({e}); using eager")
                return None
            with _FileLock(so + ".lock"):
                _remove(so)  # a bad cached file: rebuild it once
    return None
