"""The names the data side's keys take, torch-free, so that the commands check a key (``nerf_lightning.cli.keys``)
before torch loads; the modules that act on them import them from here."""

from __future__ import annotations

# render.path of nerf-render and data.render_path: the scene's held-out or render cameras, or a path made around it
RENDER_PATHS = ("test", "orbit", "spiral")
# the procedural scene's smallest number of views: its val and test splits take every tenth
PROCEDURAL_MIN_VIEWS = 10
