"""
The reproduction behind ``softshape reproduce``: the learning grid, then the distance sweep.

The grid is :mod:`softshape_ros.model.reproduce` (datasets only); the object-distance sweep
(Fig. 4(c)) of its largest stereo ``ours`` model asks the simulator.
"""

from __future__ import annotations

import json
from pathlib import Path

from softshape_ros.model.reproduce import _key, reproduce


def reproduce_with_sweep(dataset, out, cfg, work=None, sweep: bool = True, **grid) -> str:
    """Run (or resume) the grid, then the distance sweep into ``results.json``; return table."""
    from softshape_ros.experiments.object_depths import object_depths
    table = reproduce(dataset, out, cfg, work=work, object_depths=object_depths, **grid)
    out = Path(out)
    results = json.loads((out / 'results.json').read_text())
    ck = Path(results['work']) / _key('random', 'stereo', 'ours', max(cfg.sizes))
    if not sweep:
        return table
    if not (ck / 'config.json').exists():
        print(f'reproduce: no object-distance sweep (Fig. 4(c)): it needs the checkpoint {ck}, '
              'trained here or kept in --work')
        return table
    from softshape_ros.experiments.distance_sweep import distance_sweep
    results['fig4c'] = distance_sweep(ck, out / 'fig4c_distance.png')
    (out / 'results.json').write_text(json.dumps(results, indent=2))
    return table
