"""3D Gaussian splatting in plain PyTorch: projecting Gaussians into the project's pinhole cameras
(:mod:`~nerf_lightning.splats.projection`), spherical-harmonic colours (:mod:`~nerf_lightning.splats.sh`), and the
rasteriser (:mod:`~nerf_lightning.splats.rasterize`) beside its dense reference
(:mod:`~nerf_lightning.splats.rasterize_dense`), compositing through :mod:`nerf_lightning.rendering.compositing`."""
