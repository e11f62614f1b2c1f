// Footprints: what the tile loops need of one projected Gaussian, packed into one record per Gaussian.
#pragma once

#include "common.h"

namespace uw3dgs_kernels {
// ---------------------------------------------------------------------------------------------
// Footprints
// ---------------------------------------------------------------------------------------------

// What the tile loops need of one Gaussian, computed once per call (not once per tile it touches) and
// packed so that a (tile, Gaussian) pair reads one record.
//
// The footprint: pixels where the Gaussian can reach alpha_min lie in the ellipse
// {a dx^2 + 2 b dx dy + c dy^2 <= 2 lgap}, lgap = log(opacity) - log(alpha_min) + kLogMargin, whose box spans
// |dx| <= sqrt(2 lgap c / det) and |dy| <= sqrt(2 lgap a / det). These real-arithmetic bounds, widened by a
// pixel, are only used to skip pixels whose alpha is certainly below alpha_min; pixels inside get the
// reference's exact tests.
template <typename T>
struct GaussRec {
  T mx, my, a, b, c, op, logop, ha;  // ha = -a / 2
  int32_t x_lo, x_hi, y_lo, y_hi;    // pixel box (inclusive, clipped to the image); empty when y_lo > y_hi
};

// Pixels i (centre i + 0.5) with |i + 0.5 - centre| <= ext, widened by one, clipped to [0, size).
inline void pixel_range(double centre, double ext, int64_t size, int32_t& lo, int32_t& hi) {
  const double l = std::ceil(centre - ext - 0.5) - 1, u = std::floor(centre + ext - 0.5) + 1;
  // clamped in double first: no overflowing casts
  lo = static_cast<int32_t>(std::max(l, 0.0));
  hi = static_cast<int32_t>(std::min(u, static_cast<double>(size - 1)));
  if (!(l <= u) || lo > hi) { lo = 1; hi = 0; }
}

// The records live in a byte tensor, so that the forward can hand them to the backward.
template <typename T>
torch::Tensor gauss_records(const torch::Tensor& means2d, const torch::Tensor& conics,
                            const torch::Tensor& opacities, double log_cut, int64_t width, int64_t height) {
  const int64_t n = means2d.size(0);
  const T* m2 = means2d.data_ptr<T>();
  const T* cn = conics.data_ptr<T>();
  const T* op = opacities.data_ptr<T>();
  auto out = torch::empty({n * static_cast<int64_t>(sizeof(GaussRec<T>))}, torch::kUInt8);
  GaussRec<T>* recs = reinterpret_cast<GaussRec<T>*>(out.data_ptr<uint8_t>());
#pragma omp parallel for schedule(static) if (n >= kParallelMin)
  for (int64_t i = 0; i < n; ++i) {
    GaussRec<T>& g = recs[i];
    g.mx = m2[2 * i]; g.my = m2[2 * i + 1];
    g.a = cn[3 * i]; g.b = cn[3 * i + 1]; g.c = cn[3 * i + 2];
    g.op = op[i];
    g.ha = static_cast<T>(-0.5) * g.a;
    g.x_lo = 0; g.x_hi = static_cast<int32_t>(width - 1); g.y_lo = 0; g.y_hi = static_cast<int32_t>(height - 1);
    g.logop = std::log(g.op);
    const double a = g.a, b = g.b, c = g.c;
    const double lgap = static_cast<double>(g.logop) - log_cut;
    const double det = a * c - b * b;
    if (!(lgap >= 0)) { g.y_lo = 1; g.y_hi = 0; continue; }  // never reaches alpha_min (also NaN)
    if (!(a > 0) || !(det > 0) || !std::isfinite(det)) continue;  // degenerate conic: every pixel
    pixel_range(g.mx, std::sqrt(2.0 * lgap * c / det), width, g.x_lo, g.x_hi);
    pixel_range(g.my, std::sqrt(2.0 * lgap * a / det), height, g.y_lo, g.y_hi);
    if (g.x_lo > g.x_hi) { g.y_lo = 1; g.y_hi = 0; }
  }
  return out;
}

template <typename T>
const GaussRec<T>* records_of(const torch::Tensor& recs) {
  return reinterpret_cast<const GaussRec<T>*>(recs.data_ptr<uint8_t>());
}
}  // namespace uw3dgs_kernels
