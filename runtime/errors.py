"""The base class of the runtime's errors that name their field as an attribute (no caller parses a message to
recover it): ``FieldError(field, message)``, ``str(e) == f"{field}: {message}"``. runtime.views.ViewError (render
requests) and runtime.render.CameraError (cameras) derive from it."""

from __future__ import annotations


class FieldError(ValueError):
    """An input that cannot be honoured. ``field``: the field at fault ("K", "cam_to_world", "width",
    "cameras[3].fov", ...); ``message``: what is wrong with it (without the field)."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message

    def __reduce__(self):  # picklable with both arguments (worker processes)
        return (type(self), (self.field, self.message))


__all__ = ["FieldError"]
