"""Rendering: encoder position to equalized, safe output frames at the device's sample rate.

The package's names are looked up on first use (PEP 562), so that `from hostd.render import
series` (the encoder's played signal, hostd encode) does not load the pipeline and its
equalizer (scipy.signal)."""

__all__ = ["RenderConfig", "Renderer", "frames"]


def __getattr__(name: str):
    if name in __all__:
        from hostd.render import pipeline

        return getattr(pipeline, name)
    raise AttributeError(f"module 'hostd.render' has no attribute {name!r}")
