// Shared by the handlers of the native library (see setup.py and lieax/_native.py).
#ifndef LIEAX_FFI_H_
#define LIEAX_FFI_H_

#include "xla/ffi/api/ffi.h"

// A handler symbol exported from the library (it is built with hidden visibility), which
// lieax/_native.py loads with ctypes and registers with jax.ffi under a target name.
#define LIEAX_FFI_HANDLER(symbol, impl, binding)                                   \
  extern "C" __attribute__((visibility("default"))) XLA_FFI_Error* symbol(         \
      XLA_FFI_CallFrame* call_frame);                                              \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(symbol, impl, binding)

// A plain C function exported from the library (called through ctypes).
#define LIEAX_EXPORT extern "C" __attribute__((visibility("default")))

#endif  // LIEAX_FFI_H_
