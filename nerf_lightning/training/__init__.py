"""A training run from a config (:func:`~nerf_lightning.training.run.train`), and the callbacks every run has
(:mod:`~nerf_lightning.training.callbacks`)."""

from nerf_lightning.training.run import train

__all__ = ["train"]
