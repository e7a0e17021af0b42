"""Build of the optional C kernel of the QP solver's CPU fast path (everything else is in
pyproject.toml). If no C compiler is found the build goes on without it, and the solver
runs its torch implementation on the CPU too."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "torchcbf.qp._dual_kernel",
            ["torchcbf/qp/_dual_kernel.c"],
            extra_compile_args=["-O3", "-std=c99"],
            optional=True,
        )
    ]
)
