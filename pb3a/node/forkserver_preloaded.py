"""Imported by the workers' forkserver alone, last in its preload list: every module
before it is imported, so the watch of its owner that ``pb3a.node.forkserver_signals``
began ends (multiprocessing watches the same pipe from here on)."""

from pb3a.node import forkserver_signals

forkserver_signals.preloaded()
