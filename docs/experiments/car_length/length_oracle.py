"""How much of the real dev set's car AP the predicted car length costs (no model change).

Runs a checkpoint over the Argoverse 2 dev sweeps as the node does (tracker on, its own
ground mode), then re-scores its car boxes with their length replaced, the end nearer the
sensor kept where it is: as predicted, shortened by fixed amounts, at a fixed length, and at
the matched label's length (an oracle). Usage: length_oracle.py AV2_ROOT [CHECKPOINT]
"""
from __future__ import annotations

from dataclasses import replace
import sys
from typing import Any

import numpy as np

from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
from suit_ros.data.av2 import av2_sequences
from suit_ros.evaluate import evaluate, run_model
from suit_ros.structures import Detections
from suit_ros.tracking import TrackerConfig


def relength(det: Detections, car: int, new_len: Any) -> Detections:
    """Car boxes with length ``new_len(i, box)``, the end nearer the origin kept."""
    boxes = det.boxes.copy()
    for i in np.flatnonzero(det.labels == car):
        x, y, _, length, _, _, yaw = boxes[i]
        target = new_len(i, boxes[i])
        if target is None:
            continue
        axis = np.array([np.cos(yaw), np.sin(yaw)])
        centre = np.array([x, y])
        ends = [centre + axis * length / 2, centre - axis * length / 2]
        near = min(ends, key=lambda e: float(np.hypot(*e)))
        sign = 1.0 if near is ends[0] else -1.0
        boxes[i, :2] = near - sign * axis * target / 2
        boxes[i, 3] = target
    return replace(det, boxes=boxes)


def main() -> None:
    root = sys.argv[1]
    ckpt = sys.argv[2] if len(sys.argv) > 2 else str(default_checkpoint_path())
    model, cfg, _ = load_checkpoint(ckpt)
    names = tuple(cfg.class_names)
    car = names.index('car')
    seqs = list(av2_sequences(root, names))
    run = run_model(model, seqs, tracker=TrackerConfig())
    gt, scored = run.gt, run.scored_detections()
    ranges = dict.fromkeys(names, 50.0)

    def ap(dets: list[Detections]) -> str:
        res = evaluate(gt, dets, names, ranges, run.num_points)
        by = res.ap['car']
        return f"{res.class_ap['car']:.3f} ({' / '.join(f'{by[k]:.3f}' for k in sorted(by))})"

    def oracle(frame: int) -> Any:
        g = gt[frame]
        gc = g.boxes[g.labels == car]

        def f(i: int, b: np.ndarray) -> float | None:
            if not len(gc):
                return None
            d = np.hypot(gc[:, 0] - b[0], gc[:, 1] - b[1])
            j = int(np.argmin(d))
            return float(gc[j, 3]) if d[j] <= 2.0 else None
        return f

    print('as predicted', ap(scored))
    for cut in (0.2, 0.4):
        print(f'length - {cut}', ap([relength(d, car, lambda i, b, c=cut: b[3] - c)
                                     for d in scored]))
    for fixed in (4.2, 4.4, 4.6):
        print(f'length {fixed}', ap([relength(d, car, lambda i, b, v=fixed: v)
                                     for d in scored]))
    print('label length (oracle)', ap([relength(d, car, oracle(k))
                                        for k, d in enumerate(scored)]))
    lens = [d.boxes[(d.labels == car) & (d.scores >= 0.45), 3] for d in scored]
    print('published car lengths p10/p50/p90',
          np.round(np.percentile(np.concatenate(lens), [10, 50, 90]), 2))


if __name__ == '__main__':
    main()
