"""The pipeline: stages registered by name, messages routed to them by type.

Every source's messages (:data:`SOURCE_TYPES`: ``WheelTicks``, ``YawRate``, ``Frame``, ...)
are published to the :class:`Pipeline`, which hands each one to the stages that subscribe
to its type, in the order the stages were registered. A stage may publish further
messages; they are delivered at once, depth first, so one input is handled completely
before the next and a run is deterministic. Messages are frozen: a stage never changes what
it received, it publishes a new message of its own type (the floor stage turns a
:class:`~robotd.base.messages.Keyframe` into a
:class:`~robotd.base.messages.DescribedKeyframe`, visual odometry that into a
:class:`~robotd.base.messages.MeasuredKeyframe`, the map writer publishes the
:class:`~robotd.base.messages.StoredKeyframe` with its id), so the order in which a
keyframe passes the stages follows from the types, not from the order of registration.

Each stage declares what it ``produces`` and which of its subscriptions are
``optional_inputs`` (messages that may never come, e.g. forward loops without a forward
camera); :meth:`Pipeline.missing_inputs` lists every other subscription that neither a
source nor a registered stage produces, and the assembly refuses such a pipeline. The
stages are in :mod:`robotd.app.stages`, one per module; :meth:`Pipeline.mermaid` draws the
data flow from the registrations (docs/concepts.md, "Data flow").
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Callable, Mapping
from typing import Any, Protocol

from robotd.base.messages import BaseStatus, Frame, WheelDrop, WheelTicks, YawRate

log = logging.getLogger(__name__)

Handler = Callable[[Any], None]

SOURCE_TYPES: tuple[type, ...] = (WheelTicks, YawRate, BaseStatus, WheelDrop, Frame)
"""What the sources (drivers, recordings, the virtual robot) feed the pipeline."""


class Stage(Protocol):
    """One step of the pipeline.

    ``name`` identifies it (counters, logs); :meth:`subscriptions` maps each message type
    it consumes to its handler. Declared, when the stage publishes or may wait for nothing:
    ``produces`` (the message types it publishes) and ``optional_inputs`` (subscribed types
    it can do without), ``precedes`` (names of stages that must be registered after it,
    where both subscribe to one type and the order matters). Optional methods, called when present: ``attach(pipeline)`` (once,
    at registration: the stage keeps the pipeline to publish to), ``poll() -> int`` (work
    that waits on something other than a new message, e.g. frames waiting for odometry;
    returns how many items it handled), ``finish() -> int`` (end of input) and
    ``counters() -> dict[str, int]``. What a live reload may change, a stage takes through
    methods of its own (``set_spacing``, ``set_gate``, ...; :mod:`robotd.app.reload`).
    """

    name: str

    def subscriptions(self) -> Mapping[type, Handler]: ...


def produces(stage: Any) -> tuple[type, ...]:
    """The message types ``stage`` declares it publishes (none for an observer)."""
    return tuple(getattr(stage, "produces", ()))


class Pipeline:
    """Routes messages to the stages registered for their type (see the module notes)."""

    def __init__(self) -> None:
        self._stages: dict[str, Any] = {}
        self._reads: dict[str, dict[str, str]] = {}  # stage -> {owner stage: interface}
        self._routes: dict[type, list[Handler]] = collections.defaultdict(list)
        self._inherited: dict[type, list[Handler]] = {}  # subclass -> its base's handlers
        self.inputs = 0
        """Messages published from outside (the sources), a measure of progress."""
        self.unrouted: collections.Counter[str] = collections.Counter()
        """Messages of a type no stage consumes, by type name."""

    def add(self, stage: Any, *, reads: Mapping[str, str] | None = None) -> Any:
        """Register ``stage`` (after every stage registered before it); returns it.

        ``reads``: the state of other stages it reads through an explicit interface rather
        than messages, ``{owner stage name: interface name}`` (the owners registered
        before it); drawn in :meth:`mermaid`."""
        if stage.name in self._stages:
            raise ValueError(f"a stage named {stage.name!r} is already registered")
        for owner in reads or {}:
            if owner not in self._stages:
                raise ValueError(f"stage {stage.name!r} reads stage {owner!r}, which is not registered")
        self._reads[stage.name] = dict(reads or {})
        self._inherited.clear()
        self._stages[stage.name] = stage
        for msg_type, handler in stage.subscriptions().items():
            self._routes[msg_type].append(handler)
        if hasattr(stage, "attach"):
            stage.attach(self)
        return stage

    def missing_inputs(self) -> dict[str, list[type]]:
        """Per stage, the subscribed types (not declared optional) that neither a source
        (:data:`SOURCE_TYPES`) nor any registered stage produces: that stage would wait
        for something nothing makes (e.g. a map writer taking measured keyframes with no
        visual odometry stage). Empty when the pipeline is whole."""
        made = set(SOURCE_TYPES)
        for s in self._stages.values():
            made.update(produces(s))
        out: dict[str, list[type]] = {}
        for s in self._stages.values():
            optional = set(getattr(s, "optional_inputs", ()))
            missing = [t for t in s.subscriptions() if t not in made and t not in optional]
            if missing:
                out[s.name] = missing
        return out

    def misordered(self) -> list[tuple[str, str]]:
        """``(stage, other)`` for each stage registered after one it must precede: the one
        order that types do not give, between subscribers of the same message (a stage's
        ``precedes``: the pose graph must hold a stored keyframe before the floor and forward
        stages, subscribers of the same ``KeyframeStored``, publish its loop candidates)."""
        names = list(self._stages)
        return [(s.name, other) for s in self._stages.values() for other in getattr(s, "precedes", ())
                if other in self._stages and names.index(other) < names.index(s.name)]

    def check(self) -> None:
        """Raise ValueError naming every stage that reads something no source or stage
        produces (:meth:`missing_inputs`) or is registered after a stage it must precede
        (:meth:`misordered`)."""
        missing = self.missing_inputs()
        problems = [f"stage {name!r} reads {', '.join(t.__name__ for t in types)}, which nothing produces"
                    for name, types in missing.items()]
        problems += [f"stage {a!r} must be registered before {b!r}" for a, b in self.misordered()]
        if problems:
            raise ValueError("pipeline: " + "; ".join(problems))

    def mermaid(self) -> str:
        """The data flow as a Mermaid flowchart, from the registrations: an edge from each
        producer (a stage, or ``sources``) to each stage that subscribes to a type it
        produces, labelled with the types. Observers (stages that declare no ``produces``)
        are drawn when they subscribe to something."""
        lines = ["flowchart TD", "    sources([sources])"]
        for s in self._stages.values():
            lines.append(f"    {s.name}[{s.name}]")
        producers: dict[type, list[str]] = collections.defaultdict(list)
        for t in SOURCE_TYPES:
            producers[t].append("sources")
        for s in self._stages.values():
            for t in produces(s):
                producers[t].append(s.name)
        edges: dict[tuple[str, str], list[str]] = {}
        for s in self._stages.values():
            for t in s.subscriptions():
                for p in producers.get(t, []):
                    if p != s.name:
                        edges.setdefault((p, s.name), []).append(t.__name__)
        for (a, b), names in edges.items():
            lines.append(f"    {a} -->|{'<br/>'.join(names)}| {b}")
        for name, owners in self._reads.items():
            for owner, interface in owners.items():
                lines.append(f"    {owner} -.->|{interface}| {name}")
        return "\n".join(lines) + "\n"

    def instrument(self, wrap: Callable[[str, str, Callable[..., Any]], Callable[..., Any]]) -> None:
        """Replace every stage's message handlers and its ``poll``/``finish`` by
        ``wrap(stage_name, handler_name, fn)`` (a function with the same signature), e.g.
        to account CPU time per stage (``bench/bench_daemon.py``). Call it once, after
        the last stage was added and before the first message."""
        for msg_type, handlers in self._routes.items():
            handlers[:] = [wrap(getattr(getattr(h, "__self__", None), "name", "?"),
                                getattr(h, "__name__", msg_type.__name__), h) for h in handlers]
        for stage in self._stages.values():
            for what in ("poll", "finish"):
                if hasattr(stage, what):
                    setattr(stage, what, wrap(stage.name, what, getattr(stage, what)))

    def stage(self, name: str) -> Any:
        """The stage registered as ``name`` (KeyError if none)."""
        return self._stages[name]

    @property
    def stages(self) -> list[Any]:
        return list(self._stages.values())

    def subscribed(self, msg_type: type) -> bool:
        """Whether any stage consumes ``msg_type`` (lets a stage skip building a message)."""
        return bool(self._routes.get(msg_type))

    def feed(self, msg: Any) -> None:
        """A message from a source: counted as input, then published."""
        self.inputs += 1
        self.publish(msg)

    def publish(self, msg: Any) -> None:
        """Hand ``msg`` to every stage subscribed to its type, in registration order (a
        subclass of a subscribed type goes where its nearest subscribed base goes: a
        replay's frames that decode their image when first read)."""
        handlers = self._routes.get(type(msg)) or self._subclass_routes(type(msg))
        if not handlers:
            self.unrouted[type(msg).__name__] += 1
            return
        for handler in handlers:
            handler(msg)

    def _subclass_routes(self, msg_type: type) -> list[Handler]:
        """The handlers of the nearest base of ``msg_type`` that has any (remembered)."""
        got = self._inherited.get(msg_type)
        if got is None:
            got = next((self._routes[b] for b in msg_type.__mro__[1:] if self._routes.get(b)), [])
            self._inherited[msg_type] = got  # the same list: instrument() wraps it in place
        return got

    def poll(self) -> int:
        """Let every stage do waiting work; returns how many items were handled."""
        return sum(s.poll() for s in self._stages.values() if hasattr(s, "poll"))

    def finish(self) -> int:
        """End of input: every stage finishes what it holds; returns items handled."""
        return sum(s.finish() for s in self._stages.values() if hasattr(s, "finish"))

    def counters(self) -> dict[str, int]:
        """Every stage's counters in one flat mapping (the names are unique by design)."""
        out: dict[str, int] = {"inputs": self.inputs}
        for s in self._stages.values():
            if hasattr(s, "counters"):
                out.update(s.counters())
        for name, n in self.unrouted.items():
            out[f"unrouted_{name}"] = n
        return out


class Publisher:
    """Mixin: keeps the pipeline a stage publishes to."""

    pipeline: Pipeline | None = None

    def attach(self, pipeline: Pipeline) -> None:
        self.pipeline = pipeline

    def _publish(self, msg: Any) -> None:
        if self.pipeline is not None:
            self.pipeline.publish(msg)
