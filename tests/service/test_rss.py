"""The memory probes the lifelong benchmark reads (Linux /proc)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from service.replay import current_rss_mb, peak_rss_mb, reset_peak_rss


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="VmHWM and clear_refs are Linux's")
def test_peak_rss_restarts_from_the_current_rss_and_sees_a_later_spike() -> None:
    block = np.ones(40 * 2**20 // 8)  # 40 MiB, touched
    del block
    before = peak_rss_mb()
    if not reset_peak_rss():
        pytest.skip("this kernel does not let a process reset its peak RSS")
    after_reset = peak_rss_mb()
    assert after_reset < before - 20  # the old spike no longer counts
    assert after_reset == pytest.approx(current_rss_mb(), abs=2.0)
    spike = np.ones(30 * 2**20 // 8)  # 30 MiB, touched
    assert peak_rss_mb() >= after_reset + 25
    del spike
