// Compiled CPU forward and backward of the direction medium's MLP with its output activations
// (fields/direction_medium.py, one hidden layer): per pixel p with encoded direction x_p [IN],
//   raw_p = W2 sigmoid(W1 x_p + b1) + b2 [9],
//   out_p = (sigmoid(raw_p[0:3]), softplus(raw_p[3:9] + density_bias)) [9], packed as the medium compositor reads,
// PyTorch's softplus (the identity above 20). SIMD across pixels (kLanes per vector, simd.h), fused multiply-adds.
// The forward walks the hidden units one by one over a block of kBlock pixels whose inputs and 9 output sums stay in
// L1, the activations in the same pass; for the backward it keeps the hidden layer (as the PyTorch path does). The
// backward takes each unit over a block with the unit's weight gradients summed in registers, then per lane (in T
// over kFlushBlocks blocks, then in double). The inputs (the SH encoding of ray directions, fixed) get no gradient.
// Blocks and chunks depend on P alone and the chunks are reduced in order: bitwise identical results whatever the
// thread count (not the SIMD width the build was compiled for).
#include "simd.h"

namespace {

using uw3dgs_kernels::kLanes;
using uw3dgs_kernels::Simd;
using uw3dgs_kernels::splat;
using uw3dgs_kernels::vexp;
using uw3dgs_kernels::vfmadd;
using uw3dgs_kernels::vexp_floored;

constexpr int kOut = 9;    // c_med, sigma_bs, sigma_attn: 3 each
constexpr int kColor = 3;  // the first kColor outputs take a sigmoid, the others the softplus
constexpr double kSoftplusThreshold = 20.0;  // PyTorch's softplus default: x itself above this
constexpr double kExpClamp = 80.0;           // vexp's range
constexpr int64_t kParallelPixels = 4096;    // below this the forward runs on one thread
constexpr int64_t kBlockVectors = 16;        // pixel vectors per block: a block's inputs and sums stay in L1
constexpr int64_t kBlock = kBlockVectors * kLanes;
constexpr int64_t kChunkBlocks = 32;  // blocks per chunk of the backward (its unit of parallelism)
constexpr int64_t kFlushBlocks = 16;  // blocks whose weight gradients are summed in T before they go to double
constexpr int64_t kMaxChunks = 8;

template <typename V, typename T>
inline V clamp_exp_arg(V x) {
  const V lo = splat<V>(static_cast<T>(-kExpClamp)), hi = splat<V>(static_cast<T>(kExpClamp));
  return x < lo ? lo : (x > hi ? hi : x);
}

// 1 / (1 + e^-z); e^-z's argument clamped to [kExpFloor, 80] (the result then within 2e-35 of exact).
template <typename T>
inline typename Simd<T>::V vsigmoid(typename Simd<T>::V z) {
  using V = typename Simd<T>::V;
  const V x = -z, hi = splat<V>(static_cast<T>(kExpClamp));
  return splat<V>(T(1)) / (splat<V>(T(1)) + vexp_floored(V(x > hi ? hi : x)));
}

template <typename T>
struct Bits;
template <>
struct Bits<float> {
  static constexpr int kMantissa = 23, kBias = 127, kTerms = 6;  // atanh series: truncation below 1e-10
  static constexpr float kLn2Hi = 0.693145751953125f, kLn2Lo = 1.428606765330187045e-06f;
};
template <>
struct Bits<double> {
  static constexpr int kMantissa = 52, kBias = 1023, kTerms = 12;  // truncation below 1e-19
  static constexpr double kLn2Hi = .69314718055966295651160180568695068359375,
                          kLn2Lo = .28235290563031577122588448175013436025525412068e-12;
};

// log(1 + u) for u >= 0, to about 1 ulp: 1 + u rounds to y = m 2^e with m in [sqrt(1/2), sqrt(2)), log m = 2 atanh(s)
// with s = (m - 1) / (m + 1) (|s| < 0.172) as its series, plus the rounding of 1 + u: (u - (y - 1)) / y.
template <typename T>
inline typename Simd<T>::V vlog1p(typename Simd<T>::V u) {
  using V = typename Simd<T>::V;
  using I = typename Simd<T>::I;
  using Int = typename Simd<T>::Int;
  using B = Bits<T>;
  const V one = splat<V>(T(1));
  const V y = one + u;
  const V c = (u - (y - one)) / y;
  const I bits = (I)y;
  I e = (bits >> B::kMantissa) - static_cast<Int>(B::kBias);  // y >= 1: no sign bit
  V m = (V)((bits & ((Int(1) << B::kMantissa) - 1)) | (static_cast<Int>(B::kBias) << B::kMantissa));  // [1, 2)
  const I big = m > splat<V>(T(1.41421356237309504880));
  m = big ? m * T(0.5) : m;
  e -= big;  // a true lane of a mask is -1
  const V f = m - one;  // exact
  const V s = f / (splat<V>(T(2)) + f), z = s * s;
  V series = splat<V>(T(1) / T(2 * B::kTerms - 1));
  for (int j = B::kTerms - 2; j >= 0; --j) series = series * z + T(1) / T(2 * j + 1);
  const V ef = __builtin_convertvector(e, V);
  return ef * B::kLn2Hi + (ef * B::kLn2Lo + c + T(2) * s * series);
}

// The output activations of one pixel vector, raw [kOut] -> out [kOut].
template <typename T>
inline void activate(const typename Simd<T>::V* raw, T density_bias, typename Simd<T>::V* out) {
  using V = typename Simd<T>::V;
  for (int m = 0; m < kColor; ++m) out[m] = vsigmoid<T>(raw[m]);
  const V threshold = splat<V>(static_cast<T>(kSoftplusThreshold));
  for (int m = kColor; m < kOut; ++m) {
    const V x = raw[m] + density_bias;
    const V soft = vlog1p<T>(vexp(clamp_exp_arg<V, T>(x)));
    out[m] = x > threshold ? x : soft;
  }
}

// d out / d raw of one pixel vector times the output gradient, in place: sigmoid's s (1 - s), softplus's
// z / (z + 1) with z = e^x (PyTorch's softplus_backward), 1 above the threshold.
template <typename T>
inline void activate_backward(const typename Simd<T>::V* raw, T density_bias, typename Simd<T>::V* grad) {
  using V = typename Simd<T>::V;
  const V one = splat<V>(T(1));
  for (int m = 0; m < kColor; ++m) {
    const V s = vsigmoid<T>(raw[m]);
    grad[m] = grad[m] * ((one - s) * s);
  }
  const V threshold = splat<V>(static_cast<T>(kSoftplusThreshold));
  for (int m = kColor; m < kOut; ++m) {
    const V x = raw[m] + density_bias;
    const V z = vexp(clamp_exp_arg<V, T>(x));
    grad[m] = x > threshold ? grad[m] : grad[m] * z / (z + one);
  }
}

// rows [n, width] (row-major, n <= lanes) -> cols [width][lanes], zero-padded: a block's pixels as feature vectors.
template <typename T>
inline void to_columns(const T* rows, int64_t n, int width, int64_t lanes, T* cols) {
  for (int j = 0; j < width; ++j) std::fill(cols + j * lanes + n, cols + (j + 1) * lanes, T(0));
  for (int64_t p = 0; p < n; ++p)
    for (int j = 0; j < width; ++j) cols[j * lanes + p] = rows[p * width + j];
}

// splat without the scalar addition of simd.h's (0 + x, which signed zeros keep): lane 0 to every lane.
template <typename V, typename T>
inline V bcast(T x) {
  return __builtin_shuffle(V{x}, typename Simd<T>::I{});
}

// The pre-activation b + w . x of one hidden unit at one pixel vector, x [IN][stride] from `xv`: two interleaved
// sums, so consecutive pixel vectors' chains overlap in the CPU.
template <typename V, int IN, typename T>
inline V hidden_pre(const T* w, T b, const T* xv, int64_t stride) {
  V even = bcast<V>(b), odd = {};
#pragma GCC unroll 16
  for (int i = 0; i + 1 < IN; i += 2) {
    even = vfmadd(bcast<V>(w[i]), vload<V>(xv + i * stride), even);
    odd = vfmadd(bcast<V>(w[i + 1]), vload<V>(xv + (i + 1) * stride), odd);
  }
  if constexpr (IN % 2 == 1) even = vfmadd(bcast<V>(w[IN - 1]), vload<V>(xv + (IN - 1) * stride), even);
  return even + odd;
}

// Blocks of kBlock pixels: the unit of the forward's loops and of the hidden layer it keeps for the backward.
int64_t num_blocks(int64_t P) { return (P + kBlock - 1) / kBlock; }

// out [P, kOut], raw [kOut, P] (before the activations) and, when `hidden` is not null, the hidden layer as
// [blocks, H, kBlock] (zero-padded pixels included) for the backward.
template <typename T, int IN>
void forward_impl(const T* x, int64_t P, const T* w1, const T* b1, const T* w2t, const T* b2, int64_t H,
                  T density_bias, T* out, T* raw, T* hidden) {
  using V = typename Simd<T>::V;
  const int64_t blocks = num_blocks(P);
#pragma omp parallel for schedule(static) if (P >= kParallelPixels)
  for (int64_t block = 0; block < blocks; ++block) {
    const int64_t p0 = block * kBlock, n = std::min(kBlock, P - p0), nv = (n + kLanes - 1) / kLanes;
    alignas(64) T xs[IN * kBlock], rs[kOut * kBlock];
    to_columns(x + p0 * IN, n, IN, kBlock, xs);
    for (int m = 0; m < kOut; ++m) std::fill(rs + m * kBlock, rs + (m + 1) * kBlock, b2[m]);
    for (int64_t k = 0; k < H; ++k) {  // unit by unit over the block: the output sums stay in L1
      const T* w2k = w2t + k * kOut;
      T* hk = hidden ? hidden + (block * H + k) * kBlock : nullptr;
      for (int64_t v = 0; v < nv; ++v) {
        const V h = vsigmoid<T>(hidden_pre<V, IN>(w1 + k * IN, b1[k], xs + v * kLanes, kBlock));
        if (hk) vstore(hk + v * kLanes, h);
#pragma GCC unroll 16
        for (int m = 0; m < kOut; ++m) {
          T* r = rs + m * kBlock + v * kLanes;
          vstore(r, vfmadd(bcast<V>(w2k[m]), h, vload<V>(r)));
        }
      }
    }
    for (int64_t v = 0; v < nv; ++v) {
      V acc[kOut], act[kOut];
      for (int m = 0; m < kOut; ++m) acc[m] = vload<V>(rs + m * kBlock + v * kLanes);
      activate<T>(acc, density_bias, act);
      for (int m = 0; m < kOut; ++m) vstore(rs + m * kBlock + v * kLanes, act[m]);
      if (raw) {
        alignas(64) T buf[kLanes];
        const int64_t lanes_here = std::min<int64_t>(kLanes, n - v * kLanes);
        for (int m = 0; m < kOut; ++m) {
          vstore(buf, acc[m]);
          std::copy(buf, buf + lanes_here, raw + m * P + p0 + v * kLanes);
        }
      }
    }
    for (int64_t p = 0; p < n; ++p)
      for (int m = 0; m < kOut; ++m) out[(p0 + p) * kOut + m] = rs[m * kBlock + p];
  }
}

// dst[l] += v[l] for every lane, in double.
template <typename V>
inline void add_lanes(double* dst, const V& v) {
  using D = Simd<double>::V;
  D d;
  std::memcpy(&d, dst, sizeof d);
  d += __builtin_convertvector(v, D);
  std::memcpy(dst, &d, sizeof d);
}

// sums [H IN + H + kOut H + kOut] (d w1 [H, IN], d b1 [H], d w2^T [H, kOut], d b2 [kOut]) given grad [P, kOut] and
// the forward's raw [kOut, P] and hidden [blocks, H, kBlock].
template <typename T, int IN>
void backward_impl(const T* x, int64_t P, const T* w2t, int64_t H, T density_bias, const T* raw, const T* hidden,
                   const T* grad, double* sums) {
  using V = typename Simd<T>::V;
  const int64_t blocks = num_blocks(P);
  const int64_t chunks = std::max<int64_t>(1, std::min<int64_t>(kMaxChunks, blocks / kChunkBlocks));
  const int64_t o_b1 = H * IN, o_w2 = o_b1 + H, o_b2 = o_w2 + H * kOut, per_chunk = o_b2 + kOut;
  // per chunk and quantity a sum per lane: in T over up to kFlushBlocks blocks, then in double
  std::vector<double> lanes(chunks * per_chunk * kLanes, 0.0);
#pragma omp parallel for schedule(static, 1) if (chunks > 1)
  for (int64_t chunk = 0; chunk < chunks; ++chunk) {
    double* total = lanes.data() + chunk * per_chunk * kLanes;
    std::vector<T> partial(per_chunk * kLanes, T(0));
    T* acc = partial.data();
    std::vector<T> columns((IN + kOut) * kBlock);  // the block's inputs and output gradients as feature vectors
    T *xs = columns.data(), *gs = xs + IN * kBlock;
    const int64_t first = blocks * chunk / chunks, last = blocks * (chunk + 1) / chunks;
    for (int64_t block = first; block < last; ++block) {
      const int64_t p0 = block * kBlock, n = std::min(kBlock, P - p0), nv = (n + kLanes - 1) / kLanes;
      to_columns(x + p0 * IN, n, IN, kBlock, xs);
      to_columns(grad + p0 * kOut, n, kOut, kBlock, gs);  // zero-padded: the padding adds nothing below
      for (int64_t v = 0; v < nv; ++v) {  // the output gradients through the activations: d loss / d raw
        V r[kOut], g[kOut];
        alignas(64) T buf[kLanes] = {};
        const int64_t lanes_here = std::min<int64_t>(kLanes, n - v * kLanes);
        for (int m = 0; m < kOut; ++m) {
          std::copy(raw + m * P + p0 + v * kLanes, raw + m * P + p0 + v * kLanes + lanes_here, buf);
          r[m] = vload<V>(buf);
          g[m] = vload<V>(gs + m * kBlock + v * kLanes);
        }
        activate_backward<T>(r, density_bias, g);
        for (int m = 0; m < kOut; ++m) {
          vstore(gs + m * kBlock + v * kLanes, g[m]);
          T* a = acc + (o_b2 + m) * kLanes;
          vstore(a, vload<V>(a) + g[m]);
        }
      }
      for (int64_t k = 0; k < H; ++k) {  // one hidden unit over the block, its weight gradients in registers
        const T* w2k = w2t + k * kOut;
        const T* hk = hidden + (block * H + k) * kBlock;
        V g_w1[IN] = {}, g_w2[kOut] = {}, g_b1 = {};
        for (int64_t v = 0; v < nv; ++v) {
          const V h = vload<V>(hk + v * kLanes);
          V g[kOut], gh_even = {}, gh_odd = {};
#pragma GCC unroll 16
          for (int m = 0; m < kOut; ++m) {
            g[m] = vload<V>(gs + m * kBlock + v * kLanes);
            if (m % 2) gh_odd = vfmadd(bcast<V>(w2k[m]), g[m], gh_odd);
            else gh_even = vfmadd(bcast<V>(w2k[m]), g[m], gh_even);
            g_w2[m] = vfmadd(g[m], h, g_w2[m]);
          }
          const V g_pre = (gh_even + gh_odd) * ((T(1) - h) * h);
          g_b1 += g_pre;
#pragma GCC unroll 16
          for (int i = 0; i < IN; ++i) g_w1[i] = vfmadd(g_pre, vload<V>(xs + i * kBlock + v * kLanes), g_w1[i]);
        }
        const auto add = [&](int64_t q, const V& value) {
          T* a = acc + q * kLanes;
          vstore(a, vload<V>(a) + value);
        };
        for (int i = 0; i < IN; ++i) add(k * IN + i, g_w1[i]);
        add(o_b1 + k, g_b1);
        for (int m = 0; m < kOut; ++m) add(o_w2 + k * kOut + m, g_w2[m]);
      }
      if ((block - first + 1) % kFlushBlocks == 0 || block + 1 == last) {
        for (int64_t q = 0; q < per_chunk; ++q) add_lanes(total + q * kLanes, vload<V>(acc + q * kLanes));
        std::fill(partial.begin(), partial.end(), T(0));
      }
    }
  }
  for (int64_t q = 0; q < per_chunk; ++q) {  // the lanes in a fixed tree, then the chunks in order
    double sum = 0;
    for (int64_t chunk = 0; chunk < chunks; ++chunk)
      sum += uw3dgs_kernels::hsum<double>(vload<Simd<double>::V>(lanes.data() + (chunk * per_chunk + q) * kLanes));
    sums[q] = sum;
  }
}

void check_inputs(const torch::Tensor& x, const torch::Tensor& w1, const torch::Tensor& b1, const torch::Tensor& w2,
                  const torch::Tensor& b2) {
  for (const torch::Tensor* t : {&x, &w1, &b1, &w2, &b2}) {
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous(), "direction_mlp: inputs must be contiguous CPU tensors");
    TORCH_CHECK(t->scalar_type() == x.scalar_type(), "direction_mlp: inputs and weights must share one dtype");
  }
  TORCH_CHECK(x.dim() == 2 && w1.dim() == 2 && w1.size(1) == x.size(1) && b1.dim() == 1 && b1.size(0) == w1.size(0),
              "direction_mlp: x [P, IN], w1 [H, IN], b1 [H]");
  TORCH_CHECK(w2.dim() == 2 && w2.size(0) == kOut && w2.size(1) == w1.size(0) && b2.dim() == 1 && b2.size(0) == kOut,
              "direction_mlp: w2 [9, H], b2 [9]");
}

// The input width as a compile-time constant (the SH encodings of degree 0-3): the inputs stay in registers.
template <typename F>
void dispatch_width(int64_t width, F&& f) {
  switch (width) {
    case 1: f(std::integral_constant<int, 1>{}); break;
    case 4: f(std::integral_constant<int, 4>{}); break;
    case 9: f(std::integral_constant<int, 9>{}); break;
    case 16: f(std::integral_constant<int, 16>{}); break;
    default: TORCH_CHECK(false, "direction_mlp: the input width must be 1, 4, 9 or 16 (an SH encoding), got ", width);
  }
}

}  // namespace

// (out [P, 9], raw [9, P], hidden) for x [P, IN], w1 [H, IN], b1 [H], w2 [9, H], b2 [9]: out the activated outputs;
// with `for_backward` raw the MLP's outputs before the activations and hidden its hidden layer (internal layout),
// else both empty.
std::vector<torch::Tensor> direction_mlp_forward(torch::Tensor x, torch::Tensor w1, torch::Tensor b1,
                                                 torch::Tensor w2, torch::Tensor b2, double density_bias,
                                                 bool for_backward) {
  check_inputs(x, w1, b1, w2, b2);
  const int64_t P = x.size(0), H = w1.size(0);
  auto out = torch::empty({P, kOut}, x.options());
  auto raw = torch::empty({for_backward ? kOut : 0, P}, x.options());
  auto hidden = torch::empty({for_backward ? num_blocks(P) * H * kBlock : 0}, x.options());
  const auto w2t = w2.t().contiguous();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "direction_mlp_forward", [&] {
    dispatch_width(x.size(1), [&](auto in) {
      forward_impl<scalar_t, decltype(in)::value>(
          x.data_ptr<scalar_t>(), P, w1.data_ptr<scalar_t>(), b1.data_ptr<scalar_t>(), w2t.data_ptr<scalar_t>(),
          b2.data_ptr<scalar_t>(), H, static_cast<scalar_t>(density_bias), out.data_ptr<scalar_t>(),
          for_backward ? raw.data_ptr<scalar_t>() : nullptr, for_backward ? hidden.data_ptr<scalar_t>() : nullptr);
    });
  });
  return {out, raw, hidden};
}

// (d w1, d b1, d w2, d b2) given grad [P, 9] of out and the forward's raw and hidden (`for_backward`).
std::vector<torch::Tensor> direction_mlp_backward(torch::Tensor x, torch::Tensor w1, torch::Tensor b1,
                                                  torch::Tensor w2, torch::Tensor b2, torch::Tensor raw,
                                                  torch::Tensor hidden, torch::Tensor grad, double density_bias) {
  check_inputs(x, w1, b1, w2, b2);
  const int64_t P = x.size(0), H = w1.size(0), IN = x.size(1);
  TORCH_CHECK(raw.is_contiguous() && raw.sizes() == torch::IntArrayRef({kOut, P}) && hidden.is_contiguous() &&
                  hidden.numel() == num_blocks(P) * H * kBlock && grad.is_contiguous() &&
                  grad.sizes() == torch::IntArrayRef({P, kOut}),
              "direction_mlp: raw and hidden must be the forward's (for_backward) and grad a contiguous [P, 9]");
  for (const torch::Tensor* t : {&raw, &hidden, &grad})
    TORCH_CHECK(t->scalar_type() == x.scalar_type(), "direction_mlp: raw, hidden and grad must have the inputs' dtype");
  auto sums = torch::empty({H * IN + H + kOut * H + kOut}, x.options().dtype(torch::kFloat64));
  const auto w2t = w2.t().contiguous();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "direction_mlp_backward", [&] {
    dispatch_width(IN, [&](auto in) {
      backward_impl<scalar_t, decltype(in)::value>(x.data_ptr<scalar_t>(), P, w2t.data_ptr<scalar_t>(), H,
                                                    static_cast<scalar_t>(density_bias), raw.data_ptr<scalar_t>(),
                                                    hidden.data_ptr<scalar_t>(), grad.data_ptr<scalar_t>(),
                                                    sums.data_ptr<double>());
    });
  });
  auto g = sums.to(x.scalar_type());
  return {g.narrow(0, 0, H * IN).view({H, IN}), g.narrow(0, H * IN, H),
          g.narrow(0, H * IN + H, H * kOut).view({H, kOut}).t().contiguous(), g.narrow(0, H * (IN + 1 + kOut), kOut)};
}
