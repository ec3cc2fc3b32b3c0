"""The checks that say a COLMAP model is wrong without masks or reference poses: what they make of what they found
(the photos left out, the refusals), and ``nerf-process-data`` acting on them. That right models keep every photo
and wrong ones lose theirs on real photos is held by the posing tests (tests/capture/test_process_data.py: ten fox
photos, all kept) and measured on the shared captures (docs/guides/real-captures.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerf_lightning.capture.model_checks import MIN_POINTS, mappers_agreement, pose_flags


def checks(thin: list[str] = (), repeated: list[list[str]] = ()) -> dict:
    return {"thinly_posed": list(thin), "repeated": [list(pair) for pair in repeated], "mappers": None,
            "view_graph": {"median_neighbours": 6.0, "fewest_neighbours": 1, "unconnected": [], "verified_pairs": 30,
                           "median_inliers_per_pair": 120.0}}


def test_a_model_whose_photos_all_see_its_points_is_kept_whole():
    assert pose_flags(checks(), registered=12) == {"refuse": [], "warn": []}


def test_photos_posed_on_almost_no_points_are_named_to_be_left_out():
    flags = pose_flags(checks(thin=["IMG_2.JPG", "IMG_7.JPG"]), registered=15)
    assert flags["refuse"] == []
    [said] = flags["warn"]
    assert said.startswith(f"2 of the 15 posed photos see fewer than {MIN_POINTS} of the model's points") and said.endswith("IMG_2.JPG, IMG_7.JPG")
    assert "(left out unless check_poses=false)" in said


def test_one_repeated_photo_is_named_and_a_room_that_stood_still_is_refused():
    flags = pose_flags(checks(repeated=[["a.jpg", "a_again.jpg"]]), registered=26)
    assert flags == {"refuse": [], "warn": ["one picture twice (their matches do not move): a.jpg and a_again.jpg"]}
    assert pose_flags(checks(repeated=[["a.jpg", "a_again.jpg"]]), registered=6)["refuse"] == []  # a small capture's repeat too
    still = [[f"turn_{k:03d}.png", f"turn_{k + 1:03d}.png"] for k in range(0, 12, 2)]  # 12 of 36 photos in static pairs
    [refused] = pose_flags(checks(repeated=still), registered=36)["refuse"]
    assert refused.startswith("12 of the 36 posed photos match another one without moving; ") and "give the masks (masks=)" in refused


def turned_about_y(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64)


def arc_of_cameras(count: int = 8) -> dict[str, torch.Tensor]:
    """Cameras 3 from the origin on an arc about y, each looking along its own axis."""
    cameras = {}
    for k in range(count):
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, :3] = turned_about_y(0.2 * k)
        c2w[:3, 3] = 3.0 * c2w[:3, 2]
        cameras[f"p{k}.jpg"] = c2w
    return cameras


def test_the_mappers_are_compared_without_an_alignment(monkeypatch):
    """A model and the same model moved, turned and scaled as a whole agree; a model whose cameras all turned 30
    degrees about their own axes (each looking elsewhere from the same place) disagrees in its directions."""
    import nerf_lightning.capture.model_checks as model_checks

    first = arc_of_cameras()
    turn = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)  # 90 degrees about z
    moved = {}
    for name, c2w in first.items():
        other = torch.eye(4, dtype=torch.float64)
        other[:3, :3] = turn @ c2w[:3, :3]
        other[:3, 3] = 2.5 * (turn @ c2w[:3, 3]) + torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
        moved[name] = other
    looking_elsewhere = {name: torch.cat([torch.cat([c2w[:3, :3] @ turned_about_y(math.radians(30)), c2w[:3, 3:]], dim=1), c2w[3:]])
                         for name, c2w in first.items()}
    models = {"first": first, "moved": moved, "elsewhere": looking_elsewhere, "two": dict(list(first.items())[:2])}
    monkeypatch.setattr(model_checks, "cameras_of", lambda model: models[model])
    agreement = mappers_agreement("first", "moved")
    assert agreement["compared"] == 8 and agreement["median_rotation_deg"] < 1e-3 and agreement["median_direction_deg"] < 1e-3
    assert mappers_agreement("first", "elsewhere")["median_direction_deg"] > 20.0
    assert mappers_agreement("first", "two") is None  # two common photos: nothing to compare


def test_cameras_spread_far_wider_than_they_see_refuse_the_model():
    from nerf_lightning.capture.model_checks import MAX_SPREAD

    assert pose_flags({**checks(), "camera_spread": 1.03}, registered=27)["refuse"] == []
    [refused] = pose_flags({**checks(), "camera_spread": 11.2}, registered=40)["refuse"]
    assert refused.startswith("the posed cameras lie 11 times farther apart than they are from what they see; ")
    assert f"under {MAX_SPREAD:g} is taken as right" in refused


class Pose:
    def __init__(self, w2c: np.ndarray) -> None:
        self.w2c = w2c

    def matrix(self) -> np.ndarray:
        return self.w2c[:3]


class Seen:
    def __init__(self, point: int | None) -> None:
        self.point3D_id = point

    def has_point3D(self) -> bool:
        return self.point3D_id is not None


class Point:
    def __init__(self, xyz: np.ndarray) -> None:
        self.xyz = xyz


class Photo:
    def __init__(self, c2w: np.ndarray, seen: list[int]) -> None:
        self.cam_from_world = Pose(np.linalg.inv(c2w))
        self.points2D = [Seen(point) for point in seen] + [Seen(None)]
        self.num_points3D = len(seen)
        self.name = f"photo_{id(self)}.jpg"


class Model:
    """What camera_spread reads of a pycolmap Reconstruction."""

    def __init__(self, centres: list[np.ndarray], points: np.ndarray) -> None:
        self.points3D = {k: Point(xyz) for k, xyz in enumerate(points)}
        self.photos = {}
        for k, centre in enumerate(centres):
            c2w = np.eye(4)
            c2w[:3, 3] = centre
            self.photos[k] = Photo(c2w, list(range(len(points))))

    def reg_image_ids(self) -> list[int]:
        return list(self.photos)

    def image(self, image_id: int) -> Photo:
        return self.photos[image_id]


def test_the_camera_spread_is_about_one_round_an_object_and_near_zero_for_a_camera_that_did_not_move():
    from nerf_lightning.capture.model_checks import camera_spread, points_seen, thinly_posed

    points = np.random.default_rng(0).normal(scale=0.1, size=(50, 3))  # a small object at the origin
    ring = [3.0 * np.array([math.cos(a), 0.0, math.sin(a)]) for a in np.linspace(0, 2 * math.pi, 12, endpoint=False)]
    assert camera_spread(Model(ring, points)) == pytest.approx(1.0, abs=0.05)
    still = [np.array([0.0, 0.0, 3.0]) + 1e-3 * k for k in range(12)]
    assert camera_spread(Model(still, points)) < 0.01
    # photos strung far apart, each seeing points of its own close by (as the wrong models' clusters of a photo or two)
    flung = [30.0 * centre for centre in ring]
    clusters = np.concatenate([centre * 0.9 + points for centre in flung])  # a tenth of the way in from each camera
    wide = Model(flung, clusters)
    for k, photo in enumerate(wide.photos.values()):
        photo.points2D = [Seen(point) for point in range(50 * k, 50 * k + 50)]
    assert camera_spread(wide) > 4.0
    few = Model(ring[:3], points[:5])  # each photo sees 5 points: under the floor
    assert thinly_posed(points_seen(few)) == sorted(photo.name for photo in few.photos.values())
