"""nerf-lightning: neural fields and NeRF experiments on PyTorch Lightning, Kornia and Hydra."""

__version__ = "0.4.0"
