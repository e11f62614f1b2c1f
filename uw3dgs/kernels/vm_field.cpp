// Compiled CPU read of TensoRF vector-matrix (VM) fields and its backward: f(u) = softplus(W feats(u) + b), feats
// the 3R products of bilinear plane reads and linear line reads (fields/medium.py, VMField). Numerically mirrors
// VMField.forward_reference: grid_sample's align_corners=True coordinates, zero padding, softplus threshold 20.
// One pass per point instead of PyTorch's twelve grid_samples per field, their stacking, the basis product and
// the softplus, each a full pass over memory with its own backward. Several fields of one shape read at the same
// points (the medium's beta_D and beta_B) share the point's cell lookups. The factors are read channel-last, so a
// point's R components are contiguous; at R = 16 (the default) a mode's components are one GCC vector held in
// registers (Lanes16). The forward also returns the pre-activations, so the backward takes softplus's derivative
// in one vectorised pass and recomputes only a point's reads, not its [3R] features. Factor gradients are summed
// per chunk of points, the chunks fixed by N alone, and the chunks reduced in order: bitwise identical results run
// to run and whatever the thread count. The same reads with a rank per mode over box-shaped grids, as plain products
// for TensoRF's field (`vm_products_forward` / `vm_products_backward`), follow at the end of the file.
#include <torch/extension.h>

#include "exp_f32.h"
#include "vector_io.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <type_traits>
#include <vector>

namespace {

constexpr int kModes[3][3] = {{0, 1, 2}, {0, 2, 1}, {1, 2, 0}};  // (plane row axis, plane column axis, line axis)
// Backward chunks: at least this many points each, at most kMaxChunks of them (each holds a copy of the factor
// gradients, ~0.8 MB per field at G = 64, R = 16, zeroed and summed every call: more chunks cost more than the
// parallelism they add on the few cores of a CPU training machine). L_beta's 4,096 points make two chunks.
constexpr int64_t kChunkPoints = 2048;
constexpr int64_t kMaxChunks = 4;
constexpr double kSoftplusThreshold = 20.0;

// One axis of a grid read: the lower cell, the upper cell's weight, and which of the two cells are inside.
template <typename T>
struct Axis {
  int64_t i0;
  T w[2];
  bool in[2];
};

template <typename T>
inline Axis<T> axis(T u, int64_t size) {
  const T pos = (u + T(1)) / T(2) * T(size - 1);  // grid_sample, align_corners=True
  const T lower = std::floor(pos);
  const int64_t i0 = static_cast<int64_t>(lower);
  return {i0, {T(1) - (pos - lower), pos - lower}, {i0 >= 0 && i0 < size, i0 + 1 >= 0 && i0 + 1 < size}};
}

// A point's cells in every mode: plane row, plane column and line axes.
template <typename T>
struct Cells {
  Axis<T> row[3], col[3], lin[3];
};

template <typename T>
inline void locate(const T* u, int64_t G, Cells<T>& cells) {
  for (int m = 0; m < 3; ++m) {
    cells.row[m] = axis(u[kModes[m][0]], G);
    cells.col[m] = axis(u[kModes[m][1]], G);
    cells.lin[m] = axis(u[kModes[m][2]], G);
  }
}

// One field: channel-last copies of its factors (plane[m][row][col][r], line[m][k][r]), its basis and bias.
template <typename T>
struct Field {
  std::vector<T> plane, line;
  const T* basis;
  const T* bias;
};

template <typename T>
std::vector<Field<T>> channel_last(const std::vector<torch::Tensor>& planes, const std::vector<torch::Tensor>& lines,
                                   const std::vector<torch::Tensor>& basis, const std::vector<torch::Tensor>& bias) {
  std::vector<Field<T>> fields;
  const int64_t F = planes.size(), R = planes[0].size(1), G = planes[0].size(2);
  for (int64_t f = 0; f < F; ++f)
    fields.push_back({std::vector<T>(3 * G * G * R), std::vector<T>(3 * G * R), basis[f].data_ptr<T>(),
                      bias[f].data_ptr<T>()});
#pragma omp parallel for collapse(2) schedule(static) if (F * 3 * G * G * R >= kChunkPoints)
  for (int64_t f = 0; f < F; ++f)
    for (int64_t m = 0; m < 3; ++m) {
      const T* p = planes[f].data_ptr<T>();
      const T* l = lines[f].data_ptr<T>();
      // cell by cell: each cell's R values written as one run (R streams read), not R passes over the copy
      for (int64_t c = 0; c < G * G; ++c)
        for (int64_t r = 0; r < R; ++r) fields[f].plane[(m * G * G + c) * R + r] = p[(m * R + r) * G * G + c];
      for (int64_t k = 0; k < G; ++k)
        for (int64_t r = 0; r < R; ++r) fields[f].line[(m * G + k) * R + r] = l[(m * R + r) * G + k];
    }
  return fields;
}

// A field's plane values pv and line values lv [3R] at a located point; with SLOPES also their derivatives along
// the plane's row and column axes (srow, scol) and the line's axis (slin), [3R] each, in cells.
template <typename T, bool SLOPES>
inline void read_field(const Cells<T>& cells, const Field<T>& f, int64_t R, int64_t G, T* pv, T* lv,
                       T* srow = nullptr, T* scol = nullptr, T* slin = nullptr) {
  for (int m = 0; m < 3; ++m) {
    const Axis<T>&ar = cells.row[m], &ac = cells.col[m], &al = cells.lin[m];
    T* p = pv + m * R;
    T* l = lv + m * R;
    for (int64_t r = 0; r < R; ++r) p[r] = 0, l[r] = 0;
    if constexpr (SLOPES)
      for (int64_t r = 0; r < R; ++r) srow[m * R + r] = 0, scol[m * R + r] = 0, slin[m * R + r] = 0;
    for (int dy = 0; dy < 2; ++dy)
      for (int dx = 0; dx < 2; ++dx) {
        if (!ar.in[dy] || !ac.in[dx]) continue;
        const T w = ar.w[dy] * ac.w[dx];
        const T* src = f.plane.data() + ((m * G + ar.i0 + dy) * G + ac.i0 + dx) * R;
#pragma omp simd
        for (int64_t r = 0; r < R; ++r) p[r] += w * src[r];
        if constexpr (SLOPES) {
          // d w / d row = +-w_col, d w / d col = +-w_row: the bilinear weights' derivatives
          const T wy = (dy ? T(1) : T(-1)) * ac.w[dx], wx = (dx ? T(1) : T(-1)) * ar.w[dy];
          T *sr = srow + m * R, *sc = scol + m * R;
#pragma omp simd
          for (int64_t r = 0; r < R; ++r) sr[r] += wy * src[r], sc[r] += wx * src[r];
        }
      }
    for (int dz = 0; dz < 2; ++dz) {
      if (!al.in[dz]) continue;
      const T* src = f.line.data() + (m * G + al.i0 + dz) * R;
#pragma omp simd
      for (int64_t r = 0; r < R; ++r) l[r] += al.w[dz] * src[r];
      if constexpr (SLOPES) {
        const T wz = dz ? T(1) : T(-1);
        T* sl = slin + m * R;
#pragma omp simd
        for (int64_t r = 0; r < R; ++r) sl[r] += wz * src[r];
      }
    }
  }
}

// pre = W (pv * lv) + b for one point and field ([C]).
template <typename T>
inline void basis_product(const T* pv, const T* lv, const Field<T>& f, int64_t C, int64_t R, T* pre) {
  const int64_t K = 3 * R;
  for (int64_t c = 0; c < C; ++c) {
    T s = 0;
    const T* w = f.basis + c * K;
#pragma omp simd reduction(+ : s)
    for (int64_t k = 0; k < K; ++k) s += w[k] * (pv[k] * lv[k]);
    pre[c] = s + f.bias[c];
  }
}

// softplus(x) = log(1 + e^x), x itself above the threshold (PyTorch's rule), over n contiguous values in place.
// float: in plain arithmetic that vectorises (one libm exp and log1p per value cost as much as the rest of the
// read): max(x, 0) + log1p(e^-|x|), e^-|x| as the rasterizer's exp (exp_f32.h), log1p(z) = 2 atanh(z / (2 + z)) by its odd series, z in (0, 1] so t <= 1/3 and seven terms
// reach float precision (the first omitted is below 1.5e-8 t); within 3e-7 relative of the exact value over
// [-87, 20] (tests/test_medium.py), and e^-87 below (libm: a denormal or 0). double: libm.
inline void softplus_inplace(double* x, int64_t n) {
#pragma omp parallel for schedule(static) if (n >= kChunkPoints)
  for (int64_t i = 0; i < n; ++i) x[i] = x[i] > kSoftplusThreshold ? x[i] : std::log1p(std::exp(x[i]));
}

inline void softplus_inplace(float* x, int64_t n) {
#pragma omp parallel for simd schedule(static) if (n >= kChunkPoints)
  for (int64_t i = 0; i < n; ++i) {
    const float v = x[i];
    const float z = exp_f32(std::max(-std::fabs(v), -87.0f));  // e^-|v|, in (0, 1]: a normal float
    const float t = z / (2.0f + z), t2 = t * t;
    float r = 1.0f / 13.0f;
    r = r * t2 + 1.0f / 11.0f;
    r = r * t2 + 1.0f / 9.0f;
    r = r * t2 + 1.0f / 7.0f;
    r = r * t2 + 1.0f / 5.0f;
    r = r * t2 + 1.0f / 3.0f;
    r = r * t2 + 1.0f;
    const float sp = std::max(v, 0.0f) + 2.0f * t * r;
    x[i] = v > static_cast<float>(kSoftplusThreshold) ? v : sp;
  }
}

int64_t num_chunks(int64_t n) { return std::max<int64_t>(1, std::min<int64_t>(kMaxChunks, n / kChunkPoints)); }

// pre_out [N, F C] = W feats(u) + b of every point and field, out = softplus(pre_out). R16: R is 16 (Lanes16).
template <typename T, bool R16>
void forward_impl(const torch::Tensor& u, const std::vector<Field<T>>& fields, int64_t R, int64_t G, int64_t C,
                  torch::Tensor& out, torch::Tensor& pre_out) {
  const int64_t n = u.size(0), F = fields.size(), K = 3 * R;
  const T* up = u.data_ptr<T>();
  T* pre = pre_out.data_ptr<T>();
#pragma omp parallel if (n >= kChunkPoints)
  {
    std::vector<T> pv(R16 ? 0 : K), lv(R16 ? 0 : K);
    Cells<T> cells;
#pragma omp for schedule(static)
    for (int64_t i = 0; i < n; ++i) {
      locate(up + 3 * i, G, cells);
      for (int64_t f = 0; f < F; ++f) {
        if constexpr (R16) {
          pre_activation16<T>(cells, fields[f], G, C, pre + (i * F + f) * C);
        } else {
          read_field<T, false>(cells, fields[f], R, G, pv.data(), lv.data());
          basis_product<T>(pv.data(), lv.data(), fields[f], C, R, pre + (i * F + f) * C);
        }
      }
    }
  }
  T* o = out.data_ptr<T>();
  std::copy(pre, pre + n * F * C, o);
  softplus_inplace(o, n * F * C);
}

// d softplus(x) / dx = sigmoid(x) (1 above softplus's threshold, where softplus is x) times the output's gradient,
// over n contiguous values: g = go / (1 + e^-x). float: e^-x as the rasterizer's exp (exp_f32.h) in arithmetic that
// vectorises, x clamped to [-87, 87] (sigmoid there is 1 - 1.6e-38 or 1.6e-38; the exact value is within 2e-38).
inline void sigmoid_times(const double* x, const double* go, double* g, int64_t n) {
#pragma omp parallel for schedule(static) if (n >= kChunkPoints)
  for (int64_t i = 0; i < n; ++i) g[i] = x[i] > kSoftplusThreshold ? go[i] : go[i] / (1.0 + std::exp(-x[i]));
}

inline void sigmoid_times(const float* x, const float* go, float* g, int64_t n) {
#pragma omp parallel for simd schedule(static) if (n >= kChunkPoints)
  for (int64_t i = 0; i < n; ++i) {
    const float s = go[i] / (1.0f + exp_f32(std::min(std::max(-x[i], -87.0f), 87.0f)));
    g[i] = x[i] > static_cast<float>(kSoftplusThreshold) ? go[i] : s;
  }
}

// R = 16 (the default component count): a mode's 16 components as one GCC vector, kept in registers (one AVX-512
// register of floats, two of AVX2, four of SSE; the compiler splits it to the hardware). Element-wise arithmetic is
// the scalar code's, lane by lane; only the sums over components are in a fixed tree order.
template <typename T>
struct Lanes16;
template <>
struct Lanes16<float> {
  typedef float V __attribute__((vector_size(64)));
  typedef float Half __attribute__((vector_size(32)));
  typedef float Quarter __attribute__((vector_size(16)));
};
template <>
struct Lanes16<double> {
  typedef double V __attribute__((vector_size(128)));
  typedef double Half __attribute__((vector_size(64)));
  typedef double Quarter __attribute__((vector_size(32)));
};

// Sum of the 16 lanes, halves added pairwise (8 + 8, 4 + 4, then the last four in order).
template <typename T>
inline T lane_sum(const typename Lanes16<T>::V& v) {
  using L = Lanes16<T>;
  typename L::Half lo, hi;
  std::memcpy(&lo, &v, sizeof lo);
  std::memcpy(&hi, reinterpret_cast<const char*>(&v) + sizeof lo, sizeof hi);
  const typename L::Half h = lo + hi;
  typename L::Quarter qlo, qhi;
  std::memcpy(&qlo, &h, sizeof qlo);
  std::memcpy(&qhi, reinterpret_cast<const char*>(&h) + sizeof qlo, sizeof qhi);
  const typename L::Quarter q = qlo + qhi;
  return (q[0] + q[1]) + (q[2] + q[3]);
}

// One mode's reads at a located point: plane value pv and line value lv; with SLOPES also their derivatives along
// the plane's row and column axes and the line's axis, in cells.
template <typename T, bool SLOPES>
struct ModeRead {
  typename Lanes16<T>::V pv, lv, srow, scol, slin;
};

template <typename T, bool SLOPES, int M>
inline ModeRead<T, SLOPES> read_mode16(const Cells<T>& cells, const Field<T>& f, int64_t G) {
  using V = typename Lanes16<T>::V;
  constexpr int R = 16;
  const Axis<T>&ar = cells.row[M], &ac = cells.col[M], &al = cells.lin[M];
  ModeRead<T, SLOPES> out{};
  for (int dz = 0; dz < 2; ++dz) {
    if (!al.in[dz]) continue;
    const V src = vload<V>(f.line.data() + (M * G + al.i0 + dz) * R);
    out.lv += al.w[dz] * src;
    if constexpr (SLOPES) out.slin += (dz ? T(1) : T(-1)) * src;
  }
  for (int dy = 0; dy < 2; ++dy)
    for (int dx = 0; dx < 2; ++dx) {
      if (!ar.in[dy] || !ac.in[dx]) continue;
      const V src = vload<V>(f.plane.data() + ((M * G + ar.i0 + dy) * G + ac.i0 + dx) * R);
      out.pv += (ar.w[dy] * ac.w[dx]) * src;
      if constexpr (SLOPES) {
        // d w / d row = +-w_col, d w / d col = +-w_row: the bilinear weights' derivatives
        out.srow += ((dy ? T(1) : T(-1)) * ac.w[dx]) * src;
        out.scol += ((dx ? T(1) : T(-1)) * ar.w[dy]) * src;
      }
    }
  return out;
}

// pre [C] = W (pv * lv) + b of one field at a located point.
template <typename T>
inline void pre_activation16(const Cells<T>& cells, const Field<T>& f, int64_t G, int64_t C, T* pre) {
  using V = typename Lanes16<T>::V;
  const ModeRead<T, false> r0 = read_mode16<T, false, 0>(cells, f, G), r1 = read_mode16<T, false, 1>(cells, f, G),
                           r2 = read_mode16<T, false, 2>(cells, f, G);
  const V f0 = r0.pv * r0.lv, f1 = r1.pv * r1.lv, f2 = r2.pv * r2.lv;
  for (int64_t c = 0; c < C; ++c) {
    const T* w = f.basis + c * 48;
    const V s = (vload<V>(w) * f0 + vload<V>(w + 16) * f1) + vload<V>(w + 32) * f2;
    pre[c] = lane_sum<T>(s) + f.bias[c];
  }
}

// One mode's share of a point's backward (see backward_point16).
template <typename T, int M>
inline void backward_mode16(const Cells<T>& cells, const Field<T>& f, const T* gpre, int64_t G, int64_t C,
                            const typename Lanes16<T>::V& gf, typename Lanes16<T>::V* du_lanes, T* gp, T* gl, T* gw) {
  using V = typename Lanes16<T>::V;
  constexpr int R = 16;
  const ModeRead<T, true> r = read_mode16<T, true, M>(cells, f, G);
  const V gval = gf * r.lv, gline = gf * r.pv;  // d loss / d plane value, d loss / d line value
  du_lanes[kModes[M][0]] += gval * r.srow;
  du_lanes[kModes[M][1]] += gval * r.scol;
  du_lanes[kModes[M][2]] += gline * r.slin;
  const V feat = r.pv * r.lv;
  for (int64_t c = 0; c < C; ++c) {
    T* dst = gw + c * 48 + M * R;
    vstore(dst, vload<V>(dst) + gpre[c] * feat);
  }
  const Axis<T>&ar = cells.row[M], &ac = cells.col[M], &al = cells.lin[M];
  for (int dy = 0; dy < 2; ++dy)
    for (int dx = 0; dx < 2; ++dx) {
      if (!ar.in[dy] || !ac.in[dx]) continue;
      T* dst = gp + ((M * G + ar.i0 + dy) * G + ac.i0 + dx) * R;
      vstore(dst, vload<V>(dst) + (ar.w[dy] * ac.w[dx]) * gval);
    }
  for (int dz = 0; dz < 2; ++dz) {
    if (!al.in[dz]) continue;
    T* dst = gl + (M * G + al.i0 + dz) * R;
    vstore(dst, vload<V>(dst) + al.w[dz] * gline);
  }
}

// backward_point for R = 16, in registers.
template <typename T>
inline void backward_point16(const Cells<T>& cells, const Field<T>& f, const T* gpre, int64_t G, int64_t C, T* gp,
                             T* gl, T* gw, T* gb, T* du) {
  using V = typename Lanes16<T>::V;
  V gf0{}, gf1{}, gf2{};  // d loss / d feature = W^T gpre, per mode
  for (int64_t c = 0; c < C; ++c) {
    const T g = gpre[c];
    const T* w = f.basis + c * 48;
    gb[c] += g;
    gf0 += vload<V>(w) * g;
    gf1 += vload<V>(w + 16) * g;
    gf2 += vload<V>(w + 32) * g;
  }
  V du_lanes[3] = {};
  backward_mode16<T, 0>(cells, f, gpre, G, C, gf0, du_lanes, gp, gl, gw);
  backward_mode16<T, 1>(cells, f, gpre, G, C, gf1, du_lanes, gp, gl, gw);
  backward_mode16<T, 2>(cells, f, gpre, G, C, gf2, du_lanes, gp, gl, gw);
  const T half_span = T(G - 1) / T(2);
  for (int a = 0; a < 3; ++a) du[a] += lane_sum<T>(du_lanes[a]) * half_span;
}

// Adds one point's gradients of one field (`gpre` [C]: d loss / d its pre-activation) to the chunk's accumulators
// (gp, gl channel-last, gw [C, K], gb [C]) and d loss / d u to du [3]. `work` holds 7 K values. Any R.
template <typename T>
inline void backward_point(const Cells<T>& cells, const Field<T>& f, const T* gpre, int64_t R, int64_t G, int64_t C,
                           T* work, T* gp, T* gl, T* gw, T* gb, T* du) {
  const int64_t K = 3 * R;
  T *pv = work, *lv = pv + K, *srow = lv + K, *scol = srow + K, *slin = scol + K, *gf = slin + K, *gval = gf + K;
  read_field<T, true>(cells, f, R, G, pv, lv, srow, scol, slin);
  for (int64_t k = 0; k < K; ++k) gf[k] = 0;
  for (int64_t c = 0; c < C; ++c) {
    const T g = gpre[c];
    gb[c] += g;
    T* gwc = gw + c * K;
    const T* wc = f.basis + c * K;
#pragma omp simd
    for (int64_t k = 0; k < K; ++k) {
      gwc[k] += g * (pv[k] * lv[k]);
      gf[k] += wc[k] * g;
    }
  }
  const T half_span = T(G - 1) / T(2);
  for (int m = 0; m < 3; ++m) {
    const Axis<T>&ar = cells.row[m], &ac = cells.col[m], &al = cells.lin[m];
    const int64_t o = m * R;
    // d loss / d plane value (gval) and d loss / d line value (gf * pv), and the slopes' share of d loss / d u
    T drow = 0, dcol = 0, dlin = 0;
#pragma omp simd reduction(+ : drow, dcol, dlin)
    for (int64_t r = 0; r < R; ++r) {
      gval[o + r] = gf[o + r] * lv[o + r];
      drow += gval[o + r] * srow[o + r];
      dcol += gval[o + r] * scol[o + r];
      dlin += gf[o + r] * pv[o + r] * slin[o + r];
    }
    for (int dy = 0; dy < 2; ++dy)
      for (int dx = 0; dx < 2; ++dx) {
        if (!ar.in[dy] || !ac.in[dx]) continue;
        T* dst = gp + ((m * G + ar.i0 + dy) * G + ac.i0 + dx) * R;
        const T w = ar.w[dy] * ac.w[dx];
#pragma omp simd
        for (int64_t r = 0; r < R; ++r) dst[r] += w * gval[o + r];
      }
    for (int dz = 0; dz < 2; ++dz) {
      if (!al.in[dz]) continue;
      T* dst = gl + (m * G + al.i0 + dz) * R;
#pragma omp simd
      for (int64_t r = 0; r < R; ++r) dst[r] += al.w[dz] * (gf[o + r] * pv[o + r]);
    }
    du[kModes[m][0]] += drow * half_span;
    du[kModes[m][1]] += dcol * half_span;
    du[kModes[m][2]] += dlin * half_span;
  }
}

template <typename T, bool R16>
void backward_impl(const torch::Tensor& u, const torch::Tensor& pre, const std::vector<Field<T>>& fields, int64_t R,
                   int64_t G, int64_t C, const torch::Tensor& grad_out, torch::Tensor& g_u,
                   std::vector<torch::Tensor>& g_planes, std::vector<torch::Tensor>& g_lines,
                   std::vector<torch::Tensor>& g_basis, std::vector<torch::Tensor>& g_bias) {
  const int64_t n = u.size(0), F = fields.size(), K = 3 * R;
  const int64_t chunks = num_chunks(n), plane_size = 3 * G * G * R, line_size = 3 * G * R;
  const int64_t block = plane_size + line_size + C * K + C;  // one field's accumulators: planes, lines, W, b
  // each chunk's thread zeroes its own accumulators (in parallel, and in that thread's memory)
  std::unique_ptr<T[]> acc(new T[chunks * F * block]);
  std::unique_ptr<T[]> gpre(new T[n * F * C]);  // d loss / d pre-activation of every point and field
  sigmoid_times(pre.data_ptr<T>(), grad_out.data_ptr<T>(), gpre.get(), n * F * C);
  const T* up = u.data_ptr<T>();
  T* gu = g_u.data_ptr<T>();
#pragma omp parallel if (n >= kChunkPoints)
  {
    std::vector<T> work(R16 ? 0 : 7 * K);
    Cells<T> cells;
#pragma omp for schedule(static, 1)
    for (int64_t chunk = 0; chunk < chunks; ++chunk) {
      const int64_t begin = n * chunk / chunks, end = n * (chunk + 1) / chunks;
      std::fill(acc.get() + chunk * F * block, acc.get() + (chunk + 1) * F * block, T(0));
      for (int64_t i = begin; i < end; ++i) gu[3 * i] = gu[3 * i + 1] = gu[3 * i + 2] = 0;
      // one field at a time: its factors and their gradients (~1.5 MB at G = 64, R = 16) stay in a core's cache
      for (int64_t f = 0; f < F; ++f) {
        T* gp = acc.get() + (chunk * F + f) * block;
        T* gl = gp + plane_size;
        T* gw = gl + line_size;
        for (int64_t i = begin; i < end; ++i) {
          locate(up + 3 * i, G, cells);
          const T* g = gpre.get() + (i * F + f) * C;
          if constexpr (R16)
            backward_point16<T>(cells, fields[f], g, G, C, gp, gl, gw, gw + C * K, gu + 3 * i);
          else
            backward_point<T>(cells, fields[f], g, R, G, C, work.data(), gp, gl, gw, gw + C * K, gu + 3 * i);
        }
      }
    }
  }
  T* a = acc.get();
  const int64_t total = F * block;
  // each sum adds the chunks in order, whichever thread does it: the result does not depend on the threads (chunk
  // by chunk over contiguous runs, which vectorise; element by element across chunks would stride)
#pragma omp parallel for schedule(static) if (chunks > 1 && total >= kChunkPoints)
  for (int64_t j0 = 0; j0 < total; j0 += 4096) {
    const int64_t j1 = std::min(total, j0 + 4096);
    for (int64_t chunk = 1; chunk < chunks; ++chunk)
#pragma omp simd
      for (int64_t j = j0; j < j1; ++j) a[j] += a[chunk * total + j];
  }
#pragma omp parallel for collapse(2) schedule(static) if (total >= kChunkPoints)
  for (int64_t f = 0; f < F; ++f)  // back to the factors' own layout
    for (int64_t m = 0; m < 3; ++m) {
      const T* af = a + f * block;
      T *out_p = g_planes[f].data_ptr<T>(), *out_l = g_lines[f].data_ptr<T>();
      for (int64_t c = 0; c < G * G; ++c)  // cell by cell, as channel_last
        for (int64_t r = 0; r < R; ++r) out_p[(m * R + r) * G * G + c] = af[(m * G * G + c) * R + r];
      for (int64_t k = 0; k < G; ++k)
        for (int64_t r = 0; r < R; ++r) out_l[(m * R + r) * G + k] = af[plane_size + (m * G + k) * R + r];
    }
  for (int64_t f = 0; f < F; ++f) {
    const T* af = a + f * block;
    std::copy(af + plane_size + line_size, af + plane_size + line_size + C * K, g_basis[f].data_ptr<T>());
    std::copy(af + plane_size + line_size + C * K, af + block, g_bias[f].data_ptr<T>());
  }
}

void check_inputs(const torch::Tensor& u, const std::vector<torch::Tensor>& planes,
                  const std::vector<torch::Tensor>& lines, const std::vector<torch::Tensor>& basis,
                  const std::vector<torch::Tensor>& bias) {
  const size_t F = planes.size();
  TORCH_CHECK(F >= 1 && lines.size() == F && basis.size() == F && bias.size() == F,
              "vm_fields: one plane, line, basis and bias tensor per field");
  TORCH_CHECK(u.dim() == 2 && u.size(1) == 3, "vm_fields: points must be [N, 3]");
  std::vector<const torch::Tensor*> all{&u};
  for (size_t f = 0; f < F; ++f) {
    all.insert(all.end(), {&planes[f], &lines[f], &basis[f], &bias[f]});
    TORCH_CHECK(planes[f].sizes() == planes[0].sizes() && basis[f].sizes() == basis[0].sizes(),
                "vm_fields: every field must have the same shape");
  }
  for (const torch::Tensor* t : all) {
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous(), "vm_fields: inputs must be contiguous CPU tensors");
    TORCH_CHECK(t->scalar_type() == u.scalar_type(), "vm_fields: inputs must share one dtype");
  }
  const auto& p = planes[0];
  TORCH_CHECK(p.dim() == 4 && p.size(0) == 3 && p.size(2) == p.size(3), "vm_fields: planes must be [3, R, G, G]");
  TORCH_CHECK(lines[0].dim() == 3 && lines[0].size(0) == 3 && lines[0].size(1) == p.size(1) &&
                  lines[0].size(2) == p.size(2),
              "vm_fields: lines must be [3, R, G]");
  TORCH_CHECK(basis[0].dim() == 2 && basis[0].size(1) == 3 * p.size(1) && bias[0].dim() == 1 &&
                  bias[0].size(0) == basis[0].size(0),
              "vm_fields: basis must be [C, 3R] and bias [C]");
}

}  // namespace

// (softplus(W_f feats_f(u) + b_f), W_f feats_f(u) + b_f) of every field f, each [N, F * C] (field-major per point),
// at points u [N, 3] in [-1, 1]: the values and their pre-activations, which the backward takes.
std::vector<torch::Tensor> vm_fields_forward(torch::Tensor u, std::vector<torch::Tensor> planes, std::vector<torch::Tensor> lines,
                                std::vector<torch::Tensor> basis, std::vector<torch::Tensor> bias) {
  check_inputs(u, planes, lines, basis, bias);
  const int64_t F = planes.size(), R = planes[0].size(1), G = planes[0].size(2), C = basis[0].size(0);
  auto out = torch::empty({u.size(0), F * C}, u.options()), pre = torch::empty_like(out);
  AT_DISPATCH_FLOATING_TYPES(u.scalar_type(), "vm_fields_forward", [&] {
    const auto fields = channel_last<scalar_t>(planes, lines, basis, bias);
    if (R == 16)  // the default component count, unrolled
      forward_impl<scalar_t, true>(u, fields, R, G, C, out, pre);
    else
      forward_impl<scalar_t, false>(u, fields, R, G, C, out, pre);
  });
  return {out, pre};
}

// (d u [N, 3], d planes, d lines, d basis, d bias per field) given grad_out [N, F * C] and the forward's
// pre-activations `pre` [N, F * C].
std::vector<std::vector<torch::Tensor>> vm_fields_backward(torch::Tensor u, std::vector<torch::Tensor> planes,
                                                           std::vector<torch::Tensor> lines,
                                                           std::vector<torch::Tensor> basis,
                                                           std::vector<torch::Tensor> bias, torch::Tensor pre,
                                                           torch::Tensor grad_out) {
  check_inputs(u, planes, lines, basis, bias);
  const int64_t F = planes.size(), R = planes[0].size(1), G = planes[0].size(2), C = basis[0].size(0);
  for (const torch::Tensor* t : {&pre, &grad_out})
    TORCH_CHECK(t->is_contiguous() && t->scalar_type() == u.scalar_type() && t->dim() == 2 &&
                    t->size(0) == u.size(0) && t->size(1) == F * C,
                "vm_fields: pre and grad_out must be contiguous [N, F * C] tensors of the points' dtype");
  std::vector<torch::Tensor> g_u{torch::empty_like(u)}, g_planes, g_lines, g_basis, g_bias;
  for (int64_t f = 0; f < F; ++f) {
    g_planes.push_back(torch::empty_like(planes[f]));
    g_lines.push_back(torch::empty_like(lines[f]));
    g_basis.push_back(torch::empty_like(basis[f]));
    g_bias.push_back(torch::empty_like(bias[f]));
  }
  AT_DISPATCH_FLOATING_TYPES(u.scalar_type(), "vm_fields_backward", [&] {
    const auto fields = channel_last<scalar_t>(planes, lines, basis, bias);
    if (R == 16)
      backward_impl<scalar_t, true>(u, pre, fields, R, G, C, grad_out, g_u[0], g_planes, g_lines, g_basis, g_bias);
    else
      backward_impl<scalar_t, false>(u, pre, fields, R, G, C, grad_out, g_u[0], g_planes, g_lines, g_basis,
                                     g_bias);
  });
  return {g_u, g_planes, g_lines, g_basis, g_bias};
}

// VM products: the same plane and line reads with a rank per mode and a box-shaped grid (a size per axis), without
// the basis and the softplus: per point, the products P_{m,r}(u) L_{m,r}(u) of every mode m and component r,
// concatenated mode by mode [N, sum_m R_m], or summed [N] (TensoRF's appearance features before its basis, and its
// density feature: fields/tensorf.py). Each mode names the axes of u along its plane's rows and columns and its
// line, so the one read serves either axis convention. The factors are copied into blocks of at most kBlock
// components, each block channel-last (cell by cell, the block's components contiguous), so that a point's read of
// a block is one contiguous run per cell. The backward gives the planes' and lines' gradients (the points get none:
// TensoRF's samples are not trained); each block's gradients are a separate region, summed by one thread in point
// order: bitwise identical results whatever the thread count, with no per-thread copies of the (large) grids.
namespace {

constexpr int64_t kBlock = 16;

// One mode's factors in blocks (see above): the element (component r, cell c) of a block starting at component r0
// of width w sits at r0 * cells + c * w + (r - r0), for the plane and, with cells = len, the line.
template <typename T>
struct BlockedMode {
  std::vector<T> plane, line;
  int64_t R, rows, cols, len, offset;  // offset: the mode's first column of the concatenated products
  int64_t row_axis, col_axis, line_axis;
};

struct Block {
  int64_t mode, r0, w;
};

std::vector<Block> blocks_of(const std::vector<torch::Tensor>& planes) {
  std::vector<Block> blocks;
  for (int64_t m = 0; m < static_cast<int64_t>(planes.size()); ++m)
    for (int64_t r0 = 0; r0 < planes[m].size(0); r0 += kBlock)
      blocks.push_back({m, r0, std::min(kBlock, planes[m].size(0) - r0)});
  return blocks;
}

// Channel-first [R, cells] <-> blocked, one block at a time (TO_BLOCKED: src channel-first, dst blocked).
template <typename T, bool TO_BLOCKED>
inline void reorder_block(const T* src, T* dst, int64_t cells, int64_t r0, int64_t w) {
  for (int64_t c = 0; c < cells; ++c)
    for (int64_t r = 0; r < w; ++r) {
      const int64_t first = (r0 + r) * cells + c, blocked = r0 * cells + c * w + r;
      if constexpr (TO_BLOCKED)
        dst[blocked] = src[first];
      else
        dst[first] = src[blocked];
    }
}

int64_t factor_size(const std::vector<torch::Tensor>& planes, const std::vector<torch::Tensor>& lines) {
  int64_t size = 0;
  for (size_t m = 0; m < planes.size(); ++m) size += planes[m].numel() + lines[m].numel();
  return size;
}

template <typename T>
std::vector<BlockedMode<T>> blocked_modes(const std::vector<torch::Tensor>& planes,
                                          const std::vector<torch::Tensor>& lines, const std::vector<int64_t>& axes,
                                          const std::vector<Block>& blocks) {
  std::vector<BlockedMode<T>> modes;
  int64_t offset = 0;
  for (size_t m = 0; m < planes.size(); ++m) {
    const int64_t R = planes[m].size(0), rows = planes[m].size(1), cols = planes[m].size(2), len = lines[m].size(1);
    modes.push_back({std::vector<T>(R * rows * cols), std::vector<T>(R * len), R, rows, cols, len, offset,
                     axes[3 * m], axes[3 * m + 1], axes[3 * m + 2]});
    offset += R;
  }
  const int64_t nb = blocks.size(), size = factor_size(planes, lines);
#pragma omp parallel for schedule(dynamic, 1) if (nb > 1 && size >= kChunkPoints)
  for (int64_t b = 0; b < nb; ++b) {
    BlockedMode<T>& md = modes[blocks[b].mode];
    reorder_block<T, true>(planes[blocks[b].mode].data_ptr<T>(), md.plane.data(), md.rows * md.cols, blocks[b].r0,
                           blocks[b].w);
    reorder_block<T, true>(lines[blocks[b].mode].data_ptr<T>(), md.line.data(), md.len, blocks[b].r0, blocks[b].w);
  }
  return modes;
}

// A mode's cells at point x [3]: plane row, plane column, line.
template <typename T>
struct ModeCells {
  Axis<T> row, col, lin;
};

template <typename T>
inline ModeCells<T> mode_cells(const T* x, const BlockedMode<T>& md) {
  return {axis(x[md.row_axis], md.rows), axis(x[md.col_axis], md.cols), axis(x[md.line_axis], md.len)};
}

// Calls f(std::integral_constant<int64_t, W>) with W = w for the block widths TensoRF's ranks give (16, 12, 8, 4),
// whose loops the compiler then unrolls and vectorises, and W = 0 (the width known only at run time) otherwise.
template <typename F>
inline void with_width(int64_t w, F&& f) {
  switch (w) {
    case 16: f(std::integral_constant<int64_t, 16>{}); break;
    case 12: f(std::integral_constant<int64_t, 12>{}); break;
    case 8: f(std::integral_constant<int64_t, 8>{}); break;
    case 4: f(std::integral_constant<int64_t, 4>{}); break;
    default: f(std::integral_constant<int64_t, 0>{});
  }
}

// Plane values pv [w] and line values lv [w] of one block at located cells (W: w if known at compile time, else 0).
template <typename T, int64_t W>
inline void read_block(const ModeCells<T>& mc, const BlockedMode<T>& md, int64_t r0, int64_t w_run, T* pv, T* lv) {
  const int64_t w = W ? W : w_run;
  for (int64_t r = 0; r < w; ++r) pv[r] = 0, lv[r] = 0;
  const T* plane = md.plane.data() + r0 * md.rows * md.cols;
  for (int dy = 0; dy < 2; ++dy)
    for (int dx = 0; dx < 2; ++dx) {
      if (!mc.row.in[dy] || !mc.col.in[dx]) continue;
      const T wt = mc.row.w[dy] * mc.col.w[dx];
      const T* src = plane + ((mc.row.i0 + dy) * md.cols + mc.col.i0 + dx) * w;
#pragma omp simd
      for (int64_t r = 0; r < w; ++r) pv[r] += wt * src[r];
    }
  const T* line = md.line.data() + r0 * md.len;
  for (int dz = 0; dz < 2; ++dz) {
    if (!mc.lin.in[dz]) continue;
    const T* src = line + (mc.lin.i0 + dz) * w;
#pragma omp simd
    for (int64_t r = 0; r < w; ++r) lv[r] += mc.lin.w[dz] * src[r];
  }
}

// One block's products at every point: written to its columns of out [N, K], or added to out [N] (summed). Called
// inside products_forward's parallel region: its threads share the points.
template <typename T, int64_t W>
void block_forward(const T* u, int64_t n, const BlockedMode<T>& md, int64_t r0, int64_t w_run, bool summed, int64_t K,
                   T* out) {
  const int64_t w = W ? W : w_run;
#pragma omp for schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    T pv[kBlock], lv[kBlock];
    read_block<T, W>(mode_cells(u + 3 * i, md), md, r0, w, pv, lv);
    if (summed) {
      T total = out[i];
      for (int64_t r = 0; r < w; ++r) total += pv[r] * lv[r];
      out[i] = total;
    } else {
      T* o = out + i * K + md.offset + r0;
#pragma omp simd
      for (int64_t r = 0; r < w; ++r) o[r] = pv[r] * lv[r];
    }
  }
}

// Block by block (each block's factors stay in cache while all points read them), the points split among the
// threads of one parallel region (one fork for all blocks).
template <typename T>
void products_forward(const T* u, int64_t n, const std::vector<BlockedMode<T>>& modes,
                      const std::vector<Block>& blocks, bool summed, int64_t K, T* out) {
  if (summed) std::fill(out, out + n, T(0));
#pragma omp parallel if (n >= kChunkPoints)
  for (const Block& b : blocks)
    with_width(b.w, [&](auto W) { block_forward<T, W()>(u, n, modes[b.mode], b.r0, b.w, summed, K, out); });
}

// One block's share of the backward: its points in order, into its own region of the gradients.
template <typename T, int64_t W>
void block_backward(const T* u, int64_t n, const BlockedMode<T>& md, int64_t r0, int64_t w_run, bool summed,
                    int64_t K, const T* go, T* plane_grad, T* line_grad) {
  const int64_t w = W ? W : w_run;
  T pv[kBlock], lv[kBlock], gpv[kBlock], glv[kBlock];
  for (int64_t i = 0; i < n; ++i) {
    const ModeCells<T> mc = mode_cells(u + 3 * i, md);
    read_block<T, W>(mc, md, r0, w, pv, lv);
    if (summed) {
      const T g = go[i];
#pragma omp simd
      for (int64_t r = 0; r < w; ++r) gpv[r] = g * lv[r], glv[r] = g * pv[r];
    } else {
      const T* g = go + i * K + md.offset + r0;
#pragma omp simd
      for (int64_t r = 0; r < w; ++r) gpv[r] = g[r] * lv[r], glv[r] = g[r] * pv[r];
    }
    for (int dy = 0; dy < 2; ++dy)
      for (int dx = 0; dx < 2; ++dx) {
        if (!mc.row.in[dy] || !mc.col.in[dx]) continue;
        const T wt = mc.row.w[dy] * mc.col.w[dx];
        T* dst = plane_grad + ((mc.row.i0 + dy) * md.cols + mc.col.i0 + dx) * w;
#pragma omp simd
        for (int64_t r = 0; r < w; ++r) dst[r] += wt * gpv[r];
      }
    for (int dz = 0; dz < 2; ++dz) {
      if (!mc.lin.in[dz]) continue;
      T* dst = line_grad + (mc.lin.i0 + dz) * w;
#pragma omp simd
      for (int64_t r = 0; r < w; ++r) dst[r] += mc.lin.w[dz] * glv[r];
    }
  }
}

// Gradients of the blocked factors (gp, gl: the modes' layouts, zeroed) given d loss / d products `go` ([N, K], or
// [N] when summed). Each block is one task: its points in order, its own region of gp and gl.
template <typename T>
void products_backward(const T* u, int64_t n, const std::vector<BlockedMode<T>>& modes,
                       const std::vector<Block>& blocks, bool summed, int64_t K, const T* go,
                       std::vector<std::vector<T>>& gp, std::vector<std::vector<T>>& gl) {
  const int64_t nb = blocks.size();
#pragma omp parallel for schedule(dynamic, 1) if (nb > 1 && n >= kChunkPoints)
  for (int64_t b = 0; b < nb; ++b) {
    const Block& blk = blocks[b];
    const BlockedMode<T>& md = modes[blk.mode];
    T* plane_grad = gp[blk.mode].data() + blk.r0 * md.rows * md.cols;
    T* line_grad = gl[blk.mode].data() + blk.r0 * md.len;
    with_width(blk.w, [&](auto W) {
      block_backward<T, W()>(u, n, md, blk.r0, blk.w, summed, K, go, plane_grad, line_grad);
    });
  }
}

// The blocked gradients gp, gl back to the factors' layouts: grads = (planes..., lines...).
template <typename T>
void unblock_grads(const std::vector<BlockedMode<T>>& modes, const std::vector<Block>& blocks,
                   const std::vector<std::vector<T>>& gp, const std::vector<std::vector<T>>& gl,
                   std::vector<torch::Tensor>& grads) {
  const int64_t nb = blocks.size(), M = modes.size();
  int64_t size = 0;
  for (const BlockedMode<T>& md : modes) size += md.plane.size() + md.line.size();
#pragma omp parallel for schedule(dynamic, 1) if (nb > 1 && size >= kChunkPoints)
  for (int64_t b = 0; b < nb; ++b) {
    const int64_t m = blocks[b].mode;
    reorder_block<T, false>(gp[m].data(), grads[m].data_ptr<T>(), modes[m].rows * modes[m].cols, blocks[b].r0,
                            blocks[b].w);
    reorder_block<T, false>(gl[m].data(), grads[M + m].data_ptr<T>(), modes[m].len, blocks[b].r0, blocks[b].w);
  }
}

void check_products(const torch::Tensor& u, const std::vector<torch::Tensor>& planes,
                    const std::vector<torch::Tensor>& lines, const std::vector<int64_t>& axes) {
  const size_t M = planes.size();
  TORCH_CHECK(M >= 1 && lines.size() == M && axes.size() == 3 * M,
              "vm_products: one plane, line and (row, column, line) axis triple per mode");
  TORCH_CHECK(u.dim() == 2 && u.size(1) == 3, "vm_products: points must be [N, 3]");
  std::vector<const torch::Tensor*> all{&u};
  for (size_t m = 0; m < M; ++m) {
    all.insert(all.end(), {&planes[m], &lines[m]});
    TORCH_CHECK(planes[m].dim() == 3 && lines[m].dim() == 2 && lines[m].size(0) == planes[m].size(0),
                "vm_products: mode ", m, " needs a plane [R, rows, columns] and a line [R, length] of one rank R");
    TORCH_CHECK(planes[m].numel() > 0 && lines[m].numel() > 0, "vm_products: mode ", m, " is empty");
  }
  for (int64_t a : axes) TORCH_CHECK(a >= 0 && a < 3, "vm_products: axes must be 0, 1 or 2");
  for (const torch::Tensor* t : all) {
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous(), "vm_products: inputs must be contiguous CPU tensors");
    TORCH_CHECK(t->scalar_type() == u.scalar_type(), "vm_products: inputs must share one dtype");
  }
}

int64_t total_rank(const std::vector<torch::Tensor>& planes) {
  int64_t K = 0;
  for (const torch::Tensor& p : planes) K += p.size(0);
  return K;
}

}  // namespace

// The products P_{m,r}(u) L_{m,r}(u) at points u [N, 3] in [-1, 1], mode m's plane [R_m, rows, columns] read
// bilinearly at (u[axes[3m]], u[axes[3m + 1]]) and its line [R_m, length] linearly at u[axes[3m + 2]]
// (grid_sample's align_corners=True coordinates, zero outside): [N, sum_m R_m] mode by mode, or their sum [N].
torch::Tensor vm_products_forward(torch::Tensor u, std::vector<torch::Tensor> planes, std::vector<torch::Tensor> lines,
                                  std::vector<int64_t> axes, bool summed) {
  check_products(u, planes, lines, axes);
  const int64_t K = total_rank(planes);
  auto out = summed ? torch::empty({u.size(0)}, u.options()) : torch::empty({u.size(0), K}, u.options());
  AT_DISPATCH_FLOATING_TYPES(u.scalar_type(), "vm_products_forward", [&] {
    const auto blocks = blocks_of(planes);
    const auto modes = blocked_modes<scalar_t>(planes, lines, axes, blocks);
    products_forward<scalar_t>(u.data_ptr<scalar_t>(), u.size(0), modes, blocks, summed, K, out.data_ptr<scalar_t>());
  });
  return out;
}

// (d planes..., d lines...) of every mode, in the inputs' layouts, given grad_out (vm_products_forward's shape).
std::vector<torch::Tensor> vm_products_backward(torch::Tensor u, std::vector<torch::Tensor> planes,
                                                std::vector<torch::Tensor> lines, std::vector<int64_t> axes,
                                                bool summed, torch::Tensor grad_out) {
  check_products(u, planes, lines, axes);
  const int64_t K = total_rank(planes), n = u.size(0);
  TORCH_CHECK(grad_out.is_contiguous() && grad_out.scalar_type() == u.scalar_type() &&
                  (summed ? grad_out.dim() == 1 : grad_out.dim() == 2 && grad_out.size(1) == K) &&
                  grad_out.size(0) == n,
              "vm_products: grad_out must be a contiguous tensor of the products' shape and the points' dtype");
  std::vector<torch::Tensor> grads;
  for (const auto* factors : {&planes, &lines})
    for (const torch::Tensor& t : *factors) grads.push_back(torch::empty_like(t));
  AT_DISPATCH_FLOATING_TYPES(u.scalar_type(), "vm_products_backward", [&] {
    const auto blocks = blocks_of(planes);
    const auto modes = blocked_modes<scalar_t>(planes, lines, axes, blocks);
    std::vector<std::vector<scalar_t>> gp, gl;
    for (const auto& md : modes) gp.emplace_back(md.plane.size(), 0), gl.emplace_back(md.line.size(), 0);
    products_backward<scalar_t>(u.data_ptr<scalar_t>(), n, modes, blocks, summed, K,
                                grad_out.data_ptr<scalar_t>(), gp, gl);
    unblock_grads<scalar_t>(modes, blocks, gp, gl, grads);
  });
  return grads;
}
