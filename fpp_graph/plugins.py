"""The plug-ins a run selects by name: its loop detector, its pairwise registrar and its map fuser.

The configuration's ``plugins`` section names each (null: the built-in). A name is an entry
point of the point's group (:data:`POINTS`: ``fpp_graph.loop_detectors``, ``fpp_graph.registrars``,
``fpp_graph.map_fusers``) in an installed distribution, or ``module:attribute``. The attribute
is a factory (a class or any callable) with the signature its Protocol below declares; the run
calls it with its resolved :class:`~fpp_graph.config.Config` and checks that what it returns
has every member of the point's protocol (:mod:`fpp_graph.types`). Every failure (an unknown
name, an import error, a factory of another signature, a member missing) is one
:class:`~fpp_graph.errors.ConfigError` line.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any, Protocol

from fpp_graph.config import Config
from fpp_graph.errors import ConfigError
from fpp_graph.types import LoopDetector, MapFuser, PairRegistrar

if TYPE_CHECKING:
    from fpp_graph.slam.sources import FrameSource


class LoopDetectorFactory(Protocol):
    """``plugins.loop_detector``: makes the run's :class:`~fpp_graph.types.LoopDetector`, once,
    in the tracking process (a class whose constructor takes the config is one)."""

    def __call__(self, config: Config) -> LoopDetector: ...


class RegistrarFactory(Protocol):
    """``plugins.registrar``: makes the run's :class:`~fpp_graph.types.PairRegistrar` for the
    frames of ``source`` (``source.make_registrar()`` is the sensor's own, to wrap or to replace).

    Called in the tracking process and once in each worker process that verifies loop
    candidates: it must be importable there, and give the same registration each time (random
    draws seeded from ``config.run.seed``), so that a run does not depend on its worker count.
    """

    def __call__(self, config: Config, source: FrameSource) -> PairRegistrar: ...


class MapFuserFactory(Protocol):
    """``plugins.map_fuser``: makes the run's :class:`~fpp_graph.types.MapFuser`, once, before the
    run starts. A plain ``MapFuser`` runs in the tracking process; one that is also a
    :class:`~fpp_graph.types.ParallelMapFuser` or :class:`~fpp_graph.types.MeshSplittingMapFuser`
    gets its work spread over the run's workers."""

    def __call__(self, config: Config) -> MapFuser: ...


@dataclass(frozen=True)
class PluginPoint:
    """One plug-in point: the entry-point group of its names, and what its factory is and makes."""

    group: str
    factory: type
    protocol: type
    builtin: str  # what null selects, for listings

    @property
    def arguments(self) -> list[str]:
        """The factory's parameter names, in call order."""
        return [name for name in inspect.signature(self.factory.__call__).parameters if name != "self"]


POINTS: dict[str, PluginPoint] = {
    "loop_detector": PluginPoint("fpp_graph.loop_detectors", LoopDetectorFactory, LoopDetector,
                                 "proximity and appearance candidates, as the loop_closure section sets them"),
    "registrar": PluginPoint("fpp_graph.registrars", RegistrarFactory, PairRegistrar, "the frame source's own registration, make_registrar()"),
    "map_fuser": PluginPoint("fpp_graph.map_fusers", MapFuserFactory, MapFuser, "the voxel map and TSDF mesh, as the fusion section sets them"),
}
"""The plug-in points by their key in the ``plugins`` config section."""


def registered_plugins() -> dict[str, dict[str, str]]:
    """The names each point's entry-point group registers: ``{key: {name: "module:attribute"}}``."""
    return {key: {ep.name: ep.value for ep in entry_points(group=point.group)} for key, point in POINTS.items()}


def load_factory(key: str, config: Config) -> Callable[..., Any] | None:
    """The factory ``config.plugins.<key>`` names, imported and its signature checked (None: the
    built-in); a :class:`ConfigError` saying what is wrong and what to do otherwise."""
    spec = getattr(config.plugins, key)
    if spec is None:
        return None
    point = POINTS[key]
    found = {ep.name: ep for ep in entry_points(group=point.group)}
    if spec not in found and ":" not in spec:
        raise ConfigError(
            f"plugins.{key}: no plug-in named {spec!r} in the {point.group} entry points (registered: "
            f"{', '.join(sorted(found)) or 'none'}); give one of them, module:attribute, or null for the built-in"
        )
    try:
        if spec in found:
            factory = found[spec].load()
        else:
            module, _, attribute = spec.partition(":")
            factory = importlib.import_module(module)
            for name in attribute.split("."):
                factory = getattr(factory, name)
    except Exception as exc:  # noqa: BLE001 - whatever the plug-in's import raised, said in one line
        reason = (str(exc).splitlines() or [""])[0]
        raise ConfigError(
            f"plugins.{key}: {spec} could not be loaded ({type(exc).__name__}: {reason}); install the package that "
            "provides it (or put its folder on PYTHONPATH), or correct the name"
        ) from None
    arguments = point.arguments
    try:
        inspect.signature(factory).bind(*arguments)
    except TypeError:
        raise ConfigError(
            f"plugins.{key}: {spec} cannot be called as ({', '.join(arguments)}); make it a factory as "
            f"fpp_graph.plugins.{point.factory.__name__} declares"
        ) from None
    except ValueError:  # a callable without an inspectable signature: its call will tell
        pass
    return factory


def check_plugins(config: Config) -> None:
    """Load every plug-in ``config`` names (before a run starts: its failure costs no output)."""
    for key in POINTS:
        load_factory(key, config)


def _built(key: str, config: Config, *context: Any) -> Any:
    factory = load_factory(key, config)
    if factory is None:
        return None
    built = factory(config, *context)
    protocol = POINTS[key].protocol
    members = sorted(name for name in vars(protocol) if not name.startswith("_"))
    missing = [name for name in members if not callable(getattr(built, name, None))]
    if missing:
        raise ConfigError(
            f"plugins.{key}: {getattr(config.plugins, key)} made a {type(built).__name__}, which lacks "
            f"{', '.join(missing)} of the {protocol.__name__} protocol; implement every member fpp_graph.types.{protocol.__name__} declares"
        )
    return built


def chosen_loop_detector(config: Config) -> LoopDetector | None:
    """The loop detector ``plugins.loop_detector`` names (None: the keyframe manager's own)."""
    return _built("loop_detector", config)


def chosen_registrar(config: Config, source: FrameSource) -> PairRegistrar:
    """The registrar ``plugins.registrar`` names, or the source's own."""
    built = _built("registrar", config, source)
    return source.make_registrar() if built is None else built


def chosen_map_fuser(config: Config) -> MapFuser | None:
    """The map fuser ``plugins.map_fuser`` names (None: the voxel map of ``config.fusion``)."""
    return _built("map_fuser", config)
