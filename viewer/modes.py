"""Which Rerun mode a run takes when it is not told: a module of its own so that asking does
not import the Rerun SDK (half a second), which a run without a viewer never needs."""

from __future__ import annotations

import os


def default_mode() -> str:
    """"spawn" when a display is available (DISPLAY or WAYLAND_DISPLAY set), else "off"."""
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return "spawn"
    return "off"
