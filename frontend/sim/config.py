"""Config sections of the virtual FPP sensor: the strict pydantic base and validation into ConfigError.

Every section of a scene YAML (``rig``, ``render``, ``calibration``, ``turntable``, ``corridor``) is a frozen
pydantic model that rejects unknown keys; a validation failure becomes one :class:`ConfigError`
whose message names each bad key.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError

from fpp_graph.errors import ConfigError


class StrictModel(BaseModel):
    """A frozen config section; unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", frozen=True)


def config_error(exc: ValidationError, where: str) -> ConfigError:
    """One ConfigError ``"<where>: key: message; key: message"`` from a pydantic validation error."""
    parts = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"])
        parts.append(f"{loc}: {err['msg']}")
    return ConfigError(f"{where}: " + "; ".join(parts))


def validate_section(model: type[BaseModel], data: Any, where: str) -> Any:
    """Validate a config section (empty or ``None`` means all defaults) into ``model``.

    Raises
    ------
    ConfigError
        ``data`` is not a mapping, or a key is unknown or has a bad value.
    """
    try:
        return model(**(data or {}))
    except ValidationError as exc:
        raise config_error(exc, where) from None
    except TypeError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def parse_model(model: type[BaseModel], data: Any, where: str) -> Any:
    """Validate a config section (``None`` means all defaults) into ``model``.

    Raises
    ------
    ConfigError
        ``data`` is not a mapping, or a key is unknown or has a bad value.
    """
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
    try:
        return model(**data)
    except ValidationError as exc:
        raise config_error(exc, where) from None
