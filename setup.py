"""Builds the compiled kernels; everything else about the package is in pyproject.toml:
cell/perception/_kernels.pyx (occupancy integration, filters, outlier statistics; the SIMD ray walk of the
integration in _ray_lanes.h, compiled for AVX2 and chosen at run time, so no -m flag is needed),
cell/planning/vs/_objective.pyx (the entropy NBV objective, OpenMP over candidate poses) and
cell/planning/lrnbv/_raygains.pyx (the LR-NBV ray gains). ``pip install -e .`` (``make setup``) runs it."""

from Cython.Build import cythonize
from setuptools import Extension, setup

setup(ext_modules=cythonize(
    [Extension("cell.perception._kernels", ["cell/perception/_kernels.pyx"], extra_compile_args=["-O3"],
               depends=["cell/perception/_ray_lanes.h"]),
     Extension("cell.planning.vs._objective", ["cell/planning/vs/_objective.pyx"],
               extra_compile_args=["-O3", "-fopenmp"], extra_link_args=["-fopenmp"]),
     Extension("cell.planning.lrnbv._raygains", ["cell/planning/lrnbv/_raygains.pyx"],
               extra_compile_args=["-O3"])],
    compiler_directives={"language_level": 3},
))
