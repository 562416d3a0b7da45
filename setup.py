"""The native library `lieax._lieax_native`: XLA FFI handlers (the k-d tree of `lieax.icp`, the
multifrontal Cholesky of `lieax.factorgraph`) that compiled programs call by name, so that JAX's
persistent compilation cache can keep those programs (it refuses any that holds a Python callback).

It is optional: where it does not build (no C++17 compiler), pip installs lieax without it and
lieax uses its host-callback versions of the same algorithms (`lieax._native.available()`).
The XLA FFI headers are vendored in `csrc/third_party` (Apache-2.0, from jaxlib 0.10.2), so the
build needs neither jaxlib nor a network.
"""

import glob

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "lieax._lieax_native",
            sources=sorted(glob.glob("csrc/*.cc")),
            include_dirs=["csrc"],
            # the vendored headers as system headers: their own warnings are not lieax's
            extra_compile_args=[
                "-std=c++17",
                "-O3",
                "-fvisibility=hidden",
                "-fno-math-errno",
                "-isystem",
                "csrc/third_party",
            ],
            language="c++",
            optional=True,
        )
    ]
)
