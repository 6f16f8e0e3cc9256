"""Reading, composing and validating ``params.yaml`` sections into typed configs."""
from __future__ import annotations

import copy
import dataclasses
import functools
import math
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from pipeline.errors import ConfigError, MissingInputError

REPO_ROOT = Path(__file__).resolve().parents[3]
CONF_DIR = REPO_ROOT / "conf"
PARAMS_PATH = REPO_ROOT / "params.yaml"

T = TypeVar("T")


def check_image_size(where: str, width: int, height: int) -> None:
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise ConfigError(f"{where}.width, {where}.height: image size must be positive integers, got {width}x{height}")


def require_min(where: str, config: Any, names: str, low: float = 0, strict: bool = False) -> None:
    """Each field of ``config`` in ``names`` (space-separated) must be >= ``low`` (> with
    ``strict``) and finite; a ConfigError names the first that is not (NaN fails too)."""
    for name in names.split():
        value = getattr(config, name)
        if not (math.isfinite(value) and (value > low if strict else value >= low)):
            number = "" if math.isfinite(value) else "a finite number "
            raise ConfigError(f"{where}.{name} must be {number}{'>' if strict else '>='} {low:g}, got {value!r}")


def require_in(where: str, config: Any, names: str, low: float, high: float) -> None:
    """Each field of ``config`` in ``names`` (space-separated) must lie in ``[low, high]``."""
    for name in names.split():
        value = getattr(config, name)
        if not low <= value <= high:
            raise ConfigError(f"{where}.{name} must be in [{low:g}, {high:g}], got {value!r}")


def merged_section(cls: type[T], key: str, params: dict[str, Any], changes: dict[str, Any],
                   variant: str | None = None) -> T:
    """Section ``key`` of ``params`` with the partial mapping ``changes`` (of ablation variant
    ``variant``) merged in (nested mappings merge key by key), validated like a params value."""

    def merge(base: dict, extra: dict) -> dict:
        out = copy.deepcopy(base)
        for k, v in extra.items():
            out[k] = merge(out.get(k) or {}, v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
        return out

    try:
        return from_dict(cls, merge(section_mapping(key, params.get(key)), changes or {}), where=key)
    except ConfigError as exc:
        if not changes:
            raise
        merged = f"ablation.variants.{variant}.{key}" if variant else "a variant's changes"
        raise ConfigError(f"{exc} (with {merged} merged in)") from exc


def section_mapping(where: str, data: Any) -> dict[str, Any]:
    """``data`` as a config section: a mapping (``None``, an empty YAML section: ``{}``)."""
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where} must be a section (a mapping of keys to values), got {data!r}")
    return data


@functools.cache
def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _type_name(tp: Any) -> str:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return " or ".join(_type_name(t) for t in typing.get_args(tp))
    if typing.get_origin(tp) in (list, tuple):
        return "a list"
    if dataclasses.is_dataclass(tp):
        return "a section (a mapping of keys to values)"
    names = {bool: "true or false", int: "an integer", float: "a number", str: "a string", dict: "a mapping",
             type(None): "null"}
    if tp not in names:  # a new kind of field: teach this function its rule rather than skip it
        raise TypeError(f"config field type {tp!r} has no type check")
    return names[tp]


def _type_problem(key: str, value: Any, tp: Any) -> str | None:
    """Why ``value`` cannot be a field of type ``tp`` (``None`` when it can): a bool is not a
    number and an integral float not an int (nothing is rounded), a list is checked element-wise."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        if any(_type_problem(key, value, t) is None for t in typing.get_args(tp)):
            return None
    elif origin in (list, tuple):
        if isinstance(value, (list, tuple)):
            element = typing.get_args(tp)[0]
            return next((p for i, v in enumerate(value) if (p := _type_problem(f"{key}[{i}]", v, element))), None)
    elif dataclasses.is_dataclass(tp):
        if value is None or isinstance(value, (tp, dict)):  # a mapping becomes the section (nested_sections)
            return None
    elif tp is bool:
        if isinstance(value, bool):
            return None
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return None
    elif tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return None
    elif tp in (str, dict, type(None)):
        if isinstance(value, tp):
            return None
    return f"{key} must be {_type_name(tp)}, got {value!r}"


def from_dict(cls: type[T], data: dict[str, Any] | None, where: str = "") -> T:
    """Build a dataclass from a mapping, rejecting unknown keys (typos fail loudly), missing
    ones (the config fields have no defaults: conf/ gives each, and so does params.yaml) and
    values of the wrong type; the class checks the ranges (its ``__post_init__``)."""
    where = where or cls.__name__
    data = dict(section_mapping(where, data))
    fields = dataclasses.fields(cls)
    unknown = sorted(set(data) - {f.name for f in fields})
    if unknown:
        raise ConfigError(f"unknown key(s) {unknown} in config section {where}")
    missing = [f.name for f in fields if f.name not in data and f.default is dataclasses.MISSING
               and f.default_factory is dataclasses.MISSING]
    if missing:
        raise ConfigError(f"missing key(s) {missing} in config section {where} (conf/ gives every key; "
                          "`gcgs params --write` composes a complete params.yaml)")
    types_ = _field_types(cls)
    for name, value in data.items():
        if problem := _type_problem(f"{where}.{name}", value, types_[name]):
            raise ConfigError(problem)
    return cls(**data)


def nested_sections(config: Any, where: str, **classes: type) -> None:
    """Turn the nested sections of ``config`` that are still mappings (as read from YAML)
    into their dataclasses, in place; unknown and missing keys fail as in :func:`from_dict`."""
    for name, cls in classes.items():
        value = getattr(config, name)
        if isinstance(value, dict) or value is None:
            setattr(config, name, from_dict(cls, value, where=f"{where}.{name}"))


class FromConf:
    """Base of the config dataclasses that read a section of ``conf/``. ``conf/`` is the one
    source of each default value (issue 60), so their fields have none: :meth:`default` builds
    a config from ``conf/``'s default composition, where ``SECTION`` is the class's dotted key
    (``"optimize.densify"``). tests/test_config_defaults.py keeps fields and conf/ keys equal."""

    SECTION = ""

    @classmethod
    def default(cls: type[T], **changes: Any) -> T:
        """The config of ``conf/``'s default composition (each group's default preset, as in
        conf/config.yaml's defaults list: what ``gcgs params --write`` composes) with
        ``changes``: field values; a nested section given as a mapping merges key by key over
        its default one, given as a config replaces it. Validated like a params value
        (:func:`from_dict` and the class's ``__post_init__``), errors named ``SECTION.key``."""
        return default_config(cls, **changes)


def default_config(cls: type[T], **changes: Any) -> T:
    """:meth:`FromConf.default` of ``cls``: the section ``cls.SECTION`` of the composed default
    ``conf/`` with ``changes`` merged in, built by :func:`from_dict`."""
    key = getattr(cls, "SECTION", "")
    if not key:
        raise TypeError(f"{cls.__name__} is not read from a section of conf/ (it has no SECTION)")
    base = section_mapping(key, conf_defaults(key))
    return from_dict(cls, _with_changes(cls, base, changes), where=key)


def conf_defaults(key: str = "") -> Any:
    """A copy of the default composition of ``conf/`` (no overrides; composed once per process)
    at the dotted ``key`` (all of it for ``""``)."""
    node = _composed_defaults()
    for part in filter(None, key.split(".")):
        if not isinstance(node, dict) or part not in node:
            raise ConfigError(f"conf/ has no section {key!r} (its default composition lacks {part!r})")
        node = node[part]
    return copy.deepcopy(node)


@functools.cache
def _composed_defaults() -> dict[str, Any]:
    from hydra.core.global_hydra import GlobalHydra
    from hydra.initialize import get_gh_backup, restore_gh_from_backup

    if not (CONF_DIR / "config.yaml").is_file():
        raise ConfigError(f"{CONF_DIR / 'config.yaml'}: not found; the config defaults are read from the "
                          "repository's conf/ (install the package from its checkout: pip install -e .)")
    if not GlobalHydra.instance().is_initialized():
        return compose_params()
    backup = get_gh_backup()  # called inside a Hydra app (pipeline.sweep): compose beside it, then restore it
    GlobalHydra.instance().clear()
    try:
        return compose_params()
    finally:
        restore_gh_from_backup(backup)


def _section_class(tp: Any) -> type | None:
    """The config dataclass that a field of type ``tp`` holds (a nested section), else None."""
    if dataclasses.is_dataclass(tp):
        return tp
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return next((t for t in typing.get_args(tp) if dataclasses.is_dataclass(t)), None)
    return None


def _with_changes(cls: type, base: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """``base`` (a section of ``cls``) with ``changes``: a mapping given for a nested section
    merges into it key by key; any other value (a config included) replaces the key's."""
    out = dict(base)
    types_ = _field_types(cls)
    for name, value in changes.items():
        sub = _section_class(types_.get(name))
        if sub is not None and isinstance(value, dict) and isinstance(out.get(name), dict):
            value = _with_changes(sub, out[name], value)
        out[name] = value
    return out


def load_params(path: str | Path | None = None) -> dict[str, Any]:
    """Read a params file. Default: ``params.yaml`` of the working directory (DVC runs each
    stage in its project's root), else this repository's."""
    if path is None:
        path = Path("params.yaml") if Path("params.yaml").is_file() else PARAMS_PATH
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(f"{path}: params file not found")
    try:
        with open(path) as fh:
            params = yaml.safe_load(fh)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(f"{path}: not valid YAML ({getattr(exc, 'problem', None) or exc}{where})") from exc
    if params is None:
        return {}
    if not isinstance(params, dict):
        raise ConfigError(f"{path}: a params file must map section names to sections, got a {type(params).__name__}")
    return params


def section(cls: type[T], key: str, params: dict[str, Any] | None = None,
            overrides: dict[str, Any] | None = None) -> T:
    """Typed, validated config for one top-level key of params.yaml.

    ``overrides`` (command-line values) maps field names to values, dotted for nested
    sections (``{"mast3r.model": path}``); ``None`` values are not given and leave the
    params value. They are merged into the section's mapping *before* the dataclass is
    built, so an override is validated like a params value and a misspelt name fails."""
    params = load_params() if params is None else params
    data = copy.deepcopy(section_mapping(key, params.get(key)))
    for name, value in (overrides or {}).items():
        if value is None:
            continue
        *parents, leaf = name.split(".")
        node = data
        for parent in parents:
            node = node.setdefault(parent, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{key}.{name}: {parent} is not a section")
        node[leaf] = value
    return from_dict(cls, data, where=key)


def compose_params(overrides: list[str] | None = None) -> dict[str, Any]:
    """Compose ``conf/config.yaml`` with Hydra's compose API. A composition Hydra refuses (an
    override it cannot parse, an unknown key or group, a missing preset) is one ConfigError
    line naming the override, not Hydra's traceback."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException, MissingConfigException, OverrideParseException
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    overrides = list(overrides or [])
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name="config", overrides=overrides)
        return OmegaConf.to_container(cfg, resolve=True)
    except MissingConfigException as exc:
        raise ConfigError(_missing_preset(exc, overrides)) from exc
    except OverrideParseException as exc:
        raise ConfigError(f"override {exc.override!r}: {_one_line(exc.message)} (the form is KEY=VALUE)") from exc
    except (HydraException, OmegaConfBaseException) as exc:
        raise ConfigError(_composition_problem(exc, overrides)) from exc


def conf_groups() -> list[str]:
    """The config groups of ``conf/``: its folders of presets (``conf/GROUP/*.yaml``)."""
    return sorted(d.name for d in CONF_DIR.iterdir() if d.is_dir() and any(d.glob("*.yaml")))


def _one_line(message: str) -> str:
    """Hydra's (or OmegaConf's) message on one line, without its pointers to the docs, the
    search path and the node it was at (the caller names the key)."""
    lines = []
    for line in (line.strip() for line in str(message).splitlines()):
        if line.startswith(("See https://", "Config search path", "Set the environment variable", "full_key:")):
            break
        if line and not line.startswith("Error parsing override"):
            lines.append(line.rstrip("."))
    return "; ".join(lines)


def _given(overrides: list[str], key: str, value: str | None = None) -> str:
    """The override of ``key`` (and ``value``) among ``overrides``, as the user wrote it."""
    for o in reversed(overrides):
        k, _, v = o.partition("=")
        if k.lstrip("+~").split("@")[0] == key and value in (None, v.strip()):
            return o
    return key if value is None else f"{key}={value}"


def _missing_preset(exc: Any, overrides: list[str]) -> str:
    group, _, name = (exc.missing_cfg_file or "").rpartition("/")
    presets = (CONF_DIR / group).glob("*.yaml") if group else ()
    choices = sorted({p.stem for p in presets} | set(exc.options or []))
    if not choices:
        return f"{_given(overrides, group, name)}: no config group {group!r}; groups: {', '.join(conf_groups())}"
    return f"{_given(overrides, group, name)}: no preset {name!r} in conf/{group}; choices: {', '.join(choices)}"


def _composition_problem(exc: Exception, overrides: list[str]) -> str:
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError

    cause = exc.__cause__ if isinstance(exc.__cause__, (ConfigAttributeError, ConfigKeyError)) else None
    if cause is not None and cause.full_key:
        key = cause.full_key
        if "." in key or "/" in key:
            return f"{_given(overrides, key)}: unknown key {key} (conf/ has no such setting)"
        return f"{_given(overrides, key)}: no config group or key {key!r}; groups: {', '.join(conf_groups())}"
    key = getattr(exc, "full_key", None)
    return f"{key or f'conf/ with overrides {overrides}'}: {_one_line(str(exc))}"


def dump_params(params: dict[str, Any]) -> str:
    header = "# Generated from conf/ by `gcgs params --write`; do not edit by hand.\n"
    return header + yaml.safe_dump(params, sort_keys=False, default_flow_style=False)
