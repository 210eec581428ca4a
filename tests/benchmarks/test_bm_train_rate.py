"""benchmarks/bm_train_rate.py: the variants and overrides it parses (no training), and the CPU time of each
thread of a training process."""

from __future__ import annotations

import os
import sys
import threading
import time

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


linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")


def _spin(seconds: float) -> None:
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


@linux_only
def test_each_threads_cpu_time_is_its_own(rate):
    stop = threading.Event()
    idle = threading.Thread(target=stop.wait, name="idle")
    busy = threading.Thread(target=_spin, args=(0.5,), name="busy")
    idle.start()
    before = rate.thread_cpu_times()
    busy.start()
    busy.join(timeout=30)
    main_start = time.thread_time()
    _spin(0.3)
    main_used = time.thread_time() - main_start
    after = rate.thread_cpu_times()
    stop.set()
    idle.join()
    assert os.getpid() in before and idle.native_id in before
    assert busy.native_id not in before and busy.native_id not in after  # started after, ended before: unseen
    used = {tid: after[tid][1] - before[tid][1] for tid in before if tid in after}
    # clock ticks (10 ms): the main thread's 0.3 s of spinning, the idle thread's nothing
    assert used[os.getpid()] == pytest.approx(main_used, abs=0.05)
    assert used[idle.native_id] <= 0.02
    rows = rate.cpu_by_thread(before, after)
    assert rows[0][0] == "main" and rows[0][1] == pytest.approx(used[os.getpid()])
    assert [s for _, s in rows] == sorted((s for _, s in rows), reverse=True)


@linux_only
def test_a_thread_started_in_between_counts_from_zero(rate):
    after = rate.thread_cpu_times()
    rows = rate.cpu_by_thread({}, after)  # none of them there before
    assert sorted(s for _, s in rows) == sorted(s for _, s in after.values())
    assert ["main", after[os.getpid()][1]] in rows
