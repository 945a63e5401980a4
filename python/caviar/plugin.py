"""The plugin API: what a module written in Python implements.

A plugin is a class with three methods, in the spirit of Gymnasium's ``step()``::

    class Echo(caviar.Plugin):
        subscribe = ["3D.mobility.positions"]      # default subscriptions

        @dataclasses.dataclass
        class Params:                              # checked against [modules.NAME.params]
            gain: float = 1.0

        def setup(self, ctx):
            self.gain = ctx.params.gain

        def step(self, t, inbox):
            for m in inbox.on("3D.mobility.positions"):
                yield "echo.positions", {"x": m.data["position"]["x"] * self.gain}

``step`` returns (or yields) messages: ``(topic, payload)`` pairs or
:class:`Message` objects. The payload's type decides how it travels:

* ``dict``, ``list``, ``str``, numbers, ``bool``, ``None``: JSON;
* ``numpy.ndarray``: binary, with its dtype and shape (never through JSON);
* ``polars.DataFrame``: a table, binary in Apache Arrow's IPC stream format (a column a field:
  for many rows of numbers a step, a fraction of JSON's cost to make, encode and read), read
  back as a ``polars.DataFrame``;
* ``bytes``: binary;
* :class:`Artifact` or :class:`pathlib.Path` (a file in the run directory): its path.

A plugin knows nothing of transports: the same class runs in-process or elsewhere.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import json
import math
import pathlib
import typing
from typing import TYPE_CHECKING, Any, ClassVar, Iterable, Iterator, Literal, Sequence, overload

from caviar.topics import matches

if TYPE_CHECKING:
    import numpy as np

    from caviar._core import RawMessage

PayloadKind = Literal["json", "binary", "artifact"]
"""How a payload travels (the core's ``caviar._core.PayloadKind``)."""


class Artifact:
    """A file in the run directory, passed to subscribers by its path."""

    __slots__ = ("path",)

    def __init__(self, path: str | pathlib.Path):
        self.path = pathlib.Path(path)

    def __repr__(self) -> str:
        return f"Artifact({str(self.path)!r})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Artifact) and other.path == self.path


class Message:
    """A message: topic, payload and, once routed, who published it and when.

    ``data`` is decoded on first access: JSON to Python objects, arrays to read-only
    ``numpy.ndarray`` views, tables to ``polars.DataFrame``, artifacts to
    :class:`pathlib.Path` in the run directory.
    """

    __slots__ = ("topic", "source", "step", "time", "_data", "_raw", "_kind")

    def __init__(self, topic: str, data: Any = None, *, source: str | None = None,
                 step: int | None = None, time: float | None = None):
        self.topic = topic
        self.source = source
        self.step = step
        self.time = time
        self._data = data
        # (kind, body, meta, run_dir) of a message from the wire, until decoded.
        self._raw: tuple[PayloadKind, str | bytes, str | None, pathlib.Path | None] | None = None
        self._kind: PayloadKind | None = None

    @classmethod
    def _from_wire(cls, raw: RawMessage, run_dir: pathlib.Path | None) -> "Message":
        m = cls(raw.topic, source=raw.source, step=raw.step, time=raw.time)
        m._raw = (raw.kind, raw.body, raw.meta, run_dir)
        m._kind = raw.kind
        return m

    @property
    def kind(self) -> str:
        """``"json"``, ``"binary"`` or ``"artifact"``."""
        if self._kind is None:
            self._kind = encode(self.topic, self._data, None)[0]
        return self._kind

    @property
    def data(self) -> Any:
        if self._raw is not None:
            self._data = decode(*self._raw)
            self._raw = None
        return self._data

    def __repr__(self) -> str:
        where = f" from {self.source} at step {self.step}" if self.source else ""
        return f"Message({self.topic!r}{where})"


class Inbox(Sequence[Message]):
    """The messages a module received since its previous step, in delivery order."""

    def __init__(self, messages: list[Message]):
        self._messages = messages

    @overload
    def __getitem__(self, i: int) -> Message: ...

    @overload
    def __getitem__(self, i: slice) -> list[Message]: ...

    def __getitem__(self, i: int | slice) -> Message | list[Message]:
        return self._messages[i]

    def __len__(self) -> int:
        return len(self._messages)

    def __iter__(self) -> Iterator[Message]:
        return iter(self._messages)

    def on(self, pattern: str) -> list[Message]:
        """Messages whose topic matches ``pattern`` (NATS wildcards allowed)."""
        return [m for m in self._messages if matches(pattern, m.topic)]

    def latest(self, pattern: str) -> Message | None:
        """The last message matching ``pattern``, or None."""
        for m in reversed(self._messages):
            if matches(pattern, m.topic):
                return m
        return None

    def __repr__(self) -> str:
        return f"Inbox({len(self)} messages)"


@dataclasses.dataclass
class Context:
    """What a plugin learns in ``setup``."""

    name: str
    """The module's name in the configuration."""
    params: Any
    """The ``Params`` dataclass instance (or a dict if the plugin declares none)."""
    seed: int
    """The module's own seed (derived from the episode seed and the module name)."""
    ts: float
    """Sampling interval Ts in seconds."""
    steps: int | None
    """Steps in the episode, or None when a module ends it."""
    every: int
    offset: int
    run_dir: pathlib.Path
    config_dir: pathlib.Path
    step: int = 0
    """The step being run (updated before each ``step`` call)."""
    shard: int = 0
    """Which piece of the step this call computes, for plugins split across workers
    (``shards`` in the module's table, NATS transport); 0 of 1 otherwise."""
    shards: int = 1

    @property
    def rng(self) -> np.random.Generator:
        """A ``numpy.random.Generator`` seeded with :attr:`seed` (created once)."""
        rng = self.__dict__.get("_rng")
        if rng is None:
            import numpy as np

            rng = self.__dict__["_rng"] = np.random.default_rng(self.seed)
        return rng

    def resolve(self, path: str | pathlib.Path) -> pathlib.Path:
        """A path from the parameters, relative to the configuration file."""
        p = pathlib.Path(path)
        return p if p.is_absolute() else self.config_dir / p

    @property
    def artifact_dir(self) -> pathlib.Path:
        """``RUN_DIR/artifacts/NAME``, created on first use."""
        d = self.run_dir / "artifacts" / self.name
        d.mkdir(parents=True, exist_ok=True)
        return d


_GIVEN: contextvars.ContextVar[frozenset[str] | None] = contextvars.ContextVar("caviar_params_given", default=None)


def given_keys() -> frozenset[str] | None:
    """While the plugin host builds a ``Params`` dataclass (in its ``__post_init__``): the
    keys the configuration wrote for that table; None when the dataclass is built in
    Python code."""
    return _GIVEN.get()


@contextlib.contextmanager
def building(keys: typing.Iterable[str]) -> typing.Iterator[None]:
    """The plugin host's side of :func:`given_keys`."""
    token = _GIVEN.set(frozenset(keys))
    try:
        yield
    finally:
        _GIVEN.reset(token)


def apply_preset(params: Any, preset: typing.Mapping[str, Any], name: str) -> None:
    """Sets the fields of a ``Params`` dataclass that a preset fixes (``protocol = "paper"``)
    and refuses, naming the key, one that the configuration set to another value: a preset
    never overrides what a user wrote. Built in Python code (no configuration), a field
    that differs from both its default and the preset's value is refused likewise. A key
    may be a dotted path into a nested table (``raytracing.los``; a frozen table is
    replaced by a copy)."""
    given = given_keys()
    for key, value in preset.items():
        *tables, field = key.split(".")
        owner, chain = params, []
        for table in tables:
            chain.append((owner, table))
            owner = getattr(owner, table)
        default = next(field_default(f) for f in dataclasses.fields(owner) if f.name == field)
        default = None if default is dataclasses.MISSING else default
        current = getattr(owner, field)
        set_by_user = key in given if given is not None else current != default
        if set_by_user and current != value:
            raise ValueError(f"{key}: {name} sets it to {value!r}; the configuration gives {current!r} "
                             f"(remove the key, or choose another preset)")
        value = list(value) if isinstance(value, list) else value
        if not tables:
            setattr(params, field, value)
            continue
        updated = dataclasses.replace(owner, **{field: value})
        for parent, table in reversed(chain):
            if parent is params:
                setattr(params, table, updated)
            else:
                updated = dataclasses.replace(parent, **{table: updated})


def field_default(field: dataclasses.Field) -> Any:
    """A dataclass field's default value (made by its factory), or ``dataclasses.MISSING``."""
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return dataclasses.MISSING


class Plugin:
    """Base class of Python modules. Override what you need; ``step`` is the one
    most plugins implement, and ``publishes`` lets ``validate`` check the wiring."""

    subscribe: ClassVar[list[str]] = []
    """Default subscription patterns; ``subscribe`` in the config replaces them."""

    publishes: ClassVar[tuple[str, ...]] = ()
    """Topics (or patterns) the plugin may publish; ``()``: not declared (it may
    publish anything). ``caviar-core validate`` warns about subscriptions that no
    module publishes and publications that no module subscribes to."""

    optional: ClassVar[tuple[str, ...]] = ()
    """Default subscriptions the plugin works without (optional inputs; those not among
    ``subscribe`` are ignored): ``validate`` does not warn when no module publishes them. A
    subscription the configuration writes itself still warns."""

    Params: ClassVar[type | None] = None
    """A dataclass describing ``[modules.NAME.params]``: unknown keys, missing
    values and wrong types become configuration errors naming the key."""
    stateless: ClassVar[bool] = False
    """True when the plugin keeps nothing across steps that changes what it publishes
    (all it needs comes from ``setup`` and the step's inbox): a resumed run
    (``caviar-core run --resume``) sets it up again and goes on. A plugin with state
    implements :meth:`state` and :meth:`restore` instead; one with neither cannot be
    resumed (``--resume`` says so, naming it)."""
    shardable: ClassVar[bool] = False
    """True when ``step`` can compute one piece of the work (``ctx.shard`` of
    ``ctx.shards``) from the inbox alone, so that several workers can share a step.
    The pieces' messages are merged in shard order."""

    @classmethod
    def inputs(cls, params: Any) -> dict[str, str]:
        """Inputs the parameters name, beyond ``subscribe``: ``{pattern: key}``, the key of
        ``[modules.NAME.params]`` that names it (``"params.traffic.carry.0.topic"``). The
        module subscribes to them too, and a configuration in which no other module publishes
        one is refused before anything runs, naming that key."""
        return {}

    @classmethod
    def outputs(cls, params: Any) -> tuple[str, ...]:
        """Topics (or patterns) the parameters add to ``publishes``."""
        return ()

    @classmethod
    def check_params(cls, params: Any, config_dir: pathlib.Path) -> None:
        """Checks the parameters at ``validate`` time (and before a run directory
        exists), beyond what their types say: ranges, files that must exist.
        ``params`` is the ``Params`` instance, ``config_dir`` the directory relative
        paths are resolved against. Raise ``ValueError("KEY: what was expected")`` or
        ``caviar.ConfigError(message, "KEY")``; the error is reported as
        ``file:line: modules.NAME.params.KEY: …``. (A ``Params.__post_init__`` raising
        ``ValueError("KEY: …")`` is reported the same way.)"""
        return None

    def setup(self, ctx: Context) -> None:
        self.ctx = ctx

    def step(self, t: float, inbox: Inbox) -> Iterable[Message | tuple[str, Any]] | None:
        return None

    def teardown(self) -> None:
        pass

    def state(self) -> Any:
        """What the plugin must keep to go on after a crash, taken between two steps at
        each checkpoint (``output.checkpoint_every``): anything ``pickle`` can write.
        ``ctx.rng`` is saved with it by the host. Implement with :meth:`restore`."""
        raise NotImplementedError

    def restore(self, state: Any) -> None:
        """Puts back what :meth:`state` returned, after ``setup``, before the next step
        of a resumed run."""
        raise NotImplementedError


# ---------------------------------------------------------------------------
# Payload encoding (Python object <-> wire tuple)

ARROW_STREAM = "application/vnd.apache.arrow.stream"
"""The content type of a table payload (a ``polars.DataFrame``): Arrow's IPC stream format."""
_TABLE_META = json.dumps({"content_type": ARROW_STREAM}, separators=(",", ":"))


def _is_table(value: Any) -> bool:
    return type(value).__name__ == "DataFrame" and type(value).__module__.startswith("polars")


def _check_json(topic: str, value: Any) -> str:
    try:
        return json.dumps(value, separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError) as e:
        raise TypeError(
            f"payload on topic '{topic}' is not JSON-serialisable ({e}); send numpy arrays "
            "or bytes as binary payloads, files as caviar.Artifact"
        ) from None


def encode(topic: str, value: Any, run_dir: pathlib.Path | None) -> tuple[PayloadKind, Any, str | None]:
    """(kind, body, meta) of a payload."""
    if isinstance(value, (Artifact, pathlib.PurePath)):
        path = pathlib.Path(value.path if isinstance(value, Artifact) else value)
        if path.is_absolute():
            if run_dir is None:
                raise ValueError(f"artifact on topic '{topic}': no run directory to relate {path} to")
            try:
                path = path.resolve().relative_to(run_dir.resolve())
            except ValueError:
                raise ValueError(f"artifact on topic '{topic}': {path} is not inside the run directory "
                                 f"{run_dir}") from None
        return "artifact", path.as_posix(), None
    if isinstance(value, (bytes, bytearray, memoryview)):
        return "binary", bytes(value), '{"content_type":"application/octet-stream"}'
    if _is_table(value):
        import io

        out = io.BytesIO()
        value.write_ipc_stream(out)
        return "binary", out.getvalue(), _TABLE_META
    if type(value).__module__ == "numpy" and hasattr(value, "dtype"):
        import numpy as np

        arr = np.ascontiguousarray(value)
        if arr.dtype.hasobject:
            raise TypeError(f"payload on topic '{topic}': object arrays cannot travel as binary")
        meta = json.dumps({"dtype": arr.dtype.str, "shape": list(arr.shape)}, separators=(",", ":"))
        return "binary", arr.tobytes(), meta
    if isinstance(value, float) and not math.isfinite(value):
        raise TypeError(f"payload on topic '{topic}' is {value}, which JSON cannot carry")
    return "json", _check_json(topic, value), None


def decode(kind: str, body: Any, meta: str | None, run_dir: pathlib.Path | None) -> Any:
    if kind == "json":
        return json.loads(body)
    if kind == "artifact":
        return (run_dir / body) if run_dir is not None else pathlib.Path(body)
    info = json.loads(meta) if meta else {}
    if info.get("content_type") == ARROW_STREAM:
        import io

        import polars as pl

        return pl.read_ipc_stream(io.BytesIO(body))
    if "dtype" in info:
        import numpy as np

        return np.frombuffer(body, dtype=np.dtype(info["dtype"])).reshape(info["shape"])
    return body
