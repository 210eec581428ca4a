"""benchmarks/bm_train_rate.py: the variants and overrides it parses (no training)."""

from __future__ import annotations

import pytest

from tests.support.benchmarks import load_script, unload_script


@pytest.fixture(scope="module")
def rate():
    yield load_script("bm_train_rate")
    unload_script("bm_train_rate")


def test_variant_overrides_stay_with_their_variant(rate):
    args, overrides = rate.parse_args(
        ["--variant", "w32 model.encoder.width=32", "schedule.milestones=[20,40,60]", "--steps", "9",
         "--variant", "ddp trainer=ddp_cpu 'dataset.batch_size=8'"]
    )  # fmt: skip
    assert args.variant == [("w32", ["model.encoder.width=32"]), ("ddp", ["trainer=ddp_cpu", "dataset.batch_size=8"])]
    assert overrides == ["schedule.milestones=[20,40,60]"] and args.steps == 9


@pytest.mark.parametrize(
    "bad", [["--variant", "lonely"], ["--variant", ""], ["--variant", "a x=1", "--variant", "a y=2"], ["--stpes", "3"]]
)
def test_bad_variants_and_options_are_errors(rate, bad, capsys):
    with pytest.raises(SystemExit) as exit_info:
        rate.parse_args(bad)
    assert exit_info.value.code == 2
    variant = bad[0] == "--variant"
    expected = "needs a new name and at least one override" if variant else "unrecognized arguments: --stpes"
    assert expected in capsys.readouterr().err
