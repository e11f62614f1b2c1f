// Compiled CPU SSIM of channels-last images and its backward to the prediction (uw3dgs/metrics/ssim_kernel.py):
// the same map as uw3dgs/metrics/image.py's `ssim` (3DGS's 11-tap Gaussian window, zero-padded 'same' filtering,
// C1, C2), so D-SSIM costs a few passes over memory instead of PyTorch's two depthwise convolutions and some
// thirty elementwise operations, each with its own backward. The window is separable and symmetric, so the
// backward of a zero-padded blur is the same blur: the forward keeps, per pixel and channel, d SSIM / d mu_x,
// d SSIM / d E[x^2] and d SSIM / d E[xy]; the backward blurs them and combines them with x and y. Every output
// element is summed in a fixed order (rows in parallel, taps in order; the SSIM sum per row in double, then the
// rows in order): bitwise identical results whatever the thread count.
#include <torch/extension.h>

#include <algorithm>
#include <cstdint>
#include <memory>
#include <vector>

namespace {

constexpr int64_t kParallelRows = 8;  // fewer rows than this run on one thread

// out [H, W, K] = the separable blur of in [H, W, K] with the odd, symmetric `taps`, zero padding ('same' size);
// tmp [H, W, K] holds the vertical pass.
template <typename T>
void blur(const T* in, T* out, T* tmp, int64_t H, int64_t W, int64_t K, const std::vector<T>& taps) {
  const int64_t r = static_cast<int64_t>(taps.size()) / 2, row = W * K;
#pragma omp parallel for schedule(static) if (H >= kParallelRows)
  for (int64_t y = 0; y < H; ++y) {
    T* dst = tmp + y * row;
    for (int64_t j = 0; j < row; ++j) dst[j] = 0;
    for (int64_t t = 0; t < static_cast<int64_t>(taps.size()); ++t) {
      const int64_t ys = y + t - r;
      if (ys < 0 || ys >= H) continue;
      const T w = taps[t];
      const T* src = in + ys * row;
#pragma omp simd
      for (int64_t j = 0; j < row; ++j) dst[j] += w * src[j];
    }
  }
#pragma omp parallel for schedule(static) if (H >= kParallelRows)
  for (int64_t y = 0; y < H; ++y) {
    T* dst = out + y * row;
    const T* src = tmp + y * row;
    for (int64_t j = 0; j < row; ++j) dst[j] = 0;
    for (int64_t t = 0; t < static_cast<int64_t>(taps.size()); ++t) {
      const int64_t shift = t - r;  // dst[x] += w src[x + shift] for 0 <= x + shift < W
      const int64_t x0 = std::max<int64_t>(0, -shift), x1 = std::min<int64_t>(W, W - shift);
      if (x0 >= x1) continue;
      const T w = taps[t];
      T* d = dst + x0 * K;
      const T* s = src + (x0 + shift) * K;
      const int64_t n = (x1 - x0) * K;
#pragma omp simd
      for (int64_t j = 0; j < n; ++j) d[j] += w * s[j];
    }
  }
}

// A buffer every pass below writes in full before reading: not zero-filled (a std::vector would add a pass).
template <typename T>
std::unique_ptr<T[]> scratch(int64_t n) {
  return std::unique_ptr<T[]>(new T[n]);
}

template <typename T>
std::vector<T> taps_of(const torch::Tensor& taps) {
  const T* p = taps.data_ptr<T>();
  return std::vector<T>(p, p + taps.size(0));
}

template <typename T>
void forward_impl(const torch::Tensor& pred, const torch::Tensor& gt, const std::vector<T>& taps, T c1, T c2,
                  torch::Tensor& ssim_sum, torch::Tensor* grads) {
  const int64_t B = pred.size(0), H = pred.size(1), W = pred.size(2), C = pred.size(3), K = 5 * C;
  auto moments = scratch<T>(H * W * K), blurred = scratch<T>(H * W * K), tmp = scratch<T>(H * W * K);
  std::vector<double> row_sums(H);
  for (int64_t b = 0; b < B; ++b) {
    const T* x = pred.data_ptr<T>() + b * H * W * C;
    const T* y = gt.data_ptr<T>() + b * H * W * C;
    // per pixel: x, y, x^2, y^2, xy (C each), the five local moments the window averages
#pragma omp parallel for schedule(static) if (H >= kParallelRows)
    for (int64_t p = 0; p < H * W; ++p) {
      T* m = moments.get() + p * K;
      for (int64_t c = 0; c < C; ++c) {
        const T xv = x[p * C + c], yv = y[p * C + c];
        m[c] = xv, m[C + c] = yv, m[2 * C + c] = xv * xv, m[3 * C + c] = yv * yv, m[4 * C + c] = xv * yv;
      }
    }
    blur(moments.get(), blurred.get(), tmp.get(), H, W, K, taps);
    T* g = grads ? grads->data_ptr<T>() + b * H * W * 3 * C : nullptr;
#pragma omp parallel for schedule(static) if (H >= kParallelRows)
    for (int64_t row = 0; row < H; ++row) {
      double sum = 0;
      for (int64_t p = row * W; p < (row + 1) * W; ++p) {
        const T* m = blurred.get() + p * K;
        for (int64_t c = 0; c < C; ++c) {
          const T mu1 = m[c], mu2 = m[C + c];
          const T mu1_sq = mu1 * mu1, mu2_sq = mu2 * mu2, mu12 = mu1 * mu2;
          const T s1 = m[2 * C + c] - mu1_sq, s2 = m[3 * C + c] - mu2_sq, s12 = m[4 * C + c] - mu12;
          const T a = T(2) * mu12 + c1, bb = T(2) * s12 + c2, cc = mu1_sq + mu2_sq + c1, d = s1 + s2 + c2;
          const T q = cc * d, s = (a * bb) / q;
          sum += s;
          if (g) {  // d s / d mu1, d s / d E[x^2], d s / d E[xy], with s = a bb / (cc d)
            T* gp = g + p * 3 * C;
            gp[c] = (T(2) * mu2 * (bb - a) - s * T(2) * mu1 * (d - cc)) / q;
            gp[C + c] = -s * cc / q;
            gp[2 * C + c] = T(2) * a / q;
          }
        }
      }
      row_sums[row] = sum;
    }
    double total = 0;
    for (int64_t row = 0; row < H; ++row) total += row_sums[row];
    ssim_sum.data_ptr<T>()[b] = static_cast<T>(total);
  }
}

template <typename T>
void backward_impl(const torch::Tensor& pred, const torch::Tensor& gt, const torch::Tensor& grads,
                   const std::vector<T>& taps, const torch::Tensor& grad_sum, torch::Tensor& g_pred) {
  const int64_t B = pred.size(0), H = pred.size(1), W = pred.size(2), C = pred.size(3), K = 3 * C;
  auto blurred = scratch<T>(H * W * K), tmp = scratch<T>(H * W * K);
  for (int64_t b = 0; b < B; ++b) {
    blur(grads.data_ptr<T>() + b * H * W * K, blurred.get(), tmp.get(), H, W, K, taps);
    const T go = grad_sum.data_ptr<T>()[b];
    const T* x = pred.data_ptr<T>() + b * H * W * C;
    const T* y = gt.data_ptr<T>() + b * H * W * C;
    T* out = g_pred.data_ptr<T>() + b * H * W * C;
#pragma omp parallel for schedule(static) if (H >= kParallelRows)
    for (int64_t p = 0; p < H * W; ++p) {
      const T* gb = blurred.get() + p * K;
      for (int64_t c = 0; c < C; ++c) {
        const int64_t i = p * C + c;
        out[i] = go * (gb[c] + T(2) * x[i] * gb[C + c] + y[i] * gb[2 * C + c]);
      }
    }
  }
}

void check_images(const torch::Tensor& pred, const torch::Tensor& gt, const torch::Tensor& taps) {
  TORCH_CHECK(pred.device().is_cpu() && gt.device().is_cpu() && taps.device().is_cpu(), "ssim: CPU tensors only");
  TORCH_CHECK(pred.dim() == 4 && pred.sizes() == gt.sizes(), "ssim: pred and gt must be [B, H, W, C] of one shape");
  TORCH_CHECK(pred.is_contiguous() && gt.is_contiguous() && taps.is_contiguous(), "ssim: contiguous tensors only");
  TORCH_CHECK(pred.scalar_type() == gt.scalar_type() && pred.scalar_type() == taps.scalar_type(),
              "ssim: one dtype for pred, gt and taps");
  TORCH_CHECK(taps.dim() == 1 && taps.size(0) % 2 == 1, "ssim: an odd number of taps");
}

}  // namespace

// The sum of the SSIM map per image [B] of pred, gt [B, H, W, C] (taps: the 1D window); with `need_grad` also the
// map's derivatives by the blurred moments [B, H, W, 3C] (mu_x, E[x^2], E[xy]) that ssim_backward takes.
std::vector<torch::Tensor> ssim_forward(torch::Tensor pred, torch::Tensor gt, torch::Tensor taps, double c1,
                                        double c2, bool need_grad) {
  check_images(pred, gt, taps);
  auto ssim_sum = torch::empty({pred.size(0)}, pred.options());
  torch::Tensor grads;
  if (need_grad) grads = torch::empty({pred.size(0), pred.size(1), pred.size(2), 3 * pred.size(3)}, pred.options());
  AT_DISPATCH_FLOATING_TYPES(pred.scalar_type(), "ssim_forward", [&] {
    forward_impl<scalar_t>(pred, gt, taps_of<scalar_t>(taps), static_cast<scalar_t>(c1), static_cast<scalar_t>(c2),
                           ssim_sum, need_grad ? &grads : nullptr);
  });
  return need_grad ? std::vector<torch::Tensor>{ssim_sum, grads} : std::vector<torch::Tensor>{ssim_sum};
}

// d loss / d pred [B, H, W, C] from d loss / d (SSIM sum per image) `grad_sum` [B] and ssim_forward's derivatives.
torch::Tensor ssim_backward(torch::Tensor pred, torch::Tensor gt, torch::Tensor grads, torch::Tensor taps,
                            torch::Tensor grad_sum) {
  check_images(pred, gt, taps);
  TORCH_CHECK(grads.is_contiguous() && grads.size(3) == 3 * pred.size(3), "ssim_backward: bad derivative maps");
  auto g_pred = torch::empty_like(pred);
  AT_DISPATCH_FLOATING_TYPES(pred.scalar_type(), "ssim_backward", [&] {
    backward_impl<scalar_t>(pred, gt, grads, taps_of<scalar_t>(taps), grad_sum.contiguous(), g_pred);
  });
  return g_pred;
}
