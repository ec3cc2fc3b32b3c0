"""Per-image appearance embeddings: colour varies with the image, density does not; views that are not training
images get the mean appearance; rows start where asked and pay their penalty; a checkpoint's table loads at its own
size."""

import pytest
import torch

from nerf_lightning.fields import AppearanceEmbedding, GridField, HashGridEncoding


def field_with_appearance(n_images=5):
    torch.manual_seed(0)
    field = GridField(aabb=[-1, -1, -1, 1, 1, 1], encoding=HashGridEncoding(n_levels=3, log2_table_size=10, max_resolution=32),
                      hidden_width=16, geometry_features=7, appearance_dim=8, appearance_init="normal")
    field.appearance.resize(n_images)
    return field


def test_an_appearance_embedding_changes_colour_but_not_density():
    field = field_with_appearance()
    points, viewdirs = torch.rand(200, 3) * 2 - 1, torch.nn.functional.normalize(torch.randn(200, 3), dim=-1)
    first = field(points, viewdirs, torch.zeros(200, dtype=torch.long))
    second = field(points, viewdirs, torch.full((200,), 3, dtype=torch.long))
    torch.testing.assert_close(first["density"], second["density"], rtol=0, atol=0)
    assert (first["rgb"] - second["rgb"]).abs().max() > 1e-3
    # the gradient of the density never reaches the table
    field(points, viewdirs, torch.zeros(200, dtype=torch.long))["density"].sum().backward()
    assert field.appearance.rows.grad is None or not field.appearance.rows.grad.any()


def test_views_that_are_not_training_images_get_the_mean_appearance():
    field = field_with_appearance()
    points, viewdirs = torch.rand(50, 3) * 2 - 1, torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    mean = field(points, viewdirs)["rgb"]
    with torch.no_grad():
        field.appearance.rows[:] = field.appearance.rows.mean(dim=0)  # every image the mean: the same colours
    torch.testing.assert_close(field(points, viewdirs, torch.arange(50) % 5)["rgb"], mean)


def test_rows_start_at_zero_or_from_a_normal_and_a_wrong_start_is_refused():
    zeros, normal = AppearanceEmbedding(8), AppearanceEmbedding(8, init="normal")
    zeros.resize(40)
    normal.resize(40)
    assert not zeros.rows.any()
    assert 0.8 < normal.rows.std() < 1.2  # N(0, 1), nerfstudio's nn.Embedding
    with pytest.raises(ValueError, match="'uniform'"):
        AppearanceEmbedding(8, init="uniform")
    with pytest.raises(ValueError, match="penalty must be >= 0, got -1"):
        AppearanceEmbedding(8, penalty=-1)


def test_the_penalty_is_the_weighted_mean_squared_norm_of_the_rows_and_pulls_them_to_zero():
    embedding = AppearanceEmbedding(4, init="normal", penalty=0.01)
    embedding.resize(3)
    penalty = embedding.penalties()["appearance"]
    torch.testing.assert_close(penalty, 0.01 * sum(float(row @ row) for row in embedding.rows.detach()) / 3 * torch.ones(()))
    penalty.backward()
    # d/d row of 0.01 * mean |row|^2 = 0.02 / 3 * row: a gradient step shrinks every row towards 0
    torch.testing.assert_close(embedding.rows.grad, 0.02 / 3 * embedding.rows.detach())
    assert AppearanceEmbedding(4, penalty=0).penalties() == {}  # no penalty, no loss term


def test_the_table_loads_at_its_saved_size_and_refuses_an_unknown_image():
    trained = field_with_appearance(n_images=7)
    fresh = GridField(aabb=[-1, -1, -1, 1, 1, 1], encoding=HashGridEncoding(n_levels=3, log2_table_size=10, max_resolution=32),
                      hidden_width=16, geometry_features=7, appearance_dim=8)
    fresh.load_state_dict(trained.state_dict())
    torch.testing.assert_close(fresh.appearance.rows, trained.appearance.rows)
    fresh.eval()  # outside a training step (whose indices the datamodule draws; the check would make a GPU wait)
    with pytest.raises(IndexError, match="camera index 7 is beyond the 7 training views of this AppearanceEmbedding"):
        fresh.appearance(torch.tensor([7]), 1)
    with pytest.raises(IndexError, match="resize"):
        AppearanceEmbedding(4)(None, 3)
