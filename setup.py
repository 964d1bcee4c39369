"""Only here to hand the cffi build script to setuptools; metadata lives in pyproject.toml.

The extension is built against the stable ABI (cffi defines Py_LIMITED_API), so the wheel
is tagged ``cp310-abi3``: one wheel for every CPython >= 3.10 (``make wheel``)."""

from setuptools import setup

setup(cffi_modules=["build_ffi.py:ffibuilder"],
      options={"bdist_wheel": {"py_limited_api": "cp310"}})
