"""Azimuth coverage (suit_ros.coverage): a lost sector against the sensor's running norm."""
from __future__ import annotations

import numpy as np
import pytest

from suit_ros.coverage import SectorCoverage


def ring(n=7200, lost=None, seed=0):
    """Points all around the sensor; ``lost``: (start, end) degrees without returns."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, n)
    if lost is not None:
        a, b = np.deg2rad(lost[0]), np.deg2rad(lost[1])
        gone = ((az - a) % (2 * np.pi)) < ((b - a) % (2 * np.pi))
        az = az[~gone]
    r = rng.uniform(5, 40, len(az))
    return np.c_[r * np.cos(az), r * np.sin(az), rng.uniform(-1, 1, len(az))]


def test_a_lost_sector_is_found_with_its_angles():
    cov = SectorCoverage()
    assert all(cov.update(ring(seed=k)) is None for k in range(10))
    start, end = cov.update(ring(lost=(40, 160), seed=11))
    assert start == pytest.approx(40, abs=5) and end == pytest.approx(160, abs=5)
    # across 0 degrees
    start, end = cov.update(ring(lost=(300, 30), seed=12))
    assert start == pytest.approx(300, abs=5) and end == pytest.approx(30, abs=5)
    assert cov.update(ring(seed=13)) is None


def test_small_gaps_never_covered_sectors_and_warmup_raise_nothing():
    cov = SectorCoverage()
    assert cov.update(ring(lost=(0, 180))) is None                    # warming up
    front = SectorCoverage()
    for k in range(10):                                               # a forward sensor
        assert front.update(ring(lost=(90, 270), seed=k)) is None
    for k in range(10):
        cov.update(ring(seed=k))
    assert cov.update(ring(lost=(10, 25), seed=20)) is None           # 15 deg: below 30
    assert cov.update(np.zeros((0, 3))) == (0.0, 360.0)               # nothing at all


def test_a_long_outage_becomes_the_norm():
    cov = SectorCoverage()
    for k in range(10):
        cov.update(ring(seed=k))
    flagged = [cov.update(ring(lost=(90, 210), seed=100 + k)) is not None for k in range(60)]
    assert flagged[0] and not flagged[-1]
    with pytest.raises(ValueError):
        SectorCoverage(bins=2)
