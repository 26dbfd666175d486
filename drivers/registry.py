"""Backends chosen by name from the config, like python-can's ``BACKENDS``.

:data:`BACKENDS` maps ``(role, name)`` to a ``"module:callable"`` string, imported only
when :func:`open_driver` chooses it: a backend with a heavy or optional dependency
(OpenCV, ``depthai``, ``python-can``) costs nothing until a config names it. A factory
takes the role's config section (a frozen dataclass of :mod:`robotd.base.config`, or the
driver's own section type) and the injected clock, and returns an open
:class:`~drivers.base.Driver`. Adding a backend is one line here plus its module.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

from drivers.base import Driver
from robotd.base.clock import Clock
from robotd.base.errors import ConfigError

__all__ = ["BACKENDS", "known_backends", "open_driver", "resolve"]

BACKENDS: dict[tuple[str, str], str] = {
    ("base", "kobuki"): "drivers.kobuki.driver:open_kobuki",
    ("base", "can"): "drivers.can.driver:open_can",
    ("floor_camera", "v4l2"): "drivers.camera:open_v4l2",
    ("floor_camera", "depthai"): "drivers.depthai_camera:open_depthai",
    ("forward_camera", "v4l2"): "drivers.camera:open_v4l2_forward",
    ("forward_camera", "depthai"): "drivers.depthai_camera:open_depthai_forward",
    ("base", "ros2"): "drivers.ros2.inputs:open_ros2_base",
    ("floor_camera", "ros2"): "drivers.ros2.inputs:open_ros2_floor",
    ("forward_camera", "ros2"): "drivers.ros2.inputs:open_ros2_forward",
    ("replay", "mcap"): "drivers.recording.replay:open_replay",
}
"""``(role, name)`` -> ``"module:callable"`` of the factory ``(section, clock) -> Driver``."""


def known_backends(role: str) -> list[str]:
    """The backend names registered for ``role``, sorted."""
    return sorted(name for r, name in BACKENDS if r == role)


def resolve(role: str, name: str) -> Callable[[Any, Clock], Driver]:
    """Import and return the factory of backend ``name`` for ``role``.

    Raises :class:`~robotd.base.errors.ConfigError` naming the known backends when
    ``name`` is not registered, or naming the missing module when the backend's module
    (or one of its dependencies) cannot be imported.
    """
    target = BACKENDS.get((role, name))
    if target is None:
        known = known_backends(role)
        if not known:
            roles = ", ".join(sorted({r for r, _ in BACKENDS}))
            raise ConfigError(f"no driver role {role!r}; known roles: {roles}")
        raise ConfigError(f"unknown {role} driver {name!r}; known: {', '.join(known)}")
    module_name, _, attr = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"{role} driver {name!r} cannot be loaded: {exc}") from exc
    factory: Callable[[Any, Clock], Driver] = getattr(module, attr)
    return factory


def open_driver(role: str, name: str, section: Any, clock: Clock) -> Driver:
    """Open backend ``name`` for ``role`` (e.g. ``("base", "kobuki")``) from its config
    ``section`` on ``clock``.

    Raises :class:`~robotd.base.errors.ConfigError` for an unknown or unloadable backend
    and whatever the factory raises (:class:`~robotd.base.errors.DriverError` when the
    device cannot be opened).
    """
    return resolve(role, name)(section, clock)
