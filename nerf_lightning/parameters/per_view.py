"""What a model learns for each training view (an appearance embedding, a pose correction): one table row a view."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from nerf_lightning.parameters.groups import resize_to_saved


class PerViewTable(nn.Module):
    """A learnt (V, width) table ``rows``, one row a training view.

    V is known once the data is loaded: :meth:`resize` sets it (the radiance-field module does, in ``setup``, before
    the optimiser is built), and a checkpoint's table loads at the size it was saved with (``rows`` is a variable-size
    parameter, :mod:`~nerf_lightning.parameters.groups`: a model sizes it in ``on_load_checkpoint``, and a table
    loaded on its own does here).

    Args:
        width: numbers a row.
        init: ``zeros`` or ``normal`` (N(0, 1), as ``nn.Embedding``): how :meth:`resize` fills new rows.
    """

    variable_size_parameters = ("rows",)

    def __init__(self, width: int, init: str = "zeros") -> None:
        super().__init__()
        if width < 1 or init not in ("zeros", "normal"):
            raise ValueError(f"{type(self).__name__} needs a width >= 1 and init zeros or normal, got {width}, '{init}'")
        self.width, self.init = width, init
        self.rows = nn.Parameter(torch.zeros(0, width))

    def resize(self, n_views: int) -> None:
        """``n_views`` new rows; the table is kept when its size already fits."""
        if n_views < 1:
            raise ValueError(f"{type(self).__name__} needs at least one training view, got {n_views}")
        if self.rows.shape[0] != n_views:
            fill = torch.randn if self.init == "normal" else torch.zeros
            self.rows = nn.Parameter(fill(n_views, self.width, device=self.rows.device))

    def check_views(self, view_indices: torch.Tensor) -> None:
        """IndexError naming the first index beyond the table (or a table not sized yet). Not in a training step with
        gradients, whose indices the datamodule draws among the training views: reading the largest back would make
        the host wait for the device every step."""
        if self.rows.shape[0] > 0 and self.training and torch.is_grad_enabled():
            return
        if self.rows.shape[0] == 0 or int(view_indices.max()) >= self.rows.shape[0]:
            raise IndexError(f"camera index {int(view_indices.max())} is beyond the {self.rows.shape[0]} training views of this "
                             f"{type(self).__name__}" + ("" if self.rows.shape[0] else ": resize(n_training_views) first"))

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any) -> None:
        resize_to_saved(self, state_dict, prefix)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


class CentredViewTable(PerViewTable):
    """A per-view table of corrections from the training views' mean (a per-photo colour transform): its own
    learning rate, each view's row less the rows' mean (:meth:`centred`), so that the mean view, and every held-out
    view, takes no correction, and an L2 penalty on the centred rows that keeps each near the mean.

    Without the centring every row and what the model learns could drift together (darker colours, brighter
    corrections), and no correction would match no training view.

    Args:
        width: numbers a row.
        lr: the rows' learning rate (their own optimiser group).
        penalty: weight of the centred rows' mean squared norm in the loss (``train/loss_appearance``); 0 for none.
    """

    def __init__(self, width: int, lr: float, penalty: float) -> None:
        super().__init__(width, init="zeros")
        if lr <= 0 or penalty < 0:
            raise ValueError(f"{type(self).__name__} needs lr > 0 and penalty >= 0, got {lr}, {penalty}")
        self.lr, self.penalty = lr, penalty

    def centred(self) -> torch.Tensor:
        """(V, width) the rows less their mean over the training views: what each view is corrected by."""
        return self.rows - self.rows.mean(dim=0)

    def penalties(self) -> dict[str, torch.Tensor]:
        """``appearance``: ``penalty`` times the centred rows' mean squared norm (empty when ``penalty`` is 0)."""
        if self.penalty == 0:
            return {}
        return {"appearance": self.penalty * self.centred().square().sum(-1).mean()}

    def extra_repr(self) -> str:
        return f"views={self.rows.shape[0]}, lr={self.lr:g}, penalty={self.penalty:g}"
