"""Imported by the workers' forkserver alone, last in its preload list: every module
before it is imported, so the watch of its owner that ``pb3a.node.forkserver_signals``
began lets go of the forkserver's pipe (multiprocessing watches it from here on) and
watches the owner alone, to end the workers when it ends."""

from pb3a.node import forkserver_signals

forkserver_signals.preloaded()
