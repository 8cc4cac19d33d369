"""``python -m torchbrdf.bench --device cuda``: its CPU-side logic (no GPU needed)."""

import importlib

import pytest
import torch

cuda_bench = importlib.import_module("torchbrdf.bench.cuda")
bench = importlib.import_module("torchbrdf.bench.brdf")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the machine-without-CUDA message")
def test_without_cuda_says_so_in_one_line_and_exits_0(capsys):
    # What `python -m torchbrdf.bench --device cuda` runs (its __main__ exits with this code).
    assert bench.main(["--device", "cuda"]) == 0
    assert capsys.readouterr().out.strip() == cuda_bench.NO_CUDA


def test_measurement_and_report_run_on_any_device():
    logs = []
    res = cuda_bench.run(device="cpu", sizes=[1 << 10], paths=["eager", "mitsuba"], repeats=1, shade_size=16,
                         lights=2, log=logs.append)
    (row,) = [r for r in res["principled"] if r["path"] == "eager"]
    assert row["N"] == 1024 and row["fwd_rate"] > 0 and row["fwdbwd_rate"] > 0
    assert row["peak_bytes"] is None  # GPU memory only on CUDA
    (srow,) = res["shade"]
    assert srow["backend"] == "eager" and srow["lights"] == 2 and srow["fwdbwd_s"] > 0
    text = cuda_bench.report(res)
    assert "| 2^10 | eager |" in text and "| 16² | 2 | eager |" in text and "n/a" in text
    assert text.splitlines()[0].endswith(f"; {res['date']}") and len(res["date"]) == 10  # the run's day


def test_triton_path_of_the_benchmark_under_the_interpreter(monkeypatch):
    pytest.importorskip("triton")
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    rows = cuda_bench.principled_rows([1 << 10], ["triton"], torch.device("cpu"), 1, lambda m: None)
    assert "error" not in rows[0], rows[0]
    assert rows[0]["fwd_rate"] > 0


def test_failures_are_reported_not_raised():
    rows = cuda_bench.principled_rows([1 << 8], ["nonsense"], torch.device("cpu"), 1, lambda m: None)
    assert "ValueError" in rows[0]["error"]
