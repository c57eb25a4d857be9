"""Limits on what one request may cost and on the job queue.

* :mod:`app.limits.body`: request body size (413), an ASGI middleware.
* :mod:`app.limits.work`: the work a request asks for: image pixels and lights of an uploaded
  capture (read from capture.json and the image headers, nothing decoded), a calibration's
  image size, a simulated capture's size and lights (422).
* :mod:`app.limits.queue`: inspections waiting in the queue, per plate and in all (429 with
  ``Retry-After``).
* :mod:`app.limits.physical`: what a hull plate can physically be (radius, size, tolerance,
  where lights can stand): numbers outside are refused (422) before a job fails on them.

Every refusal names the request field, the limit, and the setting that raises it.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from app.settings import ENV_PREFIX, Settings


@dataclass(frozen=True)
class Limits:
    """The request and queue limits in force (see :class:`app.settings.Settings` for each)."""

    max_image_pixels: int
    max_lights: int
    max_simulated_pixels: int
    max_queued_per_plate: int
    max_queued: int

    @classmethod
    def from_settings(cls, settings: Settings) -> Limits:
        """The limits of ``settings``."""
        return cls(**{f.name: getattr(settings, f.name) for f in fields(cls)})

    @classmethod
    def defaults(cls) -> Limits:
        """The limits of a server with none of them set (the defaults of :class:`app.settings.Settings`)."""
        return cls(**{f.name: Settings.model_fields[f.name].default for f in fields(cls)})


#: The default limits (what the services apply when the caller passes none).
DEFAULT_LIMITS = Limits.defaults()


def setting_name(limit: str) -> str:
    """The environment variable that sets ``limit`` (a :class:`Limits` field), for messages."""
    if limit not in {f.name for f in fields(Limits)}:
        raise ValueError(f"limit: expected a field of Limits, got {limit!r}")
    return f"{ENV_PREFIX}{limit.upper()}"


__all__ = ["DEFAULT_LIMITS", "Limits", "setting_name"]
