"""``pb3a manager [FILE | ADDR]``: serve the ModuleManager and State Editor.

No argument: an empty document to build a system in. ``FILE``: a configuration to
edit and launch from the page. ``ADDR`` (``[tcp://]HOST:PORT``, what ``pb3a run``
prints): attach to a running system through its launcher. The app listens on
loopback by default and prints its URL with a new token; Ctrl-C or SIGTERM stop it,
and the system it launched, cleanly.
"""

from __future__ import annotations

import argparse
import importlib.util
import socket
import sys
from pathlib import Path

import psutil

UI_PACKAGES = ("starlette", "uvicorn", "websockets", "tomlkit")


def manager_command(args: argparse.Namespace) -> int:
    """Serve the manager until signalled; 1 with one sentence on any mistake."""
    missing = [name for name in UI_PACKAGES if importlib.util.find_spec(name) is None]
    if missing:
        return _fail(f"needs the 'ui' extra, missing {', '.join(missing)}: "
                     "pip install 'pb3a[ui]' (or: pip install starlette uvicorn websockets "
                     "tomlkit)")
    try:
        host, port = listen_address(args.listen)
    except ValueError as exc:
        return _fail(str(exc))
    if not args.refresh > 0 or not args.timeout > 0 or not args.import_timeout > 0:
        return _fail("--refresh, --timeout and --import-timeout take a number of seconds "
                     "above 0")

    from pb3a.loading.references import watch_imports
    from pb3a.loading.trial import tried_first
    from pb3a.manager.catalog import LONGER

    # Every class this process imports for the page (its document's, the module
    # browser's, a swap's) is tried in a child process first: a module file that loops,
    # exits or crashes as it is imported is refused, saying so, and does not hold up or
    # end the manager and the system it launched.
    before = watch_imports(tried_first(args.import_timeout, LONGER))
    try:
        return _serve(args, host, port)
    finally:
        watch_imports(before)


def _serve(args: argparse.Namespace, host: str, port: int) -> int:
    """Serve the manager at ``host:port`` until signalled."""
    from pb3a.cli.status import sigterm_interrupts
    from pb3a.errors import ConfigError, PB3AError
    from pb3a.launch.connection import CONNECT_TIMEOUT, connect
    from pb3a.manager.access import Access, new_token
    from pb3a.manager.app import bind, create_app, serve
    from pb3a.manager.document import Document
    from pb3a.manager.session import Session

    target = args.target
    options = {"timeout": args.timeout, "import_timeout": args.import_timeout}
    try:
        if target is None:
            session = Session(Document.empty(), **options)
        elif Path(target).is_file():
            session = Session(Document.open(target), **options)
        elif (address := _launcher(target)) is not None:
            # (a --timeout under 5 s bounds the connecting too)
            system = connect(address, timeout=min(CONNECT_TIMEOUT, args.timeout))
            session = Session(Document.empty(), system, owns_handle=True, **options)
        else:
            return _fail(f"no file {target!r}: give a configuration file (.toml) or the "
                         "address [tcp://]HOST:PORT of a running system")
    except ConfigError as exc:
        return _fail("; ".join(exc.problems) or str(exc))
    except (PB3AError, OSError, ValueError) as exc:
        return _fail(str(exc))
    try:
        sock = bind(host, port)
    except OSError as exc:
        session.close()
        return _fail(f"cannot listen at {host}:{port}: {exc.strerror or exc}")
    bound_port = sock.getsockname()[1]
    access = Access(new_token())
    access.serve_at(host, bound_port)
    for name in every_interface_names(host):
        access.serve_at(name, bound_port)
    shown = "127.0.0.1" if host in ("0.0.0.0", "::") else host
    shown = f"[{shown}]" if ":" in shown else shown
    print(f"PB3A manager: http://{shown}:{bound_port}/?token={access.token}", flush=True)
    session.read_classes_ahead()    # (ready, or nearly, as the page first asks for it)
    with sigterm_interrupts():     # uvicorn stops, then raises SIGTERM again: as Ctrl-C
        serve(create_app(session, access, args.refresh), sock)
    return 0


def every_interface_names(host: str) -> list[str]:
    """What a manager listening at ``host`` is also reached by when that is every
    interface (0.0.0.0, ::): this machine's names and its interfaces' addresses (of the
    family listened on; not a link-local one, whose zone a Host header cannot carry).
    Without the addresses, a manager on every interface refused the very requests it
    was opened to, another machine's at http://ADDRESS:PORT ("does not serve the host")."""
    if host not in ("0.0.0.0", "::"):
        return []
    families = (socket.AF_INET,) if host == "0.0.0.0" else (socket.AF_INET, socket.AF_INET6)
    addresses = [address.address for found in psutil.net_if_addrs().values()
                 for address in found if address.family in families
                 and "%" not in address.address and not address.address.startswith("fe80:")]
    return list(dict.fromkeys([socket.gethostname(), socket.getfqdn(), *addresses]))


def _launcher(target: str) -> str | None:
    """``target`` as a launcher's address (``tcp://HOST:PORT`` or ``HOST:PORT``, as
    ``pb3a run`` prints it), or None when it is not one (then it names a file)."""
    from pb3a.transport.addresses import launcher_address

    if target.endswith(".toml"):
        return None
    try:
        return launcher_address(target)
    except ValueError:
        return None


def listen_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:PORT`` for IPv6; PORT 0: any free one) as a host and port;
    also written ``http://HOST:PORT``, or ``tcp://HOST:PORT`` as every other ``--listen``
    of the command line is (that one said "Name or service not known")."""
    host, _, port = text.removeprefix("http://").removeprefix("tcp://").rpartition(":")
    host = host.strip("[]")
    if not host or not port.isdigit() or int(port) > 65535:
        raise ValueError(f"--listen {text!r}: give HOST:PORT, e.g. 127.0.0.1:8080 "
                         "(PORT 0: any free port)")
    return host, int(port)


def _fail(message: str) -> int:
    print(f"pb3a manager: {message}", file=sys.stderr)
    return 1
