"""Train's per-epoch CSV read back for the report's figures and the studies' curves (evaluation.training_log)."""

import math

import pytest

from adlpipe.evaluation.training_log import read_training_log, validated_rows
from adlpipe.plumbing.errors import AdlError

LOG = """epoch,step,train_loss,test_loss,val_px,lr,seconds
1,100,0.5,,,0.001,1.0
2,200,0.25,0.3,4.5,0.001,2.0
3,300,0.125,,,0.0005,3.0
4,400,0.0625,0.2,3.5,0.0,4.0
"""


def test_columns_are_numbers_with_nan_where_no_validation_ran(tmp_path):
    path = tmp_path / "log.csv"
    path.write_text(LOG)
    cols = read_training_log(path)
    assert cols["step"] == [100, 200, 300, 400]
    assert math.isnan(cols["test_loss"][0]) and cols["test_loss"][1] == 0.3
    assert validated_rows(cols, ("step", "val_px")) == {"step": [200, 400], "val_px": [4.5, 3.5]}


@pytest.mark.parametrize("text", ["epoch,step\n1,x\n", "a,b\n1,2\n", "\x00\x01 not csv"])
def test_a_file_that_is_not_a_training_log_is_one_line(tmp_path, text):
    path = tmp_path / "log.csv"
    path.write_text(text)
    with pytest.raises(AdlError, match="not a training log CSV"):
        read_training_log(path)
