"""torchbrdf.bench.residual_rate: every call timed, the residual's two routes bit-identical."""

import pytest

from torchbrdf.bench import residual_rate
from torchbrdf.kernels import build


@pytest.mark.skipif(not build.available(), reason="no C compiler for the fused kernels")
def test_rows_time_every_call_and_compare_the_routes():
    out, same = residual_rate.rows(256, 3, repeats=1)
    assert same
    assert len(out) == 10 and all(s.repeats == 1 and s.median > 0 for _, s in out)


@pytest.mark.parametrize("args, message", [
    (["--pixels", "100"], "--pixels must be at least 1 and a multiple of 128"),
    (["--reps", "0"], "--reps must be at least 1"),
    (["--lights", "0"], "--lights must be at least 1")])
def test_bad_flags_are_one_line_naming_the_flag(args, message, capsys):
    with pytest.raises(SystemExit) as e:
        residual_rate.main(args)
    assert e.value.code == 2 and message in capsys.readouterr().err
