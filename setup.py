"""Builds the compiled perception kernels (cell/perception/_kernels.pyx); everything else about the
package is in pyproject.toml. ``pip install -e .`` (``make setup``) runs it."""

from Cython.Build import cythonize
from setuptools import Extension, setup

setup(ext_modules=cythonize(
    [Extension("cell.perception._kernels", ["cell/perception/_kernels.pyx"], extra_compile_args=["-O3"])],
    compiler_directives={"language_level": 3},
))
