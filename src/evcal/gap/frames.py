"""The frames that drive a model's simulation: the measured frames as the model says the
sensor's events saw them (frame-side effects change them; without any, they are unchanged)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..recording import Frames

if TYPE_CHECKING:
    from .model import Model


def model_frames(model: Model, frames: Frames) -> Frames:
    """``frames`` as the model's frame-side effects transform them (none yet: unchanged)."""
    return frames
