"""What a model learns, below every layer that learns: named optimiser groups and parameters that change size with
their optimiser state kept in step (:mod:`~nerf_lightning.parameters.groups`), and tables of a row a training view
(:mod:`~nerf_lightning.parameters.per_view`) that appearance embeddings and camera refinement are made of. It
imports nothing of the package, so that fields, geometry and splats may build on it."""
