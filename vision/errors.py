"""The errors of ``vision``: each says what was wrong and what to do about it.

They subclass ``ValueError`` so that callers which already treat bad input as a ``ValueError``
keep working; callers that must tell bad input from bugs catch ``VisionError``.
"""

from __future__ import annotations


class VisionError(ValueError):
    """Base of every error ``vision`` raises on purpose (bad input, not a bug)."""


class SettingsError(VisionError):
    """Search or teach settings that cannot work (out of range, not finite, contradictory)."""


class TeachError(VisionError):
    """A model cannot be taught from this image region (no usable edges, region too small...)."""


class ImageError(VisionError):
    """An array that is not an image the matchers read (wrong shape or channel count)."""
