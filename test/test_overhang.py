"""Returns that hang over a gap in their column (suit_ros/overhang.py, ``overhang: drop``)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from suit_ros.overhang import Overhang

RANGE = (-51.2, -51.2, -2.0, 51.2, 51.2, 4.5)


def column(x: float, y: float, *spans: tuple[float, float], step: float = 0.05
           ) -> np.ndarray:
    """Returns of one 0.4 m column at ``(x, y)`` every ``step`` m within each height span."""
    z = np.concatenate([np.arange(lo, hi + 1e-6, step) for lo, hi in spans])
    return np.c_[np.full((len(z), 2), (x, y)), z, np.full(len(z), 0.3),
                 np.zeros(len(z))].astype(np.float32)


def reference_keep(points: np.ndarray, f: Overhang) -> np.ndarray:
    """The rule in plain numpy: a column's occupied bins split into stacks at gap_bins empty
    ones; a return goes when its stack starts at b_float or higher."""
    bins = np.floor((points[:, 2] - f.zlo) / 0.1).astype(int)
    cx = np.floor((points[:, 0] - f.x0) / f.size).astype(int)
    cy = np.floor((points[:, 1] - f.y0) / f.size).astype(int)
    inside = (cx >= 0) & (cx < f.nx) & (cy >= 0) & (cy < f.ny) & (bins >= 0) & (bins < f.n_bins)
    keep = np.ones(len(points), bool)
    for i in np.flatnonzero(inside & (bins >= f.b_float)):
        same = inside & (cx == cx[i]) & (cy == cy[i])
        occupied = sorted(set(bins[same]))
        start = occupied[0]
        r = np.hypot(f.x0 + (cx[i] + 0.5) * f.size, f.y0 + (cy[i] + 0.5) * f.size)
        gap = max(f.gap_bins, int(round(f.gap_bins_per_m * r)))
        for lower, b in zip(occupied, occupied[1:]):
            if b > bins[i]:
                break
            if b - lower - 1 >= gap:
                start = b
        keep[i] = start < f.b_float
    return keep


def test_a_canopy_over_a_pedestrian_goes_and_what_stands_on_the_ground_stays():
    f = Overhang(RANGE, 0.4)
    ped = column(10.1, 3.1, (0.0, 1.75), (2.5, 3.2))           # a canopy 0.75 m over the head
    truck = column(20.1, -5.1, (0.0, 3.6))                     # a box truck's side: no gap
    trailer = column(25.1, -5.1, (0.0, 0.05), (1.1, 4.0))      # open under the trailer
    trunk = column(-8.1, 6.1, (0.0, 2.6), (2.6, 4.2))          # a tree: trunk into its crown
    bus = column(30.1, 8.1, (0.0, 1.2), (2.6, 3.1))            # a roof above the windows
    crown = column(-8.5, 6.5, (0.0, 0.05), (2.8, 4.2))         # the crown beside it, over road
    sign = column(0.1, 30.1, (0.0, 0.05), (5.0, 5.5))          # above the model's range
    pts = np.concatenate([ped, truck, trailer, trunk, crown, sign, bus])
    keep = f.keep(pts)
    n = np.cumsum([0, len(ped), len(truck), len(trailer), len(trunk), len(crown), len(sign),
                   len(bus)])
    part = [keep[a:b] for a, b in zip(n[:-1], n[1:])]
    assert (part[0] == (ped[:, 2] < 2.0)).all()                # the canopy's returns only
    assert part[1].all() and part[2].all() and part[3].all()
    assert (part[4] == (crown[:, 2] < 2.0)).all()
    assert part[5].all()                                       # outside the bins: kept
    assert (part[6] == (bus[:, 2] < 2.0)).all()
    assert f.dropped == (~keep).sum() > 0
    out = f(pts)
    assert len(out) == keep.sum() and np.array_equal(out, pts[keep])


@pytest.mark.parametrize('gap_per_m', [0.0, 0.05])
def test_the_kernel_is_the_rule_on_random_columns(gap_per_m: float):
    rng = np.random.default_rng(3)
    f = Overhang(RANGE, 0.4, gap_per_m=gap_per_m)
    parts = []
    for _ in range(60):                    # 60 columns of random stacks and gaps, 0-50 m out
        x, y = rng.uniform(-3, 3, 2) * rng.choice([1.0, 6.0, 15.0])
        spans = []
        z = rng.uniform(-0.5, 0.5)
        while z < 4.6:
            top = z + rng.uniform(0.05, 1.2)
            spans.append((z, top))
            z = top + rng.choice([0.1, 0.3, 0.45, 0.6, 1.0])
        parts.append(column(round(x / 0.4) * 0.4 + 0.2, round(y / 0.4) * 0.4 + 0.2, *spans,
                            step=rng.uniform(0.04, 0.3)))
    pts = np.concatenate(parts)
    pts[:, :2] += rng.uniform(-0.15, 0.15, (len(pts), 2)).astype(np.float32)
    keep = f.keep(pts)
    assert np.array_equal(keep, reference_keep(pts, f))
    assert 0 < (~keep).sum() < len(pts)


def rings(x: float, y: float, spacing_deg: float, top: float) -> np.ndarray:
    """The returns of a vertical surface at ``(x, y)`` from a sensor at the origin, 1.8 m up,
    whose rings are ``spacing_deg`` apart, from the ground to ``top``."""
    r = float(np.hypot(x, y))
    angles = np.deg2rad(np.arange(-30.0, 10.0, spacing_deg))
    z = 1.8 + r * np.tan(angles)
    z = z[(z >= 0.0) & (z <= top)]
    return np.c_[np.full((len(z), 2), (x, y)), z, np.full(len(z), 0.3),
                 np.zeros(len(z))].astype(np.float32)


def test_a_range_aware_gap_keeps_a_far_trucks_side_and_still_drops_a_near_canopy():
    """16-beam rings (2 degrees) are 1 m apart at 30 m: with a fixed 0.5 m gap every return
    of a far truck's side above 2 m is a floating stack of its own; ``gap_per_m`` 0.05 (1.5 m
    at 30 m) keeps them, and a canopy 0.75 m over a pedestrian 10 m out still goes."""
    truck = rings(30.1, 0.1, 2.0, 3.6)
    assert (np.diff(truck[:, 2]) > 0.9).all() and (truck[:, 2] > 2.0).any()
    ped = column(10.1, 3.1, (0.0, 1.75), (2.5, 3.2))
    pts = np.concatenate([truck, ped])
    fixed, ranged = Overhang(RANGE, 0.4), Overhang(RANGE, 0.4, gap_per_m=0.05)
    k_fixed, k_ranged = fixed.keep(pts), ranged.keep(pts)
    assert not k_fixed[:len(truck)].all()                      # the fixed gap cuts the truck
    assert k_ranged[:len(truck)].all()
    assert (k_ranged[len(truck):] == (ped[:, 2] < 2.0)).all()  # the canopy still goes
    assert np.array_equal(k_ranged, reference_keep(pts, ranged))
    with pytest.raises(ValueError, match='gap_per_m'):
        Overhang(RANGE, 0.4, gap_per_m=-0.1)


def test_empty_low_and_bad_input():
    f = Overhang(RANGE, 0.4)
    empty = np.zeros((0, 5), np.float32)
    assert f(empty) is empty and f.dropped == 0
    low = column(1.1, 1.1, (0.0, 1.9))
    assert f(low) is low                                       # nothing tall: the same array
    bad = np.concatenate([column(1.1, 1.1, (0.0, 1.0), (3.0, 3.5)),
                          np.array([[np.nan, 1.0, 3.0, 0, 0], [1.1, 1.1, np.nan, 0, 0],
                                    [np.inf, 0, 3.0, 0, 0]], np.float32)])
    keep = f.keep(bad)
    assert keep[-3:].all() and not keep[:-3].all()             # non-finite points are kept
    with pytest.raises(ValueError, match='height within the range'):
        Overhang(RANGE, 0.4, height=5.0)


def test_the_encoder_drops_them_in_training_and_inference_alike():
    """``pillars.overhang: drop``: the pseudo-image of a cloud is that of the cloud without its
    hanging returns, on the training path and on the compiled inference path."""
    from suit_ros.config import ModelConfig, PillarConfig
    from suit_ros.model.detector import SUITDetector
    from suit_ros.model.inference import inference_copy
    torch.manual_seed(0)
    cfg = ModelConfig(pillars=PillarConfig(point_range=RANGE, overhang='drop'))
    model = SUITDetector(cfg).eval()
    pts = np.concatenate([column(10.1, 3.1, (0.0, 1.75), (2.5, 3.2)),
                          column(20.1, -5.1, (0.0, 3.6))])
    cloud = torch.from_numpy(pts)
    kept = torch.from_numpy(Overhang(RANGE, 0.4)(pts))
    enc = model.pillars
    with torch.no_grad():
        bev, _ = enc.encode_clouds([cloud])
        enc.set_overhang('keep')
        plain, _ = enc.encode_clouds([kept])
        whole, _ = enc.encode_clouds([cloud])
    assert torch.equal(bev, plain) and not torch.equal(bev, whole)
    fast = inference_copy(model).pillars
    fast.set_overhang('drop')
    with torch.no_grad():
        assert fast.compiled([cloud])
        folded, _ = fast.encode_clouds([cloud])
        fast.set_overhang('keep')
        folded_kept, _ = fast.encode_clouds([kept])
    assert torch.equal(folded, folded_kept)
    with pytest.raises(ValueError, match='overhang must be one of'):
        enc.set_overhang('some')                               # type: ignore[arg-type]


def test_the_model_config_names_it():
    from suit_ros.config import load_model_config, model_config_from_dict
    from suit_ros.errors import ConfigError
    assert load_model_config('params/model_cpu.yaml').pillars.overhang == 'keep'
    cfg = model_config_from_dict({'pillars': {'overhang': 'drop'}}, 'test')
    assert cfg.pillars.overhang == 'drop'
    with pytest.raises(ConfigError, match='overhang must be one of'):
        model_config_from_dict({'pillars': {'overhang': 'cut'}}, 'test')
    cfg = model_config_from_dict({'pillars': {'overhang': 'drop', 'overhang_gap_per_m': 0.05}},
                                 'test')
    assert cfg.pillars.overhang_gap_per_m == 0.05
    from suit_ros.model.detector import SUITDetector
    overhang = SUITDetector(cfg).pillars._overhang
    assert overhang is not None and overhang.gap_bins_per_m == pytest.approx(0.5)
    with pytest.raises(ConfigError, match='overhang_gap_per_m'):
        model_config_from_dict({'pillars': {'overhang_gap_per_m': 1.5}}, 'test')
