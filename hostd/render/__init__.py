"""Rendering: encoder position to equalized, safe output frames at the device's sample rate."""

from hostd.render.pipeline import RenderConfig, Renderer, frames

__all__ = ["RenderConfig", "Renderer", "frames"]
