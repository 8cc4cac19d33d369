"""``python -m torchbrdf``: the showcase command's refusals."""

import pytest

from torchbrdf.__main__ import main


def test_an_out_that_is_a_file_is_one_line_and_left_alone(tmp_path, capsys):
    # this was os.makedirs' FileExistsError traceback
    out = tmp_path / "figures"
    out.write_text("mine")
    with pytest.raises(SystemExit) as e:
        main(["--out", str(out)])
    assert e.value.code == 2 and f"--out {out}: {out} is a file, not a folder" in capsys.readouterr().err
    assert out.read_text() == "mine"
