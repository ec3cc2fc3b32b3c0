"""What the optimiser trains: named parameter groups, each at its own learning rate and schedule, and parameters
that are replaced or change size (Gaussian splats grow and are pruned) with their optimiser state kept in step.

A model's ``parameter_groups()`` lists groups as dicts (:func:`check_groups`)::

    [{"name": "means", "params": [splats.means], "lr": 1.6e-4 * scale, "schedule": lambda step: 0.01 ** (step / steps)},
     {"name": "opacities", "params": [splats.opacities], "lr": 5e-2}]

``lr`` is optional (the optimiser's otherwise); ``schedule`` (optional) maps the optimiser step to a factor of the
group's learning rate (:class:`GroupSchedules`); other keys go to the optimiser as torch's group options.

A parameter whose size changes in training is named in its module's ``variable_size_parameters`` (the names of its
parameters, dotted below it where they live in a submodule: ``("rows",)``, ``("splats.means",)``), so that a
checkpoint's parameter loads into a freshly built module at the size it was saved with (:func:`resize_to_saved`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import torch
from torch import nn
from torch.optim.lr_scheduler import LRScheduler

Schedule = Callable[[int], float]


def check_groups(groups: Iterable[Any], module: nn.Module) -> list[dict[str, Any]]:
    """``groups`` (named groups, or as torch also takes them, an iterable of parameters: one group ``model``) checked
    against ``module``'s parameters: ValueError naming a group without a name or a schedule it cannot call, a name
    used twice, a parameter in two groups (or twice in one), a trainable parameter of ``module`` in no group, or a
    tensor that is no parameter of it. The groups come back with their ``params`` as lists."""
    groups = list(groups)
    if all(isinstance(item, torch.Tensor) for item in groups):
        groups = [{"name": "model", "params": groups}]
    owner = type(module).__name__
    names = {id(parameter): name for name, parameter in module.named_parameters()}
    seen: dict[int, str] = {}
    checked = []
    for index, group in enumerate(groups):
        if not isinstance(group, dict) or not isinstance(group.get("name"), str) or "params" not in group:
            raise ValueError(f"{owner}.parameter_groups(): group {index} is not a dict with a 'name' and 'params': {group!r:.200}")
        name = group["name"]
        if any(other["name"] == name for other in checked):
            raise ValueError(f"{owner}.parameter_groups(): two groups are named '{name}'")
        if group.get("schedule") is not None and not callable(group["schedule"]):
            raise ValueError(f"{owner}.parameter_groups(): the schedule of group '{name}' is not a function of the step: {group['schedule']!r}")
        params = [group["params"]] if isinstance(group["params"], torch.Tensor) else list(group["params"])
        for parameter in params:
            if id(parameter) not in names:
                raise ValueError(f"{owner}.parameter_groups(): group '{name}' holds a tensor of shape {tuple(parameter.shape)} "
                                 f"that is no parameter of the {owner}")
            if id(parameter) in seen:
                raise ValueError(f"{owner}.parameter_groups(): parameter '{names[id(parameter)]}' is in group '{seen[id(parameter)]}' "
                                 f"and again in group '{name}'")
            seen[id(parameter)] = name
        checked.append({**group, "params": params})
    for name, parameter in module.named_parameters():
        if parameter.requires_grad and id(parameter) not in seen:
            raise ValueError(f"{owner}.parameter_groups(): parameter '{name}' is in no group (groups: "
                             f"{', '.join(group['name'] for group in checked)}), so nothing would train it")
    return checked


class GroupSchedules(LRScheduler):
    """Each optimiser group's learning rate a step: ``initial_lr * schedule(step)`` for the groups with a schedule of
    their own; for the others what ``fallback`` (the run's configured scheduler, built over the same optimiser and
    stepped here) makes of it, or constant without one.

    Args:
        optimizer: the optimiser, one group a schedule.
        schedules: for each of its groups, a function of the step (0 before the first optimiser step) giving the
            factor of the group's initial learning rate; None: the fallback's.
        fallback: the scheduler of the groups without a schedule, or None.
    """

    def __init__(self, optimizer: torch.optim.Optimizer, schedules: list[Schedule | None], fallback: LRScheduler | None = None) -> None:
        if len(schedules) != len(optimizer.param_groups):
            raise ValueError(f"GroupSchedules needs one schedule (or None) a group: {len(schedules)} for {len(optimizer.param_groups)} groups")
        self.schedules, self.fallback = schedules, fallback
        super().__init__(optimizer)

    def step(self, epoch: int | None = None) -> None:
        if self.fallback is not None and self.last_epoch >= 0:  # (not in __init__: the fallback has made its first step)
            self.fallback.step()
        super().step(epoch)

    def get_lr(self) -> list[float]:
        return [group["lr"] if schedule is None else base * float(schedule(self.last_epoch))
                for group, schedule, base in zip(self.optimizer.param_groups, self.schedules, self.base_lrs)]

    def state_dict(self) -> dict[str, Any]:
        """The step and the fallback's state (the schedules are code, rebuilt with the model)."""
        state = {key: value for key, value in self.__dict__.items() if key not in ("optimizer", "schedules", "fallback")}
        state["fallback"] = None if self.fallback is None else self.fallback.state_dict()
        return state

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        state = dict(state_dict)
        fallback = state.pop("fallback", None)
        self.__dict__.update(state)
        if self.fallback is not None and fallback is not None:
            self.fallback.load_state_dict(fallback)


@torch.no_grad()
def replace_parameter(owner: nn.Module, name: str, value: torch.Tensor, optimizers: Iterable[torch.optim.Optimizer] = (),
                      rows_from: torch.Tensor | None = None) -> nn.Parameter:
    """Set ``owner.<name>`` (a parameter) to a new parameter holding ``value``, and put it in the old one's place in
    each of ``optimizers`` that trains it, with the old one's state carried over row by row.

    ``rows_from`` (N_new,) long: for each row of ``value`` (N_new, ...), the row of the old (N_old, ...) parameter whose
    per-element state (Adam's ``exp_avg`` and ``exp_avg_sq``, any state of the parameter's shape) it takes, or -1
    for zeros: growing is ``[0..N_old-1, -1, ...]``, pruning the rows kept, duplicating a repeated row. None: the state is
    kept where the new parameter has the old one's shape, and zeros otherwise. Scalar state (the ``step`` count) is
    kept as it is. Works with fused and foreach Adam; without an optimiser (before it is built) only the module
    changes. Call it between an optimiser step and the next backward: the old parameter's gradient is not carried.
    """
    old = getattr(owner, name, None)
    where = f"{type(owner).__name__}.{name}"
    if not isinstance(old, nn.Parameter):
        raise ValueError(f"{where} is not a parameter to replace")
    if rows_from is not None:
        if rows_from.dim() != 1 or rows_from.shape[0] != value.shape[0] or value.shape[1:] != old.shape[1:]:
            raise ValueError(f"{where}: a new value of shape (N, {', '.join(map(str, old.shape[1:]))}) with rows_from (N,) was expected, got "
                             f"{tuple(value.shape)} and {tuple(rows_from.shape)}")
        if rows_from.numel() and not -1 <= int(rows_from.min()) <= int(rows_from.max()) < old.shape[0]:
            raise ValueError(f"{where}: rows_from must be -1 or a row of the old {old.shape[0]} rows, got {int(rows_from.min())}..{int(rows_from.max())}")
    new = nn.Parameter(value.detach(), requires_grad=old.requires_grad)
    setattr(owner, name, new)

    def carried(state: torch.Tensor) -> torch.Tensor:
        if rows_from is None:
            return state if state.shape == new.shape else state.new_zeros(new.shape)
        rows = rows_from.to(state.device)
        taken = state.index_select(0, rows.clamp(min=0))
        taken[rows < 0] = 0
        return taken

    for optimizer in optimizers:
        for group in optimizer.param_groups:
            group["params"] = [new if parameter is old else parameter for parameter in group["params"]]
        state = optimizer.state.pop(old, None)
        if state is not None:
            optimizer.state[new] = {key: carried(item) if key != "step" and torch.is_tensor(item) and item.dim() > 0 and item.shape == old.shape
                                    else item for key, item in state.items()}
    return new


def variable_size_parameters(module: nn.Module) -> dict[str, tuple[nn.Module, str]]:
    """The parameters that ``module`` and its submodules name in their ``variable_size_parameters``: qualified name ->
    (the module holding it, its attribute name)."""
    found = {}
    for prefix, submodule in module.named_modules():
        for dotted in getattr(submodule, "variable_size_parameters", ()):
            path, _, attribute = dotted.rpartition(".")
            owner = submodule.get_submodule(path) if path else submodule
            found[".".join(filter(None, (prefix, dotted)))] = (owner, attribute)
    return found


def resize_to_saved(module: nn.Module, state_dict: dict[str, Any], prefix: str = "",
                    replace: Callable[[nn.Module, str, torch.Tensor], Any] | None = None) -> None:
    """Give each of ``module``'s variable-size parameters (:func:`variable_size_parameters`) whose saved value in
    ``state_dict`` (keys under ``prefix``) has another shape a zero parameter of that shape on its device, for
    ``load_state_dict`` to fill. ``replace(owner, name, value)`` makes the swap (a model's, which keeps its optimiser
    in step); by default the module's attribute is set."""
    for name, (owner, attribute) in variable_size_parameters(module).items():
        saved, current = state_dict.get(prefix + name), getattr(owner, attribute)
        if saved is not None and saved.shape != current.shape:
            zeros = torch.zeros(saved.shape, dtype=current.dtype, device=current.device)
            if replace is not None:
                replace(owner, attribute, zeros)
            else:
                setattr(owner, attribute, nn.Parameter(zeros, requires_grad=current.requires_grad))
