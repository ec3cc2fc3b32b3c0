"""3D Gaussian splatting, laid out as gsplat lays out its kernels: projecting Gaussians into the project's pinhole
cameras (:mod:`~nerf_lightning.splats.projection`) and their spherical-harmonic colours
(:mod:`~nerf_lightning.splats.sh`), the readable reference rasteriser (:mod:`~nerf_lightning.splats.rasterize_reference`)
beside the fast ones that tests hold equal to it (plain PyTorch's pairs, :mod:`~nerf_lightning.splats.rasterize_pairs`;
the tile kernels of numba, :mod:`~nerf_lightning.splats.rasterize_tiles`, and Triton,
:mod:`~nerf_lightning.splats.rasterize_triton`, sharing :mod:`~nerf_lightning.splats.rasterize_core`), and the one
choice of what draws a view (:mod:`~nerf_lightning.splats.draw`, ``model/rasterizer``); compositing through
:mod:`nerf_lightning.rendering.compositing`."""
