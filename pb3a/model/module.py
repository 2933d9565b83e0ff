"""``Module``: the port-based module (PBM), the unit PB3A runs, swaps and moves.

A module declares ``Input``/``Output`` ports as class attributes, keeps its state
in public attributes, and has a body: ``step()`` when it has a ``period``
(threaded), ``on_input(port)`` when it overrides it (event-driven), or both.
The runtime calls every hook under the module's lock.
"""

from __future__ import annotations

import contextlib
import contextvars
import copy
import difflib
import inspect
import types
from collections.abc import Callable, Iterator
from typing import Any, ClassVar, TypeVar

from pb3a.model.ports import Input, InputPort, Output, OutputPort, _Port

RESTART_POLICIES = ("never", "fresh", "last-state")

# Attributes the runtime reads as configuration, never as state.
_FRAMEWORK_NAMES = frozenset({"period", "fixed_rate", "restart", "runtime", "displays"})
# State defaults that cannot change, shared as they are (everything else is copied).
_ATOMS = frozenset({int, float, complex, bool, str, bytes, type(None), frozenset, range})
_NOT_STATE = (_Port, types.FunctionType, classmethod, staticmethod, property, type,
              types.ModuleType, types.MethodType, types.BuiltinFunctionType)
# Set while a module is given its own state back (``restore_state``).
_RESTORING: contextvars.ContextVar[bool] = contextvars.ContextVar("pb3a_restoring",
                                                                   default=False)
# The edit a class's own ``set_state`` has admitted already (``Module._admitting``).
_ADMITTED: contextvars.ContextVar[dict[str, Any] | None] = contextvars.ContextVar(
    "pb3a_admitted", default=None)


# The methods a module class defines for the runtime to call (``Module``'s lifecycle
# hooks); a near miss of one (``on_inputs``) is never called, which ``pb3a check`` says.
HOOKS = ("setup", "step", "on_input", "teardown")

F = TypeVar("F", bound=Callable[..., Any])


class StateRefused(ValueError):
    """A ``set_state`` given values its module's class refuses (``Module.state_problems``):
    nothing was set. ``problems``: one per value, each naming the field and what it takes.
    Through the runtime it is a ``RuntimeFailure`` naming the module, in the same words."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("; ".join(problems))
        self.problems = list(problems)


class _Period:
    """A module class's ``period`` (``Module.__init_subclass__`` makes the value a class
    gives it one of these, and ``give_period`` one it has another way). Read from the
    class, it is the class's period; from an instance, the period it runs at (its
    worker puts it on the instance). Assigned on an instance its worker runs, it is set
    live, as ``set_state(name, period=...)`` sets it (the worker's
    ``_pb3a_period_set``): a module that slowed itself with ``self.period = 0.5`` slept
    its old period on, nothing said. On an instance no worker runs (in its
    ``__init__``) it is a plain attribute."""

    def __init__(self, default: Any) -> None:
        self.default = default

    def __get__(self, instance: Module | None, owner: type | None = None) -> Any:
        if instance is None:
            return self.default
        return instance.__dict__.get("period", self.default)

    def __set__(self, instance: Module, value: Any) -> None:
        setter = instance.__dict__.get("_pb3a_period_set")
        if setter is None:
            instance.__dict__["period"] = value
        else:
            setter(value)


def stepped_period(cls: type[Module], period: float | None) -> float | None:
    """The period a module of class ``cls`` given ``period`` steps at: None if the class
    has no ``step()`` (a period its class sets steps nothing)."""
    return period if cls.step is not Module.step else None


def fixed_rate_of(cls: type[Module], fixed_rate: bool | None) -> bool:
    """Whether a module of class ``cls`` given ``fixed_rate`` (None: its class's own)
    steps at a fixed rate (its steps due a period after the last one began) rather than
    a period after the last one ended."""
    return bool(cls.fixed_rate) if fixed_rate is None else fixed_rate


def give_period(module: Module, period: float | None,
                assign: Callable[[Any], None]) -> None:
    """Give ``module`` the period it runs at, on the instance (``self.period``), and have
    ``assign`` take what it assigns to ``self.period`` from then on (``_Period``). A
    class's period that is no ``_Period`` is made one first: one a class that is no
    ``Module`` gives (a mixin's), or one set on the class once made (``Sensor.period =
    0.02``), was assigned as a plain attribute, and the module stepped at its old one."""
    cls = type(module)
    own = inspect.getattr_static(cls, "period", None)
    if not hasattr(type(own), "__get__"):                   # (a property stays)
        cls.period = _Period(own)
    module.__dict__["period"] = period
    module.__dict__["_pb3a_period_set"] = assign


class Module:
    """Base class of every port-based module.

    Class attributes ``period`` (seconds between steps; ``None`` = not threaded,
    ``0`` = as fast as possible), ``fixed_rate`` (False: the period is slept after each
    step; True: a step is due a period after the last one began, drift-free, late
    periods skipped and counted as ``overruns``) and ``restart`` (``"never"``,
    ``"fresh"`` or ``"last-state"``) configure how the runtime runs it; a configuration
    may override each (a running instance's ``self.period`` is the period it runs at, the
    configuration's, ``add``'s or ``swap``'s if given, and assigning it sets it live,
    as ``set_state(name, period=...)`` does). ``displays`` tells tools how to
    show some state fields (``pb3a.model.displays``). Modules are constructed with no
    arguments.

    A class says which values of its state it refuses with the classmethod
    ``state_problems(state)`` (none by default): ``set_state`` asks it before setting
    anything, and so do ``pb3a check``, the configuration compiler, ``add``, ``swap`` and
    the State Editor, so a value the module would refuse live is refused before it runs.
    """

    period: ClassVar[float | None] = _Period(None)    # type: ignore[assignment]
    fixed_rate: ClassVar[bool] = False
    restart: ClassVar[str] = "never"
    displays: ClassVar[dict[str, Any]] = {}
    inputs: ClassVar[dict[str, Input]] = {}
    outputs: ClassVar[dict[str, Output]] = {}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        inputs: dict[str, Input] = {}
        outputs: dict[str, Output] = {}
        for klass in reversed(cls.__mro__):
            for name, value in vars(klass).items():
                if isinstance(value, Input):
                    inputs[name] = value
                    outputs.pop(name, None)
                elif isinstance(value, Output):
                    outputs[name] = value
                    inputs.pop(name, None)
        cls.inputs = inputs
        cls.outputs = outputs
        own = vars(cls).get("period")
        if "period" in vars(cls) and not hasattr(type(own), "__get__"):   # (a property stays)
            cls.period = _Period(own)

    def __init__(self) -> None:
        # Mutable class defaults (lists, dicts, arrays, deques, objects of the module's
        # own classes ...) become per-instance copies, so that two instances never share
        # state through their class: all but the immutable atoms are deep-copied.
        for name in type(self).state_names():
            if name not in self.__dict__:
                value = getattr(type(self), name)
                if type(value) not in _ATOMS:
                    # (a value deepcopy refuses, a lock say, stays shared, as it was)
                    with contextlib.suppress(TypeError, copy.Error):
                        self.__dict__[name] = copy.deepcopy(value)

    def __getstate__(self) -> dict[str, Any]:
        """What a copy or a pickle of the module takes: its attributes, less what its
        worker bound it to (ports, runtime, device: ``_pb3a_...``), so that the copy is
        the module with its state, bound to nothing. (A ``copy.deepcopy`` of a running
        module copied its worker's connections and rings, whose copies closed their
        ends as they went: the worker died.)"""
        return {name: value for name, value in self.__dict__.items()
                if not name.startswith("_pb3a_")}

    # -- lifecycle hooks (override as needed) ------------------------------
    def setup(self) -> None:
        """Called after state and ports are in place, again after every swap or move."""

    def step(self) -> None:
        """The threaded body, when ``period`` is set: called again and again, with a sleep
        of ``period`` seconds after each call (so a step that takes time slows the rate),
        or, with ``fixed_rate``, every ``period`` seconds from the first call's start."""

    def on_input(self, port: InputPort) -> None:
        """The event body: called when ``port`` receives a value (override to use)."""

    def teardown(self) -> None:
        """Called before the module is removed, swapped out or moved."""

    # -- state -------------------------------------------------------------
    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        """What the class refuses of ``state`` (fields by name: a live edit's, with the
        module's other fields as they are; a configuration entry's alone, and with the
        class's own defaults for the fields it leaves), each problem a sentence naming
        the field, its value and what it takes; none by default. Override it for a value the module
        cannot run with, judging the fields given, and call the base's:

            @classmethod
            def state_problems(cls, state):
                problems = super().state_problems(state)
                if "rate" in state and not 0 <= state["rate"] <= 5:
                    problems.append(f"Pump's rate must be from 0 to 5 l/s, got {state['rate']!r}")
                return problems

        A rule that relates fields (a maximum at least the minimum) judges them when the
        state gives them all: the module's whole state is judged too, live (an edit
        comes with the module's other fields as they are) and by the checks and ``add``
        (the entry's with the class's defaults). Read from the class, a field the state
        lacks was the class's default, not the value the module has or the entry gives.

        ``set_state`` asks it before setting anything (``StateRefused``); ``pb3a check``
        and the configuration compiler ask it for each entry's state and the module's
        whole state, ``add`` and ``swap`` for the state they give, the State Editor for an
        edit (a refusal only a ``set_state`` of its own made was found at the launch, or
        by the running module). A value of a field of a reflective class (see
        ``reflective``) is of the kind of its default by then."""
        return []

    @classmethod
    def state_names(cls) -> list[str]:
        """Names of the class-level state attributes found by reflection."""
        names: dict[str, None] = {}
        for klass in reversed(cls.__mro__):
            if klass in (object, Module) or not issubclass(klass, Module):
                continue
            for name, value in vars(klass).items():
                if _is_state(name, value):
                    names[name] = None
        return list(names)

    def get_state(self) -> dict[str, Any]:
        """The module's state: every public attribute that is not a port or a method."""
        state = {name: getattr(self, name) for name in type(self).state_names()}
        for name, value in self.__dict__.items():
            if _is_state(name, value):
                state[name] = value
        return state

    def set_state(self, state: dict[str, Any]) -> None:
        """Set state attributes by name; KeyError names any attribute the module lacks
        (unless it is given its own state back: ``restore_state``), ``StateRefused`` each
        value the class refuses (``state_problems``, given the module's whole state with
        ``state`` in it). Either way nothing is set."""
        for name, value in self._admitted(state).items():
            setattr(self, name, value)

    def _admitted(self, state: dict[str, Any]) -> dict[str, Any]:
        """What of ``state`` ``set_state`` sets, after its checks (``KeyError``,
        ``StateRefused``); ``state`` itself if ``_admitting`` admitted it already."""
        if _ADMITTED.get() is state:
            return state
        known = set(type(self).state_names()) | {
            name for name, value in self.__dict__.items() if _is_state(name, value)}
        unknown = sorted(set(state) - known)
        if unknown and _RESTORING.get():
            # (a state from an earlier class of the module, a checkpoint taken before a
            # swap: a name this class has as a method or a port stays that, not its value)
            state = {name: value for name, value in state.items()
                     if name in known or can_hold(type(self), name)}
        elif unknown:
            close = difflib.get_close_matches(unknown[0], known, n=1)
            raise KeyError(
                f"{type(self).__name__} has no state {', '.join(map(repr, unknown))}"
                f"{f' (did you mean {close[0]!r}?)' if close else ''}; "
                f"its state is: {', '.join(sorted(known)) or '(none)'}"
            )
        if not _RESTORING.get():        # (its own state back is no edit: a move, a restart
            # of a module past its class's rule lost its state)
            problems = edit_refusals(type(self), Module.get_state(self), state)
            if problems:
                raise StateRefused(problems)
        return state

    @contextlib.contextmanager
    def _admitting(self, state: dict[str, Any]) -> Iterator[dict[str, Any]]:
        """``state`` checked and judged as ``set_state`` does it (``_admitted``), for a
        class's own ``set_state`` that acts on an edit before it hands it on to the
        base's (``RemedyAgent``'s reads its case files first): the base's, called within,
        sets it without judging it again (judged twice, each edit asked the hook twice,
        and one judged by hand refused what the module's state broke before it)."""
        admitted = self._admitted(state)
        token = _ADMITTED.set(admitted)
        try:
            yield admitted
        finally:
            _ADMITTED.reset(token)

    # -- ports -------------------------------------------------------------
    @classmethod
    def is_event_driven(cls) -> bool:
        """True when the class overrides ``on_input``."""
        return cls.on_input is not Module.on_input

    def _pb3a_bind_ports(self, owner: str = "") -> dict[str, InputPort | OutputPort]:
        ports: dict[str, InputPort | OutputPort] = {}
        for name, spec in type(self).inputs.items():
            ports[name] = InputPort(spec, owner)
        for name, spec in type(self).outputs.items():
            ports[name] = OutputPort(spec, owner)
        self.__dict__["_pb3a_ports"] = ports
        return ports

    def _pb3a_adopt_ports(self, ports: dict[str, InputPort | OutputPort]) -> None:
        self.__dict__["_pb3a_ports"] = ports


def refusals(cls: type[Module], state: dict[str, Any],
             shown: dict[str, Any] | None = None) -> list[str]:
    """What module class ``cls`` refuses of ``state``: its ``state_problems``. That is the
    user's code: one that raises, or answers other than a list of texts, is a refusal
    itself, naming the class, the hook and what it raised (live, a hook with a bug came
    back as the worker's failure; ``pb3a check`` said it as this), given ``shown`` (an
    edit, of the whole state judged: it was the module's other fields, cut short)."""
    ref = f"{cls.__module__}:{cls.__qualname__}"         # (``class_ref``'s words)
    try:
        problems = cls.state_problems(state)
    except Exception as exc:
        given = repr(state if shown is None else shown)
        given = given if len(given) <= 200 else f"{given[:200]}..."   # (a map, say)
        return [f"{ref}.state_problems raised {type(exc).__name__}: {exc} (given {given}): "
                "fix it to return what it refuses, as a list of texts"]
    if not (isinstance(problems, list) and all(isinstance(p, str) for p in problems)):
        return [f"{ref}.state_problems must return a list of texts, one per value it "
                f"refuses ([] for none), got {problems!r:.200}"]
    return problems


def edit_refusals(cls: type[Module], current: dict[str, Any],
                  edit: dict[str, Any]) -> list[str]:
    """What module class ``cls`` refuses of the whole state ``current`` with ``edit`` in
    it (judged alone, a rule relating an edited field to another judged it against the
    class's default, not the module's value), less what it refused of ``current`` as it
    was: a field the module moved past a rule itself (a count) made every edit of
    another field refused. One judgement for a live ``set_state`` and the State
    Editor's."""
    problems = refusals(cls, {**current, **edit}, shown=edit)
    if problems:
        before = refusals(cls, current, shown=edit)
        problems = [problem for problem in problems if problem not in before]
    return problems


def restore_state(module: Module, state: dict[str, Any]) -> None:
    """Give ``module`` its own state back (after a move, or its undo, a ``last-state``
    restart, a swap): every field, those its instance made at run time too (in
    ``setup``, in ``on_input``), which a new instance lacks. Its ``set_state`` is called
    all the same, a class's own too; ``Module.set_state`` then skips its check for
    names the module lacks, which is for a user's or a configuration's call (a typo:
    here it refused the map a module had made, and the move, its undo and the restart
    all failed)."""
    token = _RESTORING.set(True)
    try:
        module.set_state(state)
    finally:
        _RESTORING.reset(token)


def reflective(set_state: F) -> F:
    """Mark a ``set_state`` override that takes the fields reflection finds, as
    ``Module.set_state`` does (it checks or acts on some values, then hands the state
    on to it, as ``Driver``'s does): the configuration's check and the State Editor
    then judge its keys and kinds as a class's without one (they took such a class to
    know its own fields: a typo in a driver's state passed ``pb3a check`` and failed the
    launch with a KeyError)."""
    set_state._pb3a_reflective = True       # type: ignore[attr-defined]
    return set_state


def reflective_state(cls: type[Module]) -> bool:
    """Whether the state of module class ``cls`` is the fields reflection finds:
    ``Module``'s ``get_state``, and ``Module``'s ``set_state`` or one marked
    ``reflective``."""
    return cls.get_state is Module.get_state and (
        cls.set_state is Module.set_state
        or getattr(cls.set_state, "_pb3a_reflective", False) is True)


def can_hold(cls: type[Module], name: str) -> bool:
    """Whether an instance of ``cls`` may take state field ``name`` from an instance of
    another class (a swap): yes unless ``cls`` declares the name as no state (a port, a
    method: set on the instance, it would hide it)."""
    for klass in cls.__mro__:
        if name in vars(klass):
            return _is_state(name, vars(klass)[name])
    return _is_state(name, None)


def _is_state(name: str, value: Any) -> bool:
    return (not name.startswith("_") and name not in _FRAMEWORK_NAMES
            and name not in ("inputs", "outputs") and not isinstance(value, _NOT_STATE))
