// UW-3DGS's L_z (uw3dgs/metrics/depth_consistency.py) in one pass over the Gaussians: for each visible Gaussian
// whose centre projects inside the image, |rendered range at that pixel - its distance to the camera| in units of
// the median of those rendered ranges, weighted, averaged. PyTorch's path takes a dozen passes (the visible set, a
// boolean selection of it, gathers, a norm, the median, and their index_add backwards). Serial: a few hundred
// thousand Gaussians take well under a millisecond, and the gradients' sums over Gaussians sharing a pixel keep
// their order.
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

template <typename T>
void forward_impl(const torch::Tensor& radii, const torch::Tensor& means2d, const torch::Tensor& means,
                  const torch::Tensor& center, const torch::Tensor& ranges, std::vector<int64_t>& gauss,
                  std::vector<int64_t>& pixel, std::vector<T>& rendered, std::vector<T>& own) {
  const int64_t n = means.size(0), height = ranges.size(0), width = ranges.size(1);
  const int32_t* rad = radii.data_ptr<int32_t>();
  for (auto* v : {&gauss, &pixel}) v->reserve(n);
  rendered.reserve(n);
  own.reserve(n);
  const T *m2 = means2d.data_ptr<T>(), *mp = means.data_ptr<T>(), *c = center.data_ptr<T>(),
          *rp = ranges.data_ptr<T>();
  for (int64_t i = 0; i < n; ++i) {
    if (rad[i] <= 0) continue;
    const T fx = std::floor(m2[2 * i]), fy = std::floor(m2[2 * i + 1]);
    if (!(fx >= 0 && fx < static_cast<T>(width) && fy >= 0 && fy < static_cast<T>(height))) continue;
    const int64_t q = static_cast<int64_t>(fy) * width + static_cast<int64_t>(fx);
    const T dx = mp[3 * i] - c[0], dy = mp[3 * i + 1] - c[1], dz = mp[3 * i + 2] - c[2];
    gauss.push_back(i);
    pixel.push_back(q);
    rendered.push_back(rp[q]);
    own.push_back(std::sqrt(dx * dx + dy * dy + dz * dz));
  }
}

}  // namespace

// L_z's forward: radii [N] int32, means2d [N, 2], means [N, 3], center [3], ranges [H, W], weights [N] or empty (all
// 1). Returns the loss (0-dim; 0 when no centre projects inside) and, for the backward, the Gaussians and pixels it
// read ([K] int64) and their d loss / d rendered range ([K]).
std::vector<torch::Tensor> depth_consistency_forward(torch::Tensor radii, torch::Tensor means2d, torch::Tensor means,
                                                     torch::Tensor center, torch::Tensor ranges,
                                                     torch::Tensor weights) {
  for (const torch::Tensor* t : {&radii, &means2d, &means, &center, &ranges, &weights})
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous(), "depth_consistency: contiguous CPU tensors");
  const int64_t n = means.size(0);
  TORCH_CHECK(radii.scalar_type() == torch::kInt32 && radii.numel() == n && means2d.size(0) == n &&
                  means2d.size(1) == 2 && means.size(1) == 3 && center.numel() == 3 && ranges.dim() == 2 &&
                  (weights.numel() == 0 || weights.numel() == n),
              "depth_consistency: radii [N] int32, means2d [N, 2], means [N, 3], center [3], ranges [H, W], "
              "weights [N] or empty");
  for (const torch::Tensor* t : {&means2d, &center, &ranges, &weights})
    TORCH_CHECK(t->numel() == 0 || t->scalar_type() == means.scalar_type(), "depth_consistency: one dtype");
  auto opts = means.options();
  torch::Tensor loss, gauss_t, pixel_t, coef_t;
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "depth_consistency_forward", [&] {
    using T = scalar_t;
    std::vector<int64_t> gauss, pixel;
    std::vector<T> rendered, own;
    forward_impl<T>(radii, means2d, means, center, ranges, gauss, pixel, rendered, own);
    const int64_t k = static_cast<int64_t>(gauss.size());
    gauss_t = torch::empty({k}, opts.dtype(torch::kInt64));
    pixel_t = torch::empty({k}, opts.dtype(torch::kInt64));
    coef_t = torch::empty({k}, opts);
    if (k == 0) {
      loss = torch::zeros({}, opts);
      return;
    }
    // the scale: the lower median of the rendered ranges (torch.median's), at least 1e-6
    std::vector<T> sorted(rendered);
    std::nth_element(sorted.begin(), sorted.begin() + (k - 1) / 2, sorted.end());
    const T scale = std::max(sorted[(k - 1) / 2], static_cast<T>(1e-6));
    const T* w = weights.numel() ? weights.data_ptr<T>() : nullptr;
    T* coef = coef_t.data_ptr<T>();
    double sum = 0;
    for (int64_t j = 0; j < k; ++j) {
      const T d = rendered[j] - own[j], wj = w ? w[gauss[j]] : static_cast<T>(1);
      sum += static_cast<double>(wj * (std::abs(d) / scale));
      // d / d rendered of wj |d| / scale / k (|.|'s derivative at 0 taken as 0, as autograd does)
      coef[j] = d > 0 ? wj / scale / static_cast<T>(k) : (d < 0 ? -wj / scale / static_cast<T>(k) : static_cast<T>(0));
    }
    std::copy(gauss.begin(), gauss.end(), gauss_t.data_ptr<int64_t>());
    std::copy(pixel.begin(), pixel.end(), pixel_t.data_ptr<int64_t>());
    loss = torch::tensor(sum / static_cast<double>(k), opts);
  });
  return {loss, gauss_t, pixel_t, coef_t};
}

// L_z's backward given the forward's Gaussians, pixels and coefficients and the loss's gradient g: d loss / d ranges
// [H, W] (each read pixel gets g coef; summed in Gaussian order where several read one) and d loss / d means [N, 3]
// (-g coef times the unit vector from the camera to the centre; 0 at the camera centre itself).
std::vector<torch::Tensor> depth_consistency_backward(torch::Tensor means, torch::Tensor center, torch::Tensor ranges,
                                                      torch::Tensor gauss, torch::Tensor pixel, torch::Tensor coef,
                                                      double grad) {
  auto g_ranges = torch::zeros_like(ranges);
  auto g_means = torch::zeros_like(means);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "depth_consistency_backward", [&] {
    using T = scalar_t;
    const T *mp = means.data_ptr<T>(), *c = center.data_ptr<T>(), *cf = coef.data_ptr<T>();
    const int64_t *gi = gauss.data_ptr<int64_t>(), *px = pixel.data_ptr<int64_t>();
    T *gr = g_ranges.data_ptr<T>(), *gm = g_means.data_ptr<T>();
    const T g = static_cast<T>(grad);
    for (int64_t j = 0; j < gauss.numel(); ++j) {
      const T a = g * cf[j];
      gr[px[j]] += a;
      const int64_t i = gi[j];
      const T dx = mp[3 * i] - c[0], dy = mp[3 * i + 1] - c[1], dz = mp[3 * i + 2] - c[2];
      const T norm = std::sqrt(dx * dx + dy * dy + dz * dz);
      if (norm > 0) {
        gm[3 * i] -= a * dx / norm;
        gm[3 * i + 1] -= a * dy / norm;
        gm[3 * i + 2] -= a * dz / norm;
      }
    }
  });
  return {g_ranges, g_means};
}
