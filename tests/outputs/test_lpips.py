"""LPIPS with weights the tests write (no network): its code path against torchmetrics' own LPIPS, the properties of a
distance, blur farther than noise, where the weights come from, and a weights file of the wrong shape; with the real
weights (../shared/data/lpips), the distances its authors' code gives on their example images."""

import os
from pathlib import Path

import imageio.v3 as iio
import pytest
import torch
from torch import nn

from nerf_lightning.data.image_stack import as_float_rgb
from nerf_lightning.outputs.choices import LPIPS_WEIGHTS_VARIABLE
from nerf_lightning.outputs.lpips import ALEXNET_FILE, CONVOLUTIONS, LPIPS, load_lpips, shipped_heads
from tests.conftest import SHARED_DATA

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "lpips"


def alexnet_features(seed: int = 0) -> nn.Sequential:
    """torchvision's ``AlexNet().features`` as torchvision 0.28 writes it (``torchvision/models/alexnet.py``), with
    random weights: copied from there, not built from this module's CONVOLUTIONS, so that a wrong channel count, kernel,
    stride or padding in that table fails the tests that hold LPIPS to it."""
    torch.manual_seed(seed)
    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2),
        nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(64, 192, kernel_size=5, padding=2),
        nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(192, 384, kernel_size=3, padding=1),
        nn.ReLU(inplace=True),
        nn.Conv2d(384, 256, kernel_size=3, padding=1),
        nn.ReLU(inplace=True),
        nn.Conv2d(256, 256, kernel_size=3, padding=1),
        nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
    )


def written_weights(path, seed: int = 0, heads: bool = True):
    """A weights file as a user would name it: a random AlexNet (torchvision's keys) and non-negative heads (LPIPS's)."""
    state = {f"features.{key}": value for key, value in alexnet_features(seed).state_dict().items()}
    if heads:
        generator = torch.Generator().manual_seed(seed)
        for layer, (_, channels, *_) in enumerate(CONVOLUTIONS):
            state[f"lin{layer}.model.1.weight"] = torch.rand(1, channels, 1, 1, generator=generator) / channels
    torch.save(state, path)
    return path


@pytest.fixture
def image(procedural_scene):
    """(H, W, 3) in [0, 1]: a textured view of the procedural scene, 100x100."""
    return as_float_rgb(procedural_scene.train.images[0])


def test_the_network_is_torchmetrics_lpips_with_the_same_weights(tmp_path, image, monkeypatch):
    """torchmetrics' LPIPS (the lpips package's code) with the same AlexNet and the heads it ships: the same distances."""
    reference_module = pytest.importorskip("torchmetrics.functional.image.lpips")
    features = alexnet_features(seed=3)
    monkeypatch.setattr(reference_module, "_get_tv_model_features", lambda net, pretrained=False: features)
    reference = reference_module._LPIPS(net="alex").eval()
    heads = torch.load(shipped_heads(), map_location="cpu", weights_only=True)
    ours = LPIPS({**{f"features.{key}": value for key, value in features.state_dict().items()}, **heads})
    a = image.permute(2, 0, 1)[None]
    b = torch.roll(a, shifts=3, dims=-1).flip(-2)
    noisy = (a + 0.05 * torch.randn_like(a)).clamp(0, 1)
    for other in (b, noisy):
        expected = reference(a, other, normalize=True).flatten()
        torch.testing.assert_close(ours(a, other), expected, rtol=1e-4, atol=1e-6)


def test_the_reference_backbone_is_torchvisions_alexnet():
    """Where torchvision is installed: its AlexNet's features, module for module, are the copy the tests hold LPIPS to.
    (Not in the dev extra: the only torchvision wheel on CI's index is a CUDA build, which does not load beside the CPU
    torch and then breaks torchmetrics' imports.)"""
    torchvision = pytest.importorskip("torchvision")
    assert repr(torchvision.models.alexnet(weights=None).features) == repr(alexnet_features())


def test_the_features_lpips_compares_are_alexnets_at_its_five_relus(image):
    """LPIPS's five feature maps are AlexNet's (torchvision's definition, the same random weights) read after each
    ReLU, normalised along the channels: the same shapes, so the same strides and pools, and the same values."""
    features = alexnet_features(seed=1)
    heads = {f"lin{layer}.model.1.weight": torch.zeros(1, channels, 1, 1) for layer, (_, channels, *_) in enumerate(CONVOLUTIONS)}
    ours = LPIPS({**{f"features.{key}": value for key, value in features.state_dict().items()}, **heads})
    images = image.permute(2, 0, 1)[None] * 2.0 - 1.0
    expected, x = [], (images - ours.shift) / ours.scale
    with torch.no_grad():
        for module in features:
            x = module(x)
            if isinstance(module, nn.ReLU):
                expected.append(x / (x.pow(2).sum(dim=1, keepdim=True).sqrt() + 1e-10))
        got = ours.features(images)
    assert len(got) == len(expected) == 5
    for layer, (a, b) in enumerate(zip(got, expected)):
        assert a.shape == b.shape, f"layer {layer}: {tuple(a.shape)} against AlexNet's {tuple(b.shape)}"
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_a_distance_zero_for_the_same_image_symmetric_and_larger_for_blur_than_for_slight_noise(tmp_path, image):
    network, source = load_lpips("auto", written_weights(tmp_path / "weights.pth"))
    assert network is not None and source == str(tmp_path / "weights.pth")
    assert float(network(image, image)) == 0.0
    generator = torch.Generator().manual_seed(0)
    noisy = (image + 0.02 * torch.randn(image.shape, generator=generator)).clamp(0, 1)
    kernel = torch.ones(3, 1, 7, 7) / 49.0
    blurred = nn.functional.conv2d(image.permute(2, 0, 1)[None], kernel, padding=3, groups=3)[0].permute(1, 2, 0)
    assert float(network(image, noisy)) == pytest.approx(float(network(noisy, image)), rel=1e-6)
    assert float(network(image, blurred)) == pytest.approx(float(network(blurred, image)), rel=1e-6)
    assert 0.0 < float(network(image, noisy)) < float(network(image, blurred))
    batch = torch.stack([image, noisy, blurred]).permute(0, 3, 1, 2)
    assert network(batch, batch.flip(0)).shape == (3,)


def test_the_backbone_from_the_hub_cache_and_the_heads_torchmetrics_ships(tmp_path, monkeypatch, image):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.delenv(LPIPS_WEIGHTS_VARIABLE, raising=False)
    network, said = load_lpips("auto")
    assert network is None and said.startswith("LPIPS skipped: no AlexNet weights at") and "eval.lpips_weights" in said
    assert load_lpips("off") == (None, "LPIPS off (eval.lpips=off)")
    backbone = tmp_path / "torch" / "hub" / "checkpoints" / ALEXNET_FILE
    backbone.parent.mkdir(parents=True)
    written_weights(backbone, heads=False)
    network, said = load_lpips("auto")
    assert network is not None and said == f"{backbone} + {shipped_heads()}"
    assert float(network(image, image.flip(0))) > 0.0


def test_a_weights_file_of_the_wrong_shape_is_named(tmp_path):
    path = written_weights(tmp_path / "weights.pth")
    state = torch.load(path, weights_only=True)
    state["lin2.model.1.weight"] = torch.zeros(1, 100, 1, 1)
    torch.save(state, path)
    with pytest.raises(ValueError, match=r"weights.pth: 'lin2.model.1.weight' has shape \(1, 100, 1, 1\), expected \(1, 384, 1, 1\)"):
        load_lpips("auto", path)
    (tmp_path / "text.pth").write_text("not weights")
    with pytest.raises(ValueError, match="text.pth: not a weights file"):
        load_lpips("auto", tmp_path / "text.pth")
    with pytest.raises(FileNotFoundError, match="eval.lpips_weights: no such file"):
        load_lpips("auto", tmp_path / "missing.pth")


def test_download_fetches_the_backbone_into_the_hub_cache_and_a_failed_download_is_one_line(tmp_path, monkeypatch, image):
    """eval.lpips=download: torch.hub's download of AlexNet's file (stood in for here: no network in tests), then the
    network as from the cache; without the internet, LPIPS is skipped with one line naming the URL."""
    from nerf_lightning.outputs import lpips as module

    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.delenv(LPIPS_WEIGHTS_VARIABLE, raising=False)
    asked = []

    def fake_download(url, progress=True, file_name=None):
        asked.append((url, file_name))
        target = module.hub_backbone()
        target.parent.mkdir(parents=True, exist_ok=True)
        written_weights(target, heads=False)
        return torch.load(target, weights_only=True)

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", fake_download)
    network, said = load_lpips("download")
    assert asked == [(module.ALEXNET_URL, ALEXNET_FILE)] and network is not None and said.startswith(str(module.hub_backbone()))
    assert float(network(image, image)) == 0.0

    module.hub_backbone().unlink()

    def offline(url, progress=True, file_name=None):
        raise OSError("Network is unreachable")

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", offline)
    network, said = load_lpips("download")
    assert network is None and said.startswith(f"LPIPS skipped: downloading {module.ALEXNET_URL} failed (OSError: Network is unreachable)")
    assert "\n" not in said


def reference_weights() -> Path | None:
    """The verified AlexNet backbone (``../shared/data/lpips``, its README says whence), or the file or folder
    ``$NERF_LIGHTNING_LPIPS`` names; None where neither is here."""
    named = os.environ.get(LPIPS_WEIGHTS_VARIABLE)
    for candidate in ([Path(named)] if named else []) + [SHARED_DATA / "lpips"]:
        if candidate.exists():
            return candidate
    return None


@pytest.mark.skipif(reference_weights() is None, reason="no LPIPS AlexNet weights in ../shared/data/lpips (or $NERF_LIGHTNING_LPIPS)")
def test_the_authors_example_images_at_the_distances_their_code_gives():
    """PerceptualSimilarity's ``test_network.py`` (LPIPS v0.1, AlexNet) prints ``Distances: (0.722, 0.138)`` from
    ``ex_ref.png`` to ``ex_p0.png`` and ``ex_p1.png`` (tests/fixtures/lpips/README.md): the project's LPIPS, with
    torchvision's AlexNet and the heads torchmetrics ships, gives them to the printed three decimals."""
    network, source = load_lpips("auto", reference_weights())
    assert network is not None, source
    ref, p0, p1 = (torch.from_numpy(iio.imread(FIXTURES / f"{name}.png")).float() / 255.0 for name in ("ex_ref", "ex_p0", "ex_p1"))
    assert ref.shape == (64, 64, 3)
    assert float(network(ref, p0)) == pytest.approx(0.722, abs=5e-4)
    assert float(network(ref, p1)) == pytest.approx(0.138, abs=5e-4)


def test_a_folder_named_once_in_the_environment_gives_the_weights(tmp_path, monkeypatch, image):
    """``$NERF_LIGHTNING_LPIPS`` names a folder (its ``*.pth`` read in name order) where eval.lpips_weights names
    nothing; eval.lpips_weights wins where both are set; a folder without weights is one error naming the variable."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))  # an empty hub cache: the weights come from the folder
    folder = tmp_path / "lpips"
    folder.mkdir()
    monkeypatch.setenv(LPIPS_WEIGHTS_VARIABLE, str(folder))
    with pytest.raises(FileNotFoundError, match=rf"\${LPIPS_WEIGHTS_VARIABLE}: no \*.pth file in the folder {folder}"):
        load_lpips("auto")
    written_weights(folder / "alexnet.pth", heads=False)
    network, said = load_lpips("auto")
    assert network is not None and said == f"{folder / 'alexnet.pth'} + {shipped_heads()}"
    named, said = load_lpips("auto", written_weights(tmp_path / "other.pth", seed=5))
    assert said == str(tmp_path / "other.pth") and float(named(image, image.flip(0))) != float(network(image, image.flip(0)))
    monkeypatch.setenv(LPIPS_WEIGHTS_VARIABLE, str(tmp_path / "missing"))
    with pytest.raises(FileNotFoundError, match=rf"\${LPIPS_WEIGHTS_VARIABLE}: no such file or folder"):
        load_lpips("auto")
