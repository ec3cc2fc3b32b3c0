"""Pictures of cameras, rays and samples: a PNG (matplotlib) or an interactive 3D view (viser, optional)."""
