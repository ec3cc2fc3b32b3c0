"""Named optimiser groups with their own learning rates and schedules, and a parameter that grows and is pruned in
training with its Adam state kept row by row, through a checkpoint and a resumed run."""

from __future__ import annotations

import csv
import functools

import lightning as L
import pytest
import torch
from hydra.utils import instantiate
from lightning.pytorch.callbacks import LearningRateMonitor
from lightning.pytorch.loggers import CSVLogger
from torch import nn
from torch.utils.data import DataLoader, TensorDataset

from nerf_lightning.checkpoints import load_model
from nerf_lightning.models.base import FieldModule
from nerf_lightning.models.schedules import exponential_decay

LR = 1e-2  # the optimiser's: the head's
POINTS_LR = 5e-2


def points_schedule(step: int) -> float:
    return 0.01 ** (step / 20)  # gsplat's means: to 0.01 x over the run


class Cloud(FieldModule):
    """A learnt (N, 3) point cloud, ``points``, whose size changes in training (``edits``: global step -> a function
    of the module, run after that step), and a linear head; points at their own learning rate and schedule."""

    variable_size_parameters = ("points",)

    def __init__(self, optimizer=None, scheduler=None, edits=None) -> None:
        super().__init__(optimizer or functools.partial(torch.optim.Adam, lr=LR, fused=True), scheduler)
        self.points = nn.Parameter(torch.randn(4, 3))
        self.head = nn.Linear(3, 1)
        self.edits = edits or {}
        self.losses = []

    def parameter_groups(self):
        return [{"name": "points", "params": [self.points], "lr": POINTS_LR, "schedule": points_schedule},
                {"name": "head", "params": list(self.head.parameters())}]

    def training_step(self, batch, batch_idx):
        loss = (self.head(self.points) - 1).square().mean() + 0.1 * self.points.square().mean()
        self.losses.append(float(loss.detach()))
        return loss

    def on_train_batch_end(self, outputs, batch, batch_idx) -> None:
        if self.global_step in self.edits:
            self.edits[self.global_step](self)

    def train_dataloader(self):
        return DataLoader(TensorDataset(torch.zeros(1000, 1)), batch_size=1)


def trainer(max_steps: int, **kwargs) -> L.Trainer:
    options = dict(accelerator="cpu", devices=1, max_steps=max_steps, logger=False, enable_checkpointing=False,
                   enable_progress_bar=False, enable_model_summary=False)
    return L.Trainer(**{**options, **kwargs})


def decay(steps: int = 20):
    return functools.partial(exponential_decay, final_ratio=0.1, steps=steps)


def lrs(optimizer: torch.optim.Optimizer) -> dict[str, float]:
    return {group.get("name"): group["lr"] for group in optimizer.param_groups}


def resize_and_check(model: Cloud, rows_from: list[int]) -> None:
    """Replace ``points`` by rows taken as ``rows_from`` says (new random rows for -1) and check that the optimiser
    trains the new parameter with the old rows' Adam moments, zeros for the new rows, and the step kept."""
    optimizer = model.trainer.optimizers[0]
    before = {key: value.clone() for key, value in optimizer.state[model.points].items()}
    rows = torch.tensor(rows_from)
    fresh = (rows < 0)[:, None]
    value = torch.where(fresh, torch.randn(len(rows), 3), model.points.detach()[rows.clamp(min=0)])
    new = model.replace_parameter(model, "points", value, rows_from=rows)
    assert new is model.points and optimizer.param_groups[0]["params"][0] is new and len(optimizer.param_groups[0]["params"]) == 1
    state = optimizer.state[new]
    assert state.keys() == before.keys() and len(optimizer.state) == 3  # the old parameter's state is gone
    for key in ("exp_avg", "exp_avg_sq"):
        torch.testing.assert_close(state[key], torch.where(fresh, 0.0, before[key][rows.clamp(min=0)]), rtol=0, atol=0)
    assert state["step"] is before["step"] or torch.equal(state["step"], before["step"])
    assert float(state["step"]) == model.global_step


@pytest.mark.parametrize("options", [{"fused": True}, {"foreach": True}], ids=["fused", "foreach"])
def test_points_grow_and_are_pruned_with_their_adam_state_and_resume_at_their_size(options, tmp_path):
    adam = functools.partial(torch.optim.Adam, lr=LR, **options)
    torch.manual_seed(0)
    grow = functools.partial(resize_and_check, rows_from=[0, 1, 2, 3, -1, 1, -1, 1])  # 4 -> 8: new rows, a duplicate
    prune = functools.partial(resize_and_check, rows_from=[0, 2, 4, 5, 7])  # 8 -> 5
    model = Cloud(adam, decay(), edits={3: grow, 6: prune})
    run = trainer(9)
    run.fit(model)
    assert model.points.shape == (5, 3) and len(model.losses) == 9 and all(torch.isfinite(torch.tensor(model.losses)))
    optimizer = run.optimizers[0]
    assert lrs(optimizer) == pytest.approx({"points": POINTS_LR * points_schedule(9), "head": LR * 0.1 ** (9 / 20)}, rel=1e-6)
    saved_state = {key: value.clone() for key, value in optimizer.state[model.points].items()}
    path = tmp_path / "cloud.ckpt"
    run.save_checkpoint(path)

    class AtStart(L.Callback):
        def on_train_start(self, trainer, module):
            self.points = module.points.detach().clone()
            self.state = {key: value.clone() for key, value in trainer.optimizers[0].state[module.points].items()}
            self.lrs = lrs(trainer.optimizers[0])

    resumed, at_start = Cloud(adam, decay()), AtStart()
    assert resumed.points.shape == (4, 3)
    trainer(12, callbacks=[at_start]).fit(resumed, ckpt_path=path)
    torch.testing.assert_close(at_start.points, model.points.detach(), rtol=0, atol=0)
    assert at_start.state.keys() == saved_state.keys()
    for key, value in saved_state.items():
        torch.testing.assert_close(at_start.state[key], value, rtol=0, atol=0)
    assert at_start.lrs == pytest.approx(lrs(optimizer), rel=1e-6)
    # trains on from there: 3 more steps at 5 points, the schedules where an uninterrupted run would be
    assert resumed.points.shape == (5, 3) and len(resumed.losses) == 3 and all(torch.isfinite(torch.tensor(resumed.losses)))
    assert lrs(resumed.trainer.optimizers[0]) == pytest.approx({"points": POINTS_LR * points_schedule(12), "head": LR * 0.1 ** (12 / 20)}, rel=1e-6)

    # and through load_model, as nerf-render and nerf-eval load a model
    checkpoint = torch.load(path, weights_only=False)
    checkpoint["nerf_lightning"] = {"format": 2, "kind": "field", "config": {"model": {
        "_target_": f"{__name__}.Cloud", "optimizer": {"_target_": "torch.optim.Adam", "_partial_": True, "lr": LR, **options}}}}
    torch.save(checkpoint, path)
    loaded, info = load_model(path)
    assert info["global_step"] == 9
    torch.testing.assert_close(loaded.points, model.points.detach(), rtol=0, atol=0)


def test_a_replaced_parameter_before_the_optimiser_and_bad_rows_are_refused():
    model = Cloud()
    new = model.replace_parameter(model, "points", torch.zeros(7, 3))
    assert new is model.points and model.points.shape == (7, 3) and model.points.requires_grad
    assert model.configure_optimizers()["optimizer"].param_groups[0]["params"][0] is new
    with pytest.raises(ValueError, match=r"Cloud.points: a new value of shape \(N, 3\) with rows_from \(N,\) was expected, got \(2, 3\) and \(3,\)"):
        model.replace_parameter(model, "points", torch.zeros(2, 3), rows_from=torch.tensor([0, 1, 2]))
    with pytest.raises(ValueError, match="rows_from must be -1 or a row of the old 7 rows, got -2..7"):
        model.replace_parameter(model, "points", torch.zeros(2, 3), rows_from=torch.tensor([-2, 7]))
    with pytest.raises(ValueError, match="Linear.weights is not a parameter"):
        model.replace_parameter(model.head, "weights", torch.zeros(1, 3))


def test_groups_are_logged_by_name_at_their_own_schedules(tmp_path):
    """LearningRateMonitor logs the learning rates a step is taken with: step k's, lr0 x schedule(k) for points, the
    configured scheduler's for the head; a model of one group logs lr-Adam as before groups had names."""
    logs = {}
    for name, model in (("named", Cloud(scheduler=decay())), ("one", Cloud(scheduler=decay()))):
        if name == "one":
            model.parameter_groups = functools.partial(FieldModule.parameter_groups, model)
        logger = CSVLogger(tmp_path, name=name)
        trainer(5, logger=logger, callbacks=[LearningRateMonitor(logging_interval="step")], log_every_n_steps=1).fit(model)
        with open(f"{logger.log_dir}/metrics.csv") as file:
            logs[name] = [row for row in csv.DictReader(file) if row.get("lr-Adam/points") or row.get("lr-Adam")]
    assert {"lr-Adam/points", "lr-Adam/head"} <= logs["named"][0].keys() and "lr-Adam" not in logs["named"][0]
    assert [int(row["step"]) for row in logs["named"]] == [0, 1, 2, 3, 4]
    for row in logs["named"]:
        step = int(row["step"])
        assert float(row["lr-Adam/points"]) == pytest.approx(POINTS_LR * points_schedule(step), rel=1e-6)
        assert float(row["lr-Adam/head"]) == pytest.approx(LR * 0.1 ** (step / 20), rel=1e-6)
    assert [float(row["lr-Adam"]) for row in logs["one"]] == pytest.approx([LR * 0.1 ** (step / 20) for step in range(5)], rel=1e-6)


def test_a_group_list_with_a_parameter_twice_or_missing_is_refused():
    model = Cloud()
    model.parameter_groups = lambda: [{"name": "a", "params": [model.points, model.head.weight]},
                                      {"name": "b", "params": [model.points, model.head.bias]}]
    with pytest.raises(ValueError, match="parameter 'points' is in group 'a' and again in group 'b'"):
        model.configure_optimizers()
    model.parameter_groups = lambda: [{"name": "points", "params": [model.points]}]
    with pytest.raises(ValueError, match=r"Cloud.parameter_groups\(\): parameter 'head.weight' is in no group \(groups: points\)"):
        model.configure_optimizers()
    model.parameter_groups = lambda: [{"params": list(model.parameters())}]
    with pytest.raises(ValueError, match="group 0 is not a dict with a 'name' and 'params'"):
        model.configure_optimizers()
    model.parameter_groups = lambda: [{"name": "all", "params": list(model.parameters()), "schedule": 0.5}]
    with pytest.raises(ValueError, match="the schedule of group 'all' is not a function of the step"):
        model.configure_optimizers()


@pytest.mark.parametrize("overrides", [["model=nerf"], ["experiment=fast", "model/camera_refinement=so3xr3"]], ids=["nerf", "ngp_refined"])
def test_the_shipped_schedulers_give_the_learning_rates_they_gave_before_groups_had_names(make_config, overrides):
    """What configure_optimizers built before: torch's groups without names, the configured scheduler over them."""
    model = instantiate(make_config(*overrides).model)
    built = model.configure_optimizers()
    optimizer, scheduler = built["optimizer"], built["lr_scheduler"]["scheduler"]
    if model.camera_refinement is None:
        before_groups = model.parameters()
    else:
        refinement = {id(p) for p in model.camera_refinement.parameters()}
        before_groups = [{"params": [p for p in model.parameters() if id(p) not in refinement]},
                         {"params": list(model.camera_refinement.parameters()), "lr": model.camera_refinement.lr}]
        assert [group["name"] for group in optimizer.param_groups] == ["field", "camera_refinement"]
    before_optimizer = model.make_optimizer(params=before_groups)
    before = model.make_scheduler(optimizer=before_optimizer)
    assert type(scheduler) is type(before) and scheduler.state_dict().keys() == before.state_dict().keys()
    for _ in range(200):
        assert [group["lr"] for group in optimizer.param_groups] == [group["lr"] for group in before_optimizer.param_groups]
        for step in (optimizer.step, scheduler.step, before_optimizer.step, before.step):
            step()
