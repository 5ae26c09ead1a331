"""Builds the compiled kernels (perception: cell/perception/_kernels.pyx; the LR-NBV utility:
cell/planning/lrnbv/_raygains.pyx); everything else about the package is in pyproject.toml.
``pip install -e .`` (``make setup``) runs it."""

from Cython.Build import cythonize
from setuptools import Extension, setup

setup(ext_modules=cythonize(
    [Extension("cell.perception._kernels", ["cell/perception/_kernels.pyx"], extra_compile_args=["-O3"]),
     Extension("cell.planning.lrnbv._raygains", ["cell/planning/lrnbv/_raygains.pyx"],
               extra_compile_args=["-O3"])],
    compiler_directives={"language_level": 3},
))
