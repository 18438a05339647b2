"""The LiDAR's points that do not stay put between scans (``lidar_scans.moving_points``): a car's back driving ahead
of the rig is found, the static street is not, even with the LiDAR's calibration 50 cm / 5 deg off."""

import numpy as np
from scipy.spatial.transform import Rotation

from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.stages.lidar.lidar_geometry import Extrinsic, PointTimes
from moisst_ns.stages.lidar.lidar_scans import LidarFirstConfig, ScanSet, _neighbourhood_geometry, moving_points


def street(num_scans: int = 6, speed: float = 8.0, car_speed: float = 4.0):
    """A rig driving along world x at ``speed`` m/s, scanning every 0.1 s (LiDAR frame = the reference frame, at the
    trajectory's poses): the road (z = -1.5), a wall across the street 30 m ahead and a car's back (1.6 x 1.2 m, 12 m
    ahead at the start) driving away at ``car_speed``. Returns the scans and, per point, whether it is on the car."""
    rng = np.random.default_rng(0)
    stamps = np.arange(num_scans) * 0.1
    traj_t = np.arange(-5, num_scans + 5) * 0.1
    traj = ReferenceTrajectory.from_tum(traj_t, np.column_stack([speed * traj_t, 0 * traj_t, 0 * traj_t]),
                                        np.tile([0.0, 0.0, 0.0, 1.0], (len(traj_t), 1)), t0=0.0)
    config = LidarFirstConfig()
    pts, on_car, normals, planar, thickness, offsets = [], [], [], [], [], [0]
    for t in stamps:
        road = np.column_stack([rng.uniform(2, 28, 4000), rng.uniform(-6, 6, 4000), np.full(4000, -1.5)])
        wall = np.column_stack([np.full(3000, 30.0), rng.uniform(-6, 6, 3000), rng.uniform(-1.5, 3, 3000)])
        car = np.column_stack([np.full(800, 12.0 + car_speed * t), rng.uniform(-0.8, 0.8, 800), rng.uniform(-1.0, 0.2, 800)])
        world = np.concatenate([road, wall, car])
        local = world - np.array([speed * t, 0.0, 0.0]) + rng.normal(0, 0.01, world.shape)
        n, ok, thick = _neighbourhood_geometry(local, config)
        pts.append(local), normals.append(n), planar.append(ok), thickness.append(thick)
        on_car.append(np.r_[np.zeros(7000, bool), np.ones(800, bool)])
        offsets.append(offsets[-1] + len(local))
    points = np.concatenate(pts)
    times = np.repeat(stamps, [len(p) for p in pts])
    scans = ScanSet("lidar", points, PointTimes.of(times), np.asarray(offsets), stamps, np.concatenate(normals), np.concatenate(planar),
                    np.concatenate(thickness), [], [], False)
    return traj, scans, np.concatenate(on_car)


def test_a_car_ahead_is_moving_and_the_street_is_not():
    """At the true calibration and 50 cm / 5 deg off on every axis: at least 90 % of the back of a car driving away at
    4 m/s is found moving (0.4 m between scans, against 0.15 m for walking pace; measured 93-94 %), at most 0.1 % of
    the road and the wall (measured 0-0.01 %). A car keeping the rig's speed and an oncoming one (0.8 m in the world
    between scans): at least 70 % (measured 74-78 %: its lower part's nearest surface in the next scan is the road,
    which does not face as it does, so it is not judged)."""
    off = Extrinsic(Rotation.from_rotvec(np.deg2rad([5.0, 5.0, 5.0])).as_matrix(), np.array([0.5, 0.5, 0.5]), 0.0)
    for car_speed, found in ((4.0, 0.9), (8.0, 0.7), (-8.0, 0.7)):
        traj, scans, on_car = street(car_speed=car_speed)
        for ext in (Extrinsic(np.eye(3), np.zeros(3), 0.0), off):
            moving = moving_points(traj, ext, scans)
            assert moving[on_car].mean() > found and moving[~on_car].mean() < 0.001, (car_speed, moving[on_car].mean(), moving[~on_car].mean())


def test_a_parked_car_is_not_moving():
    """The same car standing still: none of its points, nor of the street, is found moving (measured 0 and 0.01 %)."""
    traj, scans, on_car = street(car_speed=0.0)
    moving = moving_points(traj, Extrinsic(np.eye(3), np.zeros(3), 0.0), scans)
    assert not moving[on_car].any() and moving.mean() < 0.001, (moving[on_car].mean(), moving[~on_car].mean())


def test_the_same_instant_placement_leaves_out_a_match_whose_line_of_sight_passes_a_mover():
    """``lidar_instant._off_movers``: a match seen through the car's back (in the scan nearest its instant) is left out
    with every field, one towards the wall beside it (3 deg past the car's edge) and one towards the road are kept;
    with nothing moving, every match is kept."""
    from moisst_ns.stages.lidar.lidar_instant import InstantPoints, _off_movers

    traj, scans, on_car = street()
    origin = np.array([8.0 * 0.2, 0.0, 0.0])  # the rig at the third scan, 0.2 s
    edge = np.deg2rad(3.0) + np.arctan2(0.8, 12.8 - origin[0])  # the car's back spans y in [-0.8, 0.8] at x = 12.8
    targets = np.array([[12.8, 0.0, -0.4], [12.8, 0.3, 0.0], [origin[0] + 28.4 * np.cos(edge), 28.4 * np.sin(edge), -0.4], [20.0, -3.0, -1.5]])
    n = len(targets)
    pts = InstantPoints(0.21, np.tile(origin, (n, 1)), targets - origin, np.arange(n, dtype=float), np.arange(2 * n, dtype=float).reshape(n, 2), 0)
    ext = Extrinsic(np.eye(3), np.zeros(3), 0.0)
    kept = _off_movers(traj, ext, scans, on_car, pts)
    assert np.allclose(kept.ray, (targets - origin)[2:]) and kept.depth_sigma.tolist() == [2.0, 3.0]
    assert kept.shift_gradient.tolist() == [[4.0, 5.0], [6.0, 7.0]] and kept.origin.shape == (2, 3)
    assert len(_off_movers(traj, ext, scans, np.zeros_like(on_car), pts).ray) == n
