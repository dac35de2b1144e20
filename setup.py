"""The optional compiled index coder (hostd/codec/_rangecoder.c); everything else is in pyproject.toml.

optional=True: without a C compiler the build goes on and hostd uses the pure-Python coder
(hostd/codec/rangecoder.py, the reference; same bytes, slower).
"""

from setuptools import Extension, setup

setup(ext_modules=[Extension("hostd.codec._rangecoder", ["hostd/codec/_rangecoder.c"], optional=True)])
