import numpy as np

from parammap.geometry import (
    camera_centre,
    distort_normalized,
    look_at,
    pixel_to_plane,
    project_points,
    undistort_normalized,
)


def test_undistort_inverts_distort():
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.7, 0.7, (1000, 2))
    dist = np.array([-0.2, 0.08, 0.001, -0.0015, 0.01])
    back = undistort_normalized(distort_normalized(xy, dist), dist)
    np.testing.assert_allclose(back, xy, atol=1e-10)


def test_distort_matches_opencv():
    K = np.array([[500.0, 0, 320], [0, 505, 240], [0, 0, 1]])
    dist = np.array([-0.2, 0.08, 0.001, -0.0015, 0.01])
    R, t = look_at([30.0, -40, 300], [0.0, 0, 0], 0.2)
    pts = np.random.default_rng(2).uniform(-60, 60, (200, 3)) * [1, 1, 0]
    uv = project_points(pts, K, dist, R, t)
    P, hit = pixel_to_plane(uv, K, dist, R, t)
    assert hit.all()
    np.testing.assert_allclose(P, pts, atol=1e-6)


def test_look_at_centre_and_axis():
    C = np.array([10.0, 20, 300])
    R, t = look_at(C, [0.0, 0, 0])
    np.testing.assert_allclose(camera_centre(R, t), C)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0
    np.testing.assert_allclose(R[2], -C / np.linalg.norm(C))
