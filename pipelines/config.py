"""Configuration: Hydra groups in ``conf/`` are composed into ``params.yaml``; stages read it.

``params.yaml`` is the file DVC tracks (``dvc repro`` reads it as committed). It is the
composition of ``conf/config.yaml`` with its default groups; ``dvc exp run -S scale=smoke``
re-composes it (``hydra.enabled`` in ``.dvc/config``), and ``python -m pipelines.config`` does
the same by hand. Stage modules take ``key=value`` overrides on their command line:

- dotted keys (``data.on_error=skip``) change ``params.yaml``'s values for that run; values are typed
  as YAML 1.2 and OmegaConf type them (``1e-3`` and ``.5`` are floats, ``true``/``false`` booleans,
  ``null`` None, ``7`` an int, anything else a string);
- ``~key`` removes a key (the stage then reports it missing), ``+key=value`` adds a new one;
- group choices (``scale=smoke``, ``dataset=kit``) re-compose ``conf/`` first; a choice must be a
  file ``conf/<group>/<choice>.yaml``.

Unknown keys are errors, so a typo never passes silently.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import math
import re
import sys
import types
import typing
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any

import yaml
from hydra import compose, initialize_config_dir
from hydra.errors import HydraException
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

REPO_ROOT = Path(__file__).resolve().parents[1]
CONF_DIR = REPO_ROOT / "conf"
PARAMS_PATH = REPO_ROOT / "params.yaml"
GROUPS = ("dataset", "scale")


class ConfigError(ValueError):
    """A bad override or an unreadable params file."""


class Yaml12Loader(yaml.SafeLoader):
    """PyYAML's safe loader with YAML 1.2 core-schema scalars, as OmegaConf and DVC read YAML.

    PyYAML implements YAML 1.1, where ``1e-3`` is a string, ``yes``/``on`` are booleans, ``017`` is
    octal and ``1:30`` is 90. Here ``1e-3``, ``1E5`` and ``.5`` are floats, only ``true``/``false``
    are booleans, ints are decimal (or ``0x``/``0o``), dates stay strings.
    """


_YAML11_SCALARS = {f"tag:yaml.org,2002:{kind}" for kind in ("bool", "int", "float", "timestamp")}
Yaml12Loader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag not in _YAML11_SCALARS]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
Yaml12Loader.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF"))
Yaml12Loader.add_implicit_resolver(  # before float: "12" matches both
    "tag:yaml.org,2002:int", re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$"), list("-+0123456789"))
Yaml12Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"),
    list("-+0123456789."))
Yaml12Loader.add_constructor(  # decimal, 0x or 0o (PyYAML would read "017" as octal)
    "tag:yaml.org,2002:int", lambda loader, node: int(node.value, 0 if node.value[:2] in ("0x", "0o") else 10))


def parse_value(raw: str) -> Any:
    """An override's value typed as YAML 1.2 / OmegaConf type it (:class:`Yaml12Loader`); ConfigError if malformed."""
    try:
        return yaml.load(raw, Loader=Yaml12Loader)  # noqa: S506 (a safe loader)
    except yaml.YAMLError as err:
        reason = getattr(err, "problem", None) or " ".join(str(err).split())
        raise ConfigError(f"value {raw!r} is not valid YAML ({reason})") from err


#: The problems noted by the value checks inside :func:`every_problem` (None outside it: they raise).
_NOTED: ContextVar[list[str] | None] = ContextVar("noted_config_problems", default=None)


def refuse(message: str) -> None:
    """A bad value: a ConfigError with ``message``, or inside :func:`every_problem` a note, the check going on."""
    noted = _NOTED.get()
    if noted is None:
        raise ConfigError(message)
    noted.append(message)


@contextmanager
def every_problem() -> Iterator[None]:
    """Run a section's checks to their end and raise one ConfigError listing every bad value, one per line.

    The value checks (:func:`check_number`, :func:`check_choice`, :func:`check_type`, :func:`check_heads`,
    :func:`check_fields`) note a bad value and return it instead of raising. A ConfigError raised inside
    (a section that is not a mapping, an unknown key) ends the checks and joins the list; another
    exception after a noted value (code that used the bad value) ends them, the list standing for it.
    Each key is listed once, by the first check that refused it.
    """
    noted: list[str] = []
    token = _NOTED.set(noted)
    try:
        yield
    except ConfigError as err:
        noted.append(str(err))
    except Exception:
        if not noted:
            raise
    finally:
        _NOTED.reset(token)
    if noted:
        first = {}  # one line per key: the first check that refused it (a later one would repeat it)
        for message in noted:
            first.setdefault(message.split(": ", 1)[0], message)
        raise ConfigError("\n".join(first.values()))


def dotted(where: str, key: str) -> str:
    """``where.key`` (just ``key`` at the top level, ``where`` empty)."""
    return f"{where}.{key}" if where else key


def check_number(cfg: Mapping[str, Any], key: str, where: str, *, low: float, high: float | None = None,
                 low_open: bool = False, high_open: bool = False, integer: bool = False) -> float:
    """``cfg[key]`` checked to be a finite number (an int if ``integer``, never a bool) within its bounds (open
    or closed); a ConfigError naming ``<where>.<key>``, the bounds and the value otherwise (NaN and inf too)."""
    value = cfg[key]
    kinds = (int,) if integer else (int, float)
    bad_type = isinstance(value, bool) or not isinstance(value, kinds)
    if (bad_type or not math.isfinite(value) or value < low or (low_open and value == low)
            or (high is not None and value > high) or (high_open and value == high)):
        upper = "" if high is None else f" and {'<' if high_open else '<='} {high}"
        kind = "an integer" if integer else "a number"
        refuse(f"{dotted(where, key)}: expected {kind} {'>' if low_open else '>='} {low}{upper}, got {value!r}")
    return value


def is_integer(value: Any) -> bool:
    """Whether ``value`` is an int (a bool is not)."""
    return isinstance(value, int) and not isinstance(value, bool)


def check_odd(cfg: Mapping[str, Any], key: str, where: str) -> None:
    """``cfg[key]`` checked to be an odd integer >= 1 (a skip transformer's 2K + 1 layers, a centred kernel);
    a ConfigError naming ``<where>.<key>`` otherwise."""
    value = cfg[key]
    if not is_integer(value) or value < 1 or value % 2 == 0:
        refuse(f"{dotted(where, key)}: expected an odd integer >= 1, got {value!r}")


def check_choice(cfg: Mapping[str, Any], key: str, where: str, *, choices: Sequence[Any]) -> Any:
    """``cfg[key]`` checked to be one of ``choices``; a ConfigError naming the key, the value and the choices."""
    value = cfg[key]
    if not any(value == choice and type(value) is type(choice) for choice in choices):
        refuse(f"{dotted(where, key)}: expected one of {list(choices)}, got {value!r}")
    return value


def check_device(cfg: Mapping[str, Any], key: str, where: str) -> str:
    """``cfg[key]`` checked to name a device: ``auto``, ``cpu``, ``cuda`` or ``cuda:<index>``; a ConfigError naming
    the key otherwise (whether the machine has that GPU is known only where the stage runs)."""
    value = cfg[key]
    if not (isinstance(value, str) and re.fullmatch(r"auto|cpu|cuda(:[0-9]+)?", value)):
        refuse(f"{dotted(where, key)}: expected auto, cpu, cuda or cuda:<index>, got {value!r}")
    return value


def check_heads(cfg: Mapping[str, Any], key: str, where: str, *, width: int) -> None:
    """``cfg[key]``, a number of attention heads, checked to be an integer >= 1 that divides the network's
    ``width``; a ConfigError naming ``<where>.<key>`` otherwise (torch would assert when the network is built)."""
    heads = int(check_number(cfg, key, where, low=1, integer=True))
    if width % heads:
        refuse(f"{dotted(where, key)}: width {width} must be divisible by {key} {heads}")


def check_type(cfg: Mapping[str, Any], key: str, where: str, *, kind: type, nullable: bool = False) -> Any:
    """``cfg[key]`` checked to be a ``kind`` (``str``, ``bool``, ``dict``, ``list``) or, if ``nullable``, None."""
    value = cfg[key]
    if not (isinstance(value, kind) or (nullable and value is None)):
        names = {str: "a string", bool: "true or false", dict: "a mapping", list: "a list"}
        allowed = names.get(kind, kind.__name__) + (" or null" if nullable else "")
        refuse(f"{dotted(where, key)}: expected {allowed}, got {value!r}")
    return value


def check_keys(cfg: Any, where: str, names: Sequence[str]) -> Mapping[str, Any]:
    """``cfg`` checked to be a mapping with exactly the keys ``names``; ConfigError naming the others."""
    if not isinstance(cfg, Mapping):
        raise ConfigError(f"{where}: expected a mapping with keys {list(names)}, got {cfg!r}")
    unknown, missing = sorted(set(cfg) - set(names)), [name for name in names if name not in cfg]
    if unknown:
        raise ConfigError(f"{dotted(where, unknown[0])}: unknown key; {where} holds {list(names)}")
    if missing:
        raise ConfigError(f"{dotted(where, missing[0])}: missing; {where} holds {list(names)}")
    return cfg


def _allows(hint: Any, value: Any) -> bool:
    """Whether ``value`` (as read from YAML) fits the type annotation ``hint``."""
    origin = typing.get_origin(hint)
    if hint is Any:
        return True
    if origin is typing.Literal:
        return any(value == choice and type(value) is type(choice) for choice in typing.get_args(hint))
    if origin in (typing.Union, types.UnionType):
        return any(_allows(arm, value) for arm in typing.get_args(hint))
    if hint is type(None):
        return value is None
    if hint is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if origin in (list, tuple, Sequence) or hint in (list, tuple):
        return isinstance(value, list | tuple)
    if origin in (dict, Mapping) or hint is dict:
        return isinstance(value, dict)
    return isinstance(value, hint) if isinstance(hint, type) else True


def _describe(hint: Any) -> str:
    """An annotation in words for an error message (``an integer or null``, ``one of ['a', 'b']``)."""
    origin = typing.get_origin(hint)
    if origin is typing.Literal:
        return f"one of {list(typing.get_args(hint))}"
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(arm) for arm in typing.get_args(hint))
    names = {type(None): "null", int: "an integer", float: "a number", bool: "true or false", str: "a string"}
    return names.get(hint, f"a {getattr(origin or hint, '__name__', hint)}")


def check_fields(cfg: Any, cls: type, where: str, *, exclude: Sequence[str] = ()) -> Mapping[str, Any]:
    """``cfg`` checked against the fields of dataclass ``cls``: no unknown key, each value of its field's type.

    Types come from the annotations (``Literal`` ones are choices); keys left out take the field's
    default; ``exclude`` names fields the stage fills in itself (not params). ConfigError naming the key.
    """
    if not isinstance(cfg, Mapping):
        raise ConfigError(f"{where}: expected a mapping, got {cfg!r}")
    hints = typing.get_type_hints(cls)
    known = [f.name for f in dataclasses.fields(cls) if f.name not in exclude]
    for key, value in cfg.items():
        if key not in known:
            refuse(f"{dotted(where, key)}: unknown key; {where} holds {known}")
        elif not _allows(hints[key], value):
            refuse(f"{dotted(where, key)}: expected {_describe(hints[key])}, got {value!r}")
    return cfg


def group_choices(group: str) -> list[str]:
    """The choices of a Hydra group: the stems of ``conf/<group>/*.yaml``."""
    return sorted(path.stem for path in (CONF_DIR / group).glob("*.yaml"))


def group_choice(override: str) -> str | None:
    """``group=choice`` for an override choosing a group of ``conf/`` (``+group=choice`` too), else None.

    Every group is in the defaults of ``conf/config.yaml``, so a ``+`` (Hydra: append a group) can only
    mean choosing it: ``+scale=smoke`` is ``scale=smoke``.
    """
    key, sep, choice = override.partition("=")
    group = key.lstrip("+")
    return f"{group}={choice}" if sep and group in GROUPS else None


def check_group_choice(override: str) -> None:
    """``group=choice`` checked to name a file ``conf/<group>/<choice>.yaml`` (nothing outside ``conf/``)."""
    group, _, choice = override.partition("=")
    allowed = group_choices(group)
    if choice not in allowed:
        raise ConfigError(f"{group}={choice!r}: no such choice; {group} is one of {allowed}")


def compose_params(overrides: Sequence[str] = ()) -> dict[str, Any]:
    """Compose ``conf/config.yaml`` with Hydra overrides into a plain, resolved dict.

    ``+group=choice`` chooses a group as ``group=choice`` does (:func:`group_choice`); group choices must
    be files of ``conf/<group>/``; Hydra's errors become a one-line ConfigError.
    """
    hydra_overrides: list[str] = []
    for override in overrides:
        choice = group_choice(override)
        if choice is not None:
            check_group_choice(choice)
        hydra_overrides.append(override if choice is None else choice)
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3", job_name="motionforge"):
            cfg = compose(config_name="config", overrides=hydra_overrides)
        return OmegaConf.to_container(cfg, resolve=True)
    except (HydraException, OmegaConfBaseException) as err:
        raise ConfigError(" ".join(str(err).split("\n")[0].split())) from err


def read_params(path: Path = PARAMS_PATH) -> dict[str, Any]:
    """Read a params file; raises ConfigError naming the file when it is missing or malformed."""
    try:
        params = yaml.load(Path(path).read_text(encoding="utf-8"), Loader=Yaml12Loader)  # noqa: S506
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"{path}: cannot read params ({err})") from err
    if not isinstance(params, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return params


def _split_override(item: str) -> tuple[str, str]:
    key, sep, value = item.partition("=")
    if not sep or not key:
        raise ConfigError(f"override {item!r} is not of the form key=value")
    return key, value


def _remove(params: dict[str, Any], item: str) -> None:
    """Apply ``~a.b``: delete key ``a.b``; ConfigError naming it when it does not exist."""
    parts = item[1:].split(".")
    node: Any = params
    for depth, part in enumerate(parts):
        if not isinstance(node, dict) or part not in node:
            raise ConfigError(f"unknown config key {'.'.join(parts[: depth + 1])!r} in {item!r}")
        if depth < len(parts) - 1:
            node = node[part]
    del node[parts[-1]]


def apply_overrides(params: dict[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """Return a copy of ``params`` with dotted ``key=value`` overrides (values typed by :func:`parse_value`).

    A key that does not exist raises ConfigError naming it, unless written ``+key=value``; ``~key``
    removes one.
    """
    result = copy.deepcopy(params)
    for item in overrides:
        if item.startswith("~") and "=" not in item:
            _remove(result, item)
            continue
        key, raw = _split_override(item)
        add = key.startswith("+")
        parts = key.lstrip("+").split(".")
        node = result
        for depth, part in enumerate(parts[:-1]):
            child = node.get(part) if isinstance(node, dict) else None
            if not isinstance(child, dict):
                if not add or child is not None:
                    raise ConfigError(f"unknown config key {'.'.join(parts[: depth + 1])!r} in {item!r}")
                child = node[part] = {}
            node = child
        if parts[-1] not in node and not add:
            raise ConfigError(f"unknown config key {key!r} in {item!r} (use +{key}=... to add one)")
        node[parts[-1]] = parse_value(raw)
    return result


def load_params(argv: Sequence[str] | None = None, path: Path = PARAMS_PATH) -> dict[str, Any]:
    """Params for a stage run: ``params.yaml`` (or ``conf/`` when a group is chosen, ``group=choice`` or
    ``+group=choice``) + overrides."""
    argv = list(sys.argv[1:] if argv is None else argv)
    groups = [choice for choice in map(group_choice, argv) if choice is not None]
    keys = [a for a in argv if group_choice(a) is None]
    params = compose_params(groups) if groups else read_params(path)
    return apply_overrides(params, keys)


def restrict_params(params: dict[str, Any], keys: Sequence[str]) -> dict[str, Any]:
    """Only the dotted ``keys`` of ``params`` (a section or a key in one); ConfigError if one is missing.

    A stage reads only what it declares, so its DVC ``params`` list is complete by construction.
    """
    result: dict[str, Any] = {}
    for key in keys:
        source, target = params, result
        parts = key.split(".")
        for depth, part in enumerate(parts):
            if not isinstance(source, dict) or part not in source:
                raise ConfigError(f"params have no {'.'.join(parts[: depth + 1])!r}")
            source = source[part]
            if depth < len(parts) - 1:
                target = target.setdefault(part, {})
        target[parts[-1]] = source
    return result


def dump_params(params: dict[str, Any]) -> str:
    """YAML text of params as written to ``params.yaml`` (key order kept)."""
    header = "# Generated from conf/ by `python -m pipelines.config` (or `dvc exp run`). Edit conf/.\n"
    return header + yaml.safe_dump(params, sort_keys=False, default_flow_style=False)


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m pipelines.config [overrides]``: compose conf/ and write (or --check) params.yaml."""
    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. scale=smoke")
    parser.add_argument("--check", action="store_true", help="exit 1 if params.yaml differs")
    parser.add_argument("--out", type=Path, default=PARAMS_PATH)
    args = parser.parse_args(argv)
    try:
        params = compose_params(args.overrides)
    except ConfigError as err:
        sys.exit(f"pipelines.config: {err}")
    if args.check:
        if read_params(args.out) != params:
            sys.exit(f"{args.out} differs from the composition of conf/: run `python -m pipelines.config`")
        return
    tmp = args.out.with_suffix(".yaml.tmp")
    tmp.write_text(dump_params(params), encoding="utf-8")
    tmp.replace(args.out)


if __name__ == "__main__":
    main()
