// Compiled CPU view-dependent colours of 3D Gaussians and their backward: c_i = max(SH(d_i) + 0.5, 0), d_i the unit
// direction from the camera centre to the Gaussian, SH the real spherical harmonics of uw3dgs/render/sh.py (3DGS's
// constants and signs) up to the active degree. One pass per Gaussian instead of PyTorch's ~40 whole-array
// operations (the basis functions, their stacking, the band product, the offset and clamp) and their autograd
// backward; every Gaussian is independent, so it is parallel and deterministic whatever the thread count. The
// backward gives the gradients of the coefficients and, through the direction, of the means.
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr double C0 = 0.28209479177387814;
constexpr double C1 = 0.4886025119029199;
constexpr double C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                          0.5462742152960396};
constexpr double C3[7] = {-0.5900435899266435, 2.890611442640554,  -0.4570457994644658, 0.3731763325901154,
                          -0.4570457994644658, 1.445305721320277, -0.5900435899266435};
constexpr int64_t kParallelMin = 4096;
constexpr int kMaxBases = 16;

// The basis functions 1..B-1 at unit direction (x, y, z) (the constant one is C0), and with D their derivatives
// along x, y, z: basis[k - 1], grad[(k - 1) * 3 + axis].
template <typename T, bool D>
inline void basis(int degree, T x, T y, T z, T* b, T* g) {
  if (degree >= 1) {
    b[0] = T(-C1) * y, b[1] = T(C1) * z, b[2] = T(-C1) * x;
    if constexpr (D) {
      const T d[9] = {0, T(-C1), 0, 0, 0, T(C1), T(-C1), 0, 0};
      std::copy(d, d + 9, g);
    }
  }
  if (degree >= 2) {
    const T xx = x * x, yy = y * y, zz = z * z;
    b[3] = T(C2[0]) * x * y;
    b[4] = T(C2[1]) * y * z;
    b[5] = T(C2[2]) * (T(2) * zz - xx - yy);
    b[6] = T(C2[3]) * x * z;
    b[7] = T(C2[4]) * (xx - yy);
    if constexpr (D) {
      const T d[15] = {T(C2[0]) * y, T(C2[0]) * x, 0,                             //
                       0, T(C2[1]) * z, T(C2[1]) * y,                             //
                       T(-2 * C2[2]) * x, T(-2 * C2[2]) * y, T(4 * C2[2]) * z,    //
                       T(C2[3]) * z, 0, T(C2[3]) * x,                             //
                       T(2 * C2[4]) * x, T(-2 * C2[4]) * y, 0};
      std::copy(d, d + 15, g + 9);
    }
  }
  if (degree >= 3) {
    const T xx = x * x, yy = y * y, zz = z * z;
    b[8] = T(C3[0]) * y * (T(3) * xx - yy);
    b[9] = T(C3[1]) * x * y * z;
    b[10] = T(C3[2]) * y * (T(4) * zz - xx - yy);
    b[11] = T(C3[3]) * z * (T(2) * zz - T(3) * xx - T(3) * yy);
    b[12] = T(C3[4]) * x * (T(4) * zz - xx - yy);
    b[13] = T(C3[5]) * z * (xx - yy);
    b[14] = T(C3[6]) * x * (xx - T(3) * yy);
    if constexpr (D) {
      const T d[21] = {T(6 * C3[0]) * x * y, T(C3[0]) * (T(3) * xx - T(3) * yy), 0,
                       T(C3[1]) * y * z, T(C3[1]) * x * z, T(C3[1]) * x * y,
                       T(-2 * C3[2]) * x * y, T(C3[2]) * (T(4) * zz - xx - T(3) * yy), T(8 * C3[2]) * y * z,
                       T(-6 * C3[3]) * x * z, T(-6 * C3[3]) * y * z, T(C3[3]) * (T(6) * zz - T(3) * xx - T(3) * yy),
                       T(C3[4]) * (T(4) * zz - T(3) * xx - yy), T(-2 * C3[4]) * x * y, T(8 * C3[4]) * x * z,
                       T(2 * C3[5]) * x * z, T(-2 * C3[5]) * y * z, T(C3[5]) * (xx - yy),
                       T(C3[6]) * (T(3) * xx - T(3) * yy), T(-6 * C3[6]) * x * y, 0};
      std::copy(d, d + 21, g + 24);
    }
  }
}

// The unit direction from `center` to mean i and the distance (torch's normalize: divided by max(|v|, 1e-12)).
template <typename T>
inline T direction(const T* mean, const T* center, T* d) {
  const T v[3] = {mean[0] - center[0], mean[1] - center[1], mean[2] - center[2]};
  const T norm = std::max(std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]), T(1e-12));
  for (int a = 0; a < 3; ++a) d[a] = v[a] / norm;
  return norm;
}

// SH(d) + 0.5 per channel, before the clamp: the coefficient-weighted basis, the higher bands summed first.
template <typename T>
inline void expansion(const T* dc, const T* rest, const T* b, int bases, T* out) {
  for (int c = 0; c < 3; ++c) {
    T band = 0;
    for (int k = 0; k < bases - 1; ++k) band += b[k] * rest[k * 3 + c];
    out[c] = T(C0) * dc[c] + band + T(0.5);
  }
}

template <typename T>
void forward_impl(const torch::Tensor& means, const torch::Tensor& center, const torch::Tensor& dc,
                  const torch::Tensor& rest, int degree, torch::Tensor& colors) {
  const int64_t n = means.size(0), M = rest.size(1);
  const int bases = (degree + 1) * (degree + 1);
  const T *mp = means.data_ptr<T>(), *cp = center.data_ptr<T>(), *dp = dc.data_ptr<T>(), *rp = rest.data_ptr<T>();
  T* out = colors.data_ptr<T>();
#pragma omp parallel for schedule(static) if (n >= kParallelMin)
  for (int64_t i = 0; i < n; ++i) {
    T d[3], b[kMaxBases], raw[3];
    direction(mp + 3 * i, cp, d);
    basis<T, false>(degree, d[0], d[1], d[2], b, nullptr);
    expansion(dp + 3 * i, rp + i * M * 3, b, bases, raw);
    for (int c = 0; c < 3; ++c) out[3 * i + c] = std::max(raw[c], T(0));
  }
}

template <typename T>
void backward_impl(const torch::Tensor& means, const torch::Tensor& center, const torch::Tensor& dc,
                   const torch::Tensor& rest, int degree, const torch::Tensor& grad, torch::Tensor& g_means,
                   torch::Tensor& g_dc, torch::Tensor& g_rest) {
  const int64_t n = means.size(0), M = rest.size(1);
  const int bases = (degree + 1) * (degree + 1);
  const T *mp = means.data_ptr<T>(), *cp = center.data_ptr<T>(), *dp = dc.data_ptr<T>(), *rp = rest.data_ptr<T>(),
          *gp = grad.data_ptr<T>();
  T *gm = g_means.data_ptr<T>(), *gd = g_dc.data_ptr<T>(), *gr = g_rest.data_ptr<T>();
#pragma omp parallel for schedule(static) if (n >= kParallelMin)
  for (int64_t i = 0; i < n; ++i) {
    T* grest = gr + i * M * 3;
    const T* gi = gp + 3 * i;
    if (gi[0] == T(0) && gi[1] == T(0) && gi[2] == T(0)) {  // not seen in the view: every gradient is zero
      std::fill(gd + 3 * i, gd + 3 * i + 3, T(0));
      std::fill(grest, grest + M * 3, T(0));
      std::fill(gm + 3 * i, gm + 3 * i + 3, T(0));
      continue;
    }
    T d[3], b[kMaxBases], db[kMaxBases * 3], raw[3], go[3];
    const T norm = direction(mp + 3 * i, cp, d);
    basis<T, true>(degree, d[0], d[1], d[2], b, db);
    const T* r = rp + i * M * 3;
    expansion(dp + 3 * i, r, b, bases, raw);
    for (int c = 0; c < 3; ++c) go[c] = raw[c] > T(0) ? gi[c] : T(0);  // clamp_min's gradient
    for (int c = 0; c < 3; ++c) gd[3 * i + c] = T(C0) * go[c];
    std::fill(grest, grest + M * 3, T(0));
    T gdir[3] = {0, 0, 0};
    for (int k = 0; k < bases - 1; ++k) {
      T along = 0;  // d loss / d basis_k
      for (int c = 0; c < 3; ++c) {
        grest[k * 3 + c] = b[k] * go[c];
        along += r[k * 3 + c] * go[c];
      }
      for (int a = 0; a < 3; ++a) gdir[a] += along * db[k * 3 + a];
    }
    // through d = v / |v|: dv = (gdir - d (d . gdir)) / |v|
    const T dot = d[0] * gdir[0] + d[1] * gdir[1] + d[2] * gdir[2];
    for (int a = 0; a < 3; ++a) gm[3 * i + a] = (gdir[a] - d[a] * dot) / norm;
  }
}

void check_inputs(const torch::Tensor& means, const torch::Tensor& center, const torch::Tensor& dc,
                  const torch::Tensor& rest, int64_t degree) {
  for (const torch::Tensor* t : {&means, &center, &dc, &rest}) {
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous(), "sh_colors: inputs must be contiguous CPU tensors");
    TORCH_CHECK(t->scalar_type() == means.scalar_type(), "sh_colors: inputs must share one dtype");
  }
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3 && center.numel() == 3, "sh_colors: means [N, 3], center [3]");
  TORCH_CHECK(dc.dim() == 2 && dc.size(0) == means.size(0) && dc.size(1) == 3, "sh_colors: dc must be [N, 3]");
  TORCH_CHECK(rest.dim() == 3 && rest.size(0) == means.size(0) && rest.size(2) == 3, "sh_colors: rest [N, M, 3]");
  TORCH_CHECK(degree >= 0 && degree <= 3 && (degree + 1) * (degree + 1) - 1 <= rest.size(1),
              "sh_colors: degree must be 0-3 with enough coefficients in rest");
}

}  // namespace

// max(SH(normalize(means - center)) + 0.5, 0) [N, 3] from dc [N, 3] and rest [N, M, 3] up to `degree`.
torch::Tensor sh_colors_forward(torch::Tensor means, torch::Tensor center, torch::Tensor dc, torch::Tensor rest,
                                int64_t degree) {
  check_inputs(means, center, dc, rest, degree);
  auto colors = torch::empty({means.size(0), 3}, means.options());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "sh_colors_forward", [&] {
    forward_impl<scalar_t>(means, center, dc, rest, static_cast<int>(degree), colors);
  });
  return colors;
}

// (d means, d dc, d rest) given grad [N, 3] of the colours.
std::vector<torch::Tensor> sh_colors_backward(torch::Tensor means, torch::Tensor center, torch::Tensor dc,
                                              torch::Tensor rest, int64_t degree, torch::Tensor grad) {
  check_inputs(means, center, dc, rest, degree);
  TORCH_CHECK(grad.is_contiguous() && grad.sizes() == means.sizes() && grad.scalar_type() == means.scalar_type(),
              "sh_colors: grad must be a contiguous [N, 3] tensor of the means' dtype");
  auto g_means = torch::empty_like(means), g_dc = torch::empty_like(dc), g_rest = torch::empty_like(rest);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "sh_colors_backward", [&] {
    backward_impl<scalar_t>(means, center, dc, rest, static_cast<int>(degree), grad, g_means, g_dc, g_rest);
  });
  return {g_means, g_dc, g_rest};
}
