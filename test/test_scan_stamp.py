"""The scan stamp convention (core/scan.py): which beam a LaserScan's header stamp describes, and
the time a scan describes (the middle of its sweep) under each; the parameters that choose it."""
from __future__ import annotations

import numpy as np
import pytest

from localization.core.parameters import ParameterError, Parameters, default
from localization.core.scan import ScanData, first_beam_time, scan_time

N = 1081
DT = 1.0 / 40 / 1440  # s between beams: a 40 Hz Hokuyo, 1440 steps per turn


def _scan(ti=DT, n=N) -> ScanData:
    return ScanData(stamp=100.0, ranges=np.ones(n), angle_min=-2.35, angle_max=2.35, angle_increment=4.7 / (n - 1),
                    range_min=0.02, range_max=30.0, time_increment=ti)


def test_first_beam_stamp_is_the_sweep_start():
    s = _scan()
    assert first_beam_time(s) == 100.0
    assert scan_time(s) == pytest.approx(100.0 + 0.5 * (N - 1) * DT, abs=1e-12)
    assert scan_time(s, "first_beam", 0.003) == pytest.approx(100.0 - 0.003 + 0.5 * (N - 1) * DT, abs=1e-12)


def test_last_beam_stamp_is_the_sweep_end():
    """urg_node (calibrate_time false), rplidar_ros: the stamp is taken when the scan is complete;
    mid-sweep = stamp − ½ (n − 1) Δ − offset."""
    s = _scan()
    assert first_beam_time(s, "last_beam") == pytest.approx(100.0 - (N - 1) * DT, abs=1e-12)
    assert scan_time(s, "last_beam", 0.003) == pytest.approx(100.0 - 0.5 * (N - 1) * DT - 0.003, abs=1e-12)
    # the two conventions are a whole sweep apart
    assert scan_time(s) - scan_time(s, "last_beam") == pytest.approx((N - 1) * DT, abs=1e-12)


def test_without_sweep_timing_only_the_offset_counts():
    for ti in (0.0, float("nan"), -1e-5, 1.0):  # unknown, invalid, a "sweep" longer than MAX_SWEEP_S
        s = _scan(ti)
        assert scan_time(s, "last_beam", 0.01) == scan_time(s, "first_beam", 0.01) == pytest.approx(99.99)


def test_unknown_convention_is_an_error():
    with pytest.raises(ValueError, match="scan stamp convention 'middle'"):
        scan_time(_scan(), "middle")


def test_parameters_declare_the_convention():
    assert default("scan_stamp") == "first_beam" and default("scan_stamp_offset") == 0.0
    p = Parameters({"scan_stamp": "last_beam", "scan_stamp_offset": 0.01})
    assert p.scan_stamp == "last_beam" and p.scan_stamp_offset == 0.01
    with pytest.raises(ParameterError):
        Parameters({"scan_stamp": "mid_sweep"})
    with pytest.raises(ParameterError):
        Parameters({"scan_stamp_offset": float("nan")})
