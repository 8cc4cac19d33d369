"""Threads that reach the kernel build at once (torchbrdf/kernels/build.py)."""

import shutil
import threading
import time

import pytest

from torchbrdf.kernels import build

pytestmark = pytest.mark.skipif(not build.available(), reason="no C compiler")


def test_threads_racing_the_compiler_lookup_never_see_no_compiler(monkeypatch):
    # Four threads ask at once with a fresh state, while the lookup is slow: before the
    # lookup was locked, the ones that came second read "checked, no compiler" and ran eager.
    which = shutil.which

    def slow_which(name, *args, **kw):
        time.sleep(0.002)
        return which(name, *args, **kw)

    monkeypatch.setattr(shutil, "which", slow_which)
    eager = 0
    for _ in range(50):
        monkeypatch.setattr(build, "_state", build._State())
        start = threading.Barrier(4)
        answers = []

        def ask():
            start.wait()
            answers.append(build.available())

        threads = [threading.Thread(target=ask) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert len(answers) == 4
        eager += answers.count(False)
    assert eager == 0
