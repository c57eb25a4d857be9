"""Errors raised by the services; the routes turn them into HTTP answers."""

from __future__ import annotations


class ServiceError(Exception):
    """A request the service refuses; ``field`` names the request field concerned (or None)."""

    def __init__(self, detail: str, *, field: str | None = None):
        super().__init__(detail)
        self.detail = detail
        self.field = field


class NotFoundError(ServiceError):
    """The thing asked for does not exist (404)."""


class UnprocessableError(ServiceError):
    """A well-formed request that cannot be accepted as it is (422)."""


class ConflictError(ServiceError):
    """A request the resource's current state does not allow (409): e.g. advice for a plate whose target
    is not a cylinder with its material."""
