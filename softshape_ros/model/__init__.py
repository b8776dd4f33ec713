"""
The visual forward model (no rclpy): networks, training, evaluation, checkpoints, export.

The inference node needs only::

    from softshape_ros.model import Predictor, CheckpointError
    pred = Predictor.from_checkpoint(path)
    out = pred.predict(initial, pressures_pa)
"""

from softshape_ros.model.checkpoint import (  # noqa: F401
    CheckpointError, load_checkpoint, save_checkpoint)
from softshape_ros.model.networks import ARCHS, build_network  # noqa: F401
from softshape_ros.model.predictor import Predictor  # noqa: F401
