"""
Forward model: batch-1 inference latency on one CPU thread and training throughput.

Latency is ``Predictor.predict`` end to end (uint8 images + Pa in, uint8 out), stereo gray,
for both networks, plus the exported ONNX graph under onnxruntime (one thread). Throughput
is Adam steps at the paper's batch of 256 on the synthetic stand-in data, one thread (the
setting of the reproduction; two threads swing wildly when other work shares the cores).
"""

import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from softshape_ros.model import Predictor, build_network, save_checkpoint
from softshape_ros.model.export import export_onnx
from softshape_ros.model.synthetic import MAX_PA, make_samples


def _latency(fn, n=300, warm=20) -> dict:
    for _ in range(warm):
        fn()
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    ts = np.array(ts) * 1000
    return {'median_ms': round(float(np.median(ts)), 3),
            'p99_ms': round(float(np.percentile(ts, 99)), 3)}


def run() -> dict:
    out = {}
    initial, target, pressure, _ = make_samples(256, 16, views=('main', 'side'), seed=0)
    threads = 1     # training throughput on one thread: steadier on a shared machine
    restore = torch.get_num_threads()
    with tempfile.TemporaryDirectory() as tmp:
        for arch in ('paper', 'ours'):
            torch.manual_seed(0)
            net = build_network(arch, 2, 1)
            ck = save_checkpoint(Path(tmp) / arch, net, {
                'arch': arch, 'arch_params': {}, 'views': ['main', 'side'], 'channels': 1,
                'image_size': 64, 'max_pressure_pa': [MAX_PA] * 6})
            pred = Predictor.from_checkpoint(ck)
            torch.set_num_threads(1)
            res = {'params': sum(p.numel() for p in net.parameters())}
            res['predict_batch1_1thread'] = _latency(
                lambda: pred.predict(initial[0], pressure[0]))
            onnx_path = Path(tmp) / f'{arch}.onnx'
            export_onnx(ck, onnx_path, batch=2)
            x = initial[:1].reshape(1, 2, 64, 64).astype(np.float32) / 255
            p = (pressure[:1] / MAX_PA).astype(np.float32)
            import onnxruntime as ort   # pinned in requirements.txt
            so = ort.SessionOptions()
            so.intra_op_num_threads = 1
            sess = ort.InferenceSession(str(onnx_path), so, providers=['CPUExecutionProvider'])
            res['onnxruntime_batch1_1thread'] = _latency(
                lambda: sess.run(['predicted'], {'image': x, 'pressure': p}))
            torch.set_num_threads(threads)
            opt = torch.optim.Adam(net.parameters(), lr=1e-3)
            xb = torch.from_numpy(initial.reshape(256, 2, 64, 64).astype(np.float32) / 255)
            tb = torch.from_numpy(target.reshape(256, 2, 64, 64).astype(np.float32) / 255)
            pb = torch.from_numpy(pressure / MAX_PA)
            steps, t0 = 0, time.perf_counter()
            while steps < 3 or time.perf_counter() - t0 < 8:
                loss = torch.mean((net(xb, pb) - tb) ** 2)
                opt.zero_grad()
                loss.backward()
                opt.step()
                steps += 1
            res['train_samples_per_s_batch256'] = round(256 * steps /
                                                        (time.perf_counter() - t0), 1)
            res['train_threads'] = threads
            out[arch] = res
    torch.set_num_threads(restore)
    return out
