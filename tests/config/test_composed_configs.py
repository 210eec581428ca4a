"""Every shipped experiment and group option composes to the validated config recorded in
``tests/fixtures/composed_configs.yaml`` (``tests/support/composed.py``): a change of ``conf/`` or of the schema
that moves a setting of a shipped run fails here until the record is written again on purpose."""

from __future__ import annotations

import pytest

from tests.support.composed import BASE, cases, composed_settings, difference, recorded

RECORD = recorded()


def test_the_record_holds_every_case() -> None:
    # a new experiment or group option is recorded as well
    assert list(RECORD) == cases()


@pytest.mark.parametrize("case", cases())
def test_composed_config_is_the_recorded_one(case: str) -> None:
    settings = composed_settings(case)
    if case == BASE:
        assert settings == RECORD[BASE]
    else:
        assert difference(settings, RECORD[BASE]) == RECORD[case]
