"""The one place where Hydra configs become objects, and the allow-list that keeps configs from running code.

Every component (dataset, model, rasterizer, loss, ...) is built here. A config names what to build
with ``_target_``; since configs come from files and the command line, every ``_target_`` at every
depth is checked BEFORE anything is built:

* it must resolve to a class or function *defined* in the project's own package ``src`` (its
  ``__module__.__qualname__`` is the target itself, so ``src.run.torch.load`` -- torch reached
  through a project module's namespace -- is refused), or be one of :data:`EXTRA_TARGETS`;
* the keys of the node must be parameters of that callable, so a config meant for another reader
  or model fails with one line naming the node, the key and what the callable accepts, instead of a
  ``TypeError`` from inside Hydra.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Iterator
from typing import Any

from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, ListConfig, OmegaConf

#: The package whose callables configs may build.
PROJECT_PACKAGE = "src"
#: Callables outside the project that a config may name (none is needed by the shipped configs).
EXTRA_TARGETS: frozenset[str] = frozenset()
#: Hydra's own instantiate keys (not parameters of the target).
HYDRA_KEYS = frozenset({"_target_", "_partial_", "_convert_", "_recursive_", "_args_"})


class ConfigError(ValueError):
    """A config node that cannot be built: unknown or forbidden ``_target_``, or keys the target does not take."""


def iter_targets(node: Any, path: str = "") -> Iterator[tuple[str, str]]:
    """Yield (dotted path of the node, its ``_target_``) for every node with a ``_target_``, at every depth.

    OmegaConf containers are walked unresolved (an interpolated ``_target_`` is checked as written,
    hence refused), so nothing is evaluated before the check.
    """
    if isinstance(node, DictConfig | ListConfig):
        node = OmegaConf.to_container(node, resolve=False)
    if isinstance(node, dict):
        if "_target_" in node:
            yield path or "<root>", str(node["_target_"])
        for k, child in node.items():
            yield from iter_targets(child, f"{path}.{k}" if path else str(k))
    elif isinstance(node, list | tuple):
        for i, child in enumerate(node):
            yield from iter_targets(child, f"{path}[{i}]")


def _name_of(obj: Any) -> str:
    """Where ``obj`` is defined: a module's name, or ``module.qualname`` of a class or function."""
    if inspect.ismodule(obj):
        return obj.__name__
    return f"{getattr(obj, '__module__', '?')}.{getattr(obj, '__qualname__', type(obj).__name__)}"


def _inside_project(obj: Any) -> bool:
    """True for a module of the project's package, or a class / function defined in one."""
    name = obj.__name__ if inspect.ismodule(obj) else getattr(obj, "__module__", None)
    if not isinstance(name, str):
        return False
    return name == PROJECT_PACKAGE or name.startswith(PROJECT_PACKAGE + ".")


def _resolve_target(target: str, where: str) -> Any:
    """Import and return the callable named ``target`` if the allow-list admits it (ConfigError otherwise)."""
    if target in EXTRA_TARGETS:
        module_name, _, attr = target.rpartition(".")
        return getattr(importlib.import_module(module_name), attr)
    parts = target.split(".")
    if parts[0] != PROJECT_PACKAGE or len(parts) < 2 or not all(p.isidentifier() for p in parts):
        raise ConfigError(f"{where}: _target_ {target!r} is not allowed: only callables defined in the project's "
                          f"package {PROJECT_PACKAGE!r} may be built from a config")
    obj: Any = None
    for i in range(len(parts) - 1, 0, -1):  # longest importable module prefix, then attributes
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for attr in parts[i:]:
            if not _inside_project(obj):  # e.g. src.run.torch.load: torch reached through a project module
                raise ConfigError(f"{where}: _target_ {target!r} is not allowed: it passes through "
                                  f"{_name_of(obj)!r}, which is not part of the project's package")
            try:
                obj = getattr(obj, attr)
            except AttributeError:
                raise ConfigError(f"{where}: _target_ {target!r} does not exist") from None
        break
    else:
        raise ConfigError(f"{where}: _target_ {target!r} does not exist")
    if not callable(obj) or inspect.ismodule(obj) or not _inside_project(obj):
        raise ConfigError(f"{where}: _target_ {target!r} is not allowed: it resolves to {_name_of(obj)!r}, not to "
                          f"a class or function defined in the project's package")
    return obj


def _named(sig: inspect.Signature) -> tuple[list[str], bool]:
    """(names a signature takes by keyword, whether it also takes ``**kwargs``); ``self`` left out."""
    params = [p for p in sig.parameters.values() if p.name != "self"]
    by_name = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    return ([p.name for p in params if p.kind in by_name],
            any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params))


def _base_keywords(cls: type) -> list[str] | None:
    """The names a class's ``**kwargs`` reach when its ``__init__`` hands them to its base class.

    Walks the MRO past ``cls`` to the ``__init__`` of each base that defines one: a base of the project's
    package adds its named parameters, and the walk stops at the first that takes no ``**kwargs``
    (``SugarLoss`` -> ``SplatLoss``). None where the walk reaches a base outside the package (e.g.
    ``torch.nn.Module``) or one that takes ``**kwargs`` it never forwards: any name may then be taken.
    """
    names: list[str] = []
    for base in cls.__mro__[1:]:
        init = base.__dict__.get("__init__")
        if init is None:
            continue
        if not _inside_project(base):
            return None
        try:
            more, open_ended = _named(inspect.signature(init))
        except (TypeError, ValueError):
            return None
        names += [n for n in more if n not in names]
        if not open_ended:
            return names
    return None


def _accepted(obj: Any) -> tuple[set[str] | None, list[str]]:
    """(parameter names ``obj`` accepts by keyword, or None if it takes any ``**kwargs``; names for messages).

    A callable whose ``**kwargs`` take only certain names lists them in ``extra_keywords``
    (``SplatFieldNetwork``'s flat head keys); they are checked as parameters. A class whose ``**kwargs`` go
    to its base class's ``__init__`` takes that base's named parameters too (:func:`_base_keywords`).
    """
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):
        return None, []
    names, open_ended = _named(sig)
    if open_ended:
        extra = getattr(obj, "extra_keywords", None)
        if extra is None and inspect.isclass(obj):
            extra = _base_keywords(obj)
        if extra is None:
            return None, names
        names += [n for n in extra if n not in names]
    return set(names), names


def takes(cfg: DictConfig | dict, **optional: Any) -> dict[str, Any]:
    """Those of ``optional`` that the target of ``cfg`` takes by name (as :func:`check_targets` sees them).

    For runtime objects only some components use, e.g. ``build(cfg.loss, **takes(cfg.loss, extent=...))``:
    a loss that takes the scene's extent gets it, the others are built as before. A target that takes any
    ``**kwargs`` gets them all.
    """
    target = cfg.get("_target_") if isinstance(cfg, dict | DictConfig) else None
    if target is None:
        return {}
    accepted, _ = _accepted(_resolve_target(str(target), "config"))
    return dict(optional) if accepted is None else {k: v for k, v in optional.items() if k in accepted}


def check_targets(cfg: Any, root: str = "") -> None:
    """Check every ``_target_`` in ``cfg`` (allow-list) and that each node's keys are parameters of its target.

    Args:
        cfg: a config tree (DictConfig, dict, list). A top-level ``hydra`` node is skipped (Hydra's own).
        root: dotted name of ``cfg`` in the whole config, used in messages (e.g. ``dataset``).

    Raises:
        ConfigError: one line naming the node, the target and the offending key.
    """
    plain = OmegaConf.to_container(cfg, resolve=False) if isinstance(cfg, DictConfig | ListConfig) else cfg
    nodes = []
    for path, target in iter_targets(plain):  # first every target against the allow-list ...
        if root == "" and path.split(".", 1)[0].split("[", 1)[0] == "hydra":
            continue
        where = root if path == "<root>" and root else (f"{root}.{path}" if root and path != "<root>" else path)
        nodes.append((path, target, where, _resolve_target(target, where)))
    for path, target, where, obj in nodes:  # ... then each node's keys against its target's parameters
        accepted, names = _accepted(obj)
        if accepted is None:
            continue
        node = plain if path == "<root>" else _select_plain(plain, path)
        keys = {str(k) for k in node.keys()} - HYDRA_KEYS
        unknown = sorted(keys - accepted)
        if unknown:
            raise ConfigError(f"{where}: {target} does not take {', '.join(repr(k) for k in unknown)} "
                              f"(it takes: {', '.join(names)}); this config group option is not meant for "
                              f"this component")


def _select_plain(cfg: Any, path: str) -> Any:
    """The node at dotted ``path`` (with ``[i]`` list indices) of a plain dict/list tree."""
    node = cfg
    for part in path.replace("[", ".[").split("."):
        if not part:
            continue
        node = node[int(part[1:-1])] if part.startswith("[") else node[part]
    return node


def build(cfg: DictConfig | dict, **kwargs: Any) -> Any:
    """Instantiate ``cfg`` (a node with ``_target_``), passing runtime-only objects as ``kwargs``.

    Every nested ``_target_`` is checked against the allow-list first (:func:`check_targets`).

    Raises:
        ConfigError (a ValueError): no ``_target_``, a target outside the allow-list, or keys it does not take.
    """
    target = cfg.get("_target_") if isinstance(cfg, dict | DictConfig) else None
    name = cfg._get_full_key(None) if isinstance(cfg, DictConfig) and cfg._get_parent() is not None else ""
    if target is None:
        keys = list(cfg.keys()) if isinstance(cfg, dict | DictConfig) else type(cfg).__name__
        raise ConfigError(f"{name or 'config'}: cannot build a component from a config without _target_ "
                          f"(keys: {keys})")
    check_targets(cfg, root=str(name))
    if isinstance(cfg, dict):
        cfg = OmegaConf.create(cfg)
    try:
        return instantiate(cfg, _convert_="all", **kwargs)
    except InstantiationException as e:
        cause = _project_error(e)
        if cause is None:
            raise
        raise cause from None  # the component's own one-line message, not Hydra's four-line wrapper


def _project_error(e: BaseException) -> ValueError | None:
    """The first ``ValueError`` defined in the project (e.g. ``DatasetError``) in ``e``'s cause chain, or None.

    Such errors describe what the user gave (a missing dataset root, a malformed file): they keep their
    one-line message when a component raises them while Hydra builds it.
    """
    seen: set[int] = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, ValueError) and type(e).__module__.split(".")[0] == PROJECT_PACKAGE:
            return e
        e = e.__cause__ or e.__context__
    return None
