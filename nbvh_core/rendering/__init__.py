"""Cameras, shading, metrics, the render engine's scene renderer."""
