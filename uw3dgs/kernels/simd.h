// SIMD helpers of the compositing stage: GCC vector types over the pixels of a tile row.
#pragma once

#include "common.h"

namespace uw3dgs_kernels {
// ---------------------------------------------------------------------------------------------
// SIMD helpers
// ---------------------------------------------------------------------------------------------

// Compositing works on kLanes consecutive pixels of a tile row at once, written with GCC vector
// extensions so one source serves float and double and compiles to AVX-512, AVX2 or plain SSE. Every
// lane does exactly the scalar per-pixel arithmetic of the reference; masks replace its branches.
#ifdef __AVX512F__
constexpr int kLanes = 16;  // one 512-bit register of floats
#else
constexpr int kLanes = 8;   // one 256-bit register of floats
#endif

template <typename T>
struct Simd;
template <>
struct Simd<float> {
  typedef float V __attribute__((vector_size(kLanes * 4)));
  typedef int32_t I __attribute__((vector_size(kLanes * 4)));
  using Int = int32_t;
};
template <>
struct Simd<double> {
  typedef double V __attribute__((vector_size(kLanes * 8)));
  typedef int64_t I __attribute__((vector_size(kLanes * 8)));
  using Int = int64_t;
};

template <typename V, typename T>
inline V splat(T x) { return V{} + x; }

// Bit i set when lane i of the mask is set.
template <typename I>
inline unsigned mask_bits(const I& m) {
#if defined(__AVX512F__)
  const __m512i* h = reinterpret_cast<const __m512i*>(&m);
  if constexpr (sizeof(m[0]) == 4) {
    return static_cast<unsigned>(_mm512_test_epi32_mask(h[0], h[0]));
  } else {
    return static_cast<unsigned>(_mm512_test_epi64_mask(h[0], h[0])) |
           (static_cast<unsigned>(_mm512_test_epi64_mask(h[1], h[1])) << 8);
  }
#elif defined(__AVX2__)
  if constexpr (sizeof(m[0]) == 4) {
    return static_cast<unsigned>(_mm256_movemask_ps(_mm256_castsi256_ps(reinterpret_cast<const __m256i&>(m))));
  } else {
    const __m256i* h = reinterpret_cast<const __m256i*>(&m);
    return static_cast<unsigned>(_mm256_movemask_pd(_mm256_castsi256_pd(h[0]))) |
           (static_cast<unsigned>(_mm256_movemask_pd(_mm256_castsi256_pd(h[1]))) << 4);
  }
#else
  unsigned bits = 0;
  for (int i = 0; i < kLanes; ++i) bits |= (m[i] != 0 ? 1u : 0u) << i;
  return bits;
#endif
}

// Horizontal sum in a fixed order (deterministic): a pairwise tree, lanes i and i + n / 2 first.
template <typename T, typename V>
inline T hsum(const V& v) {
  T buf[kLanes];
  std::memcpy(buf, &v, sizeof v);
  for (int n = kLanes / 2; n > 0; n /= 2)
    for (int i = 0; i < n; ++i) buf[i] += buf[i + n];
  return buf[0];
}

// exp(x) for x in [-80, 80] (callers clamp), in plain vector arithmetic so it vectorises (exp_f32.h; the double
// version below: Cody-Waite reduction and Sleef's minimax polynomial, about 1 ulp like the Sleef exp torch uses).
inline Simd<float>::V vexp(Simd<float>::V x) {
  using V = Simd<float>::V;
  using I = Simd<float>::I;
  V q;
  const V u = exp_f32_reduced(x, q);
#ifdef __AVX512F__
  return _mm512_scalef_ps(u, q);  // u 2^q in one instruction: the same rounding as the product below
#else
  const I scale = (__builtin_convertvector(q, I) + 127) << 23;  // 2^q, a normal float for |q| <= 126
  return u * (V)scale;  // a vector cast reinterprets the bits
#endif
}

inline Simd<double>::V vexp(Simd<double>::V x) {
  using V = Simd<double>::V;
  using I = Simd<double>::I;
  V q = x * 1.442695040888963407359924681001892137;
  q = (q + 6755399441055744.0) - 6755399441055744.0;  // round to nearest: 1.5 * 2^52
  V s = x - q * .69314718055966295651160180568695068359375;
  s = s - q * .28235290563031577122588448175013436025525412068e-12;
  V u = splat<V>(+0.2081276378237164457e-8);
  u = u * s + 0.2511210703042288022e-7;
  u = u * s + 0.2755762628169491192e-6;
  u = u * s + 0.2755723402025388239e-5;
  u = u * s + 0.2480158687479686264e-4;
  u = u * s + 0.0001984126989855865850;
  u = u * s + 0.001388888888914497797;
  u = u * s + 0.008333333333314938210;
  u = u * s + 0.04166666666666602598;
  u = u * s + 0.1666666666666669072;
  u = u * s + 0.5;
  u = 1.0 + ((s * s) * u + s);
  const I scale = (__builtin_convertvector(q, I) + 1023) << 52;
  return u * (V)scale;
}

// a b + c, in one fused instruction for float where the CPU has it, for kernels whose results only need to be within
// float rounding of their references (-ffp-contract=off keeps every other product and sum rounded as the references').
template <typename V>
inline V vfmadd(V a, V b, V c) {
#if defined(__AVX512F__)
  if constexpr (std::is_same_v<V, Simd<float>::V>) return (V)_mm512_fmadd_ps((__m512)a, (__m512)b, (__m512)c);
#elif defined(__FMA__)
  if constexpr (std::is_same_v<V, Simd<float>::V>) return (V)_mm256_fmadd_ps((__m256)a, (__m256)b, (__m256)c);
#endif
  return a * b + c;
}

// exp(x) for x <= 80 (callers clamp above), floored at kExpFloor (the result is then below 2e-35), for values that
// only enter sums: the medium compositor's water factors, the direction MLP's sigmoid. Floats under AVX-512:
// exp_f32.h's reduction and polynomial with fused multiply-adds, the rounding by roundscale and the scaling by scalef,
// about 14 instructions instead of vexp's 22, within an ulp of it. Compositing's alpha also decides which pixels
// blend, so it stays vexp (the same bits in forward and backward).
inline Simd<float>::V vexp_floored(Simd<float>::V x) {
#ifdef __AVX512F__
  const auto c = [](float v) { return _mm512_set1_ps(v); };
  const __m512 xc = _mm512_max_ps(x, c(static_cast<float>(kExpFloor)));
  const __m512 q = _mm512_roundscale_ps(_mm512_mul_ps(xc, c(1.442695040888963407359924681001892137f)),
                                        _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  const __m512 s = _mm512_fnmadd_ps(q, c(1.428606765330187045e-06f), _mm512_fnmadd_ps(q, c(0.693145751953125f), xc));
  __m512 u = _mm512_fmadd_ps(s, c(0.000198527617612853646278381f), c(0.00139304355252534151077271f));
  for (const float k : {0.00833336077630519866943359f, 0.0416664853692054748535156f, 0.166666671633720397949219f,
                        0.5f})
    u = _mm512_fmadd_ps(u, s, c(k));
  u = _mm512_add_ps(_mm512_fmadd_ps(_mm512_mul_ps(s, s), u, s), c(1.0f));
  return _mm512_scalef_ps(u, q);
#else
  using V = Simd<float>::V;
  return vexp(V(x < static_cast<float>(kExpFloor) ? splat<V>(static_cast<float>(kExpFloor)) : x));
#endif
}

inline Simd<double>::V vexp_floored(Simd<double>::V x) {
  using V = Simd<double>::V;
  return vexp(V(x < kExpFloor ? splat<V>(kExpFloor) : x));
}

// ---------------------------------------------------------------------------------------------
// Compositing
// ---------------------------------------------------------------------------------------------

// A tile's Gaussians are composited in batches of kBatch, in two passes:
//  1. for every Gaussian of the batch and every kLanes-pixel chunk of its footprint box (chunks aligned
//     to the tile, so a pixel is always in the same lane), compute the exponent and test it; the chunks
//     with a pixel left are appended to a list without branching;
//  2. walk the list (in Gaussian order, which is all the per-pixel sums need) and blend, skipping the
//     pixels that terminated since pass 1.
// Pass 2 has no data-dependent branch but the rare early termination, so the CPU overlaps consecutive
// chunks instead of stalling on the exp's latency and on mispredicted short loops.
constexpr int64_t kBatch = 16;

// What the forward records for the backward. For every chunk in which a Gaussian blended a pixel, one
// 32-bit code: tile row, chunk column (kRowBits bits each) and the mask of blended lanes (top kLanes bits). Per
// (tile, Gaussian) pair the number of its codes; per tile its codes' thread buffer and range. The backward
// recomputes alpha at exactly those lanes (bit-identical: same code path), so it needs no footprint
// search, no exp of pixels that were not blended and no termination logic. About 4 bytes per blended chunk.
struct CodeBuf {  // growable without zero-filling; the memory is handed to a tensor at the end
  uint32_t* data = nullptr;
  int64_t size = 0, cap = 0;
  void reserve(int64_t n) {
    if (n <= cap) return;
    cap = std::max<int64_t>(n, 2 * cap);
    data = static_cast<uint32_t*>(std::realloc(data, cap * sizeof(uint32_t)));
    TORCH_CHECK(data != nullptr, "out of memory");
  }
  torch::Tensor release() {
    if (size == 0) { std::free(data); data = nullptr; return torch::empty({0}, torch::kInt32); }
    uint32_t* d = data;
    data = nullptr;
    return torch::from_blob(d, {size}, [](void* q) { std::free(q); }, torch::kInt32);
  }
  ~CodeBuf() { std::free(data); }
};
constexpr int kMaskShift = 32 - kLanes, kRowBits = kMaskShift / 2, kMaxTile = 1 << kRowBits;
}  // namespace uw3dgs_kernels
