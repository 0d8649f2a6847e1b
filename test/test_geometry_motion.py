"""Pose composition, angle wrapping and the motion model (robot-frame noise)."""
import math

import numpy as np
import pytest

from localization.core import geometry
from localization.core.geometry import (
    circular_mean,
    compose,
    compose_numpy,
    integrate_twist,
    integrate_twists,
    integrate_twists_numpy,
    inverse,
    quaternion_to_yaw,
    relative,
    wrap_angle,
    yaw_to_quaternion,
)
from localization.core.models.motion import MotionModel


def test_wrap_angle_range():
    a = np.linspace(-20, 20, 10001)
    w = wrap_angle(a)
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    assert np.allclose(np.sin(w), np.sin(a)) and np.allclose(np.cos(w), np.cos(a))
    assert wrap_angle(np.pi) == pytest.approx(np.pi) and wrap_angle(-np.pi) == pytest.approx(np.pi)


def test_compose_relative_inverse_roundtrip():
    rng = np.random.default_rng(3)
    a = rng.uniform(-5, 5, (50, 3))
    b = rng.uniform(-5, 5, (50, 3))
    assert np.allclose(compose(a, relative(a, b))[:, :2], b[:, :2])
    assert np.allclose(np.cos(compose(a, relative(a, b))[:, 2]), np.cos(b[:, 2]))
    assert np.allclose(compose(a, inverse(a)), 0.0, atol=1e-12)


EDGE_ANGLES = [0.0, -0.0, np.pi, -np.pi, 2 * np.pi, -2 * np.pi, 3 * np.pi, 1e-300, -1e-300, 1e6, np.nan, np.inf]


def _poses(seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = rng.uniform(-50.0, 50.0, (n, 3))
    poses[:, 2] = rng.uniform(-10.0, 10.0, n)
    poses[:len(EDGE_ANGLES), 2] = EDGE_ANGLES
    return poses


def _relative_numpy(a, b):
    """``relative`` through numpy's broadcasting (a stack of one row takes that path)."""
    return relative(np.asarray(a)[None, :], np.asarray(b)[None, :])[0]


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # numpy's cos(inf) and remainder(inf)
def test_one_pose_paths_equal_numpy_bit_for_bit():
    """One pose goes through Python floats (the filter's many small calls), with numpy's results."""
    a, b = _poses(0, 400), _poses(1, 400)[::-1].copy()
    for p, d in zip(a, b):
        np.testing.assert_array_equal(compose(p, d), compose_numpy(p, d))
        np.testing.assert_array_equal(relative(p, d), _relative_numpy(p, d))
        np.testing.assert_array_equal(compose(tuple(p.tolist()), list(d.tolist())), compose_numpy(p, d))
    np.testing.assert_array_equal(inverse(a[20]), _relative_numpy(a[20], np.zeros(3)))


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_stack_with_one_pose_equals_numpy_bit_for_bit():
    """A stack composed with one pose (either side) runs compiled, with numpy's results."""
    stack, one = _poses(2, 300), _poses(3, 20)
    for d in one:
        np.testing.assert_array_equal(compose(stack, d), compose_numpy(stack, d))
        np.testing.assert_array_equal(compose(d, stack), compose_numpy(d, stack))
        np.testing.assert_array_equal(compose(stack[:, None, :][:, 0, :][::2], d), compose_numpy(stack[::2], d))
    np.testing.assert_array_equal(compose(stack[:1], one[0]), compose_numpy(stack[:1], one[0]))  # (1, 3) stays 2-D
    assert compose(np.zeros((0, 3)), one[0]).shape == (0, 3)
    np.testing.assert_array_equal(compose(stack, stack[::-1]), compose_numpy(stack, stack[::-1]))  # numpy's own


def test_integrate_twists_compiled_equals_numpy_and_the_scalar_form():
    rng = np.random.default_rng(4)
    vx, vy, wz, dt = (rng.uniform(-3.0, 3.0, 500) for _ in range(4))
    wz[:100] *= 1e-7  # the second-order branch
    wz[100] = 0.0
    np.testing.assert_array_equal(integrate_twists(vx, vy, wz, dt), integrate_twists_numpy(vx, vy, wz, dt))
    np.testing.assert_array_equal(integrate_twists(1.5, 0.0, 0.3, dt), integrate_twists_numpy(1.5, 0.0, 0.3, dt))
    np.testing.assert_array_equal(integrate_twists(1.5, 0.1, 0.3, 0.02), integrate_twist(1.5, 0.1, 0.3, 0.02))
    grid = integrate_twists(vx.reshape(20, 25), vy.reshape(20, 25), wz.reshape(20, 25), dt.reshape(20, 25))
    np.testing.assert_array_equal(grid, integrate_twists_numpy(vx, vy, wz, dt).reshape(20, 25, 3))
    if geometry._integrate_twists_kernel is not None:  # numba is pinned: the compiled loop is what ran above
        assert geometry._compose_kernel is not None


def test_deterministic_motion_is_exact_composition_by_hand():
    # Odometry that takes the robot from [-1, 3, pi/6] to [2, 1, 11pi/60], applied to [3, 4, pi/3].
    c, s = math.cos(math.pi / 6), math.sin(math.pi / 6)
    ox, oy = c * 3 + s * -2, -s * 3 + c * -2  # world displacement (3, -2) seen from heading pi/6
    odom = np.array([ox, oy, 11 * math.pi / 60 - math.pi / 6])
    assert np.allclose(odom, relative([-1, 3, math.pi / 6], [2, 1, 11 * math.pi / 60]))
    c3, s3 = math.cos(math.pi / 3), math.sin(math.pi / 3)
    expected = [3 + c3 * ox - s3 * oy, 4 + s3 * ox + c3 * oy, math.pi / 3 + math.pi / 60]
    moved = MotionModel(deterministic=True).evaluate(np.array([[3.0, 4.0, math.pi / 3]] * 4), odom)
    assert np.allclose(moved, expected)
    assert expected[0] == pytest.approx(6.598, abs=1e-3) and expected[1] == pytest.approx(3.768, abs=1e-3)


def test_noise_is_added_in_the_robot_frame():
    # Heading pi/2: forward motion moves +y; along-track noise (large here) must show up in world y,
    # cross-track noise (tiny here) in world x. World-frame noise would spread both alike.
    model = MotionModel(rng=0, a_trans=0.3, a_lateral=0.0, a_rot=0.0, a_rot_to_trans=0.0, a_trans_to_rot=0.0,
                        floor_xy=0.001, floor_theta=0.0)
    particles = np.tile([0.0, 0.0, np.pi / 2], (20000, 1))
    moved = model.evaluate(particles, [1.0, 0.0, 0.0])
    assert np.mean(moved[:, 1]) == pytest.approx(1.0, abs=0.01)
    assert np.mean(moved[:, 0]) == pytest.approx(0.0, abs=0.01)
    assert np.std(moved[:, 1]) == pytest.approx(0.301, rel=0.05)
    assert np.std(moved[:, 0]) < 0.01


def test_motion_keeps_angles_wrapped_and_input_untouched():
    model = MotionModel(rng=1)
    particles = np.tile([0.0, 0.0, 3.1], (1000, 1))
    before = particles.copy()
    moved = model.evaluate(particles, [0.1, 0.0, 0.5])
    assert np.array_equal(particles, before)
    assert np.all(moved[:, 2] > -np.pi) and np.all(moved[:, 2] <= np.pi)


def test_no_motion_adds_no_noise():
    particles = np.random.default_rng(2).uniform(-1, 1, (100, 3))
    assert np.allclose(MotionModel(rng=0).evaluate(particles, [0.0, 0.0, 0.0]), particles, rtol=0, atol=1e-12)


def test_motion_noise_is_seeded():
    p = np.zeros((10, 3))
    a = MotionModel(rng=5).evaluate(p, [0.3, 0.0, 0.1])
    b = MotionModel(rng=5).evaluate(p, [0.3, 0.0, 0.1])
    assert np.array_equal(a, b) and not np.array_equal(a, MotionModel(rng=6).evaluate(p, [0.3, 0.0, 0.1]))


def test_bad_noise_parameters_are_rejected():
    with pytest.raises(ValueError):
        MotionModel(a_trans=-1.0)
    with pytest.raises(TypeError):
        MotionModel(not_a_param=1.0)


def test_quaternion_and_circular_mean():
    q = yaw_to_quaternion(2.5)
    assert quaternion_to_yaw(*q) == pytest.approx(2.5)
    assert circular_mean([np.pi - 0.1, -np.pi + 0.1]) == pytest.approx(np.pi, abs=1e-9) or \
        circular_mean([np.pi - 0.1, -np.pi + 0.1]) == pytest.approx(-np.pi, abs=1e-9)
