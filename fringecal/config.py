"""Typed configuration (pydantic + YAML).

Unknown keys are errors (``extra="forbid"``), relative paths resolve against the
YAML file's folder, and every error names the file and the offending key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

__all__ = ["ConfigError", "StrictModel", "RigConfig", "load_yaml_model", "package_root", "thesis_dir"]


class ConfigError(ValueError):
    """A configuration file is invalid; the message names the file and keys."""


class StrictModel(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def package_root() -> Path:
    """The checkout holding ``configs/`` (fringecal is installed editable from it)."""
    return Path(__file__).resolve().parents[1]


def thesis_dir() -> Path:
    return package_root() / "configs" / "thesis"


class RigConfig(StrictModel):
    """A rig data set: sensors, artefact and (for simulation) artefact poses."""

    name: str
    reference_scanner: str
    sensors: Path
    sensors_initial: Optional[Path] = None
    artefact: Path
    rods: Optional[Path] = None
    artefact_poses: Optional[Path] = None
    ballbar: Optional[Path] = None
    materials: Optional[Path] = None


def _format_validation_error(path: Path, err: ValidationError) -> str:
    lines = [f"{path}: invalid configuration"]
    for e in err.errors():
        loc = ".".join(str(x) for x in e["loc"]) or "(top level)"
        msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"]
        lines.append(f"  {loc}: {msg}")
    return "\n".join(lines)


def _resolve_paths(model: BaseModel, base: Path) -> BaseModel:
    updates: dict[str, Any] = {}
    for name in type(model).model_fields:
        v = getattr(model, name)
        if isinstance(v, Path) and not v.is_absolute():
            updates[name] = (base / v).resolve()
        elif isinstance(v, BaseModel):
            updates[name] = _resolve_paths(v, base)
    return model.model_copy(update=updates) if updates else model


def load_yaml_model(path, model: type[BaseModel], overrides: dict | None = None):
    """Load ``path`` into ``model``; relative paths resolve against the file's folder."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({err})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, found {type(data).__name__}")
    if overrides:
        data = _deep_update(data, overrides)
    try:
        obj = model.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format_validation_error(path, err)) from None
    obj = _resolve_paths(obj, path.parent)
    missing = [f"{k}: {v}" for k, v in _paths(obj) if not v.exists()]
    if missing:
        raise ConfigError(f"{path}: referenced file(s) not found: " + "; ".join(missing))
    return obj


def _paths(model: BaseModel, prefix: str = ""):
    for name in type(model).model_fields:
        v = getattr(model, name)
        if isinstance(v, Path):
            yield prefix + name, v
        elif isinstance(v, BaseModel):
            yield from _paths(v, prefix + name + ".")


def _deep_update(base: dict, upd: dict) -> dict:
    out = dict(base)
    for k, v in upd.items():
        out[k] = _deep_update(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out
