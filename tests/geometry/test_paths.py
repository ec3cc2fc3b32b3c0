"""Render paths: orbit and spiral around where the training cameras look, on their arc for a partial capture."""

import math

import torch

from nerf_lightning.geometry.paths import _orbit_frame, covered_arc, orbit_path, spiral_path


def azimuths(c2w, reference):
    centre, _, e1, e2, _, _ = _orbit_frame(reference)
    offsets = c2w[:, :3, 3] - centre
    return torch.atan2(offsets @ e2, offsets @ e1)


def test_paths_circle_a_capture_all_around(procedural_scene):
    cameras = procedural_scene.train.c2w
    for path in (orbit_path(cameras, 60), spiral_path(cameras, 60)):
        angles = torch.sort(azimuths(path, cameras)).values
        assert float((angles[1:] - angles[:-1]).max()) < math.radians(20)  # no gap: all the way round
        assert float(angles[-1] - angles[0]) > math.radians(330)


def test_paths_stay_on_the_arc_of_a_partial_capture(procedural_scene):
    cameras = procedural_scene.train.c2w
    every = azimuths(cameras, cameras)
    # the cameras of a 100-degree wedge: a capture that walked part of the way round its subject, like fox
    partial = cameras[(every > math.radians(-40)) & (every < math.radians(60))]
    start, span = covered_arc(partial, *(_orbit_frame(partial)[i] for i in (0, 2, 3)))
    assert math.radians(60) < span < math.radians(100)
    low, high = azimuths(partial, partial).min(), azimuths(partial, partial).max()
    for path in (orbit_path(partial, 40), spiral_path(partial, 40)):
        angles = azimuths(path, partial)
        assert float(angles.min()) >= float(low) - 1e-4 and float(angles.max()) <= float(high) + 1e-4
        assert float(angles.max() - angles.min()) > 0.9 * span  # and it does sweep the arc
    # every path camera looks at the subject
    path = spiral_path(partial, 40)
    centre = _orbit_frame(partial)[0]
    towards = torch.nn.functional.normalize(centre - path[:, :3, 3], dim=-1)
    assert float((towards * path[:, :3, 2]).sum(-1).min()) > 0.999
