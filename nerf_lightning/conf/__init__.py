"""Hydra configs shipped inside the package, so nerf-train finds them from any working directory."""
