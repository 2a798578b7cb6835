"""The memory probes the lifelong benchmark reads (Linux /proc)."""

from __future__ import annotations

import mmap
import sys

import pytest

from service.offline.replay import current_rss_mb, peak_rss_mb, reset_peak_rss


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="VmHWM and clear_refs are Linux's")
def _touched(mib: int) -> mmap.mmap:
    """`mib` MiB of fresh anonymous pages, written so they are resident. (A numpy array
    may come from free heap memory that is already resident, late in a long test run.)"""
    block = mmap.mmap(-1, mib * 2**20)
    for offset in range(0, len(block), mmap.PAGESIZE):
        block[offset] = 1
    return block


def test_peak_rss_restarts_from_the_current_rss_and_sees_a_later_spike() -> None:
    _touched(40).close()
    before = peak_rss_mb()
    if not reset_peak_rss():
        pytest.skip("this kernel does not let a process reset its peak RSS")
    after_reset = peak_rss_mb()
    assert after_reset < before - 20  # the old spike no longer counts
    assert after_reset == pytest.approx(current_rss_mb(), abs=2.0)
    spike = _touched(30)
    assert peak_rss_mb() >= after_reset + 25
    spike.close()
