// exp for float in plain arithmetic that vectorises (no libm call), shared by the rasterizer's compositing (GCC
// vector types) and the VM read's softplus (scalar float in a SIMD loop): Cody-Waite reduction and Sleef's
// minimax polynomial, about 1 ulp like the Sleef exp torch uses. Returns u with e^x = u 2^q; the caller scales by
// 2^q in its own type (a normal float for |q| <= 126, i.e. x in about [-87, 87]).
#pragma once

#include <cstdint>

template <typename V>
inline V exp_f32_reduced(V x, V& q) {
  q = x * 1.442695040888963407359924681001892137f;
  q = (q + 12582912.0f) - 12582912.0f;  // round to nearest: 1.5 * 2^23 (no -ffast-math, so not folded)
  V s = x - q * 0.693145751953125f;  // q * L2U is exact
  s = s - q * 1.428606765330187045e-06f;
  V u = s * 0.000198527617612853646278381f + 0.00139304355252534151077271f;
  u = u * s + 0.00833336077630519866943359f;
  u = u * s + 0.0416664853692054748535156f;
  u = u * s + 0.166666671633720397949219f;
  u = u * s + 0.5f;
  return 1.0f + ((s * s) * u + s);
}

// e^x for float x in [-87, 87] (callers clamp), in arithmetic that vectorises in a SIMD loop.
inline float exp_f32(float x) {
  float q;
  const float u = exp_f32_reduced(x, q);
  const int32_t bits = (static_cast<int32_t>(q) + 127) << 23;  // 2^q
  float scale;
  __builtin_memcpy(&scale, &bits, sizeof scale);
  return u * scale;
}
