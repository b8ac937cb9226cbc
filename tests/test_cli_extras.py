import pytest

from spk2img.cli.extras import needs_extra
from spk2img.core.errors import InputError


def test_missing_extra_becomes_a_one_line_input_error():
    with pytest.raises(
        InputError, match=r"training needs the train extra: pip install 'spk2img\[train\]'"
    ):
        with needs_extra("train", "training"):
            import spk2img_no_such_module  # noqa: F401
