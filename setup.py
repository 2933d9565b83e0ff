"""Only the C extension lives here: setup.cfg cannot declare one (metadata is in setup.cfg)."""

from setuptools import Extension, setup

setup(ext_modules=[Extension("pb3a.transport._ringcore", ["pb3a/transport/_ringcore.c"],
                             extra_compile_args=["-O2", "-std=gnu11"])])
