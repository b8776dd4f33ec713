"""
Due link over a real pty (virtual Due): sustained command rate and command->ack round trip.

Targets from issue 4: at least 500 Hz of commands with zero lost frames, and an
acknowledgement round-trip p99 under 5 ms. "Lost" = a command sent but never applied,
read from the virtual Due's own log of applied set-points (by sequence number).
"""

import os
import statistics
import time

from softshape_ros.hardware.link import DueLink
from softshape_ros.hardware.virtual_due import VirtualDue

LIM = [150000.0] * 6


def _rate(link, vd, hz: float, seconds: float) -> dict:
    period = 1.0 / hz
    sent = []
    t0 = time.perf_counter()
    nxt = t0
    k = 0
    while time.perf_counter() - t0 < seconds:
        k += 1
        sent.append(link.send_command([float(k % 140000)] + [0.0] * 5))
        nxt += period
        delay = nxt - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
    elapsed = time.perf_counter() - t0
    link.wait_ack(sent[-1], 1.0)
    time.sleep(0.05)
    applied = {a.seq for a in vd.applied() if a.reason == 'command'}
    lost = sum(1 for s in sent if s not in applied)
    return {'target_hz': hz, 'achieved_hz': round(len(sent) / elapsed, 1), 'sent': len(sent),
            'lost': lost}


def run() -> dict:
    with VirtualDue(LIM, noise_pa=0.0) as vd:
        link = DueLink(vd.path, LIM, ack_timeout_s=0.05).start()
        if not link.wait_connected(5):
            raise RuntimeError(f'virtual Due link did not come up: {link.last_error}')
        rtts = []
        for k in range(1000):
            t = time.perf_counter()
            seq = link.send_command([float(k)] * 6)
            if not link.wait_ack(seq, 1.0):
                raise RuntimeError(f'command {seq} not acknowledged')
            rtts.append(time.perf_counter() - t)
        rtts.sort()
        rates = [_rate(link, vd, hz, 2.0) for hz in (500.0, 1000.0, 2000.0)]
        link.close()
    best = max((r['achieved_hz'] for r in rates if r['lost'] == 0), default=0.0)
    return {
        'ack_rtt_median_ms': round(1e3 * statistics.median(rtts), 3),
        'ack_rtt_p99_ms': round(1e3 * rtts[int(0.99 * len(rtts)) - 1], 3),
        'ack_rtt_max_ms': round(1e3 * rtts[-1], 3),
        'rtt_samples': len(rtts),
        'rates': rates,
        'max_rate_zero_loss_hz': best,
        'retransmits': link.counters['retransmits'],
        'transport': 'pty (virtual Due), 115200 baud nominal (a pty ignores baud)',
        'load_avg_1min': round(os.getloadavg()[0], 2),   # p99 depends on what else runs
    }
