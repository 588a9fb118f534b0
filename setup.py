"""Build of the optional C kernels (torchsgal/functional/_native.c: the SGal(3) kernels;
torchsgal/estimation/_native.c: batched Cholesky solves of small systems;
torchsgal/imu/_native.c: IMU preintegration); everything else is in pyproject.toml.  The
extensions are optional: where they do not compile, the package installs without them and runs
the same operations as tensor code (torchsgal.functional.ops, torchsgal.estimation.dense_solve,
torchsgal.imu._kernels)."""
import sys

from setuptools import Extension, setup

args = [] if sys.platform == "win32" else ["-O3", "-std=c99", "-fno-math-errno", "-ffp-contract=off"]
libraries = ["dl"] if sys.platform.startswith("linux") else []  # dlopen: torch's OpenMP
common = ["torchsgal/functional/_native_common.h", "torchsgal/functional/_native_sgal3.h"]
setup(
    ext_modules=[
        Extension(
            "torchsgal.functional._native",
            sources=["torchsgal/functional/_native.c"],
            depends=common + ["torchsgal/functional/_native_products.h", "torchsgal/functional/_native_se2.h",
                              "torchsgal/functional/_native_sim3.h", "torchsgal/functional/_native_lanes_f32.h",
                              "torchsgal/functional/_native_affine.h"],
            extra_compile_args=args,
            libraries=libraries,
            optional=True,
        ),
        Extension(
            "torchsgal.estimation._native",
            sources=["torchsgal/estimation/_native.c"],
            depends=common + ["torchsgal/functional/_native_products.h",
                              "torchsgal/estimation/_native_cholesky.h",
                              "torchsgal/estimation/_native_cholesky_lanes.h",
                              "torchsgal/estimation/_native_block_cholesky.h",
                              "torchsgal/estimation/_native_factors.h",
                              "torchsgal/estimation/_native_normal.h",
                              "torchsgal/estimation/_native_round.h"],
            extra_compile_args=args,
            libraries=libraries,
            optional=True,
        ),
        Extension(
            "torchsgal.imu._native",
            sources=["torchsgal/imu/_native.c"],
            depends=common + ["torchsgal/imu/_native_imu.h"],
            extra_compile_args=args,
            libraries=libraries,
            optional=True,
        ),
    ]
)
