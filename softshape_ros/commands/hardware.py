"""``softshape virtual-due``: an emulated Due on a pty, to try the bridge without the rig."""

from __future__ import annotations

import json
import time

from softshape_ros.config import load_rig_config


def _virtual_due(args) -> int:
    from softshape_ros.hardware.virtual_due import VirtualDue

    limits = load_rig_config(args.config).max_pressures_pa
    for name in ('drop_rx', 'drop_tx', 'corrupt_rx', 'corrupt_tx'):
        p = getattr(args, name)
        if not 0.0 <= p <= 1.0:
            raise ValueError(f'--{name.replace("_", "-")} is a probability, got {p}')
    vd = VirtualDue(limits, link=args.link, tau_s=args.tau, noise_pa=args.noise, seed=args.seed)
    for name in ('drop_rx', 'drop_tx', 'corrupt_rx', 'corrupt_tx'):
        setattr(vd, name, getattr(args, name))
    log = open(args.log, 'a', encoding='utf-8') if args.log else None
    vd.start()
    print(f'virtual Due on {vd.path} (limits {[round(x) for x in limits]} Pa); '
          f'run: ros2 run softshape_ros pressure_bridge --ros-args -p port:={vd.path}',
          flush=True)
    written = 0
    t_end = time.monotonic() + args.duration if args.duration > 0 else float('inf')
    try:
        while time.monotonic() < t_end:
            time.sleep(0.05)
            if log is not None:
                entries = vd.applied()[written:]
                for a in entries:
                    log.write(json.dumps({'t': a.t, 'setpoints_pa': list(a.setpoints_pa),
                                          'reason': a.reason, 'seq': a.seq}) + '\n')
                written += len(entries)
                log.flush()
    except KeyboardInterrupt:
        pass
    finally:
        vd.stop()
        if log is not None:
            log.close()
    print(f'virtual Due stopped: {len(vd.applied())} set-point changes applied, {vd.stats}')
    return 0


#: The subcommands :func:`register` adds; ``softshape NAME`` registers only NAME's module.
COMMANDS = ('virtual-due',)


def register(sub) -> None:
    p = sub.add_parser('virtual-due', help='emulate the Arduino Due pressure bridge on a pty')
    p.add_argument('--link', default=None,
                   help='stable symlink to the pty (re-pointed on reconnect), e.g. /tmp/ttyDUE')
    p.add_argument('--config', default=None, help='rig YAML (firmware limits come from it)')
    p.add_argument('--tau', type=float, default=0.03, help='regulator time constant, s')
    p.add_argument('--noise', type=float, default=30.0, help='feedback noise (std), Pa')
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--drop-rx', type=float, default=0.0, help='P(drop) per byte from the host')
    p.add_argument('--drop-tx', type=float, default=0.0, help='P(drop) per byte to the host')
    p.add_argument('--corrupt-rx', type=float, default=0.0, help='P(bit flip) per host write')
    p.add_argument('--corrupt-tx', type=float, default=0.0, help='P(bit flip) per firmware write')
    p.add_argument('--log', default=None, help='append applied set-points here as JSON lines')
    p.add_argument('--duration', type=float, default=0.0, help='stop after S seconds (0: never)')
    p.set_defaults(func=_virtual_due)
