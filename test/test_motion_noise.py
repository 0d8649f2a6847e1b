"""The motion noise is a random walk in the distance travelled and the angle turned: the spread after
a motion does not depend on how many odometry / scan pieces it arrives in (rate-free)."""
from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from localization.core.geometry import compose, integrate_twist, wrap_angle
from localization.core.models import motion as motion_module
from localization.core.models.motion import ROBOT_MODELS, MotionModel, MotionNoiseParams, robot_model
from localization.core.parameters import ParameterError, Parameters

CONFIG = Path(__file__).resolve().parents[1] / "config"
N = 20_000

# (vx, vy, wz) driven for 1 s: 0.10 m straight, a 0.10 m arc turning 0.3 rad, 0.5 rad on the spot,
# and (omni) 0.10 m sideways
MOTIONS = {"straight": (0.10, 0.0, 0.0), "arc": (0.10, 0.0, 0.3), "turn_on_the_spot": (0.0, 0.0, 0.5),
           "sideways": (0.0, 0.10, 0.0)}
CASES = [(robot, motion) for robot in ("ackermann", "differential", "omni") for motion in MOTIONS
         if not (motion == "sideways" and robot != "omni")]


def car_noise(robot: str = "ackermann") -> MotionNoiseParams:
    """The car's motion noise (config/real_params.yaml's motion_* values) with the given robot model."""
    section = yaml.safe_load((CONFIG / "real_params.yaml").read_text())["particle_filter"]["ros__parameters"]
    motion = {k: v for k, v in section.items() if k.startswith("motion_")}
    assert len(motion) >= 5
    return MotionNoiseParams.from_parameters(Parameters(motion, robot_model_type=robot))


def spread(model: MotionModel, twist, steps: int, heading: float = 0.4) -> np.ndarray:
    """Std of world x, y, θ of N particles from one pose after the twist's 1-s motion in ``steps`` pieces."""
    particles = np.tile([1.0, -2.0, heading], (N, 1))
    piece = integrate_twist(*twist, 1.0 / steps)
    for _ in range(steps):
        model.evaluate(particles, piece, out=particles)
    th = wrap_angle(particles[:, 2] - (heading + twist[2]))
    return np.array([particles[:, 0].std(), particles[:, 1].std(), th.std()])


@pytest.mark.parametrize("robot, motion", CASES)
def test_spread_does_not_depend_on_how_the_motion_is_split(robot, motion):
    twist = MOTIONS[motion]
    one = spread(MotionModel(rng=1, params=car_noise(robot)), twist, 1)
    assert np.all(one > 1e-3), one  # every component has noise to compare
    for steps in (2, 5, 10):
        split = spread(MotionModel(rng=steps, params=car_noise(robot)), twist, steps)
        assert split == pytest.approx(one, rel=0.05), (steps, one, split)


def test_variance_grows_linearly_with_distance_like_a_random_walk():
    model = MotionModel(rng=3, a_trans=0.2, a_lateral=0.1, a_rot=0.0, a_rot_to_trans=0.0, a_trans_to_rot=0.0,
                        floor_xy=0.0, floor_theta=0.0)
    short = spread(model, (0.1, 0.0, 0.0), 1, heading=0.0)
    long = spread(model, (0.4, 0.0, 0.0), 1, heading=0.0)
    assert short[:2] == pytest.approx([0.2 * math.sqrt(0.1), 0.1 * math.sqrt(0.1)], rel=0.03)
    assert long[:2] == pytest.approx(2.0 * short[:2], rel=0.03)  # 4x the distance: 2x the std


def test_covariance_of_a_straight_piece_is_the_continuous_random_walk():
    """Heading noise picked up along the way moves the end sideways: Var y = q_y t + q_θ t³/3,
    Cov(y, θ) = q_θ t²/2, Var θ = q_θ t (q: variance per metre)."""
    model = MotionModel(a_trans=0.3, a_lateral=0.1, a_rot=0.0, a_rot_to_trans=0.0, a_trans_to_rot=0.5,
                        floor_xy=0.0, floor_theta=0.0)
    t = 0.8
    cov = model.noise_covariance([t, 0.0, 0.0])
    expected = np.array([[0.09 * t, 0.0, 0.0], [0.0, 0.01 * t + 0.25 * t ** 3 / 3, 0.25 * t ** 2 / 2],
                         [0.0, 0.25 * t ** 2 / 2, 0.25 * t]])
    assert cov == pytest.approx(expected, abs=1e-12)
    assert model.noise_sigmas([t, 0.0, 0.0]) == pytest.approx(np.sqrt(np.diag(expected)))


def test_a_standing_robot_gets_no_noise_and_deterministic_is_exact():
    particles = np.random.default_rng(2).uniform(-1, 1, (100, 3))
    arc = integrate_twist(0.3, 0.0, 0.2, 1.0)  # a piece every base can drive
    for robot in ROBOT_MODELS:
        model = MotionModel(rng=0, params=car_noise(robot))
        assert np.allclose(model.evaluate(particles, [0.0, 0.0, 0.0]), particles, rtol=0, atol=1e-12)
        assert not model.noise_covariance([0.0, 0.0, 0.0]).any()
        exact = MotionModel(deterministic=True, params=car_noise(robot)).evaluate(particles, arc)
        assert np.allclose(exact, compose(particles, arc), rtol=0, atol=1e-12)


def test_course_facade_keeps_working_with_no_arguments():
    from localization.motion_model import MotionModel as CourseMotionModel
    model = CourseMotionModel()
    assert model.robot.name == "ackermann"
    moved = model.evaluate(np.zeros((500, 3)), [0.1, 0.0, 0.05])
    assert moved.shape == (500, 3) and np.all(np.isfinite(moved))
    assert abs(moved[:, 0].mean() - 0.1) < 0.01 and moved[:, 0].std() > 0


# ------------------------------------------------------------------------------ robot models
@pytest.mark.parametrize("name, expected", [
    ("ackermann", "ackermann"), ("differential", "differential"), ("omni", "omni"),
    ("nav2_amcl::DifferentialMotionModel", "differential"), ("nav2_amcl::OmniMotionModel", "omni"),
    ("omnidirectional", "omni")])
def test_robot_model_names_and_nav2_names(name, expected):
    assert robot_model(name).name == expected
    assert Parameters(robot_model_type=name).robot_model_type == name


def test_unknown_robot_model_is_rejected():
    with pytest.raises(ValueError, match="robot_model_type"):
        robot_model("tank")
    with pytest.raises(ParameterError):
        Parameters(robot_model_type="tank")


def test_differential_turns_on_the_spot_with_rotation_noise_only_from_rotation():
    model = MotionModel(rng=4, robot_model_type="differential", a_trans=0.2, a_lateral=0.1, a_rot=0.3,
                        a_rot_to_trans=0.0, a_trans_to_rot=0.2, floor_xy=0.0, floor_theta=0.0)
    moved = model.evaluate(np.zeros((N, 3)), [0.0, 0.0, 0.5])
    assert moved[:, 2].mean() == pytest.approx(0.5, abs=0.01)
    assert moved[:, 2].std() == pytest.approx(0.3 * math.sqrt(0.5), rel=0.03)
    assert np.abs(moved[:, :2]).max() == 0.0  # no translation noise without a translation source


def test_differential_ignores_sideways_odometry_with_one_warning(caplog):
    model = MotionModel(deterministic=True, robot_model_type="differential")
    p = np.zeros((3, 3))
    with caplog.at_level(logging.WARNING, logger="localization.motion"):
        a = model.evaluate(p, integrate_twist(0.5, 0.2, 0.4, 0.1))
        b = model.evaluate(p, integrate_twist(0.5, 0.3, 0.4, 0.1))
    assert a == pytest.approx(np.tile(integrate_twist(0.5, 0.0, 0.4, 0.1), (3, 1)), abs=1e-12)  # vy forced to 0
    assert np.allclose(a, b, rtol=0, atol=1e-15)
    warnings = [r for r in caplog.records if r.name == "localization.motion"]
    assert len(warnings) == 1 and "vy" in warnings[0].getMessage() and "differential" in warnings[0].getMessage()
    # the car and the omni base keep the sideways motion
    for robot in ("ackermann", "omni"):
        kept = MotionModel(deterministic=True, robot_model_type=robot).evaluate(p, integrate_twist(0.5, 0.2, 0.4, 0.1))
        assert kept[0] == pytest.approx(integrate_twist(0.5, 0.2, 0.4, 0.1), abs=1e-12)


def test_omni_noise_follows_the_direction_of_travel():
    """Moving sideways, the omni base's along-travel noise (a_trans) is sideways in the robot frame and
    its strafe noise (a_lateral) is forward; a car's noise stays in its own axes."""
    noise = dict(a_trans=0.3, a_lateral=0.05, a_rot=0.0, a_rot_to_trans=0.0, a_trans_to_rot=0.0, floor_xy=0.0,
                 floor_theta=0.0)
    omni = MotionModel(rng=5, robot_model_type="omni", **noise).evaluate(np.zeros((N, 3)), [0.0, 0.2, 0.0])
    assert omni[:, 1].mean() == pytest.approx(0.2, abs=0.01)
    assert omni[:, 1].std() == pytest.approx(0.3 * math.sqrt(0.2), rel=0.03)  # along the travel: sideways
    assert omni[:, 0].std() == pytest.approx(0.05 * math.sqrt(0.2), rel=0.03)
    car = MotionModel(rng=5, robot_model_type="ackermann", **noise).evaluate(np.zeros((N, 3)), [0.0, 0.2, 0.0])
    assert car[:, 0].std() == pytest.approx(0.3 * math.sqrt(0.2), rel=0.03)  # the car's x axis


# ------------------------------------------------------------------------------ nav2 alphas
def test_nav2_alphas_map_onto_the_motion_noise_with_one_log_line(caplog):
    with caplog.at_level(logging.INFO, logger="localization.motion"):
        p = MotionNoiseParams.from_parameters(Parameters(robot_model_type="nav2_amcl::DifferentialMotionModel",
                                                         alpha1=0.2, alpha2=0.1, alpha3=0.4, alpha4=0.05,
                                                         alpha5=0.3, motion_a_lateral=0.07))
    d, a = motion_module.NAV2_UPDATE_MIN_D, motion_module.NAV2_UPDATE_MIN_A
    assert p.a_rot == pytest.approx(math.sqrt(0.2 * a))
    assert p.a_trans_to_rot == pytest.approx(math.sqrt(2 * 0.1 * d))  # nav2's differential draws it twice
    assert p.a_trans == pytest.approx(math.sqrt(0.4 * d))
    assert p.a_rot_to_trans == pytest.approx(math.sqrt(0.05 * a))
    assert p.a_lateral == 0.07  # alpha5 is the omni model's only
    lines = [r.getMessage() for r in caplog.records if r.name == "localization.motion"]
    assert len(lines) == 1
    for text in ("alpha1", "motion_a_rot", "alpha3", "motion_a_trans", "alpha5", "ignored"):
        assert text in lines[0]
    omni = MotionNoiseParams.from_parameters(Parameters(robot_model_type="omni", alpha2=0.1, alpha5=0.3))
    assert omni.a_lateral == pytest.approx(math.sqrt(0.3 * d))
    assert omni.a_trans_to_rot == pytest.approx(math.sqrt(0.1 * d))
    assert omni.a_trans == Parameters().motion_a_trans  # unset alphas leave motion_* alone


def test_no_alpha_no_log_line(caplog):
    with caplog.at_level(logging.INFO, logger="localization.motion"):
        p = MotionNoiseParams.from_parameters(Parameters())
    assert not [r for r in caplog.records if r.name == "localization.motion"]
    assert p.a_trans == Parameters().motion_a_trans and p.robot_model_type == "ackermann"


def test_alpha_must_be_unset_or_non_negative():
    with pytest.raises(ParameterError):
        Parameters(alpha3=-0.5)


# ------------------------------------------------------------------------------ kernel vs numpy
@pytest.mark.parametrize("robot", sorted(ROBOT_MODELS))
@pytest.mark.parametrize("odometry", [[0.1, 0.02, 0.3], [0.0, 0.0, 0.4], [-0.05, 0.01, -3.0], [0.0, 0.0, 0.0]])
def test_compiled_kernel_equals_the_numpy_reference(monkeypatch, robot, odometry):
    assert motion_module._move_kernel is not None  # numba is pinned: the compiled pass is the one used
    particles = np.random.default_rng(0).uniform(-4, 4, (3000, 3))
    compiled = MotionModel(rng=3, params=car_noise(robot)).evaluate(particles, odometry)
    monkeypatch.setattr(motion_module, "_move_kernel", None)
    plain = MotionModel(rng=3, params=car_noise(robot)).evaluate(particles, odometry)
    assert np.allclose(compiled, plain, rtol=0, atol=1e-12)


@pytest.mark.parametrize("piece", [(0.3, 0.0, 0.0), (0.2, 0.05, 0.4), (0.0, 0.0, 0.7), (0.1, -0.2, -1.2),
                                   (1e-8, 0.0, 1e-9)])
def test_covariance_kernel_equals_its_numpy_reference(piece):
    if motion_module._covariance_kernel is None:
        pytest.skip("numba missing")  # pragma: no cover - numba is pinned
    vx, vy, w = piece
    args = (vx, vy, w, 0.3, 0.02, 0.01, 0.005)
    got = motion_module._covariance_kernel(*args, motion_module._GL_TAU, motion_module._GL_W)
    np.testing.assert_allclose(got, motion_module.covariance_reference(*args), rtol=1e-12, atol=1e-18)
