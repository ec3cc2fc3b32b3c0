"""Which images of a capture look alike, from their own SIFT descriptors: the loop closures of sequential matching.

Matching each image with its neighbours in time (COLMAP's sequential matcher) can leave the last photos of a walk
round an object unmatched with the first, or a second ring with the first one, though they see the same side. Without
those pairs a mapper strings the images into a chain whose drift nothing corrects, and can close it wrong: on
moldGoldCape's 59 photos (a path that wanders over the object's sphere and comes back), sequential matching alone
gave a model with every image registered and the cameras 94 % of their spread off (docs/benchmarks.md). COLMAP finds
loop closures with a vocabulary tree, which it downloads; this project does not download at run time, and pycolmap's
``VisualIndex.query`` does not hand its scores back to Python. So the images are compared here by VLAD (Jégou et
al., 2010): each image's descriptors summed as residuals to a few dozen visual words clustered from the capture's own
descriptors, and each image paired with those whose summaries are nearest.

Pure torch on (n, 128) descriptor arrays; :func:`nerf_lightning.capture.colmap.loop_closure_pairs` reads them from
COLMAP's database.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

# visual words: 64 is VLAD's usual count for SIFT (an 8192-long summary an image); 256 retrieved the photographer's
# nearest views of moldGoldCape about as well (recall 0.67 against 0.61) at twice the time
WORDS = 64


def root_sift(descriptors: torch.Tensor) -> torch.Tensor:
    """(n, 128) SIFT descriptors (COLMAP's uint8) -> (n, 128) RootSIFT: L1-normalised, square-rooted (Arandjelović and
    Zisserman, 2012), whose Euclidean distance is the Hellinger kernel that compares histograms better."""
    descriptors = descriptors.float()
    return (descriptors / descriptors.sum(dim=1, keepdim=True).clamp_min(1e-12)).sqrt()


def visual_words(descriptors: Sequence[torch.Tensor], words: int = WORDS, per_image: int = 2000, iterations: int = 20,
                 seed: int = 0) -> torch.Tensor:
    """(words, 128) visual words: k-means over the RootSIFT of up to ``per_image`` SIFT descriptors drawn from each
    image's (n_i, 128), started from drawn ones (Lloyd's iterations; a word left empty keeps its centre)."""
    generator = torch.Generator().manual_seed(seed)
    # RootSIFT of the drawn descriptors alone: float copies of a long capture's every descriptor would take gigabytes
    sample = torch.cat([root_sift(image[torch.randperm(len(image), generator=generator)[:per_image]]) for image in descriptors])
    if len(sample) < words:
        raise ValueError(f"visual_words: {len(sample)} descriptors in all, fewer than the {words} words to cluster them into")
    centres = sample[torch.randperm(len(sample), generator=generator)[:words]].clone()
    for _ in range(iterations):
        nearest = torch.cdist(sample, centres).argmin(dim=1)
        sums = torch.zeros_like(centres).index_add_(0, nearest, sample)
        counts = torch.bincount(nearest, minlength=words)
        filled = counts > 0
        centres[filled] = sums[filled] / counts[filled, None].float()
    return centres


def vlad(descriptors: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
    """(n, D) descriptors of one image, (K, D) visual words -> (K D,) its VLAD: the residuals to each descriptor's
    nearest word summed a word, each word's sum L2-normalised (intra-normalisation, so that a repeated pattern's many
    descriptors on one word do not outweigh the rest), then signed square root and L2 over the whole."""
    nearest = torch.cdist(descriptors, centres).argmin(dim=1)
    residuals = torch.zeros_like(centres).index_add_(0, nearest, descriptors - centres[nearest])
    summary = F.normalize(residuals, dim=1).flatten()
    return F.normalize(summary.sign() * summary.abs().sqrt(), dim=0)


def nearest_pairs(similarity: torch.Tensor, neighbours: int) -> set[tuple[int, int]]:
    """(N, N) how alike N images are (higher: more; -inf: never paired; the diagonal is ignored) -> each image paired
    with its ``neighbours`` most alike (fewer where there are fewer other images, or fewer it may be paired with), as
    (i, j) with i < j."""
    count = len(similarity)
    taken = min(neighbours, count - 1)
    if taken <= 0:
        return set()
    similarity = similarity.clone().fill_diagonal_(-float("inf"))
    nearest = similarity.topk(taken, dim=1)
    return {(min(i, j), max(i, j)) for i in range(count) for j, alike in zip(nearest.indices[i].tolist(), nearest.values[i].tolist())
            if alike > -float("inf")}


def retrieved_pairs(descriptors: Sequence[torch.Tensor], neighbours: int, words: int = WORDS, seed: int = 0) -> set[tuple[int, int]]:
    """Each of N images, given as its (n_i, 128) SIFT descriptors, paired with its ``neighbours`` most alike by the
    VLAD of its RootSIFT over words clustered from them all: pairs (i, j), i < j, indices into ``descriptors``. None
    where the capture has fewer descriptors in all than ``words`` (too few to compare images by; such a capture does
    not register either, and says so). An image without descriptors summarises to zeros and is paired by chance."""
    if sum(len(image) for image in descriptors) < words:
        return set()
    centres = visual_words(descriptors, words=words, seed=seed)
    summaries = torch.stack([vlad(root_sift(image), centres) for image in descriptors])
    return nearest_pairs(summaries @ summaries.T, neighbours)
