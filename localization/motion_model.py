"""The course's ``MotionModel``: ``from localization.motion_model import MotionModel``.

``MotionModel(node)`` as in the course's skeleton and tests: ``deterministic`` is read from the
node's ``deterministic`` parameter (declared when the node has not); ``MotionModel()`` and the
keyword arguments of ``localization.core.motion.MotionModel`` work as well. ``evaluate(particles,
odometry)`` moves (N, 3) particles by ``[dx, dy, dθ]`` in the robot frame, with noise unless
``deterministic`` (then exact composition).
"""
from __future__ import annotations

from localization.core.models.motion import MotionModel as _CoreMotionModel
from localization.core.models.motion import MotionNoiseParams


class MotionModel(_CoreMotionModel):
    """The course's constructor over the project's motion model (``localization.core.motion``)."""

    def __init__(self, node=None, *, deterministic: bool | None = None, rng=None,
                 params: MotionNoiseParams | None = None, **noise):
        if deterministic is None:
            deterministic = False
            if node is not None:
                from localization.ros.course_parameters import course_parameter
                deterministic = bool(course_parameter(node, "deterministic", False))
        super().__init__(deterministic=deterministic, rng=rng, params=params, **noise)


__all__ = ["MotionModel", "MotionNoiseParams"]
