// Unaligned loads and stores of GCC vectors (vector_size types) from and to plain arrays, shared by the kernels:
// memcpy, which the compiler turns into one unaligned vector move.
#pragma once

#include <cstring>

template <typename V, typename T>
inline V vload(const T* p) {
  V v;
  std::memcpy(&v, p, sizeof v);
  return v;
}

template <typename V, typename T>
inline void vstore(T* p, const V& v) {
  std::memcpy(p, &v, sizeof v);
}
