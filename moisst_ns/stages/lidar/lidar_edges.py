"""A spinning LiDAR's depth edges: the points on the near side of a jump in range between neighbours of one ring (a
pole, a car, a building corner) or of adjacent beams (a roof). The camera sees them as occluding contours, which is
what the shared view (``lidar_view``) matches against the reference camera's image edges. No nerfstudio import.
"""

from __future__ import annotations

from typing import Tuple

import numpy as np
from jaxtyping import Float, Int

RING_BIN_DEG = 0.15
"""Points of one laser share an elevation: points are grouped into rings by elevation bins of this width, degrees."""
NEIGHBOUR_DEG = 0.6
"""Two points of a ring, or of adjacent rings, are neighbours when their azimuths differ by less than this, degrees."""
BEAM_VALLEY = 0.02
"""Elevation bins with at most this share of the fullest bin's points separate one beam from the next (``_beams``)."""
MAX_RING_GAP_DEG = 2.5
"""Adjacent rings more than this apart in elevation are not neighbours, degrees (a 16-beam scanner's rings are 2 deg
apart, a 64-beam one's 0.4 deg)."""
JUMP = (0.5, 0.1)
"""A point is a depth edge when a neighbour lies farther by more than ``JUMP[0]`` metres plus ``JUMP[1]`` of its
range (the near side of a discontinuity: its silhouette is what the camera sees)."""


def scan_edges(points: Float[np.ndarray, "num 3"]) -> Tuple[Int[np.ndarray, "edges"], float]:
    """A scan's depth edges: indices of its points on the near side of a range discontinuity between neighbours of one
    ring (an occluding contour across the rings: a pole's side) or of adjacent rings (along them: a car's roof against
    the building behind, which is what places the vertical lever arm); and the coarsest angle between the neighbours
    they compare.

    Between rings, flat ground seen at grazing incidence also jumps in range (a ring at -5 deg meets it at 19 m from
    1.7 m up, the next one 1.1 deg higher at 25 m): such a jump is an edge only beyond where the line through the near
    point and its other neighbour (the surface, continued) meets the farther ray, and only where that neighbour exists.

    A depth edge's near point lies anywhere between its occluding contour and one neighbour step inside the object, all
    on the object's side: for a roof, every one below the edge the camera sees. So the shared view's placement is biased
    by up to this angle (at each point's range, for a lever arm), half of it on average; ``search_held``'s sigma counts it.

    Args:
        points: one scan, in the LiDAR frame (z up, a spinning scanner), metres.

    Returns:
        The edges' indices into ``points`` (sorted), and the angle (radians): the median azimuth step along a ring, or
        the median elevation step between adjacent beams where the scan's beams are apart, whichever is larger.
    """
    rng, azimuth, _, (a, b), members, centre = _neighbours(points)
    jump = lambda near: JUMP[0] + JUMP[1] * rng[near]
    near = [a[rng[b] - rng[a] > jump(a)], b[rng[a] - rng[b] > jump(b)]]  # along a ring
    above, below = np.full(len(points), -1), np.full(len(points), -1)  # across beams: the nearest azimuth up and down
    for lower, upper, c_low, c_up in zip(members[:-1], members[1:], centre[:-1], centre[1:]):
        if c_up - c_low > MAX_RING_GAP_DEG:
            continue
        for source, target, neighbour in ((lower, upper, above), (upper, lower, below)):
            az = azimuth[target]
            k = np.searchsorted(az, azimuth[source])
            left, right = np.clip(k - 1, 0, len(az) - 1), np.clip(k, 0, len(az) - 1)
            k = np.where(np.abs(az[left] - azimuth[source]) <= np.abs(az[right] - azimuth[source]), left, right)
            close = np.abs(az[k] - azimuth[source]) < NEIGHBOUR_DEG
            neighbour[source[close]] = target[k[close]]
    for farther, other in ((above, below), (below, above)):  # the far side above (a roof), then below (an overhang)
        p = np.flatnonzero((farther >= 0) & (other >= 0))
        q = farther[p]
        continued = _continued_range(points[other[p]], points[p], points[q])
        near.append(p[rng[q] - np.maximum(rng[p], continued) > jump(p)])
    steps = [np.median(np.abs(azimuth[b] - azimuth[a])) if len(a) else 0.0]
    beams = np.diff(centre)
    steps.append(np.median(beams[beams <= MAX_RING_GAP_DEG]) if (beams <= MAX_RING_GAP_DEG).any() else 0.0)
    return np.unique(np.concatenate(near)), float(np.deg2rad(max(steps)))


def _neighbours(points: Float[np.ndarray, "num 3"]):
    """A scan's range, azimuth and elevation (degrees) per point; the neighbour pairs ``(a, b)`` along its rings
    (consecutive in azimuth within ``NEIGHBOUR_DEG``; rings are elevation bins ``RING_BIN_DEG`` wide); its beams
    (``_beams``: each one's points in azimuth order) and their median elevations."""
    rng = np.linalg.norm(points, axis=1)
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    elevation = np.degrees(np.arcsin(points[:, 2] / np.maximum(rng, 1e-9)))
    ring = np.floor(elevation / RING_BIN_DEG).astype(np.int64)
    order = np.lexsort((azimuth, ring))
    a, b = order[:-1], order[1:]
    same = (ring[a] == ring[b]) & (np.abs(azimuth[b] - azimuth[a]) < NEIGHBOUR_DEG)
    beam = _beams(elevation)
    members = [m[np.argsort(azimuth[m])] for m in (np.flatnonzero(beam == k) for k in range(beam.max() + 1 if len(beam) else 0))]
    return rng, azimuth, elevation, (a[same], b[same]), members, np.array([np.median(elevation[m]) for m in members])


def _beams(elevation: Float[np.ndarray, "num"]) -> Int[np.ndarray, "num"]:
    """Each point's beam (0 = the lowest), or -1 for every point when the scan's beams are not apart: beams are the runs
    of elevation bins (``RING_BIN_DEG`` / 3 wide) holding more than ``BEAM_VALLEY`` of the fullest one's points, and
    they are apart when every run is at most ``RING_BIN_DEG`` * 2 wide. A scanner whose lasers sit off its origin (KITTI's
    HDL-64E) spreads each laser's elevation with range over neighbouring bins: there, no valley separates one laser
    from the next, and a point's neighbour across rings would often be its own laser farther along (degrees in)."""
    width = RING_BIN_DEG / 3
    if len(elevation) == 0:
        return np.zeros(0, dtype=np.int64)
    index = np.floor((elevation - elevation.min()) / width).astype(np.int64)
    counts = np.bincount(index)
    full = counts > BEAM_VALLEY * counts.max()
    run = np.cumsum(np.r_[full[0], full[1:] & ~full[:-1]]) - 1  # run number of every full bin
    lengths = np.bincount(run[full])
    if lengths.max() * width > 2 * RING_BIN_DEG:
        return np.full(len(elevation), -1)
    return np.where(full[index], run[index], -1)


def _continued_range(before: Float[np.ndarray, "num 3"], at: Float[np.ndarray, "num 3"],
                     ray: Float[np.ndarray, "num 3"]) -> Float[np.ndarray, "num"]:
    """Range (metres) at which the direction of ``ray`` meets the line through ``before`` and ``at`` (LiDAR-frame
    points of adjacent rings), in the vertical plane of the azimuth; infinite where it never does (the surface runs
    away from the ray: ground towards the horizon)."""
    s = lambda p: np.hypot(p[:, 0], p[:, 1])
    vs, vz = s(at) - s(before), at[:, 2] - before[:, 2]
    den = s(ray) * vz - ray[:, 2] * vs
    t = (s(at) * vz - at[:, 2] * vs) / np.where(np.abs(den) > 1e-12, den, np.nan)  # along ``ray``: 1 at its point
    return np.where(np.isfinite(t) & (t > 0), t * np.linalg.norm(ray, axis=1), np.inf)
