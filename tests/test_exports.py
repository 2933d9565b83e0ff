"""The public API is exactly what ``pb3a.__all__`` says, and each name is importable."""

from __future__ import annotations

import pydoc

import pb3a


def test_public_names_are_exactly_the_documented_ones() -> None:
    assert pb3a.__all__ == sorted(pb3a.__all__, key=lambda name: (name[0].islower(), name))
    assert set(pb3a.__all__) == {
        "Agent", "ConfigError", "Connection", "connect", "Driver", "Environment", "Input",
        "InputPort", "Macro", "MigrationReport",
        "Module", "ModuleNotFound", "Output", "OutputPort", "PB3AError", "Running",
        "RuntimeCancelled", "RuntimeFailure", "RuntimeTimeout", "StateRefused", "System",
        "SystemStopped",
        "serve_device"}
    for name in pb3a.__all__:
        assert getattr(pb3a, name).__doc__, f"{name} has no docstring"


def test_errors_subclass_the_nearest_builtin() -> None:
    assert issubclass(pb3a.ConfigError, ValueError)
    assert issubclass(pb3a.ModuleNotFound, LookupError)
    assert issubclass(pb3a.RuntimeTimeout, TimeoutError)
    assert issubclass(pb3a.RuntimeFailure, RuntimeError)
    assert issubclass(pb3a.RuntimeCancelled, pb3a.RuntimeFailure)    # caught as before
    assert issubclass(pb3a.SystemStopped, pb3a.RuntimeFailure)       # caught as before
    assert all(issubclass(e, pb3a.PB3AError) for e in (
        pb3a.ConfigError, pb3a.ModuleNotFound, pb3a.RuntimeTimeout, pb3a.RuntimeFailure))


def test_help_on_the_env_module_gives_each_port_its_meaning() -> None:
    """An agent's author reads in ``help(pb3a.Environment)`` what each port carries and
    in what unit (it listed the ports' names only; the meaning was in the module's
    docstring, which help() on the class does not show)."""
    shown = pydoc.render_doc(pb3a.Environment, renderer=pydoc.plaintext)
    for name, port in pb3a.Environment.outputs.items():
        assert port.__doc__ and port.__doc__ != type(port).__doc__, name
        assert port.__doc__.splitlines()[0] in shown, name
