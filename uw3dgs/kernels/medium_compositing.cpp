// The medium compositor on the CPU (WaterSplatting's water between depth-sorted Gaussians): forward and hand-written
// backward, numerically mirroring uw3dgs/render/medium_reference.py (see it and MediumRasterOutput for the maths).
// It takes the screen-space Gaussians and the tile lists made by the shared projection and binning, and composites
// each pixel front to back with the 3DGS rules (power <= 0, alpha_min, alpha_max, early termination) plus the water:
//   restored = sum_i w_i c_i, object = sum_i w_i c_i exp(-sigma_attn z_i), water = c_med (1 - sum_i w_i exp(-sigma_bs z_i))
// (the interval sum of the definition telescoped). Depths take no gradient. Parallel over tiles; per-(tile, Gaussian)
// slots reduced per Gaussian in list order, so results do not depend on the thread count.
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

namespace {

constexpr double kExpFloor = -80.0;

template <typename T>
struct Inputs {
  const T *xy, *conic, *opac, *color, *depth, *medium;
  const int64_t *starts, *counts, *ids;
  int64_t width, height, tile, tiles_x, n_tiles;
  T alpha_min, alpha_max, t_min;
};

template <typename T>
Inputs<T> inputs(const torch::Tensor& means2d, const torch::Tensor& conics, const torch::Tensor& opacities,
                 const torch::Tensor& colors, const torch::Tensor& depths, const torch::Tensor& medium,
                 const torch::Tensor& starts, const torch::Tensor& counts, const torch::Tensor& ids, int64_t width,
                 int64_t height, int64_t tile, double alpha_min, double alpha_max, double t_min) {
  const int64_t tiles_x = (width + tile - 1) / tile, tiles_y = (height + tile - 1) / tile;
  TORCH_CHECK(starts.numel() == tiles_x * tiles_y && counts.numel() == tiles_x * tiles_y, "tile lists do not fit");
  TORCH_CHECK(medium.size(0) == height && medium.size(1) == width && medium.size(2) == 9, "medium must be [H, W, 9]");
  return {means2d.data_ptr<T>(), conics.data_ptr<T>(), opacities.data_ptr<T>(), colors.data_ptr<T>(),
          depths.data_ptr<T>(), medium.data_ptr<T>(), starts.data_ptr<int64_t>(), counts.data_ptr<int64_t>(),
          ids.data_ptr<int64_t>(), width, height, tile, tiles_x, tiles_x * tiles_y,
          static_cast<T>(alpha_min), static_cast<T>(alpha_max), static_cast<T>(t_min)};
}

// One blended Gaussian of a pixel: its position in the tile list, alpha, the transmittance in front of it, and
// (for the backward) dx, dy.
template <typename T>
struct Hit {
  int64_t j;
  T alpha, T_before, dx, dy;
};

// The pixel (px, py) (its centre) walked front to back over tile t's list: its blended Gaussians in order.
template <typename T>
void walk(const Inputs<T>& in, int64_t t, T px, T py, std::vector<Hit<T>>& hits) {
  hits.clear();
  const int64_t start = in.starts[t], k = in.counts[t];
  T tr = 1;
  for (int64_t j = 0; j < k; ++j) {
    const int64_t g = in.ids[start + j];
    const T dx = px - in.xy[2 * g], dy = py - in.xy[2 * g + 1];
    const T a = in.conic[3 * g], b = in.conic[3 * g + 1], c = in.conic[3 * g + 2];
    const T log_op = std::log(in.opac[g]);
    // log(opacity) + power, in the reference's order: (-c dy^2/2 + log op) + (-a dx^2/2) + (-b dy) dx
    const T e = ((static_cast<T>(-0.5) * c * dy * dy + log_op) + static_cast<T>(-0.5) * a * dx * dx) + (-b * dy) * dx;
    if (!(e <= log_op)) continue;  // power > 0 (or NaN)
    T alpha = std::exp(std::max(e, static_cast<T>(kExpFloor)));
    alpha = std::min(alpha, in.alpha_max);
    if (!(alpha >= in.alpha_min)) continue;
    const T t_next = tr * (static_cast<T>(1) - alpha);
    if (!(t_next >= in.t_min)) break;  // early termination: this one and all behind it are dropped
    hits.push_back({j, alpha, tr, dx, dy});
    tr = t_next;
  }
}

template <typename T>
void forward_impl(const Inputs<T>& in, T* restored, T* depth, T* alpha_img, T* object, T* water, T* slot_w,
                  int32_t* slot_n) {
  const int64_t W = in.width;
#pragma omp parallel
  {
    std::vector<Hit<T>> hits;
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < in.n_tiles; ++t) {
      const int64_t x0 = (t % in.tiles_x) * in.tile, y0 = (t / in.tiles_x) * in.tile, start = in.starts[t];
      for (int64_t j = 0; j < in.counts[t]; ++j) {
        slot_w[start + j] = 0;
        slot_n[start + j] = 0;
      }
      for (int64_t y = y0; y < std::min(y0 + in.tile, in.height); ++y)
        for (int64_t x = x0; x < std::min(x0 + in.tile, W); ++x) {
          walk(in, t, static_cast<T>(x) + static_cast<T>(0.5), static_cast<T>(y) + static_cast<T>(0.5), hits);
          const int64_t q = y * W + x;
          const T* med = in.medium + 9 * q;
          T rest[3] = {0, 0, 0}, obj[3] = {0, 0, 0}, scat[3] = {0, 0, 0}, d = 0, a = 0;
          for (const Hit<T>& h : hits) {
            const int64_t g = in.ids[start + h.j];
            const T w = h.alpha * h.T_before, z = in.depth[g];
            for (int c = 0; c < 3; ++c) {
              const T col = in.color[3 * g + c];
              rest[c] += w * col;
              obj[c] += w * col * std::exp(-med[6 + c] * z);
              scat[c] += w * std::exp(-med[3 + c] * z);
            }
            d += w * z;
            a += w;
            slot_w[start + h.j] += w;
            slot_n[start + h.j] += 1;
          }
          for (int c = 0; c < 3; ++c) {
            restored[3 * q + c] = rest[c];
            object[3 * q + c] = obj[c];
            water[3 * q + c] = med[c] * (static_cast<T>(1) - scat[c]);
          }
          depth[q] = d;
          alpha_img[q] = a;
        }
    }
  }
}

constexpr int kRow = 11;  // per slot: mean x, y, conic a, b, c, opacity, colour r, g, b, |d mean x|, |d mean y|

template <typename T>
void backward_impl(const Inputs<T>& in, const T* g_rest, const T* g_depth, const T* g_alpha, const T* g_obj,
                   const T* g_water, T* slots, T* g_medium) {
  const int64_t W = in.width;
#pragma omp parallel
  {
    std::vector<Hit<T>> hits;
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < in.n_tiles; ++t) {
      const int64_t x0 = (t % in.tiles_x) * in.tile, y0 = (t / in.tiles_x) * in.tile, start = in.starts[t];
      std::fill(slots + start * kRow, slots + (start + in.counts[t]) * kRow, static_cast<T>(0));
      for (int64_t y = y0; y < std::min(y0 + in.tile, in.height); ++y)
        for (int64_t x = x0; x < std::min(x0 + in.tile, W); ++x) {
          walk(in, t, static_cast<T>(x) + static_cast<T>(0.5), static_cast<T>(y) + static_cast<T>(0.5), hits);
          const int64_t q = y * W + x;
          const T* med = in.medium + 9 * q;
          const T *gr = g_rest + 3 * q, *go = g_obj + 3 * q, *gw = g_water + 3 * q;
          T gm[3];  // dL / d(sum_i w_i exp(-sigma_bs z_i)) = -g_water c_med
          for (int c = 0; c < 3; ++c) gm[c] = gw[c] * med[c];
          T scat[3] = {0, 0, 0}, scat_z[3] = {0, 0, 0}, att_z[3] = {0, 0, 0};
          T S = 0;  // sum over the Gaussians behind of w_j dL/dw_j
          for (auto h = hits.rbegin(); h != hits.rend(); ++h) {
            const int64_t g = in.ids[start + h->j];
            const T w = h->alpha * h->T_before, z = in.depth[g];
            T gw_i = g_depth[q] * z + g_alpha[q];  // dL/dw_i
            T* row = slots + (start + h->j) * kRow;
            for (int c = 0; c < 3; ++c) {
              const T col = in.color[3 * g + c];
              const T ea = std::exp(-med[6 + c] * z), eb = std::exp(-med[3 + c] * z);
              gw_i += gr[c] * col + go[c] * col * ea - gm[c] * eb;
              row[6 + c] += w * (gr[c] + go[c] * ea);
              scat[c] += w * eb;
              scat_z[c] += w * z * eb;
              att_z[c] += w * col * z * ea;
            }
            // dL/dalpha_i = T_i g_i - S_i / (1 - alpha_i); dL/dpower = alpha dL/dalpha (0 where clamped)
            const T g_alpha_i = h->T_before * gw_i - S / (static_cast<T>(1) - h->alpha);
            S += w * gw_i;
            const T G = h->alpha < in.alpha_max ? h->alpha * g_alpha_i : static_cast<T>(0);
            const T a = in.conic[3 * g], b = in.conic[3 * g + 1], c = in.conic[3 * g + 2];
            const T dx = h->dx, dy = h->dy;
            const T gx = G * (a * dx + b * dy), gy = G * (b * dx + c * dy);
            row[0] += gx;
            row[1] += gy;
            row[2] += static_cast<T>(-0.5) * G * dx * dx;
            row[3] += -G * dx * dy;
            row[4] += static_cast<T>(-0.5) * G * dy * dy;
            row[5] += G / std::max(in.opac[g], std::numeric_limits<T>::min());
            row[9] += std::abs(gx);
            row[10] += std::abs(gy);
          }
          T* gmed = g_medium + 9 * q;
          for (int c = 0; c < 3; ++c) {
            gmed[c] = gw[c] * (static_cast<T>(1) - scat[c]);
            gmed[3 + c] = gm[c] * scat_z[c];
            gmed[6 + c] = -go[c] * att_z[c];
          }
        }
    }
  }
}

torch::Tensor c64(const torch::Tensor& t) { return t.to(torch::kInt64).contiguous(); }

}  // namespace

std::vector<torch::Tensor> medium_composite_forward(torch::Tensor means2d, torch::Tensor conics,
                                                    torch::Tensor opacities, torch::Tensor colors,
                                                    torch::Tensor depths, torch::Tensor medium,
                                                    torch::Tensor tile_starts, torch::Tensor tile_counts,
                                                    torch::Tensor gauss_ids, int64_t width, int64_t height,
                                                    int64_t tile, double alpha_min, double alpha_max, double t_min) {
  const auto opts = means2d.options();
  const int64_t n = means2d.size(0), pairs = gauss_ids.numel();
  auto starts = c64(tile_starts), counts = c64(tile_counts), ids = c64(gauss_ids);
  auto restored = torch::empty({height, width, 3}, opts), object = torch::empty({height, width, 3}, opts);
  auto water = torch::empty({height, width, 3}, opts);
  auto depth = torch::empty({height, width}, opts), alpha = torch::empty({height, width}, opts);
  auto slot_w = torch::empty({pairs}, opts);
  auto slot_n = torch::empty({pairs}, opts.dtype(torch::kInt32));
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "medium_composite_forward", [&] {
    const auto in = inputs<scalar_t>(means2d, conics, opacities, colors, depths, medium, starts, counts, ids, width,
                                     height, tile, alpha_min, alpha_max, t_min);
    forward_impl<scalar_t>(in, restored.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(),
                           alpha.data_ptr<scalar_t>(), object.data_ptr<scalar_t>(), water.data_ptr<scalar_t>(),
                           slot_w.data_ptr<scalar_t>(), slot_n.data_ptr<int32_t>());
  });
  // per Gaussian, in list order: independent of the thread count
  auto weight_sum = torch::zeros({n}, opts).index_add_(0, ids, slot_w);
  auto pixel_count = torch::zeros({n}, opts.dtype(torch::kInt32)).index_add_(0, ids, slot_n);
  return {restored, depth, alpha, object, water, weight_sum, pixel_count};
}

std::vector<torch::Tensor> medium_composite_backward(torch::Tensor means2d, torch::Tensor conics,
                                                     torch::Tensor opacities, torch::Tensor colors,
                                                     torch::Tensor depths, torch::Tensor medium,
                                                     torch::Tensor tile_starts, torch::Tensor tile_counts,
                                                     torch::Tensor gauss_ids, int64_t width, int64_t height,
                                                     int64_t tile, double alpha_min, double alpha_max, double t_min,
                                                     torch::Tensor g_restored, torch::Tensor g_depth,
                                                     torch::Tensor g_alpha, torch::Tensor g_object,
                                                     torch::Tensor g_water) {
  const auto opts = means2d.options();
  const int64_t n = means2d.size(0), pairs = gauss_ids.numel();
  auto starts = c64(tile_starts), counts = c64(tile_counts), ids = c64(gauss_ids);
  auto slots = torch::empty({pairs, kRow}, opts);
  auto g_medium = torch::empty({height, width, 9}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "medium_composite_backward", [&] {
    const auto in = inputs<scalar_t>(means2d, conics, opacities, colors, depths, medium, starts, counts, ids, width,
                                     height, tile, alpha_min, alpha_max, t_min);
    backward_impl<scalar_t>(in, g_restored.data_ptr<scalar_t>(), g_depth.data_ptr<scalar_t>(),
                            g_alpha.data_ptr<scalar_t>(), g_object.data_ptr<scalar_t>(),
                            g_water.data_ptr<scalar_t>(), slots.data_ptr<scalar_t>(), g_medium.data_ptr<scalar_t>());
  });
  auto grads = torch::zeros({n, kRow}, opts).index_add_(0, ids, slots);
  return {grads.slice(1, 0, 2).contiguous(), grads.slice(1, 2, 5).contiguous(), grads.select(1, 5).contiguous(),
          grads.slice(1, 6, 9).contiguous(), g_medium, grads.slice(1, 9, 11).contiguous()};
}
