"""
Interaction-shape control (no rclpy): search the pressures whose predicted images reach a goal.

::

    from softshape_ros.control import Controller, Goal, GoalError
    ctl = Controller(Predictor.from_checkpoint(path), load_rig_config())
    ctl.set_initial({'main': rest_main, 'side': rest_side})      # camera frames at rest
    loop = ctl.start(ctl.goal_from_images({'main': goal_main, 'side': goal_side}))
    while not loop.done:
        plan = loop.plan()                 # PlanResult: pressures_pa, predicted, cost, ...
        ...                                # command plan.pressures_pa, let it settle, film
        loop.observe(camera_images)        # V x C x 64 x 64 uint8, as the dataset has them

The ``shape_controller`` node runs exactly this over ROS; ``softshape control-eval`` runs it
against the simulator (docs/control.md).
"""

from softshape_ros.control.controller import Controller  # noqa: F401
from softshape_ros.control.features import SceneContext, SceneContextError  # noqa: F401
from softshape_ros.control.goal import Goal, GoalError, GoalSpec  # noqa: F401
from softshape_ros.control.loop import Observation, ShapeLoop, Tolerance  # noqa: F401
from softshape_ros.control.planner import (Bank, Planner, PlannerConfig,  # noqa: F401
                                           PlanResult, RandomSearch)
