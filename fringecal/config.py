"""Typed configuration (pydantic + YAML).

Unknown keys are errors (``extra="forbid"``), numbers must be finite (``.inf`` and
``.nan`` are refused), relative paths resolve against the YAML file's folder, an empty
file is refused (it would silently mean "every default"), and every error names the
file and the offending key.

Every YAML file fringecal reads (configurations, ``dataset.yaml``, ``sequence.yaml``,
``standards.yaml``) goes through :func:`load_yaml_text`, a safe loader that also
refuses what a plain ``yaml.safe_load`` lets through silently:

* a key given twice in one mapping (the last value would win: a second
  ``reference_scanner`` would switch the calibration's frame), naming both lines;
* a document that aliases expand beyond :data:`MAX_YAML_VALUES` values (an "alias
  bomb": a few lines of nested ``&a``/``*a`` grow to gigabytes when expanded), and
  aliases that refer to themselves. The expanded size is counted on the parsed node
  graph, before anything is built or validated; the largest configuration fringecal
  reads holds a few hundred values.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any, Optional

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from fringecal.names import not_a_file

__all__ = ["ConfigError", "StrictModel", "RigConfig", "load_yaml_model", "read_yaml_mapping", "validate_model",
           "deep_update", "configs_dir", "thesis_dir", "bundled_config", "load_yaml_text", "yaml_problem", "validate_section",
           "YAMLRefused", "MAX_YAML_VALUES"]


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


def _format_validation_error(path: Path, err: ValidationError, prefix: str = "") -> str:
    """One line for one error (``FILE: invalid configuration: key.path: message``), else
    a first line and one line per error; ``prefix`` goes before every key path."""
    found = []
    for e in err.errors():
        loc = prefix + ".".join(str(x) for x in e["loc"]) or "(top level)"
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


#: the most values (scalars, lists, mappings) a YAML document may expand to through aliases
MAX_YAML_VALUES = 100_000


class YAMLRefused(yaml.YAMLError):
    """A YAML document :func:`load_yaml_text` refuses; ``line`` (1-based) when known."""

    def __init__(self, message: str, line: int | None = None):
        super().__init__(message)
        self.message, self.line = message, line

    def __str__(self) -> str:
        return f"line {self.line}: {self.message}" if self.line else self.message


class _StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a mapping key given twice."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            first: dict = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue  # "<<: *base" merges on purpose; explicit keys override merged ones
                key = self.construct_object(key_node, deep=True)
                try:
                    line = first.setdefault(key, key_node.start_mark.line + 1)
                except TypeError:  # an unhashable key: SafeLoader refuses it itself
                    continue
                if line != key_node.start_mark.line + 1:
                    raise YAMLRefused(f"key {key!r} is given twice (first on line {line}); a mapping takes each "
                                      "key once (the last value would silently win)", key_node.start_mark.line + 1)
        return super().construct_mapping(node, deep)


def _expanded_size(root, limit: int) -> int:
    """How many values the node graph of a document expands to (aliases repeat the node
    they refer to); stops counting past ``limit``. A node reachable from itself is refused."""
    sizes: dict[int, int] = {}
    active: set[int] = set()

    def size(node) -> int:
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in active:
            raise YAMLRefused("an alias refers to the value that holds it (a recursive structure)",
                              node.start_mark.line + 1)
        active.add(key)
        n = 1
        if isinstance(node, yaml.SequenceNode):
            for child in node.value:
                n += size(child)
                if n > limit:
                    break
        elif isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                n += size(k) + size(v)
                if n > limit:
                    break
        active.discard(key)
        sizes[key] = n = min(n, limit + 1)
        return n

    return size(root)


def load_yaml_text(text: str):
    """The value of a YAML document, loaded safely (see the module notes: no key given
    twice, at most :data:`MAX_YAML_VALUES` values once aliases are expanded). Raises
    ``yaml.YAMLError`` (:class:`YAMLRefused` for those two refusals)."""
    loader = _StrictLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        if _expanded_size(node, MAX_YAML_VALUES) > MAX_YAML_VALUES:
            raise YAMLRefused(f"the document expands to more than {MAX_YAML_VALUES:,} values through its aliases "
                              "(&anchor/*alias); a configuration holds a few hundred (an alias bomb?)")
        return loader.construct_document(node)
    finally:
        loader.dispose()


def yaml_problem(err: yaml.YAMLError) -> str:
    """One line saying what is wrong with a YAML document (its line when known)."""
    if isinstance(err, YAMLRefused):
        return str(err)
    return f"not valid YAML ({' '.join(str(err).split())})"


def read_yaml_mapping(path, empty_hint: str = "expected a mapping of settings") -> dict:
    """The top-level mapping of a YAML file.

    An empty file (or one of comments only) is refused with ``empty_hint``: taken as
    "every default", it would run something the user did not write down.
    """
    path = Path(path)
    if (kind := not_a_file(path)) is not None and kind != "a folder":  # a FIFO would be waited on forever
        raise ConfigError(f"{path}: {kind}, not a YAML file")
    try:
        data = load_yaml_text(path.read_text(encoding="utf-8"))
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
        raise ConfigError(f"{path}: {yaml_problem(err)}") from None
    if data is None:
        raise ConfigError(f"{path}: the file is empty; {empty_hint}")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, found {type(data).__name__}")
    return data


def validate_section(data, model: type[BaseModel], source, prefix: str) -> None:
    """Check ``data`` against ``model`` alone, errors naming ``source`` and the keys under
    ``prefix`` (a data set's ``processing.bundle`` before it is merged into a run config,
    so that its errors name ``dataset.yaml``, not the run configuration)."""
    try:
        model.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format_validation_error(Path(source), err, prefix)) from None


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
