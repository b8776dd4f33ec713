"""
Write the renderer's reference images (test_sim_render compares today's renderer with them).

The images are the ones the z-buffered numpy ray caster (swept spheres, analytic objects)
made before the compiled renderer replaced it. To remake them, run this file with that
renderer first on the path, e.g. from a checkout of the code before it::

    PYTHONPATH=/path/to/old/checkout python test/data/render_reference/make_reference.py

Each case stores its scene and backbone (so later changes to the solver cannot move the
robot under the images) and one gray PNG per camera, plus the 64x64 network inputs.
"""

import json
from pathlib import Path

import cv2
import numpy as np

from softshape_ros.config import load_rig_config
from softshape_ros.scene import Scene
from softshape_ros.sim import SimRig
from softshape_ros.vision.preprocess import to_gray

HERE = Path(__file__).resolve().parent
CASES = [
    ('bent_alone', None, [1.5e5, 0, 0, 1.5e5, 0, 0]),
    ('cylinder', Scene(id=1, object='cylinder', position_m=(0.025, 0.0, 0.02),
                       dims={'radius_m': 0.008, 'height_m': 0.05}), [0, 1e5, 0, 0, 1.2e5, 0]),
    ('ring', Scene(id=2, object='ring', position_m=(-0.03, 0.0, 0.025),
                   rpy_rad=(1.5707963, 0.0, 0.0),
                   dims={'major_radius_m': 0.012, 'minor_radius_m': 0.003}),
     [0, 1e5, 0, 0, 1.2e5, 0]),
    ('prism', Scene(id=3, object='prism', position_m=(0.0, 0.03, 0.01), rpy_rad=(0.2, 0.3, 0.5),
                    dims={'width_m': 0.02, 'depth_m': 0.015, 'height_m': 0.03,
                          'skew_rad': 0.3}), [0, 0, 0, 0, 0, 0]),
    ('sphere_front', Scene(id=4, object='sphere', position_m=(0.02, -0.03, 0.03),
                           dims={'radius_m': 0.006}), [0, 1e5, 0, 0, 1.2e5, 0]),
    ('sphere_peek', Scene(id=5, object='sphere', position_m=(0.02, 0.04, 0.03),
                          dims={'radius_m': 0.006}), [0, 0, 0, 0, 0, 0]),
    ('plane', Scene(id=6, object='plane', position_m=(0.0, 0.0, -0.01), dims={}),
     [0, 1.5e5, 1.5e5, 0, 0, 1.5e5]),
]


def main():
    cfg = load_rig_config()
    rig = SimRig(cfg)
    index = []
    for name, scene, pressures in CASES:
        rig.set_scene(scene)
        st = rig.solve(pressures)
        for cam, img in rig.render(st).items():
            cv2.imwrite(str(HERE / f'{name}_{cam}.png'), to_gray(img))
        for cam, inp in rig.render_inputs(st).items():
            cv2.imwrite(str(HERE / f'{name}_{cam}_input.png'), inp[0])
        index.append({'name': name, 'scene': json.loads(scene.to_json()) if scene else None,
                      'backbone_m': np.round(st.backbone_m, 12).tolist(),
                      'radii_m': st.radii_m.tolist()})
    (HERE / 'cases.json').write_text(json.dumps(index, indent=1) + '\n')


if __name__ == '__main__':
    main()
