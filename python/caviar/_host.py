"""The Python half of the in-process bridge; the core calls these functions.

Kept in Python so that plugin loading, parameter checks and payload encoding are
the same code whatever the transport.
"""

from __future__ import annotations

import dataclasses
import gc
import importlib
import json
import os
import pathlib
import sys
import traceback
import types
import typing
import warnings
from importlib import metadata
from typing import Any

from caviar._core import RawMessage
from caviar.errors import ConfigError, ConfigWarning
from caviar.plugin import Context, Inbox, Message, PayloadKind, Plugin, building, encode, field_default
from caviar.topics import matches

OutgoingTuple = tuple[str, PayloadKind, "str | bytes", "str | None"]
"""A published message as the core takes it: ``(topic, kind, body, meta)``."""

ENTRY_POINT_GROUP = "caviar.plugins"


def format_exception(exc: BaseException, tb: types.TracebackType | None = None) -> str:
    return "".join(traceback.format_exception(type(exc), exc, tb or exc.__traceback__))


def resolve_plugin(spec: str) -> type[Plugin]:
    """``package.module:Class`` or an entry-point name of group ``caviar.plugins``."""
    if ":" in spec:
        module_name, _, attr = spec.partition(":")
        try:
            module = importlib.import_module(module_name)
        except ImportError as e:
            raise ConfigError(f"cannot import '{module_name}' for plugin '{spec}': {e}", "plugin") from None
        cls: Any = module
        for part in attr.split("."):
            cls = getattr(cls, part, None)
            if cls is None:
                raise ConfigError(f"module '{module_name}' has no '{attr}' (plugin '{spec}')", "plugin")
    else:
        eps = metadata.entry_points(group=ENTRY_POINT_GROUP)
        found = [ep for ep in eps if ep.name == spec]
        if not found:
            known = ", ".join(sorted(ep.name for ep in eps)) or "none installed"
            raise ConfigError(
                f"no plugin named '{spec}': expected 'package.module:Class' or an entry point "
                f"of group '{ENTRY_POINT_GROUP}' ({known})", "plugin")
        try:
            cls = found[0].load()
        except ImportError as e:
            raise ConfigError(f"cannot load plugin '{spec}' ({found[0].value}): {e}", "plugin") from None
    if not (isinstance(cls, type) and issubclass(cls, Plugin)):
        raise ConfigError(f"'{spec}' is not a subclass of caviar.Plugin", "plugin")
    return cls


def _type_ok(value: Any, hint: Any) -> bool:
    if hint is Any:
        return True
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_type_ok(value, h) for h in typing.get_args(hint))
    if hint is type(None):
        return value is None
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if origin in (list, tuple, typing.Sequence):
        args = typing.get_args(hint)
        if not isinstance(value, list):
            return False
        if origin is tuple and args and args[-1] is not Ellipsis:
            return len(args) == len(value) and all(_type_ok(v, h) for v, h in zip(value, args, strict=True))
        return not args or all(_type_ok(v, args[0]) for v in value)
    if origin is dict:
        return isinstance(value, dict)
    if isinstance(hint, type):
        return isinstance(value, hint)
    return True


def _type_name(hint: Any) -> str:
    if typing.get_origin(hint) is not None:  # list[float], not "list"
        return str(hint).replace("typing.", "")
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")


def _mismatch(value: Any, hint: Any) -> str:
    """Why ``value`` is not a ``hint``: the first offending item of a list."""
    table = _table_of(hint)
    if table is not None:
        keys = ", ".join(f.name for f in dataclasses.fields(table) if f.init)
        return f"expected a table ({keys}), got {type(value).__name__} {value!r}"
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (list, typing.Sequence) and args and isinstance(value, list):
        for i, v in enumerate(value):
            if not _type_ok(v, args[0]):
                return f"expected {_type_name(hint)}, item {i} is {type(v).__name__} {v!r}"
    if origin is tuple and args and args[-1] is not Ellipsis and isinstance(value, list) and len(value) != len(args):
        return f"expected {_type_name(hint)} ({len(args)} items), got {len(value)} items {value!r}"
    return f"expected {_type_name(hint)}, got {type(value).__name__} {value!r}"


def _keyed(e: Exception, fields: typing.Iterable[str], path: str = "params") -> ConfigError:
    """A plugin's check failing as ``ValueError("speed: must be > 0")`` (or a ConfigError
    with ``key="speed"``) becomes a ConfigError on ``params.speed`` (``path.speed`` for a
    nested table's check); a key inside a parameter's tables and arrays (``sites.1.array``)
    names its full path."""
    message = getattr(e, "message", None) or str(e)
    key = getattr(e, "key", None)
    if key is None:
        name, sep, rest = message.partition(": ")
        if sep and " " not in name and name.split(".")[0] in fields:
            key, message = name, rest
    if key is None:
        return ConfigError(message, path)
    return ConfigError(message, key if key.startswith("params") else f"{path}.{key}")


def check_params(cls: type[Plugin], params: dict[str, Any]) -> Any:
    """Builds the plugin's ``Params`` dataclass from the config table, or explains why not.
    A field typed as a dataclass (or ``X | None``) is a table of its own, and one typed
    ``list[X]`` an array of such tables, checked the same way, recursively: an error names
    the whole key path (``params.handover.time_to_trigger_s``, ``params.traffic.carry.0.topic``)."""
    schema = cls.Params
    if schema is None:
        return params
    if not dataclasses.is_dataclass(schema):
        raise TypeError(f"{cls.__name__}.Params must be a dataclass")
    return _build(schema, params, "params", cls.__name__)


def _table_of(hint: Any) -> Any:
    """The dataclass a field's type hint names (``X`` or ``X | None``), else None."""
    if dataclasses.is_dataclass(hint) and isinstance(hint, type):
        return hint
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        tables = [h for h in typing.get_args(hint) if dataclasses.is_dataclass(h) and isinstance(h, type)]
        return tables[0] if len(tables) == 1 else None
    return None


def _rows_of(hint: Any) -> Any:
    """The dataclass of a field typed as a list of tables (``list[X]``), else None."""
    if typing.get_origin(hint) is list:
        args = typing.get_args(hint)
        if len(args) == 1 and dataclasses.is_dataclass(args[0]) and isinstance(args[0], type):
            return args[0]
    return None


def _example(new_key: str, value: Any) -> str:
    """``table = { key = value }`` for a moved key's message (TOML-like)."""
    *tables, key = new_key.split(".")
    text = json.dumps(value) if isinstance(value, (bool, int, float, str)) else repr(value)
    text = text.lower() if isinstance(value, bool) else text
    for table in reversed(tables):
        text = f"{{ {key} = {text} }}"
        key = table
    return f"{key} = {text}"


def _key_paths(params: dict[str, Any], prefix: str = "") -> list[str]:
    """Every key a table wrote, those of its nested tables as dotted paths (``raytracing.los``)."""
    keys = []
    for key, value in params.items():
        keys.append(prefix + key)
        if isinstance(value, dict):
            keys += _key_paths(value, f"{prefix}{key}.")
    return keys


def _build(schema: Any, params: dict[str, Any], path: str, owner: str, base: Any = None,
           moved_here: dict[str, str] | None = None) -> Any:
    """``schema(**params)`` with every key, type and nested table checked; errors name
    ``path.key`` (``path`` is ``params`` or the key path of a nested table). A nested table
    starts from its field's default (``base``: the plugin's defaults for the keys the
    configuration leaves out). A key the schema lists in its ``moved`` mapping (a class
    attribute: old key -> new key path within the same table; a dotted old key names a key of
    a nested table; ``moved_here`` holds those of the tables above, their new keys in full) is
    refused with the new key named in full."""
    hints = typing.get_type_hints(schema)
    fields = {f.name: f for f in dataclasses.fields(schema) if f.init}
    values: dict[str, Any] = {}
    if base is not None:
        values = {name: getattr(base, name) for name in fields if hasattr(base, name)}
    here = path.partition(".")[2]  # (this table's key path within params: "" at the top)
    moved: dict[str, str] = {old: f"{here}.{new}" if here else new
                             for old, new in (getattr(schema, "moved", None) or {}).items()}
    moved.update(moved_here or {})  # (the tables above name their new keys in full)
    for key, value in params.items():
        where = f"{path}.{key}"
        if key not in fields:
            if key in moved:
                raise ConfigError(f"'{key}' has moved: write it as {moved[key]} (for example "
                                  f"{_example(moved[key], value)})", where)
            raise ConfigError(f"unknown parameter '{key}' of {owner}, expected one of: "
                              f"{', '.join(fields) or 'none'}", where)
        hint = hints.get(key, Any)
        table = _table_of(hint)
        if table is not None and isinstance(value, dict):
            default = field_default(fields[key])
            inner = {old[len(key) + 1:]: new for old, new in moved.items() if old.startswith(f"{key}.")}
            values[key] = _build(table, value, where, f"{owner}.{key}",
                                 base=default if isinstance(default, table) else None, moved_here=inner)
            continue
        rows = _rows_of(hint)
        if rows is not None and isinstance(value, list):  # an array of tables, each checked
            for i, row in enumerate(value):
                if not isinstance(row, dict):
                    raise ConfigError(_mismatch(row, rows), f"{where}.{i}")
            values[key] = [_build(rows, row, f"{where}.{i}", f"{owner}.{key}") for i, row in enumerate(value)]
            continue
        if not _type_ok(value, hint):
            raise ConfigError(_mismatch(value, hint), where)
        values[key] = float(value) if hint is float else value
    missing = [n for n, f in fields.items() if n not in params
               and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    if missing:
        raise ConfigError(f"missing required parameter(s) of {owner}: {', '.join(missing)}", path)
    try:
        with building(_key_paths(params)), warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            built = schema(**values)  # (what the configuration wrote: caviar.given_keys())
    except (TypeError, ValueError) as e:  # __post_init__ checks of the plugin
        raise _keyed(e, fields, path) from None
    _warn_again(caught, path)
    return built


def _warn_again(caught: list[warnings.WarningMessage], path: str) -> None:
    """Issues again the warnings caught while a table at ``path`` was built: a
    :class:`~caviar.errors.ConfigWarning`'s key made the full path (``params.traffic.by_type.Tank``)."""
    for w in caught:
        m = w.message
        if isinstance(m, ConfigWarning):
            key = path if m.key is None else m.key if m.key.startswith("params") else f"{path}.{m.key}"
            warnings.warn(ConfigWarning(m.message, key), stacklevel=2)
        else:
            warnings.warn_explicit(m, w.category, w.filename, w.lineno)


class Hosted:
    """One plugin instance and its context, as the core sees it."""

    def __init__(self, name: str, plugin: Plugin, params: Any):
        self.name = name
        self.plugin = plugin
        self.params = params
        self.ctx: Context | None = None
        self.run_dir: pathlib.Path | None = None
        self.settled = False  # (what its set-up and first step made is frozen for the collector)

    def setup(self, seed: int, ts: float, steps: int | None, every: int, offset: int,
              run_dir: str | os.PathLike[str], config_dir: str | os.PathLike[str], shards: int = 1) -> None:
        if shards > 1 and not type(self.plugin).shardable:
            raise ConfigError(f"{type(self.plugin).__name__} cannot split a step into shards "
                              f"(it does not declare shardable = True)", "shards")
        # Absolute: artifact paths are recorded relative to it, whatever the current directory.
        self.run_dir = pathlib.Path(run_dir).resolve()
        self.ctx = Context(name=self.name, params=self.params, seed=seed, ts=ts, steps=steps,
                           every=every, offset=offset, run_dir=self.run_dir,
                           config_dir=pathlib.Path(config_dir), shards=shards)
        self.plugin.setup(self.ctx)
        self.settled = False
        gc.freeze()  # (what set-up made: see settle)

    def step(self, step: int, t: float, raw: list[RawMessage], shard: int = 0) -> list[OutgoingTuple]:
        """Runs the plugin's step; returns what it published as ``(topic, kind, body, meta)``."""
        ctx = self.ctx
        assert ctx is not None, "the core calls setup before step"
        ctx.step = step
        ctx.shard = shard
        run_dir = self.run_dir
        inbox = Inbox([Message._from_wire(r, run_dir) for r in raw])
        try:
            return self._published(self.plugin.step(t, inbox), run_dir)
        finally:
            if not self.settled:
                self.settle()

    def _published(self, result: Any, run_dir: pathlib.Path | None) -> list[OutgoingTuple]:
        """What a step returned or yielded, as ``(topic, kind, body, meta)``."""
        out: list[OutgoingTuple] = []
        if result is None:
            return out
        # A single message may be returned bare.
        if isinstance(result, Message) or (isinstance(result, tuple) and len(result) == 2
                                           and isinstance(result[0], str)):
            result = [result]
        for item in result:
            if isinstance(item, Message):
                topic, value = item.topic, item.data
            else:
                try:
                    topic, value = item
                except (TypeError, ValueError):
                    raise TypeError(f"{type(self.plugin).__name__}.step must return messages as "
                                    f"(topic, payload) pairs or caviar.Message, got {item!r}") from None
            if not isinstance(topic, str):
                raise TypeError(f"topic must be a str, got {topic!r}")
            out.append((topic, *encode(topic, value, run_dir)))
        return out

    def settle(self) -> None:
        """After the first step (where plugins trace, compile and load lazily; :meth:`setup` does
        the same after set-up): the objects the process holds then (Sionna's scene, torch's
        compiled code, the plugins' tables) are frozen out of Python's cyclic garbage collector
        (``gc.freeze``), so that the collections a step's allocations trigger no longer walk
        them, up to several ms a step with torch and Sionna loaded; :meth:`teardown` gives them
        back to it. The freeze is the process's: a cycle that becomes garbage meanwhile, this
        run's or another's, waits for a teardown to be collected."""
        self.settled = True
        gc.freeze()

    def teardown(self) -> None:
        try:
            self.plugin.teardown()
        finally:
            gc.unfreeze()  # (what was frozen is collected again, at exit too)

    def state(self) -> tuple[str, Any]:
        """For a checkpoint: ``("stateless", None)``, ``("saved", bytes)`` (the plugin's
        :meth:`~caviar.Plugin.state` and its ``ctx.rng``'s position, pickled: a stateless
        plugin that draws random numbers has its stream saved too) or
        ``("unsupported", why)``."""
        import pickle

        cls = type(self.plugin)
        hooks = cls.state is not Plugin.state and cls.restore is not Plugin.restore
        rng = self.ctx.__dict__.get("_rng") if self.ctx is not None else None
        if not hooks and not cls.stateless:
            return "unsupported", (f"plugin {cls.__module__}.{cls.__qualname__} has no state()/restore() "
                                   f"hooks and does not declare stateless = True")
        if not hooks and rng is None:
            return "stateless", None
        saved = {"hooks": hooks, "plugin": self.plugin.state() if hooks else None,
                 "rng": rng.bit_generator.state if rng is not None else None}
        return "saved", pickle.dumps(saved, protocol=pickle.HIGHEST_PROTOCOL)

    def restore(self, data: bytes) -> None:
        import pickle

        saved = pickle.loads(data)
        if saved["rng"] is not None:
            assert self.ctx is not None, "the core calls setup before restore"
            self.ctx.rng.bit_generator.state = saved["rng"]
        if saved["hooks"]:
            self.plugin.restore(saved["plugin"])


def declared_publishes(cls: type[Plugin]) -> list[str]:
    """The plugin's ``publishes`` as a list of valid patterns (empty: not declared)."""
    declared = cls.publishes
    if isinstance(declared, str) or not all(isinstance(p, str) for p in declared):
        raise ConfigError(f"{cls.__name__}.publishes must be a tuple of topic names or patterns, "
                          f"got {declared!r}", "plugin")
    for p in declared:
        try:
            matches(p, "x")
        except ValueError as e:
            raise ConfigError(f"{cls.__name__}.publishes: {e}", "plugin") from None
    return list(declared)


def load_plugin(name: str, spec: str, params_json: str, config_dir: str
                ) -> tuple[Hosted, list[str], list[str], list[str], list[tuple[str, str]]]:
    """The hosted plugin, its default subscriptions, what it declares publishing, which of
    its default subscriptions are optional inputs, and the inputs its parameters name
    (pattern, key)."""
    cls = resolve_plugin(spec)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        params = check_params(cls, json.loads(params_json))
        plugin_cls = cls
        try:
            plugin_cls.check_params(params, pathlib.Path(config_dir))
        except (TypeError, ValueError) as e:  # ConfigError is a ValueError
            schema = plugin_cls.Params
            fields = [f.name for f in dataclasses.fields(schema)] if dataclasses.is_dataclass(schema) else params
            raise _keyed(e, fields) from None
    for w in caught:  # (a ConfigWarning as the core prints its own warnings, naming the key)
        m = w.message
        if isinstance(m, ConfigWarning):
            print(f"warning: modules.{name}.{m.key or 'params'}: {m.message}", file=sys.stderr, flush=True)
        else:
            warnings.warn_explicit(m, w.category, w.filename, w.lineno)
    publishes = declared_publishes(cls)
    required = [(pattern, key) for pattern, key in cls.inputs(params).items()]
    subscribe = list(dict.fromkeys([*cls.subscribe, *(p for p, _ in required)]))
    if publishes:
        publishes = list(dict.fromkeys([*publishes, *cls.outputs(params)]))
    # (A subclass that narrows ``subscribe`` keeps the optional inputs it still has.)
    optional = [o for o in cls.optional if o in cls.subscribe]
    plugin = cls()
    return Hosted(name, plugin, params), subscribe, publishes, optional, required
