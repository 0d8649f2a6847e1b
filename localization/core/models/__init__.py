"""The models: ``motion`` (odometry noise in the robot frame), ``sensor`` (the sensor-model protocol) and
its two models, ``beam`` and ``likelihood_field``."""
