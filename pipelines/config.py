"""Configuration: Hydra groups in ``conf/`` are composed into ``params.yaml``; stages read it.

``params.yaml`` is the file DVC tracks (``dvc repro`` reads it as committed). It is the
composition of ``conf/config.yaml`` with its default groups; ``dvc exp run -S scale=smoke``
re-composes it (``hydra.enabled`` in ``.dvc/config``), and ``python -m pipelines.config`` does
the same by hand. Stage modules take ``key=value`` overrides on their command line:

- dotted keys (``data.on_error=skip``) change ``params.yaml``'s values for that run;
- group choices (``scale=smoke``, ``dataset=kit``) re-compose ``conf/`` first.

Unknown keys are errors (``+key=value`` adds a new one), so a typo never passes silently.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

REPO_ROOT = Path(__file__).resolve().parents[1]
CONF_DIR = REPO_ROOT / "conf"
PARAMS_PATH = REPO_ROOT / "params.yaml"
GROUPS = ("dataset", "scale")


class ConfigError(ValueError):
    """A bad override or an unreadable params file."""


def check_number(cfg: Mapping[str, Any], key: str, where: str, *, low: float, high: float | None = None,
                 low_open: bool = False, high_open: bool = False, integer: bool = False) -> float:
    """``cfg[key]`` checked to be a number (an int if ``integer``, never a bool) within its bounds (open or
    closed); a ConfigError naming ``<where>.<key>``, the bounds and the value otherwise."""
    value = cfg[key]
    kinds = (int,) if integer else (int, float)
    bad_type = isinstance(value, bool) or not isinstance(value, kinds)
    if (bad_type or value < low or (low_open and value == low) or (high is not None and value > high)
            or (high_open and value == high)):
        upper = "" if high is None else f" and {'<' if high_open else '<='} {high}"
        kind = "an integer" if integer else "a number"
        raise ConfigError(f"{where}.{key}: expected {kind} {'>' if low_open else '>='} {low}{upper}, got {value!r}")
    return value


def compose_params(overrides: Sequence[str] = ()) -> dict[str, Any]:
    """Compose ``conf/config.yaml`` with Hydra overrides into a plain, resolved dict."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3", job_name="motionforge"):
        cfg = compose(config_name="config", overrides=list(overrides))
    return OmegaConf.to_container(cfg, resolve=True)


def read_params(path: Path = PARAMS_PATH) -> dict[str, Any]:
    """Read a params file; raises ConfigError naming the file when it is missing or malformed."""
    try:
        params = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
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


def apply_overrides(params: dict[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """Return a copy of ``params`` with dotted ``key=value`` overrides (values parsed as YAML).

    A key that does not exist raises ConfigError naming it, unless written ``+key=value``.
    """
    result = yaml.safe_load(yaml.safe_dump(params))
    for item in overrides:
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
        node[parts[-1]] = yaml.safe_load(raw) if raw else None
    return result


def load_params(argv: Sequence[str] | None = None, path: Path = PARAMS_PATH) -> dict[str, Any]:
    """Params for a stage run: ``params.yaml`` (or ``conf/`` when a group is chosen) + overrides."""
    argv = list(sys.argv[1:] if argv is None else argv)
    groups = [a for a in argv if _split_override(a)[0] in GROUPS]
    dotted = [a for a in argv if a not in groups]
    params = compose_params(groups) if groups else read_params(path)
    return apply_overrides(params, dotted)


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
    params = compose_params(args.overrides)
    if args.check:
        if read_params(args.out) != params:
            sys.exit(f"{args.out} differs from the composition of conf/: run `python -m pipelines.config`")
        return
    tmp = args.out.with_suffix(".yaml.tmp")
    tmp.write_text(dump_params(params), encoding="utf-8")
    tmp.replace(args.out)


if __name__ == "__main__":
    main()
