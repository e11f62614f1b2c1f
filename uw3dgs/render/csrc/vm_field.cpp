// Compiled CPU read of TensoRF vector-matrix (VM) fields and its backward: f(u) = softplus(W feats(u) + b), feats
// the 3R products of bilinear plane reads and linear line reads (fields/medium.py, VMField). Numerically mirrors
// VMField.forward_reference: grid_sample's align_corners=True coordinates, zero padding, softplus threshold 20.
// One pass per point instead of PyTorch's twelve grid_samples per field, their stacking, the basis product and
// the softplus, each a full pass over memory with its own backward. Several fields of one shape read at the same
// points (the medium's beta_D and beta_B) share the point's cell lookups. The factors are read channel-last, so a
// point's R components are contiguous, and R = 16 (the default) is unrolled. The backward recomputes a point's
// reads instead of storing [N, 3R] features. Factor gradients are summed per chunk of points, the chunks fixed by
// N alone, and the chunks reduced in order: bitwise identical results run to run and whatever the thread count.
#include <torch/extension.h>

#include "exp_f32.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
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
      for (int64_t r = 0; r < R; ++r) {
        for (int64_t c = 0; c < G * G; ++c) fields[f].plane[(m * G * G + c) * R + r] = p[(m * R + r) * G * G + c];
        for (int64_t k = 0; k < G; ++k) fields[f].line[(m * G + k) * R + r] = l[(m * R + r) * G + k];
      }
    }
  return fields;
}

// A field's plane values pv and line values lv [3R] at a located point; with SLOPES also their derivatives along
// the plane's row and column axes (srow, scol) and the line's axis (slin), [3R] each, in cells.
template <typename T, int RC, bool SLOPES>
inline void read_field(const Cells<T>& cells, const Field<T>& f, int64_t R_in, int64_t G, T* pv, T* lv,
                       T* srow = nullptr, T* scol = nullptr, T* slin = nullptr) {
  const int64_t R = RC > 0 ? RC : R_in;
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
template <typename T, int RC>
inline void basis_product(const T* pv, const T* lv, const Field<T>& f, int64_t C, int64_t R_in, T* pre) {
  const int64_t K = 3 * (RC > 0 ? RC : R_in);
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
    const float a = std::max(-std::fabs(v), -87.0f);  // e^a stays a normal float
    float q;
    const float u = exp_f32_reduced(a, q);
    const int32_t bits = (static_cast<int32_t>(q) + 127) << 23;  // 2^q
    float scale;
    std::memcpy(&scale, &bits, sizeof scale);
    const float z = u * scale;  // e^-|v|, in (0, 1]
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

template <typename T, int RC>
void forward_impl(const torch::Tensor& u, const std::vector<Field<T>>& fields, int64_t R_in, int64_t G, int64_t C,
                  torch::Tensor& out) {
  const int64_t n = u.size(0), F = fields.size(), R = RC > 0 ? RC : R_in, K = 3 * R;
  const T* up = u.data_ptr<T>();
  T* o = out.data_ptr<T>();
#pragma omp parallel if (n >= kChunkPoints)
  {
    std::vector<T> pv(K), lv(K), pre(C);
    Cells<T> cells;
#pragma omp for schedule(static)
    for (int64_t i = 0; i < n; ++i) {
      locate(up + 3 * i, G, cells);
      for (int64_t f = 0; f < F; ++f) {
        read_field<T, RC, false>(cells, fields[f], R, G, pv.data(), lv.data());
        basis_product<T, RC>(pv.data(), lv.data(), fields[f], C, R, pre.data());
        for (int64_t c = 0; c < C; ++c) o[(i * F + f) * C + c] = pre[c];
      }
    }
  }
  softplus_inplace(o, n * F * C);
}

// Adds one point's gradients of one field (gradient `go` [C] of its output) to the chunk's accumulators (gp, gl
// channel-last, gw [C, K], gb [C]) and d loss / d u to du [3]. `work` holds 7 K values.
template <typename T, int RC>
inline void backward_point(const Cells<T>& cells, const Field<T>& f, const T* go, int64_t R_in, int64_t G, int64_t C,
                           T* work, T* pre, T* gp, T* gl, T* gw, T* gb, T* du) {
  const int64_t R = RC > 0 ? RC : R_in, K = 3 * R;
  T *pv = work, *lv = pv + K, *srow = lv + K, *scol = srow + K, *slin = scol + K, *gf = slin + K, *gval = gf + K;
  read_field<T, RC, true>(cells, f, R, G, pv, lv, srow, scol, slin);
  basis_product<T, RC>(pv, lv, f, C, R, pre);
  for (int64_t k = 0; k < K; ++k) gf[k] = 0;
  for (int64_t c = 0; c < C; ++c) {
    T g = go[c];  // d / d pre = sigmoid(pre) below softplus's threshold
    if (pre[c] <= T(kSoftplusThreshold)) {
      const T z = std::exp(pre[c]);
      g = g * z / (z + T(1));
    }
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

template <typename T, int RC>
void backward_impl(const torch::Tensor& u, const std::vector<Field<T>>& fields, int64_t R_in, int64_t G, int64_t C,
                   const torch::Tensor& grad_out, torch::Tensor& g_u, std::vector<torch::Tensor>& g_planes,
                   std::vector<torch::Tensor>& g_lines, std::vector<torch::Tensor>& g_basis,
                   std::vector<torch::Tensor>& g_bias) {
  const int64_t n = u.size(0), F = fields.size(), R = RC > 0 ? RC : R_in, K = 3 * R;
  const int64_t chunks = num_chunks(n), plane_size = 3 * G * G * R, line_size = 3 * G * R;
  const int64_t block = plane_size + line_size + C * K + C;  // one field's accumulators: planes, lines, W, b
  // each chunk's thread zeroes its own accumulators (in parallel, and in that thread's memory)
  std::unique_ptr<T[]> acc(new T[chunks * F * block]);
  const T *up = u.data_ptr<T>(), *go = grad_out.data_ptr<T>();
  T* gu = g_u.data_ptr<T>();
#pragma omp parallel if (n >= kChunkPoints)
  {
    std::vector<T> work(7 * K), pre(C);
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
          backward_point<T, RC>(cells, fields[f], go + (i * F + f) * C, R, G, C, work.data(), pre.data(), gp, gl,
                                gw, gw + C * K, gu + 3 * i);
        }
      }
    }
  }
  T* a = acc.get();
  const int64_t total = F * block;
  // each sum adds the chunks in order, whichever thread does it: the result does not depend on the threads
#pragma omp parallel for schedule(static) if (chunks > 1 && total >= kChunkPoints)
  for (int64_t j = 0; j < total; ++j) {
    T s = a[j];
    for (int64_t chunk = 1; chunk < chunks; ++chunk) s += a[chunk * total + j];
    a[j] = s;
  }
#pragma omp parallel for collapse(2) schedule(static) if (total >= kChunkPoints)
  for (int64_t f = 0; f < F; ++f)  // back to the factors' own layout
    for (int64_t m = 0; m < 3; ++m) {
      const T* af = a + f * block;
      T *out_p = g_planes[f].data_ptr<T>(), *out_l = g_lines[f].data_ptr<T>();
      for (int64_t r = 0; r < R; ++r) {
        for (int64_t c = 0; c < G * G; ++c) out_p[(m * R + r) * G * G + c] = af[(m * G * G + c) * R + r];
        for (int64_t k = 0; k < G; ++k) out_l[(m * R + r) * G + k] = af[plane_size + (m * G + k) * R + r];
      }
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

// softplus(W_f feats_f(u) + b_f) of every field f, [N, F * C] (field-major per point), at points u [N, 3] in [-1, 1].
torch::Tensor vm_fields_forward(torch::Tensor u, std::vector<torch::Tensor> planes, std::vector<torch::Tensor> lines,
                                std::vector<torch::Tensor> basis, std::vector<torch::Tensor> bias) {
  check_inputs(u, planes, lines, basis, bias);
  const int64_t F = planes.size(), R = planes[0].size(1), G = planes[0].size(2), C = basis[0].size(0);
  auto out = torch::empty({u.size(0), F * C}, u.options());
  AT_DISPATCH_FLOATING_TYPES(u.scalar_type(), "vm_fields_forward", [&] {
    const auto fields = channel_last<scalar_t>(planes, lines, basis, bias);
    if (R == 16)  // the default component count, unrolled
      forward_impl<scalar_t, 16>(u, fields, R, G, C, out);
    else
      forward_impl<scalar_t, 0>(u, fields, R, G, C, out);
  });
  return out;
}

// (d u [N, 3], d planes, d lines, d basis, d bias per field) given grad_out [N, F * C].
std::vector<std::vector<torch::Tensor>> vm_fields_backward(torch::Tensor u, std::vector<torch::Tensor> planes,
                                                           std::vector<torch::Tensor> lines,
                                                           std::vector<torch::Tensor> basis,
                                                           std::vector<torch::Tensor> bias, torch::Tensor grad_out) {
  check_inputs(u, planes, lines, basis, bias);
  const int64_t F = planes.size(), R = planes[0].size(1), G = planes[0].size(2), C = basis[0].size(0);
  TORCH_CHECK(grad_out.is_contiguous() && grad_out.scalar_type() == u.scalar_type() && grad_out.dim() == 2 &&
                  grad_out.size(0) == u.size(0) && grad_out.size(1) == F * C,
              "vm_fields: grad_out must be a contiguous [N, F * C] tensor of the points' dtype");
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
      backward_impl<scalar_t, 16>(u, fields, R, G, C, grad_out, g_u[0], g_planes, g_lines, g_basis, g_bias);
    else
      backward_impl<scalar_t, 0>(u, fields, R, G, C, grad_out, g_u[0], g_planes, g_lines, g_basis, g_bias);
  });
  return {g_u, g_planes, g_lines, g_basis, g_bias};
}
