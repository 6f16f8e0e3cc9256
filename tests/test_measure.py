"""pipeline.measure: peak memory of a block of this process and of a child process."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline import measure

MB = 2**20


def _allocate(n_mb: int) -> float:
    a = np.ones(n_mb * MB // 8)  # touched: resident
    return float(a.sum())


def _fail(message: str) -> None:
    raise ValueError(message)


def test_block_peak_is_the_blocks_own():
    ballast = np.ones(300 * MB // 8)  # ~300 MB resident before the block, freed before it starts
    del ballast
    with measure.measure() as usage:
        _allocate(150)
    if not usage.peak_is_own:
        pytest.skip("this kernel does not allow resetting the peak RSS (/proc/self/clear_refs)")
    assert 140 < usage.added_mb < 200  # the block's 150 MB array, not the 300 MB before it
    assert usage.wall_s > 0 and usage.cpu_s > 0
    assert measure.peak_rss_mb() >= measure.rss_mb() > 0


def test_child_reports_its_own_peak_not_the_parents():
    ballast = np.ones(400 * MB // 8)  # ~400 MB in this process
    result, usage = measure.run_in_child(_allocate, 150)
    assert result == 150 * MB // 8
    # The child's 150 MB array plus a fresh interpreter with numpy (~30-60 MB), not this
    # process's 400 MB.
    assert 150 < usage.peak_rss_mb < 300
    assert usage.wall_s > 0 and usage.cpu_s > 0
    assert ballast[0] == 1.0


def test_child_exception_is_raised_here():
    with pytest.raises(ValueError, match="bad input"):
        measure.run_in_child(_fail, "bad input")


def test_usage_rounds_for_reports():
    u = measure.Usage(wall_s=1.23456, cpu_s=2.0, peak_rss_mb=100.04, start_rss_mb=50.0)
    assert u.as_dict() == {"wall_s": 1.23, "cpu_s": 2.0, "peak_rss_mb": 100.0, "start_rss_mb": 50.0,
                           "peak_is_own": True}
    assert u.added_mb == pytest.approx(50.04)
    assert measure.Usage().added_mb is None
