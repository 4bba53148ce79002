#!/usr/bin/env python3
"""The dense part of the SUIT step (backbone + head on the pillar pseudo-image) in torch (the
node's float32 and bfloat16 inference copies), ONNX Runtime and OpenVINO, one thread each, on
the same demo-drive inputs, in one run (interleaved). Prints the p50 per runtime, the ratio to
torch bfloat16 (the node's default on this CPU) and the largest output difference to torch
float32.

Not part of the product: run it in a separate virtual environment that has the three runtimes
(see README.md here).
"""
from __future__ import annotations

import time

import numpy as np
import torch

torch.set_num_threads(1)


def main() -> None:
    import onnxruntime as ort
    import openvino as ov

    from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
    from suit_ros.data.sequences import synthetic_sequence
    from suit_ros.evaluate import step_inputs
    from suit_ros.model.inference import inference_copy
    from suit_ros.model.sweeps import SweepBuffer
    model, cfg, _ = load_checkpoint(str(default_checkpoint_path()), 'cpu')
    f32 = inference_copy(model, channels_last=False)
    bf16 = inference_copy(model, precision='bfloat16')

    class Dense(torch.nn.Module):
        def __init__(self, m):
            super().__init__()
            self.m = m

        def forward(self, x):
            out = self.m.head(self.m.backbone(x))
            return tuple(out[k] for k in sorted(out))
    frames = synthetic_sequence('demo-real', 7, 14)
    buf = SweepBuffer(3)
    images = []
    with torch.no_grad():
        for f in frames:
            pts, stamp, T_ob, T_bl = step_inputs(f)
            mp = buf.push(pts, T_ob @ T_bl, stamp, T_bl)
            rows = torch.cat([torch.zeros(len(mp), 1), torch.from_numpy(mp)], 1)
            images.append(f32.pillars(rows, 1).contiguous())
    dense = Dense(f32).eval()
    torch.onnx.export(dense, (images[0],), '/tmp/dense.onnx', input_names=['x'], dynamo=False,
                      opset_version=17)
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    sess = ort.InferenceSession('/tmp/dense.onnx', so, providers=['CPUExecutionProvider'])
    core = ov.Core()
    ov_f32 = core.compile_model('/tmp/dense.onnx', 'CPU', {'INFERENCE_NUM_THREADS': 1,
                                                          'INFERENCE_PRECISION_HINT': 'f32'})
    ov_bf16 = core.compile_model('/tmp/dense.onnx', 'CPU', {'INFERENCE_NUM_THREADS': 1,
                                                           'INFERENCE_PRECISION_HINT': 'bf16'})
    dense_bf16 = Dense(bf16).eval()
    runners = {
        'torch float32': lambda x: [t.numpy() for t in dense(x)],
        'torch bfloat16 (node default)': lambda x: [t.float().numpy() for t in dense_bf16(
            x.contiguous(memory_format=torch.channels_last))],
        'onnxruntime float32': lambda x: sess.run(None, {'x': x.numpy()}),
        'openvino float32': lambda x: list(ov_f32(x.numpy()).values()),
        'openvino bfloat16': lambda x: list(ov_bf16(x.numpy()).values()),
    }
    times: dict[str, list[float]] = {k: [] for k in runners}
    diff = dict.fromkeys(runners, 0.0)
    with torch.no_grad():
        for i, x in enumerate(images):
            ref = runners['torch float32'](x)
            for k, run in runners.items():
                t0 = time.perf_counter()
                out = run(x)
                dt = time.perf_counter() - t0
                if i >= 3:
                    times[k].append(dt)
                diff[k] = max(diff[k], max(float(np.abs(np.asarray(a) - b).max())
                                           for a, b in zip(out, ref)))
    base = np.median(times['torch bfloat16 (node default)'])
    print(f'{"runtime":<32}{"p50 ms":>8}{"vs torch bf16":>15}{"max |diff| to f32":>20}')
    for k in runners:
        p50 = np.median(times[k])
        print(f'{k:<32}{p50 * 1e3:>8.1f}{p50 / base:>14.2f}x{diff[k]:>20.4f}')


if __name__ == '__main__':
    main()
