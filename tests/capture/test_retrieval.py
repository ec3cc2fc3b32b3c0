"""Loop closures for sequential matching: images paired with those that look most alike them (capture/retrieval.py),
on descriptors of a made-up ring of views and on the procedural turntable's own SIFT features; the stronger pass's
pairs that can overlap."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from nerf_lightning.capture.colmap import sequential_pairs
from nerf_lightning.capture.retrieval import nearest_pairs, retrieved_pairs, root_sift, vlad, visual_words
from tests.capture.test_process_data import needs_pycolmap


def ring_of_views(views: int = 24, landmarks_a_view: int = 60, seen_over: int = 2, seed: int = 0) -> list[torch.Tensor]:
    """(n_i, 128) uint8-valued descriptors of ``views`` views round a ring: landmarks spread along the ring, each view
    seeing those within ``seen_over`` views of it (round the end of the ring too) with a little noise, so that the first
    and the last view share landmarks as neighbours do."""
    generator = torch.Generator().manual_seed(seed)
    landmarks = torch.randint(0, 256, (views * landmarks_a_view, 128), generator=generator).float()
    home = torch.arange(views * landmarks_a_view) // landmarks_a_view  # the view each landmark stands before
    images = []
    for view in range(views):
        apart = (home - view).abs()
        seen = torch.minimum(apart, views - apart) <= seen_over
        noise = torch.randn(int(seen.sum()), 128, generator=generator) * 12
        images.append((landmarks[seen] + noise).clamp(0, 255).round())
    return images


def ring_distance(i: int, j: int, views: int) -> int:
    return min(abs(i - j), views - abs(i - j))


def test_root_sift_is_a_unit_vector_whose_squares_are_the_histogram():
    descriptors = torch.randint(0, 256, (5, 128)).float()
    rooted = root_sift(descriptors)
    assert torch.allclose(rooted.norm(dim=1), torch.ones(5), atol=1e-5)
    assert torch.allclose(rooted**2, descriptors / descriptors.sum(dim=1, keepdim=True), atol=1e-6)


def test_vlad_is_a_unit_summary_that_tells_images_of_different_things_apart():
    images = ring_of_views(views=12, seen_over=0)
    centres = visual_words(images, words=16)
    assert centres.shape == (16, 128)
    summaries = torch.stack([vlad(root_sift(image), centres) for image in images])
    assert summaries.shape == (12, 16 * 128)
    assert torch.allclose(summaries.norm(dim=1), torch.ones(12), atol=1e-5)
    # an image's own descriptors, noised again, are nearer its summary than any other image's
    generator = torch.Generator().manual_seed(1)
    again = torch.stack([vlad(root_sift((image + torch.randn(image.shape, generator=generator) * 6).clamp(0, 255)), centres)
                         for image in images])
    assert torch.equal((again @ summaries.T).argmax(dim=1), torch.arange(12))


def test_vlad_sums_residuals_a_word_normalises_each_word_then_takes_signed_square_roots():
    centres = torch.tensor([[0.0, 0.0], [10.0, 0.0]])
    descriptors = torch.tensor([[1.0, 2.0], [-1.0, 2.0], [13.0, 0.0]])
    # word 0's residuals sum to (0, 4), word 1's to (3, 0): each to a unit vector, then sqrt(|x|) sign(x), then L2
    expected = torch.tensor([0.0, 1.0, 1.0, 0.0]) / 2**0.5
    assert torch.allclose(vlad(descriptors, centres), expected, atol=1e-6)
    # a pattern repeated on one word (its descriptors three times over) does not outweigh the other word
    repeated = torch.cat([descriptors[:2]] * 3 + [descriptors[2:]])
    assert torch.allclose(vlad(repeated, centres), expected, atol=1e-6)
    # signed roots: a residual sum of (-3, 1) on a word keeps its signs, its magnitudes square-rooted
    summary = vlad(torch.tensor([[-3.0, 1.0]]), centres)[:2]
    assert summary[0] < 0 < summary[1] and torch.isclose(summary[0] ** 2 / summary[1] ** 2, torch.tensor(3.0))


def test_images_without_features_are_paired_and_a_featureless_capture_gives_no_pairs():
    images = ring_of_views(views=6)
    empty = torch.zeros(0, 128)
    pairs = retrieved_pairs([*images, empty], neighbours=2)
    assert all(0 <= i < j <= 6 for i, j in pairs) and any(6 in pair for pair in pairs)
    assert retrieved_pairs([torch.zeros(10, 128)] * 3, neighbours=2) == set()  # 30 descriptors: fewer than the words


def test_nearest_pairs_pairs_each_image_with_its_most_alike_once():
    summaries = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0], [0.9, 0.1], [0.0, 1.0], [0.1, 0.9]]), dim=1)
    similarity = summaries @ summaries.T
    assert nearest_pairs(similarity, 1) == {(0, 1), (2, 3)}
    assert nearest_pairs(similarity[:1, :1], 3) == set()
    assert len(nearest_pairs(similarity, 10)) == 6  # every pair, each once, where fewer images than neighbours


def test_retrieval_closes_the_ring_that_sequential_neighbours_leave_open():
    views = 24
    pairs = retrieved_pairs(ring_of_views(views), neighbours=4)
    # every view paired with views that share its landmarks, the first with the last among them
    assert all(ring_distance(i, j, views) <= 2 for i, j in pairs), sorted(pairs)
    assert {(0, 23), (0, 22), (1, 23)} <= pairs
    sequential = {pair for chunk in sequential_pairs(views, overlap=3) for pair in chunk}
    assert (0, 23) not in sequential  # what only the loop closure gives
    merged = [pair for chunk in sequential_pairs(views, overlap=3, chunk=7, loops=pairs) for pair in chunk]
    assert len(merged) == len(set(merged)) == len(sequential | pairs) and merged == sorted(merged)
    assert all(i < j for i, j in merged)


@needs_pycolmap
def test_the_turntables_own_features_pair_photos_that_see_the_same_side(tmp_path):
    """COLMAP's SIFT features of the procedural turntable's photos, inside their masks: the retrieved pairs are photos
    whose cameras stand close round the object, far more often than pairs drawn at random are."""
    from nerf_lightning.capture.colmap import colmap_log, extract_features, loop_closure_pairs
    from nerf_lightning.data.formats import make_turntable_capture

    capture = make_turntable_capture(tmp_path / "capture")
    names = sorted(path.name for path in (capture / "images").iterdir())
    masks = tmp_path / "colmap_masks"
    masks.mkdir()
    for name in names:  # COLMAP's mask of IMG.png is IMG.png.png
        (masks / f"{name}.png").write_bytes((capture / "masks" / name).read_bytes())
    database = tmp_path / "database.db"
    with colmap_log(False):
        extract_features(database, capture / "images", names, "PINHOLE", True, 192, 2048, False, masks=masks)
    pairs = loop_closure_pairs(database, names, neighbours=4)

    frames = {frame["file_path"].split("/")[-1]: np.array(frame["transform_matrix"]) for frame in
              json.loads((capture / "transforms.json").read_text())["frames"]}
    directions = np.stack([frames[name][:3, 3] / np.linalg.norm(frames[name][:3, 3]) for name in names])  # from the object

    def angle(i: int, j: int) -> float:
        return math.degrees(math.acos(float(np.clip(directions[i] @ directions[j], -1.0, 1.0))))

    near = np.mean([angle(i, j) < 45.0 for i, j in pairs])
    generator = np.random.default_rng(0)
    drawn = [tuple(generator.choice(len(names), 2, replace=False)) for _ in range(2000)]
    by_chance = np.mean([angle(i, j) < 45.0 for i, j in drawn])
    assert near > 0.6 and near > 2 * by_chance, (near, by_chance)


def test_the_stronger_pass_matches_neighbours_round_the_ring_the_alike_and_the_verified(monkeypatch):
    """The stronger pass's pairs: each photo with its next 3 round the ring (the last with the first: a turntable's
    photos close it), the retrieved ones, and those a first pass verified; each pair once, far fewer than every pair."""
    import nerf_lightning.capture.colmap as colmap

    names = [f"turn_{k:03d}.jpg" for k in range(40)]
    monkeypatch.setattr(colmap, "loop_closure_pairs", lambda database, names, neighbours, seed: {(0, 20), (5, 25), (0, 1)})
    chunks = colmap.overlapping_pairs(Path("unused.db"), names, chunk=25)
    pairs = [pair for chunk in chunks for pair in chunk]
    assert len(pairs) == len(set(pairs)) and all(len(chunk) <= 25 for chunk in chunks)
    assert {(0, 1), (0, 3), (36, 39), (0, 39), (0, 37), (1, 39)} <= set(pairs) and (0, 4) not in pairs  # round the ring, 3 ahead
    assert {(0, 20), (5, 25)} <= set(pairs)  # the photos most alike
    assert len(pairs) == 40 * 3 + 2 < 40 * 39 // 2
