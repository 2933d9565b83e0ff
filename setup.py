"""Only the C extensions live here: setup.cfg cannot declare them (metadata is in setup.cfg)."""

from setuptools import Extension, setup

_FLAGS = ["-O2", "-std=gnu11"]

setup(ext_modules=[Extension("pb3a.transport._ringcore", ["pb3a/transport/_ringcore.c"],
                             extra_compile_args=_FLAGS),
                   # (sqrt inline: nothing reads errno)
                   Extension("rave._raycore", ["rave/_raycore.c"],
                             extra_compile_args=[*_FLAGS, "-fno-math-errno"])])
