"""Typed configuration (pydantic + YAML).

Unknown keys are errors (``extra="forbid"``), numbers must be finite (``.inf`` and
``.nan`` are refused), relative paths resolve against the YAML file's folder, an empty
file is refused (it would silently mean "every default"), and every error names the
file and the offending key.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any, Optional

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

__all__ = ["ConfigError", "StrictModel", "RigConfig", "load_yaml_model", "read_yaml_mapping", "validate_model",
           "deep_update", "configs_dir", "thesis_dir", "bundled_config"]


class ConfigError(ValueError):
    """A configuration file is invalid; the message names the file and keys."""


class StrictModel(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def configs_dir() -> Path:
    """The bundled configurations and the thesis's data: the repository's ``configs/``,
    installed as the package data ``fringecal.configs`` (read through importlib.resources,
    so an installed fringecal finds them from any working directory)."""
    return Path(str(resources.files("fringecal.configs")))


def thesis_dir() -> Path:
    """The thesis's tables and the default rig (``configs/thesis``)."""
    return configs_dir() / "thesis"


def bundled_config(path) -> Path:
    """``path`` if it names a file, else the bundled configuration of that name
    (``run_thesis_realistic`` or ``run_thesis_realistic.yaml``); unchanged when neither
    exists, for the caller's error to name it."""
    path = Path(path)
    if path.exists() or path.parent != Path("."):
        return path
    for name in (path.name, f"{path.name}.yaml"):
        if (configs_dir() / name).is_file():
            return configs_dir() / name
    return path


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
    """One line for one error (``FILE: invalid configuration: key.path: message``), else
    a first line and one line per error."""
    found = []
    for e in err.errors():
        loc = ".".join(str(x) for x in e["loc"]) or "(top level)"
        msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"].removeprefix("Value error, ")
        found.append(f"{loc}: {msg}")
    if len(found) == 1:
        return f"{path}: invalid configuration: {found[0]}"
    return "\n".join([f"{path}: invalid configuration"] + [f"  {f}" for f in found])


def _resolve_paths(model: BaseModel, base: Path) -> BaseModel:
    updates: dict[str, Any] = {}
    for name in type(model).model_fields:
        v = getattr(model, name)
        if isinstance(v, Path) and not v.is_absolute():
            updates[name] = (base / v).resolve()
        elif isinstance(v, BaseModel):
            updates[name] = _resolve_paths(v, base)
    return model.model_copy(update=updates) if updates else model


def read_yaml_mapping(path, empty_hint: str = "expected a mapping of settings") -> dict:
    """The top-level mapping of a YAML file.

    An empty file (or one of comments only) is refused with ``empty_hint``: taken as
    "every default", it would run something the user did not write down.
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a folder, not a YAML file") from None
    except OSError as err:
        raise ConfigError(f"{path}: cannot be read ({err.strerror or err})") from None
    except UnicodeDecodeError as err:
        line = err.object.count(b"\n", 0, err.start) + 1
        raise ConfigError(f"{path}: line {line}: byte 0x{err.object[err.start]:02x} is not UTF-8 text; "
                          "save the file as UTF-8") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({' '.join(str(err).split())})") from None
    if data is None:
        raise ConfigError(f"{path}: the file is empty; {empty_hint}")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, found {type(data).__name__}")
    return data


def validate_model(data: dict, model: type[BaseModel], source, base: Path):
    """``model`` from ``data``; relative paths resolve against ``base``; every path must exist.

    Errors name ``source`` and the offending key path.
    """
    try:
        obj = model.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format_validation_error(Path(source), err)) from None
    obj = _resolve_paths(obj, Path(base))
    missing = [f"{k}: {v}" for k, v in _paths(obj) if not v.exists()]
    if missing:
        raise ConfigError(f"{source}: referenced file(s) not found: " + "; ".join(missing))
    return obj


def load_yaml_model(path, model: type[BaseModel], overrides: dict | None = None):
    """Load ``path`` into ``model``; relative paths resolve against the file's folder."""
    path = Path(path)
    data = read_yaml_mapping(path)
    if overrides:
        data = deep_update(data, overrides)
    return validate_model(data, model, path, path.parent)


def _paths(model: BaseModel, prefix: str = ""):
    for name in type(model).model_fields:
        v = getattr(model, name)
        if isinstance(v, Path):
            yield prefix + name, v
        elif isinstance(v, BaseModel):
            yield from _paths(v, prefix + name + ".")


def deep_update(base: dict, upd: dict) -> dict:
    """``base`` with ``upd`` merged in, mappings merged key by key."""
    out = dict(base)
    for k, v in upd.items():
        out[k] = deep_update(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out
