"""The checks that say a COLMAP model is likely wrong without masks or reference poses: the flags they raise at their
calibrated thresholds, and the refusal ``nerf-process-data`` answers them with. That right models pass and wrong
ones are flagged on real photos is held by the posing tests (tests/capture/test_process_data.py: ten fox photos,
right, no flag) and measured on the shared captures (docs/guides/real-captures.md)."""

from __future__ import annotations

import pytest

from nerf_lightning.capture.model_checks import AGREE_DEGREES, MIN_NEIGHBOURS, STRONG_PAIR, pose_flags


def checks(rotation: float = 0.5, position: float = 0.4, neighbours: float = 6.0, mappers: bool = True) -> dict:
    return {"mappers": {"compared": 12, "median_rotation_deg": rotation, "max_rotation_deg": rotation * 2,
                        "median_position_percent_of_spread": position, "max_position_percent_of_spread": position * 2} if mappers else None,
            "view_graph": {"median_neighbours": neighbours, "fewest_neighbours": 1, "unconnected": [], "verified_pairs": 30,
                           "median_inliers_per_pair": 120.0},
            "repeated": []}


def test_a_model_both_mappers_agree_on_whose_photos_are_well_tied_is_not_flagged():
    assert pose_flags(checks(), registered=12) == []
    assert pose_flags(checks(mappers=False), registered=12) == []  # one mapper built a model: nothing to compare


@pytest.mark.parametrize("rotation, position", [(AGREE_DEGREES + 1.0, 0.4), (0.5, 30.0)])
def test_mappers_that_place_the_photos_apart_flag_the_model(rotation, position):
    [flag] = pose_flags(checks(rotation, position), registered=12)
    assert flag.startswith("COLMAP's two mappers place the 12 photos both posed differently") and "strung the photos wrongly" in flag


def test_photos_tied_by_too_few_matches_flag_the_model():
    [flag] = pose_flags(checks(neighbours=MIN_NEIGHBOURS - 0.5), registered=12)
    assert f"shares {STRONG_PAIR} or more verified matches with 1.5 other posed photos" in flag
