"""Geometry ops: rotated BEV IoU against shapely, NMS against brute force, SE(3) helpers."""
from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import Polygon
import torch

from suit_ros.ops.geometry import ego_transform, pose_from_xyz_rpy, se3_inverse, transform_boxes
from suit_ros.ops.iou import bev_corners, bev_iou
from suit_ros.ops.nms import batched_nms, circle_nms, rotated_nms, suppress_near


def random_boxes(n, seed):
    rng = np.random.default_rng(seed)
    return torch.tensor(np.c_[rng.uniform(-4, 4, (n, 2)), np.zeros(n), rng.uniform(0.3, 5, (n, 2)),
                              np.ones(n), rng.uniform(-4, 4, n)], dtype=torch.float32)


def shapely_iou(a, b):
    ca, cb = bev_corners(a.double()).numpy(), bev_corners(b.double()).numpy()
    out = np.zeros((len(a), len(b)))
    for i in range(len(a)):
        for j in range(len(b)):
            pa, pb = Polygon(ca[i]), Polygon(cb[j])
            inter = pa.intersection(pb).area
            out[i, j] = inter / (pa.area + pb.area - inter)
    return out


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_bev_iou_matches_shapely(seed):
    a, b = random_boxes(30, seed), random_boxes(25, seed + 10)
    np.testing.assert_allclose(bev_iou(a, b).numpy(), shapely_iou(a, b), atol=1e-5)


def test_bev_iou_special_cases():
    box = torch.tensor([[0, 0, 0, 4, 2, 1, 0.3]])
    far = torch.tensor([[50, 0, 0, 4, 2, 1, 0.0]])
    assert bev_iou(box, box).item() == pytest.approx(1.0, abs=1e-6)
    assert bev_iou(box, far).item() == 0.0
    turned = box.clone()
    turned[0, 6] += np.pi                                # same footprint
    assert bev_iou(box, turned).item() == pytest.approx(1.0, abs=1e-5)
    assert bev_iou(torch.zeros(0, 7), box).shape == (0, 1)


def test_paired_iou_edge_configurations_match_shapely():
    """Shared edges, containment, a cross (no corner inside the other box), touching boxes."""
    from suit_ros.ops.iou import paired_bev_iou
    a = torch.tensor([[0, 0, 0, 4, 2, 1, 0.0],      # shifted by half its length: shared edges
                      [0, 0, 0, 4, 2, 1, 0.4],      # contains the small box
                      [0, 0, 0, 6, 1, 1, 0.0],      # a cross with the turned box
                      [0, 0, 0, 2, 2, 1, 0.0],      # touching along a whole edge
                      [0, 0, 0, 2, 2, 1, 0.0]])     # touching at a corner
    b = torch.tensor([[2, 0, 0, 4, 2, 1, 0.0],
                      [0.2, 0.1, 0, 1, 0.5, 1, 1.0],
                      [0, 0, 0, 6, 1, 1, np.pi / 2],
                      [2, 0, 0, 2, 2, 1, 0.0],
                      [2, 2, 0, 2, 2, 1, 0.0]])
    want = np.diag(shapely_iou(a, b))
    np.testing.assert_allclose(paired_bev_iou(a, b).numpy(), want, atol=1e-5)
    assert want[0] == pytest.approx(1 / 3) and want[3] == 0.0


def brute_nms(boxes, scores, thr):
    order = np.argsort(-scores, kind='stable')
    iou = shapely_iou(boxes, boxes)
    keep = []
    for i in order:
        if all(iou[i, k] <= thr for k in keep):
            keep.append(i)
    return keep


# float32 boxes on the CPU take the compiled greedy pass, float64 ones the tensor path
@pytest.mark.parametrize('dtype', [torch.float32, torch.float64])
@pytest.mark.parametrize('seed', [3, 4])
def test_rotated_nms_matches_brute_force(seed, dtype):
    boxes = random_boxes(40, seed).to(dtype)
    scores = torch.tensor(np.random.default_rng(seed).uniform(size=40), dtype=torch.float32)
    assert rotated_nms(boxes, scores, 0.2).tolist() == brute_nms(boxes, scores.numpy(), 0.2)


@pytest.mark.parametrize('dtype', [torch.float32, torch.float64])
@pytest.mark.parametrize('seed', [5, 6])
def test_batched_and_refined_nms_match_brute_force(seed, dtype):
    from suit_ros.model.sampling import refined_nms
    rng = np.random.default_rng(seed)
    boxes = random_boxes(60, seed).to(dtype)
    scores = rng.uniform(size=60)
    labels = rng.integers(0, 3, 60)
    iou = shapely_iou(boxes, boxes)
    order = np.argsort(-scores, kind='stable')
    keep = []
    for i in order:
        if all(labels[i] != labels[k] or iou[i, k] <= 0.2 for k in keep):
            keep.append(i)
    got = batched_nms(boxes, torch.tensor(scores, dtype=torch.float32), torch.tensor(labels),
                      'rotated', 0.2)
    assert got.tolist() == keep
    # refined NMS: per frame (labels as frames here), IoU or centre distance suppresses
    dist = np.hypot(*(boxes[:, None, :2].numpy() - boxes[None, :, :2].numpy()).transpose(2, 0, 1))
    keep = []
    for i in order:
        if all(labels[i] != labels[k] or (iou[i, k] <= 0.3 and dist[i, k] >= 1.5)
               for k in keep):
            keep.append(i)
    got = refined_nms(boxes, torch.tensor(scores, dtype=torch.float32), torch.tensor(labels),
                      0.3, 1.5)
    assert got.tolist() == keep


def test_compiled_nms_keeps_what_the_tensor_path_keeps_on_crowded_boxes():
    """A few hundred boxes in clusters (a top-K of a heatmap: neighbouring cells decode
    nearly the same box), ties in score among them: the compiled greedy pass and the tensor
    path keep the same boxes in the same order, per class and per frame with a centre
    distance."""
    from suit_ros.model.sampling import refined_nms
    rng = np.random.default_rng(11)
    centres = rng.uniform(-40, 40, (60, 2))
    pick = rng.integers(0, 60, 400)
    boxes = np.zeros((400, 7), np.float32)
    boxes[:, :2] = centres[pick] + rng.normal(0, 0.6, (400, 2))
    boxes[:, 3:6] = rng.uniform([0.5, 0.5, 1.0], [5.0, 2.5, 2.0], (400, 3))
    boxes[:, 6] = rng.uniform(-np.pi, np.pi, 400)
    b32 = torch.from_numpy(boxes)
    scores = torch.from_numpy(np.round(rng.uniform(size=400), 2).astype(np.float32))
    labels = torch.from_numpy(rng.integers(0, 3, 400))
    for thr in (0.1, 0.2, 0.5):
        assert (batched_nms(b32, scores, labels, 'rotated', thr).tolist()
                == batched_nms(b32.double(), scores, labels, 'rotated', thr).tolist())
        assert rotated_nms(b32, scores, thr).tolist() == rotated_nms(b32.double(), scores,
                                                                      thr).tolist()
        assert (refined_nms(b32, scores, labels, thr, 0.8).tolist()
                == refined_nms(b32.double(), scores, labels, thr, 0.8).tolist())
    empty = torch.zeros(0, 7)
    assert batched_nms(empty, torch.zeros(0), torch.zeros(0, dtype=torch.long)).numel() == 0


def test_circle_nms_and_class_awareness():
    centers = torch.tensor([[0.0, 0.0], [0.5, 0.0], [3.0, 0.0], [3.2, 0.1]])
    scores = torch.tensor([0.9, 0.8, 0.7, 0.95])
    assert circle_nms(centers, scores, 1.0).tolist() == [3, 0]
    boxes = torch.tensor([[0, 0, 0, 4, 2, 1, 0], [0.2, 0, 0, 4, 2, 1, 0]], dtype=torch.float32)
    same = batched_nms(boxes, torch.tensor([0.9, 0.8]), torch.tensor([0, 0]), 'rotated', 0.2)
    diff = batched_nms(boxes, torch.tensor([0.9, 0.8]), torch.tensor([0, 1]), 'rotated', 0.2)
    assert same.tolist() == [0] and sorted(diff.tolist()) == [0, 1]


def test_suppress_near_drops_only_movable_boxes_near_a_kept_one_of_their_class():
    # in score order; radius 1.0 m for class 0, 3.0 m for class 1
    centers = torch.tensor([[0.0, 0.0], [0.5, 0.0], [0.6, 0.1], [0.8, 0.0], [5.0, 0.0],
                            [7.5, 0.0], [20.0, 0.0], [20.4, 0.0]])
    labels = torch.tensor([0, 0, 0, 1, 1, 1, 0, 0])
    movable = torch.tensor([False, True, False, True, False, True, True, True])
    keep = suppress_near(centers, labels, movable, torch.tensor([1.0, 3.0]))
    # 1: near 0 (same class) -> dropped; 2: not movable -> stays; 3: class 1, nothing surer of
    # its class near -> stays; 5: 2.5 m from 4 (class 1, radius 3) -> dropped; 6 stays (first);
    # 7: near 6, both movable, 6 kept -> dropped
    assert keep.tolist() == [True, False, True, True, True, False, True, False]
    # a dropped box suppresses nothing: 1 goes (near 0); 2 is 0.9 m from 1, which went
    chain = suppress_near(torch.tensor([[0.0, 0.0], [0.9, 0.0], [1.8, 0.0]]),
                          torch.tensor([0, 0, 0]), torch.tensor([False, True, True]),
                          torch.tensor([1.0]))
    assert chain.tolist() == [True, False, True]
    none = suppress_near(centers, labels, torch.zeros(8, dtype=torch.bool),
                         torch.tensor([1.0, 3.0]))
    assert bool(none.all())
    assert suppress_near(torch.zeros(0, 2), torch.zeros(0, dtype=torch.long),
                         torch.zeros(0, dtype=torch.bool), torch.tensor([1.0])).shape == (0,)


def test_ego_transform_static_object():
    world = np.array([[12.0, -3.0, 0.8, 4.5, 1.9, 1.6, 0.4]])
    p0 = pose_from_xyz_rpy((1, 2, 1.8), (0, 0, 0.2))
    p1 = pose_from_xyz_rpy((2.4, 2.3, 1.8), (0, 0, 0.25))
    b0, _ = transform_boxes(se3_inverse(p0), world)
    b1, _ = transform_boxes(se3_inverse(p1), world)
    moved, _ = transform_boxes(ego_transform(p1, p0), b0)
    np.testing.assert_allclose(moved, b1, atol=1e-5)
    np.testing.assert_allclose(se3_inverse(p0) @ p0, np.eye(4), atol=1e-12)


def test_cell_index_lists_each_rectangle_in_exactly_the_cells_it_spans():
    """A rectangle is listed in every cell its corners span, and in no other."""
    from suit_ros.ops.geometry import CellIndex
    rng = np.random.default_rng(3)
    xy = rng.uniform(-30, 30, (5000, 2))
    lo = np.array([[-10.0, -3.0], [5.0, 5.0], [100.0, 100.0]])
    hi = np.array([[-4.0, 7.5], [5.5, 20.0], [101.0, 101.0]])
    index = CellIndex(xy, lo, hi, 2.0)
    start, owners = index.box_lists()
    assert len(start) == index.shape[0] * index.shape[1] + 1
    cell_of_entry = np.repeat(np.arange(len(start) - 1), np.diff(start))
    for k in range(3):
        cells = cell_of_entry[owners == k]
        ix = cells // index.shape[1] + index.origin[0]
        iy = cells % index.shape[1] + index.origin[1]
        x0, y0 = np.floor(lo[k] / 2).astype(int)
        x1, y1 = np.floor(hi[k] / 2).astype(int)
        want = {(a, b) for a in range(x0, x1 + 1) for b in range(y0, y1 + 1)}
        assert len(cells) == len(want) and set(zip(ix.tolist(), iy.tolist())) == want
    empty = CellIndex(xy[:0], lo, hi, 2.0)
    assert len(empty.box_lists()[1]) == 0


def test_count_points_in_boxes_matches_the_dense_membership_on_a_large_cloud():
    from suit_ros.ops.geometry import count_points_in_boxes, points_in_boxes
    rng = np.random.default_rng(4)
    xyz = np.c_[rng.uniform(-50, 50, (60_000, 2)), rng.uniform(-1, 3, 60_000)]
    boxes = np.c_[rng.uniform(-45, 45, (30, 2)), rng.uniform(0, 1, 30), rng.uniform(1, 8, 30),
                  rng.uniform(0.5, 3, 30), rng.uniform(1, 3, 30), rng.uniform(-3, 3, 30)]
    np.testing.assert_array_equal(count_points_in_boxes(xyz, boxes),
                                  points_in_boxes(xyz, boxes).sum(0))
    # non-finite and far points are in no box, in float32 clouds as in float64 ones
    xyz[:50, 0], xyz[50:60, 1], xyz[60:70] = np.nan, np.inf, -1e20
    for cloud in (xyz, xyz.astype(np.float32)):
        with np.errstate(invalid='ignore'):
            want = points_in_boxes(cloud.astype(np.float64), boxes).sum(0)
        np.testing.assert_array_equal(count_points_in_boxes(cloud, boxes), want)


def test_suppress_near_is_the_sequential_rule_on_random_boxes():
    """The vectorised pass gives what the plain rule in score order gives: a movable box goes
    when a box of its class that stays (movable or not) lies earlier within its radius."""
    rng = np.random.default_rng(3)
    for _ in range(30):
        n = int(rng.integers(1, 60))
        centers = torch.from_numpy(rng.uniform(0, 12, (n, 2)))
        labels = torch.from_numpy(rng.integers(0, 2, n))
        movable = torch.from_numpy(rng.random(n) < 0.6)
        radius = torch.tensor([1.5, 2.5])
        want = np.ones(n, bool)
        for i in range(n):
            if movable[i]:
                for j in range(i):
                    if (want[j] and labels[j] == labels[i]
                            and float(torch.dist(centers[i], centers[j])) < radius[labels[i]]):
                        want[i] = False
                        break
        assert suppress_near(centers, labels, movable, radius).numpy().tolist() == want.tolist()
