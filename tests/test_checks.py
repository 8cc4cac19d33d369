"""torchbrdf._checks: the global validation switch."""

import pytest

import torchbrdf


@pytest.mark.parametrize("value", ["no", "yes", None])
def test_set_validation_refuses_what_is_not_a_bool(value):
    # set_validation("no") turned the checks on (bool("no") is True); set_fast_path refused it already
    before = torchbrdf.validation_enabled()
    with pytest.raises(ValueError, match=f"set_validation: enabled must be True or False, got {value!r}"):
        torchbrdf.set_validation(value)
    assert torchbrdf.validation_enabled() is before
    with pytest.raises(ValueError, match="enabled must be True or False"):
        with torchbrdf.validation(value):
            pass
    assert torchbrdf.validation_enabled() is before
