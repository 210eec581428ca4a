"""Where random numbers for a device are drawn (:func:`unicorn.hostsync.draw_device`) and the sync-free switch."""

from __future__ import annotations

import torch

from unicorn.hostsync import draw_device, is_sync_free, sync_free


def test_draws_are_made_on_the_device_unless_a_generator_lives_elsewhere():
    assert draw_device("meta") == torch.device("meta")  # no generator: torch's global stream on the device
    assert draw_device(torch.device("meta"), torch.Generator()) == torch.device("cpu")  # the caller's, where it is
    with sync_free():  # the same inside the steps without host reads
        assert draw_device("meta") == torch.device("meta")
    # a draw made where draw_device says, then moved, is the draw of the generator on its own device
    g = torch.Generator().manual_seed(3)
    expected = torch.rand(4, generator=torch.Generator().manual_seed(3))
    assert torch.equal(torch.rand(4, generator=g, device=draw_device("cpu", g)), expected)


def test_sync_free_blocks_nest_and_restore():
    assert not is_sync_free()
    with sync_free():
        assert is_sync_free()
        with sync_free(False):
            assert not is_sync_free()
        assert is_sync_free()
    assert not is_sync_free()
