"""Build of the optional C kernels (everything else is in pyproject.toml): the QP solver's
CPU fast path, the Lie terms of quadric barriers on a few states, the safety filter's
real-time path and MPPI's fused rollouts. If no C compiler is found the build goes on
without them, and the solver, the barriers, the filter and the planner run their torch
implementations on the CPU too."""

import platform
import sys

from setuptools import Extension, setup

# glibc's vector math library (libmvec) lets the rollout kernel's sin/cos/log vectorise
_mvec = sys.platform.startswith("linux") and platform.machine() in ("x86_64", "AMD64")

setup(
    ext_modules=[
        Extension(
            "torchcbf.qp._dual_kernel",
            ["torchcbf/qp/_dual_kernel.c"],
            depends=["torchcbf/qp/_dual_kernel.h"],
            extra_compile_args=["-O3", "-std=c99"],
            optional=True,
        ),
        Extension(  # closed-form Lie terms of quadric barriers on a few states
            "torchcbf.barriers._lie_kernel",
            ["torchcbf/barriers/_lie_kernel.c"],
            depends=["torchcbf/barriers/_lie_kernel.h"],
            extra_compile_args=["-O3", "-std=c99"],
            libraries=["m"],
            optional=True,
        ),
        Extension(  # the safety filter's real-time path, linked with the QP kernel
            "torchcbf.filters._filter_kernel",
            ["torchcbf/filters/_filter_kernel.c", "torchcbf/qp/_dual_kernel.c"],
            depends=["torchcbf/qp/_dual_kernel.h", "torchcbf/barriers/_lie_kernel.h"],
            extra_compile_args=["-O3", "-std=c99"],
            libraries=["m"],
            optional=True,
        ),
        Extension(
            "torchcbf.mppi._rollout_kernel",
            ["torchcbf/mppi/_rollout_kernel.c"],
            depends=["torchcbf/mppi/_rollout_kernel.h"],
            extra_compile_args=["-O3", "-std=c99", "-fno-math-errno"],
            libraries=(["mvec", "m"] if _mvec else ["m"]),
            optional=True,
        ),
    ]
)
