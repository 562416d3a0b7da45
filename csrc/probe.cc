// A trivial handler, y = 2 x: the build's smoke test (tests/test_native.py), which also checks that
// a program holding a lieax custom call is served by JAX's persistent compilation cache.
#include "lieax_ffi.h"

namespace ffi = xla::ffi;

static ffi::Error Twice(ffi::Buffer<ffi::F64> x, ffi::ResultBuffer<ffi::F64> y) {
  const double* in = x.typed_data();
  double* out = y->typed_data();
  for (size_t i = 0, n = x.element_count(); i < n; ++i) out[i] = 2.0 * in[i];
  return ffi::Error::Success();
}

LIEAX_FFI_HANDLER(LieaxProbe, Twice,
                  ffi::Ffi::Bind().Arg<ffi::Buffer<ffi::F64>>().Ret<ffi::Buffer<ffi::F64>>());
