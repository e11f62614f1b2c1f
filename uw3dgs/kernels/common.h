// What every stage of the compiled CPU rasterizer shares: includes, OpenMP shims, numerical constants.
// The stages (projection.cpp; footprint.h, binning.h, simd.h, compositing.h / compositing.cpp) numerically mirror
// uw3dgs/render/reference.py. Parallel across Gaussians (projection) and tiles (compositing) with OpenMP;
// compositing is SIMD across the pixels of a tile row (simd.h). Every gradient is written to a per-(tile, Gaussian)
// slot and reduced per Gaussian in a fixed order, so results are bitwise identical run to run and independent of
// the thread count (not of the SIMD width the build was compiled for: sums are split across lanes).
#pragma once

#include <torch/extension.h>

#include "exp_f32.h"
#include "vector_io.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <type_traits>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#else
inline int omp_get_max_threads() { return 1; }
inline int omp_get_thread_num() { return 0; }
#endif
#ifdef __AVX2__
#include <immintrin.h>
#endif

namespace uw3dgs_kernels {

constexpr double kFovClamp = 1.3;
constexpr double kExpFloor = -80.0;
// exp(e) < alpha_min is certain when e < log(alpha_min) - kLogMargin (exp's error is far below 1%), so
// such pixels are skipped before the exp; the exact alpha_min test decides the rest, as in the reference.
constexpr double kLogMargin = 0.01;
// Below this many Gaussians / (tile, Gaussian) pairs a loop runs on one thread: waking a team costs more,
// and far more on a loaded machine, where a descheduled thread stalls the whole region.
constexpr int64_t kParallelMin = 4096;

template <typename T>
inline T clampv(T v, T lo, T hi) { return v < lo ? lo : (v > hi ? hi : v); }


inline void check_cpu(const torch::Tensor& t, const char* name) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
}

}  // namespace uw3dgs_kernels
