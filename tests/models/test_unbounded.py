"""A capture in its own coordinates, end to end: experiment=fast_unbounded trains on a transforms.json (contracted
field and grid, cone steps); nerf-eval on a second file of the same capture; export and render map back to the
capture's coordinates."""

import json
import math

import numpy as np
import pytest
import torch

from nerf_lightning.checkpoints import load_model
from nerf_lightning.config import compose_config
from nerf_lightning.data.formats import load_transforms
from nerf_lightning.data.formats.shared import apply_similarity
from nerf_lightning.outputs.mesh import read_mesh
from nerf_lightning.geometry.cameras import opengl_to_opencv
from nerf_lightning.training import train
from tests.conftest import run_cli
from tests.data.test_transforms import write_transforms

# the capture's own coordinates: the procedural world turned, scaled 3x and moved, as a COLMAP world would be
CAPTURE_FROM_PROCEDURAL = torch.tensor([[0.0, -3.0, 0.0, 5.0], [3.0, 0.0, 0.0, -2.0], [0.0, 0.0, 3.0, 7.0], [0.0, 0.0, 0.0, 1.0]])
HELD_OUT = list(range(0, 60, 10))  # holdout_every=10 over the 60 frames

QUICK_UNBOUNDED = ["experiment=fast_unbounded", "data.scene.downscale=2", "data.scene.holdout_every=10", "model.field.encoding.n_levels=6",
                   "model.field.encoding.log2_table_size=15", "model.field.encoding.max_resolution=256", "model.sampler.grid.resolution=32",
                   "data.batch_size=512", "data.val_views=2", "data.val_every=300", "trainer.max_steps=300",
                   "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false"]

# Why 14 dB: predicting each validation view's own mean colour scores 12.0 dB; this run reached 16.6 dB (seed 0,
# 300 steps, 61 s on 2 cores). 14 dB sits 2 dB above the guess and 2.6 dB below the run.
PSNR_BAR_DB = 14.0


@pytest.fixture(scope="module")
def capture(procedural_scene, tmp_path_factory):
    """60 procedural views as a transforms.json in the capture's coordinates, and a second file with the held-out 6."""
    views = procedural_scene.train.subset(list(range(60)))
    views.c2w = opengl_to_opencv(apply_similarity(CAPTURE_FROM_PROCEDURAL, opengl_to_opencv(views.c2w))).float()
    root = write_transforms(views, tmp_path_factory.mktemp("capture") / "fox_like")
    meta = json.loads((root / "transforms.json").read_text())
    second = dict(meta, frames=[meta["frames"][index] for index in HELD_OUT])
    (root / "held_out.json").write_text(json.dumps(second))
    return root, views


@pytest.fixture(scope="module")
def trained(capture, tmp_path_factory):
    root, _ = capture
    run = tmp_path_factory.mktemp("unbounded") / "run"
    metrics = train(compose_config([*QUICK_UNBOUNDED, f"data.root={root}", f"paths.output_dir={run}"]))
    return run, metrics


def test_an_unbounded_capture_trains_with_a_contracted_field(trained):
    run, metrics = trained
    assert metrics["step"] == 300 and metrics["val/psnr"] > PSNR_BAR_DB
    model, _ = load_model(run / "checkpoints" / "last.ckpt")
    assert model.space.contraction is not None and model.sampler.cone_angle > 0
    assert model.field.aabb.tolist() == model.sampler.grid.aabb.tolist() == list(model.space.contraction.bounds)
    # the loader's similarity (capture -> scene) is kept: it takes the subject the cameras look at to the origin
    subject = model.space.world_from_capture.double() @ torch.cat([CAPTURE_FROM_PROCEDURAL[:3, 3], torch.ones(1)]).double()
    torch.testing.assert_close(subject[:3], torch.zeros(3, dtype=torch.float64), atol=1e-3, rtol=0)
    assert 0.0 < model.sampler.grid.binary.float().mean() < 1.0


def test_eval_on_a_second_file_of_the_capture_matches_the_held_out_split(trained, capture, tmp_path):
    """What nerf-eval calls (evaluate_checkpoint), in this process: the run's held-out views, and the same views from a
    second file of the capture, loaded into the trained scene's world."""
    from nerf_lightning.outputs.evaluation import evaluate_checkpoint

    run, _ = trained
    root, _ = capture
    ckpt = run / "checkpoints" / "last.ckpt"
    own = evaluate_checkpoint(ckpt, tmp_path / "own", split="val", lpips="off")
    second = evaluate_checkpoint(ckpt, tmp_path / "second", root=root / "held_out.json", lpips="off")
    assert second["views"] == own["views"] == len(HELD_OUT) and second["scene"].endswith("held_out.json")
    # the same views, loaded from another file into the trained scene's world: the same pictures
    for a, b in zip(own["per_view"], second["per_view"]):
        assert a["view"] == b["view"] and a["psnr"] == pytest.approx(b["psnr"], abs=1e-3)


def test_export_and_render_map_back_to_the_capture(trained, capture, tmp_path):
    """nerf-export and nerf-render's own functions on their composed configs, in this process."""
    from nerf_lightning.cli.export import export
    from nerf_lightning.cli.render import render

    run, _ = trained
    ckpt = run / "checkpoints" / "last.ckpt"
    model, _ = load_model(ckpt)
    for frame in ("scene", "capture"):
        export(compose_config([f"ckpt_path={ckpt}", "resolution=48", "threshold=5", f"frame={frame}", f"output_dir={tmp_path / frame}"], "export"))
    scene_vertices = np.asarray(read_mesh(tmp_path / "scene" / "mesh.ply").vertices)
    capture_vertices = np.asarray(read_mesh(tmp_path / "capture" / "mesh.ply").vertices)
    assert len(scene_vertices) > 100 and len(scene_vertices) == len(capture_vertices)
    world_from_capture = model.space.world_from_capture.double().numpy()
    mapped = capture_vertices @ world_from_capture[:3, :3].T + world_from_capture[:3, 3]
    np.testing.assert_allclose(mapped, scene_vertices, atol=1e-4)
    # the procedural surfaces lie within 1.3 of its origin: in the capture's coordinates, around (5, -2, 7) at 3x
    centre = CAPTURE_FROM_PROCEDURAL[:3, 3].numpy()
    assert np.median(np.linalg.norm(capture_vertices - centre, axis=1)) < 3 * 1.3

    render(compose_config([f"ckpt_path={ckpt}", "render.path=spiral", "render.frames=4", "render.scale=0.5", f"output_dir={tmp_path / 'render'}"], "render"))
    rendered = load_transforms(tmp_path / "render", normalise=False, holdout_every=0)  # the frames load back as a capture
    assert len(rendered.train) == 4 and rendered.train.width == 25
    centres = rendered.train.c2w[:, :3, 3].double()
    # the spiral circles the capture's subject at the training cameras' distance (4 procedural units, 12 here)
    distances = (centres - CAPTURE_FROM_PROCEDURAL[:3, 3].double()).norm(dim=-1)
    torch.testing.assert_close(distances, torch.full((4,), 12.0, dtype=torch.float64), atol=0.3, rtol=0)



# experiment=nerfacto_360_cpu shrunk like QUICK_UNBOUNDED: proposal networks, a contracted hash grid, appearance.
QUICK_NERFACTO = ["experiment=nerfacto_360_cpu", "data.scene.downscale=2", "data.scene.holdout_every=10", "model.field.encoding.n_levels=6",
                  "model.field.encoding.log2_table_size=15", "model.field.encoding.max_resolution=256", "data.batch_size=512",
                  "data.val_views=2", "data.val_every=300", "trainer.max_steps=300", "trainer.enable_progress_bar=false",
                  "trainer.enable_model_summary=false"]

# Why 15 dB: each validation view's own mean colour scores 12.0 dB; this run reached 16.6 dB (seed 0, 300 steps, 30 s
# on 2 cores; 16.9 with the appearance rows of before, N(0, 1) and no penalty; 18.5 dB without the appearance
# embedding, which a capture of one exposure does not need). Without the renderer's gradient scaling the proposal sampler
# let every camera paint its picture on a fog just in front of it: 18 dB on the training views, 11.2 dB on the held-out
# ones, below the mean colour.
NERFACTO_PSNR_BAR_DB = 15.0


@pytest.mark.slow  # a real preset trained; test_an_unbounded_capture_trains_with_a_contracted_field stays in CI
def test_the_360_preset_trains_on_a_capture_in_its_own_coordinates(capture, tmp_path):
    root, _ = capture
    metrics = train(compose_config([*QUICK_NERFACTO, f"data.root={root}", f"paths.output_dir={tmp_path / 'run'}"]))
    assert metrics["step"] == 300 and metrics["val/psnr"] > NERFACTO_PSNR_BAR_DB
    assert metrics["train/samples_per_ray"] <= 24  # the field sees the proposal sampler's 24 intervals a ray, no more
    model, _ = load_model(tmp_path / "run" / "checkpoints" / "last.ckpt")
    assert model.field.appearance.rows.shape[0] == 54 and model.renderer.gradient_scaling_distance == 1.0


def test_a_camera_path_in_the_captures_coordinates_renders_its_photos_views(trained, capture, tmp_path):
    """Training frames copied into nerfstudio's camera_path.json render as the trained scene sees those frames; the same
    path in nerfstudio's normalised world renders the same with its dataparser_transforms.json (through nerf-render),
    and the transforms.json a render writes renders the same again."""
    import imageio.v3 as iio

    from nerf_lightning.checkpoints import load_run_data
    from nerf_lightning.outputs.frames import render_camera_path

    run, _ = trained
    root, _ = capture
    ckpt = run / "checkpoints" / "last.ckpt"
    model, info = load_model(ckpt)
    meta = json.loads((root / "transforms.json").read_text())
    frames = [meta["frames"][index] for index in (3, 17)]
    fov = math.degrees(2.0 * math.atan(0.5 * meta["h"] / meta["fl_y"]))
    path = {"camera_type": "perspective", "render_height": meta["h"], "render_width": meta["w"], "fps": 10, "seconds": 0.2, "keyframes": [],
            "camera_path": [{"camera_to_world": sum(frame["transform_matrix"], []), "fov": fov, "aspect": 1.0} for frame in frames]}
    (tmp_path / "camera_path.json").write_text(json.dumps(path))
    written = render_camera_path(model, info["config"], tmp_path / "copied", str(tmp_path / "camera_path.json"), scale=0.5)
    assert (tmp_path / "copied" / "rgb.gif") in written
    # the scene's own cameras of those frames (the loader's mapping, not the path's) render the same pictures
    train = load_run_data(info["config"]).scene.train
    for index, frame in enumerate(frames):
        view = train.names.index(frame["file_path"].split("/")[-1])
        expected = model.render_view(train.K[view], train.c2w[view], train.height, train.width)["rgb"]
        got = torch.from_numpy(iio.imread(tmp_path / "copied" / "frames" / f"rgb_{index:04d}.png")).float() / 255.0
        assert got.shape == expected.shape and (got - expected.clamp(0, 1)).abs().max() < 2.0 / 255.0

    # nerfstudio's normalised world: turned, moved and scaled by its dataparser
    transform = torch.tensor([[0.0, 1.0, 0.0, -0.4], [0.0, 0.0, 1.0, 0.2], [1.0, 0.0, 0.0, 1.5]], dtype=torch.float64)
    scale = 0.1
    (tmp_path / "dataparser_transforms.json").write_text(json.dumps({"transform": transform.tolist(), "scale": scale}))
    nerfstudio_from_capture = torch.eye(4, dtype=torch.float64)
    nerfstudio_from_capture[:3] = scale * transform
    capture_c2w = torch.tensor([frame["transform_matrix"] for frame in frames], dtype=torch.float64)
    path["camera_path"] = [dict(camera, camera_to_world=matrix.flatten().tolist())
                           for camera, matrix in zip(path["camera_path"], apply_similarity(nerfstudio_from_capture, capture_c2w))]
    (tmp_path / "nerfstudio_path.json").write_text(json.dumps(path))
    run_cli("render", f"ckpt_path={ckpt}", f"render.path={tmp_path / 'nerfstudio_path.json'}", "render.scale=0.5",
            f"render.dataparser_transforms={tmp_path / 'dataparser_transforms.json'}", f"output_dir={tmp_path / 'nerfstudio'}", cwd=tmp_path)
    render_camera_path(model, info["config"], tmp_path / "again", str(tmp_path / "copied" / "transforms.json"))
    for index in range(2):
        first = iio.imread(tmp_path / "copied" / "frames" / f"rgb_{index:04d}.png").astype(int)
        for other in ("nerfstudio", "again"):
            assert abs(iio.imread(tmp_path / other / "frames" / f"rgb_{index:04d}.png").astype(int) - first).max() <= 1, other
