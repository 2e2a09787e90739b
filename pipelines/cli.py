"""What every stage's command line shares: the params it may read, their checks, ``--help``, ``--cfg``.

``python -m stages.<name> [key=value ...] [--cfg] [--help]`` composes params
(:mod:`pipelines.config`), keeps only the keys the stage declares (its DVC ``params`` list: reading
any other key is an error, so the two cannot drift; ``tests/test_dvc_deps.py`` checks ``dvc.yaml``),
checks them all before any work starts (the shared sections here, the stage's own sections by the
checks it passes to :func:`run_main`) and runs it. User errors (bad params, missing files) end the
process with status 1 and one line per problem naming the key or file, without a traceback.
``--help`` lists the keys the stage reads with their values and meaning; ``--cfg`` prints them as YAML
(and checks them) without running.
"""

from __future__ import annotations

import json
import re
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from functools import partial
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import yaml

from pipelines.config import (
    CONF_DIR,
    GROUPS,
    REPO_ROOT,
    ConfigError,
    check_choice,
    check_device,
    check_number,
    check_type,
    every_problem,
    group_choices,
    load_params,
    restrict_params,
)


def _null_or_count(section: Mapping[str, Any], key: str, where: str) -> object:
    """null, or an integer >= 1 (a bound such as a number of items or a batch size)."""
    return section[key] is None or check_number(section, key, where, low=1, integer=True)


#: ``HOST:PORT`` or ``ray://HOST:PORT`` (an IPv6 host in brackets), the forms ``ray.init`` connects to
RAY_HOST_PORT = re.compile(r"(?:ray://)?(?:\[[0-9A-Fa-f:.]+\]|[^\s:/\[\]]+):(\d{1,5})")


def check_ray_address(section: Mapping[str, Any], key: str, where: str) -> None:
    """null (a local Ray), ``auto``, ``local``, ``[ray://]HOST:PORT`` with a port in 1..65535, or
    ``scheme://...`` where ``scheme`` is an installed module: ``ray.init`` imports it for its client
    builder (a provider's package). Not http(s): that is the dashboard's address, not a cluster's."""
    value = section[key]
    if value is None or value in ("auto", "local"):
        return
    if isinstance(value, str):
        match = RAY_HOST_PORT.fullmatch(value)
        if match and 1 <= int(match.group(1)) <= 65535:
            return
        scheme, sep, _ = value.partition("://")
        if sep and scheme.isidentifier() and scheme not in ("ray", "http", "https") and find_spec(scheme):
            return
    raise ConfigError(f"{where}.{key}: expected null, 'auto', 'local' or HOST:PORT (e.g. 10.0.0.1:6379, "
                      f"ray://10.0.0.1:10001), got {value!r}")


#: Checks of the sections several stages share, one per dotted key: ``check(section, key, where)``
#: raises a ConfigError naming the key, its value and what is allowed. A stage's own section is
#: checked by the stage (the ``checks`` of :func:`run_main`).
SHARED_KEYS: dict[str, Callable[[Mapping[str, Any], str, str], Any]] = {
    "seed": partial(check_number, low=0, integer=True),
    "paths.artifacts": partial(check_type, kind=str),
    "paths.ray_storage": partial(check_type, kind=str),
    "data.name": partial(check_type, kind=str),
    "data.root": partial(check_type, kind=str),
    "data.skeleton": partial(check_choice, choices=("humanml3d", "kit")),  # data/skeleton.py SKELETONS
    "data.source": partial(check_choice, choices=("joints", "features", "auto")),
    "data.on_error": partial(check_choice, choices=("fail", "skip")),
    "data.feature_frames_below": partial(check_number, low=2, integer=True),
    "features.out": partial(check_type, kind=str),
    "features.workers": partial(check_number, low=1, integer=True),
    "features.text_encoder": partial(check_choice, choices=("minilm", "clip")),  # data/text_encoders.py ENCODERS
    "features.text_encoder_path": partial(check_type, kind=str, nullable=True),
    "features.max_text_tokens": partial(check_number, low=1, integer=True),
    "features.text_batch_size": partial(check_number, low=1, integer=True),
    "ray.address": check_ray_address,
    "ray.num_workers": partial(check_number, low=0, integer=True),
    "ray.use_gpu": partial(check_choice, choices=("auto", True, False)),
    "ray.cpus_per_worker": partial(check_number, low=0, low_open=True),
    "ray.max_failures": partial(check_number, low=-1, integer=True),  # -1: no limit (runner.fit_retrying)
    "ray.checkpoint_every": partial(check_number, low=1, integer=True),
    "ray.report_every": partial(check_number, low=0, integer=True),
    "ray.storage": partial(check_type, kind=str, nullable=True),
    "ray.local": partial(check_type, kind=bool),
    "ray.placement_strategy": partial(check_choice, choices=("PACK", "SPREAD")),
    "ray.runtime_env": partial(check_type, kind=dict, nullable=True),
    "ray.wandb_project": partial(check_type, kind=str),
    "sample.device": check_device,
    "sample.mld_guidance": partial(check_number, low=0.0),
    "sample.emdm_guidance": partial(check_number, low=0.0),
    "sample.emdm_action_guidance": partial(check_number, low=0.0),
    "sample.motiondiffuse_guidance": partial(check_number, low=0.0),
    "sample.motiondiffuse_ddpm_items": _null_or_count,
    "sample.motiondiffuse_ddpm_replications": _null_or_count,
    "sample.motion_batch": _null_or_count,
    "sample.motionlcm_guidance": partial(check_number, low=1.0),
    "sample.control_refine_steps": partial(check_number, low=0, integer=True),
    "sample.control_refine_lr": partial(check_number, low=0.0, low_open=True),
    "sample.control_refine_project": partial(check_type, kind=bool),
    "sample.control_refine_batch": _null_or_count,
}
SHARED_SECTIONS = frozenset(key.split(".")[0] for key in SHARED_KEYS)
HELP_FLAGS = ("-h", "--help")
CFG_FLAG = "--cfg"

Check = Callable[[dict[str, Any]], object]


def param(params: dict[str, Any], dotted: str) -> Any:
    """``params['a']['b']`` for ``'a.b'``; ConfigError naming the key when it is missing."""
    node: Any = params
    for depth, part in enumerate(dotted.split(".")):
        if not isinstance(node, dict) or part not in node:
            raise ConfigError(f"params have no {'.'.join(dotted.split('.')[: depth + 1])!r}")
        node = node[part]
    return node


def repo_path(params: dict[str, Any], dotted: str) -> Path:
    """The path at params key ``dotted`` made absolute (relative paths are relative to the repository root)."""
    return (REPO_ROOT / param(params, dotted)).resolve()


def artifacts_dir(params: dict[str, Any]) -> Path:
    """``paths.artifacts`` as an absolute path."""
    return repo_path(params, "paths.artifacts")


def check_shared(params: dict[str, Any], keys: Sequence[str]) -> list[str]:
    """Problems of the shared sections in ``params`` (restricted to a stage's ``keys``), one line each.

    Each present key of a shared section is checked by :data:`SHARED_KEYS`; a key it does not know
    is an error, and so is a missing one when the stage reads the whole section.
    """
    errors = []
    for section in sorted(SHARED_SECTIONS & set(params)):
        expected = [key for key in SHARED_KEYS if key == section or key.startswith(section + ".")]
        if expected == [section]:  # a top-level key such as ``seed``
            node, where, present = params, "", [section]
        elif not isinstance(params[section], dict):
            errors.append(f"{section}: expected a mapping, got {params[section]!r}")
            continue
        else:
            node, where = params[section], section
            present = [f"{section}.{key}" for key in node]
        if section in keys:
            errors += [f"{key}: missing; {section} holds {[k.split('.', 1)[-1] for k in expected]}"
                       for key in expected if key not in present]
        for key in present:
            check = SHARED_KEYS.get(key)
            if check is None:
                errors.append(f"{key}: unknown key; {section} holds {[k.split('.', 1)[-1] for k in expected]}")
                continue
            try:
                check(node, key.rpartition(".")[2], where)
            except ConfigError as err:
                errors.append(str(err))
    return errors


def check_params(params: dict[str, Any], keys: Sequence[str], checks: Sequence[Check]) -> list[str]:
    """Every problem of a stage's params, one line each: the shared sections', then each check's
    (:func:`pipelines.config.every_problem`: all its bad values, up to one that stops it)."""
    errors = check_shared(params, keys)
    for check in checks:
        try:
            with every_problem():
                check(params)
        except ValueError as err:
            errors += str(err).splitlines()
    return errors


def conf_comments() -> dict[str, str]:
    """The meaning of dotted keys: the trailing ``# comment`` of their line in ``conf/config.yaml`` or a dataset."""
    comments: dict[str, str] = {}
    for path in [CONF_DIR / "config.yaml", *sorted(CONF_DIR.glob("dataset/*.yaml"))]:  # scale/: values, not meaning
        stack: list[tuple[int, str]] = []  # (indent, key) of the enclosing mappings
        for line in path.read_text(encoding="utf-8").splitlines():
            match = re.match(r"^( *)([A-Za-z_]\w*):(.*)$", line)
            if not match:
                continue
            indent, key, rest = len(match[1]), match[2], match[3]
            while stack and stack[-1][0] >= indent:
                stack.pop()
            stack.append((indent, key))
            comment = re.search(r"(?:^|\s)#\s*(.*)$", rest)
            if comment:
                comments.setdefault(".".join(k for _, k in stack), comment[1].strip())
    return comments


def _flatten(node: Any, prefix: str) -> Iterator[tuple[str, Any, bool]]:
    """(dotted key, value, is a mapping) of ``node`` and everything under it, in order."""
    if isinstance(node, dict):
        if prefix:
            yield prefix, node, True
        for key, value in node.items():
            yield from _flatten(value, f"{prefix}.{key}" if prefix else key)
    else:
        yield prefix, node, False


def help_text(name: str, params: dict[str, Any]) -> str:
    """``--help``: usage, then each key the stage reads with its value and its meaning (from ``conf/``)."""
    groups = " ".join(f"[{group}={'|'.join(group_choices(group))}]" for group in GROUPS)
    lines = [f"usage: {name} [key=value ...] [~key] {groups} [--cfg] [--help]",
             "  key=value: change a key for this run (values typed as YAML 1.2: 1e-3 is a float); ~key: remove it",
             "  --cfg: print the params the stage would run with, as YAML, and check them; --help: this list",
             "", f"keys {name} reads (values from params.yaml with the overrides given; # meaning from conf/):"]
    comments = conf_comments()
    for key, value, is_mapping in _flatten(params, ""):
        meaning = f"  # {comments[key]}" if key in comments else ""
        if is_mapping:
            if meaning:
                lines.append(f"  {key}:{meaning}")
            continue
        shown = value if isinstance(value, str) else json.dumps(value)
        lines.append(f"  {key} = {shown}{meaning}")
    return "\n".join(lines)


def run_main(name: str, run: Callable[[dict[str, Any]], Any], keys: Sequence[str],
             argv: Sequence[str] | None = None, checks: Sequence[Check] = ()) -> None:
    """A stage's command line: params (+ overrides) restricted to ``keys``, checked, then ``run``.

    ``checks`` validate the stage's own sections up front (each raises a ValueError naming the key);
    the shared sections are checked here. ``--help`` prints the keys and returns; ``--cfg`` prints the
    params as YAML, checks them and returns without running. User errors (bad params, missing files)
    exit with status 1 and one line per problem on stderr.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    options = [arg for arg in argv if arg.startswith("-")]
    overrides = [arg for arg in argv if not arg.startswith("-")]
    unknown = sorted(set(options) - {*HELP_FLAGS, CFG_FLAG})
    if unknown:
        sys.exit(f"{name}: unknown option(s) {unknown}; options are --help and --cfg, the rest is key=value")
    try:
        params = restrict_params(load_params(overrides), keys)
        if set(options) & set(HELP_FLAGS):
            print(help_text(name, params))
            return
        if CFG_FLAG in options:
            print(yaml.safe_dump(params, sort_keys=False, default_flow_style=False), end="")
        errors = check_params(params, keys, checks)
        if errors:
            sys.exit("\n".join(f"{name}: {error}" for error in errors))
        if CFG_FLAG not in options:
            run(params)
    except (ValueError, OSError) as err:  # bad params, missing or unwritable files: one line, no traceback
        sys.exit(f"{name}: {err}")
