"""What the commands make of a trained model, through the model contract (:mod:`nerf_lightning.models.contract`):
frames and camera-path renders (:mod:`~nerf_lightning.outputs.frames`), held-out evaluation
(:mod:`~nerf_lightning.outputs.evaluation`), meshes and other exports (:mod:`~nerf_lightning.outputs.mesh`,
:mod:`~nerf_lightning.outputs.export`). Nothing here knows which kind of model it is given; rendering knows
nothing of files or checkpoints: this layer joins them."""
