"""The dataset base class: the bad-file policy and the in-memory item cache."""

from __future__ import annotations

from typing import Any

import pytest
import torch

from unicorn.data.common import UnicornDataset
from unicorn.data.images import DatasetError, ImageLoadError


class Counting(UnicornDataset):
    """Items i -> image filled with i; index ``bad`` unreadable; counts the loads."""

    def __init__(self, n: int = 5, bad: int | None = None, **kw: Any) -> None:
        super().__init__(**kw)
        self.n, self.bad, self.loads = n, bad, [0] * n

    def __len__(self) -> int:
        return self.n

    def load(self, index: int) -> dict[str, Any]:
        self.loads[index] += 1
        if index == self.bad:
            raise ImageLoadError(f"bad{index}.png", "truncated")
        return {"image": torch.full((3, 2, 2), float(index)), "name": f"item{index}"}


def test_cache_loads_each_item_once_and_returns_copies() -> None:
    ds = Counting()
    ds.cache_items()
    first = [ds[i] for i in range(5)]
    first[2]["image"].zero_()  # a caller changing its item ...
    first[3]["extra"] = 1
    second = [ds[i - 5] for i in range(5)]  # negative indices hit the same entries
    assert ds.loads == [1] * 5
    for i, item in enumerate(second):
        assert torch.equal(item["image"], torch.full((3, 2, 2), float(i))) and item["index"] == i  # ... not the cache
        assert set(item) == {"image", "name", "index"}
    assert second[1]["image"].data_ptr() != ds[1]["image"].data_ptr()


def test_without_cache_every_read_loads() -> None:
    ds = Counting()
    for _ in range(2):
        ds[0]
    assert ds.loads[0] == 2


def test_cache_keeps_the_skip_policy() -> None:
    ds = Counting(bad=1, on_error="skip")
    ds.cache_items()
    with pytest.warns(RuntimeWarning, match="skipping unreadable file"):
        item = ds[1]
    assert item["index"] == 2 and torch.equal(ds[1]["image"], item["image"])
    assert ds.loads == [0, 1, 1, 0, 0]  # the replacement was cached under the index asked for


def test_augmented_items_cannot_be_cached() -> None:
    ds = Counting()
    ds.augment = True
    with pytest.raises(DatasetError, match="Counting augments its items at random"):
        ds.cache_items()


def test_a_skipped_file_is_one_of_unicorns_warnings_logged_in_one_line(caplog) -> None:
    """The skip is a :class:`~unicorn.errors.UnicornWarning` (still a RuntimeWarning): the command-line programs log
    it in one line, into a run's train.log too, not as Python prints a warning (file, line, source line)."""
    import warnings

    from unicorn.cli.errors import WARNINGS_LOGGER, log_warnings
    from unicorn.data.common import SkippedFileWarning
    from unicorn.errors import UnicornWarning

    assert issubclass(SkippedFileWarning, UnicornWarning) and issubclass(SkippedFileWarning, RuntimeWarning)
    printed = []
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = lambda *args, **kwargs: printed.append(args)
        with log_warnings(), caplog.at_level("WARNING", logger=WARNINGS_LOGGER):
            assert Counting(bad=1, on_error="skip")[1]["index"] == 2
    assert [(r.name, r.getMessage()) for r in caplog.records] == [
        (WARNINGS_LOGGER, "SkippedFileWarning: skipping unreadable file: cannot read image bad1.png: truncated")
    ]
    assert printed == []
