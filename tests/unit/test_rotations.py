"""rigidbench.rotations: the one home of quaternion maths (w, x, y, z)."""

import math

import numpy as np

from rigidbench.rotations import (quat_about_y, quat_about_z, quat_canonical, quat_conjugate, quat_continuous,
                                  quat_log_vec, quat_mul, quat_to_matrix)
from rigidbench.scene_spec.types import quat_mul as spec_quat_mul


def test_products_rotations_and_matrices_agree():
    a, b = np.array(quat_about_z(0.7)), np.array(quat_about_y(-0.4))
    ab = quat_mul(a, b)
    assert np.allclose(quat_to_matrix(ab), quat_to_matrix(a) @ quat_to_matrix(b))
    assert np.allclose(quat_mul(a, quat_conjugate(a)), [1, 0, 0, 0])
    assert np.allclose(quat_log_vec(a), [0, 0, 0.7])
    assert np.allclose(quat_to_matrix(quat_about_z(math.pi / 2)) @ [1, 0, 0], [0, 1, 0])
    # the spec's tuple product is the same product, as plain floats
    t = spec_quat_mul(quat_about_z(0.7), quat_about_y(-0.4))
    assert all(type(v) is float for v in t) and np.array_equal(np.array(t), ab)


def test_signs():
    q = np.array([[[1.0, 0, 0, 0], [-1.0, 0, 0, 0], [-0.8, 0.6, 0, 0]]])
    assert np.array_equal(quat_continuous(q)[0, :, 0], [1.0, 1.0, 0.8])
    assert np.array_equal(quat_canonical(q[0]), [[1, 0, 0, 0], [1, 0, 0, 0], [0.8, -0.6, 0, 0]])
    # normalize=False takes the quaternion as it is (a spec's exact poses)
    assert np.array_equal(quat_to_matrix([1.0, 1.0, 0, 0], normalize=False), [[1, 0, 0], [0, -1, -2], [0, 2, -1]])
    assert np.allclose(quat_to_matrix([1.0, 1.0, 0, 0]), [[1, 0, 0], [0, 0, -1], [0, 1, 0]])
