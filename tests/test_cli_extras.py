import pytest

from spk2img.cli.extras import MissingExtra, needs_extra
from spk2img.errors import InputError


def test_missing_extra_becomes_a_one_line_input_error():
    with pytest.raises(
        MissingExtra, match=r'training needs the train extra .*pip install -e "\.\[train\]"'
    ):
        with needs_extra("train", "training"):
            import spk2img_no_such_module  # noqa: F401
    assert issubclass(MissingExtra, InputError)
