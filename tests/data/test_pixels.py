import imageio.v3 as iio
import numpy as np
import pytest
import torch

from nerf_lightning.data import PixelDataModule, default_image, downscale, load_image, pixel_grid
from nerf_lightning.data.batches import steps_to_next_validation


def test_default_image_is_deterministic_and_detailed():
    first, second = default_image(), default_image()
    assert first.shape == (256, 384, 3) and first.dtype == torch.float32
    assert torch.equal(first, second)
    assert 0.0 <= first.min() and first.max() <= 1.0
    # detail from coarse to fine: strong energy both at low and at the highest frequencies
    spectrum = torch.fft.rfft2(first.mean(-1) - first.mean()).abs()
    low, high = spectrum[:8, :8].sum(), spectrum[64:, 96:].sum()
    assert low > 0 and high > 0.05 * low


def test_pixel_grid_centres():
    grid = pixel_grid(2, 4)
    assert grid.shape == (2, 4, 2)
    torch.testing.assert_close(grid[0, 0], torch.tensor([0.125, 0.25]))
    torch.testing.assert_close(grid[1, 3], torch.tensor([0.875, 0.75]))
    assert pixel_grid(10, 20, scale=2.5).shape == (25, 50, 2)


def test_load_image_divides_8_bit_values_by_255(tmp_path):
    pixels = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3) * 4
    iio.imwrite(tmp_path / "a.png", pixels)
    image = load_image(tmp_path / "a.png")
    assert image.shape == (4, 5, 3)
    torch.testing.assert_close(image, torch.from_numpy(pixels).float() / 255.0)


def test_rgba_is_composited_on_white(tmp_path):
    pixels = np.zeros((2, 2, 4), dtype=np.uint8)
    pixels[0, 0] = [255, 0, 0, 255]  # opaque red
    iio.imwrite(tmp_path / "a.png", pixels)  # the rest: fully transparent
    image = load_image(tmp_path / "a.png")
    torch.testing.assert_close(image[0, 0], torch.tensor([1.0, 0.0, 0.0]))
    torch.testing.assert_close(image[1, 1], torch.tensor([1.0, 1.0, 1.0]))


def test_missing_and_corrupt_images_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere.png"):
        load_image(tmp_path / "nothere.png")
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    with pytest.raises(ValueError, match="could not read image .*broken.png"):
        load_image(tmp_path / "broken.png")


def test_downscale_averages_blocks():
    image = torch.arange(4 * 6 * 1, dtype=torch.float32).reshape(4, 6, 1)
    small = downscale(image, 2)
    assert small.shape == (2, 3, 1)
    assert small[0, 0, 0] == (0 + 1 + 6 + 7) / 4


def test_batches_have_the_shapes_and_ranges_of_the_course():
    data = PixelDataModule(batch_size=1000, seed=3)
    data.setup()
    batch = next(iter(data.train_dataloader()))
    assert batch["xy"].shape == (1000, 2) and batch["rgb"].shape == (1000, 3)
    assert batch["xy"].dtype == batch["rgb"].dtype == torch.float32
    assert 0.0 < batch["xy"].min() and batch["xy"].max() < 1.0
    assert 0.0 <= batch["rgb"].min() and batch["rgb"].max() <= 1.0
    # every colour is the image's colour at that position
    height, width = data.image_size
    cols = (batch["xy"][:, 0] * width).long()
    rows = (batch["xy"][:, 1] * height).long()
    torch.testing.assert_close(batch["rgb"], data.image[rows, cols])
    # a new pass draws other pixels; the same seed draws the same ones
    again = PixelDataModule(batch_size=1000, seed=3)
    again.setup()
    assert torch.equal(next(iter(again.train_dataloader()))["xy"], batch["xy"])


def test_validation_batch_is_the_whole_image():
    data = PixelDataModule(downscale=4)
    data.setup()
    (whole,) = list(data.val_dataloader())
    assert (whole["height"], whole["width"]) == (64, 96)
    assert whole["xy"].shape == (64 * 96, 2)
    torch.testing.assert_close(whole["image"], data.image)


def test_segments_end_at_validation_steps():
    val_steps = [10, 100, 200, 400, 1000]
    step, ends = 0, []
    while step < 1000:
        step += steps_to_next_validation(step, val_steps, None, 1000)
        ends.append(step)
    assert ends == val_steps
    assert steps_to_next_validation(0, [], 250, 1000) == 250
    assert steps_to_next_validation(1000, val_steps, None, 1200) == 200
    with pytest.raises(ValueError, match="max_steps"):
        steps_to_next_validation(5, [], None, -1)
