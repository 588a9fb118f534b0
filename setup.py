"""Build of the optional C kernels (torchsgal/functional/_native.c); everything else is in
pyproject.toml.  The extension is optional: where it does not compile, the package installs
without it and runs the same closed forms as tensor operations (torchsgal.functional.native)."""
import sys

from setuptools import Extension, setup

args = [] if sys.platform == "win32" else ["-O3", "-std=c99", "-fno-math-errno", "-ffp-contract=off"]
setup(
    ext_modules=[
        Extension(
            "torchsgal.functional._native",
            sources=["torchsgal/functional/_native.c"],
            depends=["torchsgal/functional/_native_sgal3.h", "torchsgal/functional/_native_imu.h",
                     "torchsgal/functional/_native_tls.h"],
            extra_compile_args=args,
            libraries=["dl"] if sys.platform.startswith("linux") else [],  # dlopen: torch's OpenMP
            optional=True,
        )
    ]
)
