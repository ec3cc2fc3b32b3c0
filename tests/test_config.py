"""The shipped configs compose, and a mistyped key is refused with its name."""

import subprocess
import sys

import pytest
from hydra.errors import ConfigCompositionException

from nerf_lightning.config import compose_config


def test_train_config_composes_the_image_preset():
    cfg = compose_config(["experiment=image", "paths.output_dir=/tmp/x"])
    assert cfg.name == "image"
    assert cfg.model.optimizer.lr == 0.01 and cfg.data.batch_size == 10_000
    assert cfg.model.field.num_frequencies == 10 and cfg.model.field.hidden_width == 256
    assert cfg.trainer.max_steps == 1000 and list(cfg.data.val_steps) == [10, 100, 200, 400, 1000]
    assert cfg.data.seed == cfg.seed


def test_unknown_key_is_refused():
    with pytest.raises(ConfigCompositionException, match="model.field.levels"):
        compose_config(["model.field.levels=3", "paths.output_dir=/tmp/x"])


def test_unknown_key_on_the_command_line_exits_non_zero_naming_it(tmp_path):
    result = subprocess.run([sys.executable, "-m", "nerf_lightning.cli.train", "data.pth=x.png"], cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode != 0
    assert "data.pth" in result.stderr
    assert not (tmp_path / "outputs").exists() or not any((tmp_path / "outputs").rglob("metrics.json"))


def test_radiance_presets_compose_their_recipes():
    course = compose_config(["experiment=nerf_course", "data.root=lego.npz", "paths.output_dir=/tmp/x"])
    assert course.data.scene._target_.endswith("load_npz") and course.data.root == "lego.npz"
    assert (course.data.scene.near, course.data.scene.far, course.model.sampler.n_samples, course.data.batch_size) == (2.0, 6.0, 64, 10_000)
    assert course.model.optimizer.lr == 5e-4 and course.model.sampler._target_.endswith("StratifiedSampler")

    blender = compose_config(["experiment=nerf_blender", "data.root=lego", "paths.output_dir=/tmp/x"])
    assert blender.data.scene.downscale == 4 and blender.data.batch_size == 2048
    assert blender.model.sampler.coarse_field.hidden_layers == 8 and blender.model.sampler.n_fine_samples == 128
    assert blender.model.scheduler.final_ratio == 0.1 and blender.model.scheduler.steps == blender.trainer.max_steps

    procedural = compose_config(["experiment=nerf_procedural", "paths.output_dir=/tmp/x"])
    assert procedural.data.scene._target_.endswith("load_procedural") and procedural.trainer.max_steps == 3000


def test_the_paper_model_is_the_default_nerf():
    cfg = compose_config(["model=nerf", "data=rays", "data/scene=procedural", "paths.output_dir=/tmp/x"])
    field = cfg.model.field
    assert (field.position_frequencies, field.direction_frequencies, field.hidden_width, field.hidden_layers, field.skip_layer, field.view_width) == (10, 4, 256, 8, 4, 128)
    sampler = cfg.model.sampler
    assert sampler.coarse_field == field and (sampler.n_samples, sampler.n_fine_samples) == (64, 128)


def test_fast_presets_build_their_fields_and_one_box_for_field_and_grid():
    from hydra.utils import instantiate

    from nerf_lightning.fields import GridField, HashGridEncoding, NeRFField, TensorVMEncoding
    from nerf_lightning.rendering import OccupancyGridSampler

    for preset, encoding_type, box in (("fast", HashGridEncoding, 1.3), ("fast_blender", HashGridEncoding, 1.5),
                                       ("fast_blender_tensorf", TensorVMEncoding, 1.5), ("nerf_blender_grid", None, 1.5)):
        cfg = compose_config([f"experiment={preset}", "paths.output_dir=/tmp/x", *(["data.root=lego"] if preset != "fast" else [])])
        model = instantiate(cfg.model)
        assert isinstance(model.sampler, OccupancyGridSampler)
        assert model.sampler.grid.aabb.tolist() == pytest.approx([-box] * 3 + [box] * 3)
        if encoding_type is None:
            assert isinstance(model.field, NeRFField)
        else:
            assert type(model.field) is GridField and isinstance(model.field.encoding, encoding_type)
            assert model.field.aabb.tolist() == model.sampler.grid.aabb.tolist()
    assert model.sampler.step_size == (6.0 - 2.0) / 64  # the paper MLP on the grid: the stratified spacing


def test_the_field_and_sampler_groups_mix_freely():
    from hydra.utils import instantiate

    from nerf_lightning.rendering import HierarchicalSampler, StratifiedSampler

    for field in ("nerf", "hash_grid", "tensorf"):
        for sampler, kind in (("stratified", StratifiedSampler), ("hierarchical", HierarchicalSampler)):
            cfg = compose_config(["model=ngp", f"model/field={field}", f"model/sampler={sampler}", "data=rays", "data/scene=procedural", "paths.output_dir=/tmp/x"])
            model = instantiate(cfg.model)
            assert isinstance(model.sampler, kind)
            if sampler == "hierarchical":  # the coarse network is built like the field, with its own weights
                assert type(model.sampler.coarse_field) is type(model.field) and model.sampler.coarse_field is not model.field


def test_a_key_that_0_2_moved_is_refused_with_the_key_to_use(tmp_path):
    result = subprocess.run([sys.executable, "-m", "nerf_lightning.cli.train", "experiment=fast", "model.fine_field=null"],
                            cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode != 0
    assert "'model.fine_field' was moved in nerf-lightning 0.2" in result.stderr and "model.sampler.coarse_field" in result.stderr
    assert "Traceback" not in result.stderr
    result = subprocess.run([sys.executable, "-m", "nerf_lightning.cli.train", "experiment=fast", "model.field.n_levels=4"],
                            cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode != 0 and "use model.field.encoding.n_levels" in result.stderr


def test_the_commands_answer_a_wrong_key_before_loading_torch(tmp_path):
    """The commands import torch and Lightning (seconds) only once the config is composed: a typo is answered at once."""
    modules = ["train", "render", "evaluate", "export", "view", "viz_cameras", "process_data"]
    probe = "import sys\n" + "".join(f"import nerf_lightning.cli.{name}\n" for name in modules) + "print(sorted({'torch', 'lightning'} & set(sys.modules)))"
    result = subprocess.run([sys.executable, "-c", probe], cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode == 0 and result.stdout.strip() == "[]", result.stdout + result.stderr
    result = subprocess.run([sys.executable, "-m", "nerf_lightning.cli.render", "ckpt_path=x.ckpt", "render.sacle=2"],
                            cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode != 0 and "render.sacle" in result.stderr
