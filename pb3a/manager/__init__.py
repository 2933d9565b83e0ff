"""The ModuleManager and State Editor: a web app to build, see and change a system live.

``pb3a manager [FILE | ADDR]`` serves it (``pb3a/cli/manager.py``); it is one more
client of the control surface (``SystemHandle``), and its HTTP API is the page's own
(``docs/manager.md``). It needs the ``ui`` extra: ``pip install 'pb3a[ui]'``.
"""
