"""Hyperparameter files in rl-zoo3's layout, and the Stable-Baselines3 objects they name.

A file (YAML or JSON) maps env ids to sections, as rl-zoo3's ``hyperparams/<algo>.yml``
does; the section of the trial's env is used. A file whose top level is one section (no
env ids) is used as it is. In a section:

- ``n_envs``, ``n_timesteps``, ``policy``: the vector env's size, the default budget and
  the policy (``MlpPolicy`` unless given);
- ``normalize``: ``true`` or ``"dict(norm_obs=True, norm_reward=False)"``: a
  ``VecNormalize`` below the shaping wrapper;
- ``frame_stack``: a ``VecFrameStack`` below the shaping wrapper;
- ``env_wrapper``: an import path (or a list of them, or ``{path: kwargs}`` entries) of
  gymnasium wrappers applied to each env, above its ``Monitor``;
- ``policy_kwargs``: a dict, or rl-zoo3's string form (``"dict(net_arch=[64, 64],
  activation_fn=nn.ReLU)"``), read without ``eval``: literals, ``dict(...)`` and the
  names of ``torch.nn`` / ``torch.optim`` classes only;
- ``lin_<x>`` for any value: a schedule decaying linearly from x to 0 (rl-zoo3's);
- every other key: a keyword of the algorithm's constructor.

``callback`` and ``vec_env_wrapper`` are refused: they would change what is being
compared.
"""

from __future__ import annotations

import ast
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["Hyperparams", "HyperparamsError", "load_section", "resolve"]

#: Keys of a section that are not algorithm keywords.
_ZOO_KEYS = frozenset(
    {"n_envs", "n_timesteps", "policy", "normalize", "frame_stack", "env_wrapper"}
)
#: Keys rl-zoo3 knows that a trial refuses.
_REFUSED = {
    "callback": "a callback changes training itself, not what the trial compares",
    "vec_env_wrapper": "a VecEnv wrapper would sit above the shaping wrapper",
}


class HyperparamsError(ValueError):
    """A hyperparameter file that cannot be used, with the file and the key in its message."""


@dataclass(frozen=True)
class Hyperparams:
    """A section resolved into Stable-Baselines3 objects.

    Attributes:
        n_envs: Environments of the vector env.
        policy: The policy's name (``MlpPolicy``...).
        algo_kwargs: The algorithm's keyword arguments (schedules and classes built).
        normalize: ``VecNormalize``'s keyword arguments, or ``None`` for none.
        frame_stack: Frames stacked by ``VecFrameStack``, or ``None``.
        env_wrappers: Each env's wrappers, innermost first: (class, kwargs).
    """

    n_envs: int = 1
    policy: str = "MlpPolicy"
    algo_kwargs: dict[str, Any] = field(default_factory=dict)
    normalize: dict[str, Any] | None = None
    frame_stack: int | None = None
    env_wrappers: list[tuple[Callable[..., Any], dict[str, Any]]] = field(default_factory=list)


def load_section(path: str | Path, env_id: str) -> dict[str, Any]:
    """The section of ``env_id`` in the file at ``path`` (YAML or JSON), as written.

    Raises:
        HyperparamsError: The file cannot be read or parsed, or has no section for the env.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise HyperparamsError(f"--hyperparams {path}: {exc.strerror or exc}") from None
    try:
        if path.suffix == ".json":
            data = json.loads(text)
        else:
            import yaml

            # rl-zoo3's files are plain YAML (!!float tags included); safe_load suffices.
            data = yaml.safe_load(text)
    except Exception as exc:  # yaml.YAMLError, json.JSONDecodeError
        raise HyperparamsError(f"--hyperparams {path}: does not parse: {exc}") from None
    if not isinstance(data, dict):
        raise HyperparamsError(
            f"--hyperparams {path}: expected a mapping of env ids to sections, got "
            f"{type(data).__name__}"
        )
    if env_id in data:
        section = data[env_id]
    elif all(not isinstance(v, dict) or k == "policy_kwargs" for k, v in data.items()):
        section = data  # one section, no env ids
    else:
        names = ", ".join(sorted(map(str, data))) or "none"
        raise HyperparamsError(f"--hyperparams {path}: no section for {env_id} (sections: {names})")
    if not isinstance(section, dict):
        raise HyperparamsError(f"--hyperparams {path}: the section of {env_id} is not a mapping")
    for key, why in _REFUSED.items():
        if key in section:
            raise HyperparamsError(f"--hyperparams {path}: {key!r} is not supported: {why}")
    return json.loads(json.dumps(section))  # type: ignore[no-any-return]


def _linear(start: float) -> Callable[[float], float]:
    """rl-zoo3's ``lin_<x>``: x at the start of training, 0 at the end."""

    def schedule(progress_remaining: float) -> float:
        return progress_remaining * start

    return schedule


def _value(key: str, raw: Any) -> Any:
    """One value: ``lin_<x>`` becomes a schedule, ``policy_kwargs`` strings are read."""
    if isinstance(raw, str) and raw.startswith("lin_"):
        try:
            return _linear(float(raw[4:]))
        except ValueError:
            raise HyperparamsError(f"{key}: {raw!r} is not lin_<number>") from None
    if key in ("policy_kwargs", "replay_buffer_kwargs") and isinstance(raw, str):
        return _literal(key, raw)
    if key == "policy_kwargs" and isinstance(raw, dict):
        return {k: _literal(f"{key}.{k}", v) if isinstance(v, str) else v for k, v in raw.items()}
    return raw


def _class_named(key: str, dotted: str) -> Any:
    """Return a class of ``torch.nn`` or ``torch.optim`` by its rl-zoo3 spelling.

    ``nn.ReLU``, ``th.optim.Adam``, ``torch.nn.Tanh``.
    """
    import torch

    parts = dotted.split(".")
    if parts[0] in ("th", "torch"):
        parts = parts[1:]
    if len(parts) == 2 and parts[0] in ("nn", "optim"):
        obj = getattr(getattr(torch, parts[0]), parts[1], None)
        if isinstance(obj, type):
            return obj
    raise HyperparamsError(f"{key}: {dotted!r} is not a torch.nn or torch.optim class")


def _literal(key: str, text: str) -> Any:
    """rl-zoo3's string form of a value, read without ``eval``."""
    try:
        tree = ast.parse(text, mode="eval").body
    except SyntaxError as exc:
        raise HyperparamsError(f"{key}: {text!r} does not parse: {exc.msg}") from None

    def read(node: ast.expr) -> Any:
        if isinstance(node, ast.Constant):
            return node.value
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
            return -read(node.operand)
        if isinstance(node, (ast.List, ast.Tuple)):
            items = [read(e) for e in node.elts]
            return items if isinstance(node, ast.List) else tuple(items)
        if isinstance(node, ast.Dict):
            return {
                read(k): read(v)
                for k, v in zip(node.keys, node.values, strict=True)
                if k is not None
            }
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and node.func.id == "dict"
            and not node.args
        ):
            return {kw.arg: read(kw.value) for kw in node.keywords if kw.arg is not None}
        if isinstance(node, (ast.Attribute, ast.Name)):
            return _class_named(key, ast.unparse(node))
        raise HyperparamsError(f"{key}: {ast.unparse(node)!r} is not allowed in {text!r}")

    return read(tree)


def _wrappers(raw: Any) -> list[tuple[Callable[..., Any], dict[str, Any]]]:
    """``env_wrapper`` entries as (class, kwargs), importing each."""
    import importlib

    entries = raw if isinstance(raw, list) else [raw]
    out: list[tuple[Callable[..., Any], dict[str, Any]]] = []
    for entry in entries:
        if isinstance(entry, dict):
            if len(entry) != 1:
                raise HyperparamsError(f"env_wrapper: {entry!r} is not {{path: kwargs}}")
            ((path, kwargs),) = entry.items()
        else:
            path, kwargs = entry, {}
        module, _, name = str(path).rpartition(".")
        try:
            cls = getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError, ValueError) as exc:
            raise HyperparamsError(f"env_wrapper: cannot import {path!r}: {exc}") from None
        out.append((cls, dict(kwargs or {})))
    return out


def resolve(section: Mapping[str, Any]) -> Hyperparams:
    """Stable-Baselines3's objects for a section (``n_timesteps`` is the caller's).

    Raises:
        HyperparamsError: A value that cannot be read (an unknown class, a bad schedule).
    """
    normalize = section.get("normalize", False)
    if isinstance(normalize, str):
        normalize = _literal("normalize", normalize)
    if normalize is True:
        normalize = {}
    elif normalize is False or normalize is None:
        normalize = None
    elif not isinstance(normalize, dict):
        raise HyperparamsError(f"normalize: {normalize!r} is not true, false or a dict")
    frame_stack = section.get("frame_stack")
    if frame_stack is not None and (
        isinstance(frame_stack, bool) or not isinstance(frame_stack, int)
    ):
        raise HyperparamsError(f"frame_stack: {frame_stack!r} is not an integer")
    n_envs = section.get("n_envs", 1)
    if isinstance(n_envs, bool) or not isinstance(n_envs, int) or n_envs < 1:
        raise HyperparamsError(f"n_envs: {n_envs!r} is not a positive integer")
    return Hyperparams(
        n_envs=n_envs,
        policy=str(section.get("policy", "MlpPolicy")),
        algo_kwargs={
            k: _value(k, v) for k, v in section.items() if k not in _ZOO_KEYS and k != "n_timesteps"
        },
        normalize=normalize,
        frame_stack=frame_stack or None,
        env_wrappers=_wrappers(section["env_wrapper"]) if section.get("env_wrapper") else [],
    )
