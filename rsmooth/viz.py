"""Artifacts a person looks at: metrics, figures, animations, written atomically.

Every file is written to a temporary name in the destination folder and renamed into place,
so an interrupted run never leaves a half-written file behind.

``viz.plt`` is matplotlib's pyplot on its ``Agg`` backend (no screen needed), imported on first
use: importing it takes about half a second, which a solve that draws nothing should not pay.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from rsmooth._files import atomic_path

__all__ = ["atomic_path", "write_metrics", "save_figure", "save_animation"]


def __getattr__(name: str):
    if name == "plt":
        import matplotlib

        matplotlib.use("Agg")  # no screen needed; must precede pyplot
        import matplotlib.pyplot as plt

        globals()["plt"] = plt
        return plt
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _plain(value):
    """Converts arrays and numpy scalars to plain JSON numbers, lists and strings."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        return _plain(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)  # JSON has no NaN or infinity; keep it readable rather than invalid
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    raise TypeError(f"cannot write {type(value).__name__} to metrics.json")


def write_metrics(path: str | os.PathLike, metrics: dict) -> Path:
    """Writes `metrics` as indented JSON of plain numbers and strings."""
    text = json.dumps(_plain(metrics), indent=2, sort_keys=True)
    with atomic_path(path) as tmp:
        tmp.write_text(text + "\n")
    return Path(path)


def save_figure(fig, path: str | os.PathLike, dpi: int = 120) -> Path:
    """Saves a matplotlib figure (format from the suffix) and closes it."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    __getattr__("plt").close(fig)
    return Path(path)


def save_animation(frames, path: str | os.PathLike, fps: int = 10) -> Path:
    """Writes frames (a sequence of HxWx3 or HxW arrays, floats in [0, 1] or uint8) as a GIF."""
    import imageio.v3 as iio

    images = []
    for frame in frames:
        frame = np.asarray(frame)
        if frame.dtype != np.uint8:
            frame = (np.clip(frame, 0.0, 1.0) * 255).astype(np.uint8)
        images.append(frame)
    if not images:
        raise ValueError("frames must contain at least one image")
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, np.stack(images), extension=Path(path).suffix, duration=1000 / fps, loop=0)
    return Path(path)
