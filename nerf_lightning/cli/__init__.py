"""The command-line entry points (``nerf-train``, ``nerf-render``, ...): each composes its config and calls the
library. Nothing imports them."""
