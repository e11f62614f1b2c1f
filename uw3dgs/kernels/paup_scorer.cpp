// Compiled CPU forward and backward of PAUP's phi: m_i = sigmoid(sum_j w2_j relu(w1_j x_i + b1_j) + b2), a 2-layer
// MLP of one input (the score PUS_i) per Gaussian (uw3dgs/paup/scorer.py). PyTorch forms the [N, H] hidden layer,
// its ReLU and their gradients as whole arrays, several passes over N x H values; here the forward sums a block of
// Gaussians unit by unit in SIMD registers (no sums across lanes), and so does the backward. The weights' gradients
// are summed in double per block and chunk of Gaussians, both fixed by N alone, and the chunks reduced in order:
// bitwise identical results whatever the thread count.
#include <torch/extension.h>

#include "exp_f32.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr int64_t kChunk = 16384;
constexpr int64_t kMaxChunks = 8;

int64_t num_chunks(int64_t n) { return std::max<int64_t>(1, std::min<int64_t>(kMaxChunks, n / kChunk)); }

constexpr int64_t kBlock = 256;  // Gaussians whose hidden layers are summed together (SIMD across Gaussians)

// sigmoid(z) = 1 / (1 + e^-z); float: e^-z in arithmetic that vectorises (exp_f32.h), clamped to [-87, 87]
// (sigmoid there is 1 - 1.6e-38 or 1.6e-38; the exact value is within 2e-38).
inline float sigmoid(float z) { return 1.0f / (1.0f + exp_f32(std::min(std::max(-z, -87.0f), 87.0f))); }
inline double sigmoid(double z) { return 1.0 / (1.0 + std::exp(-z)); }

template <typename T>
void forward_impl(const torch::Tensor& x, const torch::Tensor& w1, const torch::Tensor& b1, const torch::Tensor& w2,
                  const torch::Tensor& b2, torch::Tensor& m) {
  const int64_t n = x.size(0), h = w1.size(0), blocks = (n + kBlock - 1) / kBlock;
  const T *xp = x.data_ptr<T>(), *w1p = w1.data_ptr<T>(), *b1p = b1.data_ptr<T>(), *w2p = w2.data_ptr<T>();
  const T b2v = b2.data_ptr<T>()[0];
  T* mp = m.data_ptr<T>();
#pragma omp parallel for schedule(static) if (n >= kChunk)
  for (int64_t block = 0; block < blocks; ++block) {
    const int64_t i0 = block * kBlock, nb = std::min(kBlock, n - i0);
    const T* xb = xp + i0;
    T s[kBlock] = {};
    for (int64_t j = 0; j < h; ++j) {  // unit by unit over a block of Gaussians: no sums across SIMD lanes
      const T a = w1p[j], b = b1p[j], c = w2p[j];
#pragma omp simd
      for (int64_t i = 0; i < nb; ++i) s[i] += c * std::max(a * xb[i] + b, T(0));
    }
#pragma omp simd
    for (int64_t i = 0; i < nb; ++i) mp[i0 + i] = sigmoid(s[i] + b2v);
  }
}

template <typename T>
void backward_impl(const torch::Tensor& x, const torch::Tensor& w1, const torch::Tensor& b1, const torch::Tensor& w2,
                   const torch::Tensor& m, const torch::Tensor& grad, torch::Tensor& g_x, torch::Tensor& g_w1,
                   torch::Tensor& g_b1, torch::Tensor& g_w2, torch::Tensor& g_b2) {
  const int64_t n = x.size(0), h = w1.size(0), chunks = num_chunks(n), stride = 3 * h + 1;
  const T *xp = x.data_ptr<T>(), *w1p = w1.data_ptr<T>(), *b1p = b1.data_ptr<T>(), *w2p = w2.data_ptr<T>(),
          *mp = m.data_ptr<T>(), *gp = grad.data_ptr<T>();
  T* gx = g_x.data_ptr<T>();
  // per chunk: d w1 [h], d b1 [h], d w2 [h], d b2, in double: each is a sum over up to N / chunks Gaussians
  std::vector<double> acc(chunks * stride, 0.0);
#pragma omp parallel for schedule(static, 1) if (n >= kChunk)
  for (int64_t chunk = 0; chunk < chunks; ++chunk) {
    double *gw1 = acc.data() + chunk * stride, *gb1 = gw1 + h, *gw2 = gb1 + h;
    const int64_t end = n * (chunk + 1) / chunks;
    for (int64_t i0 = n * chunk / chunks; i0 < end; i0 += kBlock) {  // as the forward: unit by unit over a block
      const int64_t nb = std::min(kBlock, end - i0);
      const T* xb = xp + i0;
      T gz[kBlock], dx[kBlock];
      double sum_gz = 0;
#pragma omp simd reduction(+ : sum_gz)
      for (int64_t i = 0; i < nb; ++i) {
        gz[i] = gp[i0 + i] * mp[i0 + i] * (T(1) - mp[i0 + i]);  // through the sigmoid
        dx[i] = 0;
        sum_gz += gz[i];
      }
      for (int64_t j = 0; j < h; ++j) {
        const T a = w1p[j], b = b1p[j], c = w2p[j];
        double s_w1 = 0, s_b1 = 0, s_w2 = 0;
#pragma omp simd reduction(+ : s_w1, s_b1, s_w2)
        for (int64_t i = 0; i < nb; ++i) {  // branch-free: inactive units add zeros
          const T pre = a * xb[i] + b;
          const T on = pre > T(0) ? T(1) : T(0);
          const T gpre = gz[i] * c * on;
          s_w2 += gz[i] * pre * on;
          s_w1 += gpre * xb[i];
          s_b1 += gpre;
          dx[i] += gpre * a;
        }
        gw1[j] += s_w1;
        gb1[j] += s_b1;
        gw2[j] += s_w2;
      }
      gw2[h] += sum_gz;
      std::copy(dx, dx + nb, gx + i0);
    }
  }
  for (int64_t chunk = 1; chunk < chunks; ++chunk)  // in order: the sums do not depend on the threads
    for (int64_t k = 0; k < stride; ++k) acc[k] += acc[chunk * stride + k];
  std::copy(acc.begin(), acc.begin() + h, g_w1.data_ptr<T>());  // converts to T
  std::copy(acc.begin() + h, acc.begin() + 2 * h, g_b1.data_ptr<T>());
  std::copy(acc.begin() + 2 * h, acc.begin() + 3 * h, g_w2.data_ptr<T>());
  g_b2.data_ptr<T>()[0] = static_cast<T>(acc[3 * h]);
}

void check_inputs(const torch::Tensor& x, const torch::Tensor& w1, const torch::Tensor& b1, const torch::Tensor& w2,
                  const torch::Tensor& b2) {
  for (const torch::Tensor* t : {&x, &w1, &b1, &w2, &b2}) {
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous() && t->dim() == 1,
                "floater_mlp: inputs must be contiguous 1-D CPU tensors");
    TORCH_CHECK(t->scalar_type() == x.scalar_type(), "floater_mlp: inputs must share one dtype");
  }
  TORCH_CHECK(b1.size(0) == w1.size(0) && w2.size(0) == w1.size(0) && b2.size(0) == 1,
              "floater_mlp: w1, b1, w2 [H] and b2 [1]");
}

}  // namespace

// m [N] = sigmoid(w2 . relu(w1 x + b1) + b2) for scores x [N].
torch::Tensor floater_mlp_forward(torch::Tensor x, torch::Tensor w1, torch::Tensor b1, torch::Tensor w2,
                                  torch::Tensor b2) {
  check_inputs(x, w1, b1, w2, b2);
  auto m = torch::empty_like(x);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "floater_mlp_forward",
                             [&] { forward_impl<scalar_t>(x, w1, b1, w2, b2, m); });
  return m;
}

// (d x, d w1, d b1, d w2, d b2) given the forward's m [N] and grad [N].
std::vector<torch::Tensor> floater_mlp_backward(torch::Tensor x, torch::Tensor w1, torch::Tensor b1, torch::Tensor w2,
                                                torch::Tensor b2, torch::Tensor m, torch::Tensor grad) {
  check_inputs(x, w1, b1, w2, b2);
  TORCH_CHECK(m.sizes() == x.sizes() && grad.sizes() == x.sizes() && m.is_contiguous() && grad.is_contiguous(),
              "floater_mlp: m and grad must be contiguous [N]");
  auto g_x = torch::empty_like(x), g_w1 = torch::empty_like(w1), g_b1 = torch::empty_like(b1),
       g_w2 = torch::empty_like(w2), g_b2 = torch::empty_like(b2);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "floater_mlp_backward", [&] {
    backward_impl<scalar_t>(x, w1, b1, w2, m, grad, g_x, g_w1, g_b1, g_w2, g_b2);
  });
  return {g_x, g_w1, g_b1, g_w2, g_b2};
}
