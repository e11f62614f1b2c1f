// The medium compositor on the CPU (WaterSplatting's water between depth-sorted Gaussians), forward and hand-written
// backward, numerically mirroring uw3dgs/render/medium_reference.py (see it and MediumRasterOutput for the maths). A
// sibling of compositing.cpp: the same Gaussian records, binning and SIMD tile structs (compositing.h), whose
// blending of the restored colour, depth and alpha (3DGS's, features = colour + depth) is extended through their
// hook by the water of each pixel:
//   object = sum_i w_i c_i exp(-sigma_attn z_i), water = c_med (1 - sum_i w_i exp(-sigma_bs z_i))
// (the interval sum of the definition telescoped), w_i = alpha_i T_i. Depths take no gradient. Per (tile, Gaussian)
// slots reduced per Gaussian in a fixed order, so results do not depend on the thread count.
#include "compositing.h"

using namespace uw3dgs_kernels;

namespace {

constexpr int kColor = 3;       // the features: colour (3), then depth
constexpr int kFeats = kColor + 1;
constexpr int kMediumValues = 9;  // per pixel: c_med, sigma_bs, sigma_attn (3 each)

// The per-pixel part of a water factor as a short series: exp(x) = 1 + x + ... + x^(kTerms-1) / (kTerms-1)! for
// |x| <= kBound, within the remainder |x|^kTerms / kTerms! e^|x| (relative; float: 6e-9, double: 3e-19).
template <typename T>
struct WaterSeries;
template <>
struct WaterSeries<float> {
  static constexpr int kTerms = 6;
  static constexpr float kBound = 0.125f;
};
template <>
struct WaterSeries<double> {
  static constexpr int kTerms = 10;
  static constexpr double kBound = 0.0625;
};

// 1 / i! for i < N.
template <typename T, int N>
struct InverseFactorials {
  T v[N] = {};
  constexpr InverseFactorials() {
    v[0] = 1;
    for (int i = 1; i < N; ++i) v[i] = v[i - 1] / static_cast<T>(i);
  }
};

// The water of one tile as planes shaped like the tile structs' (channel-major, rows padded to whole chunks), per
// kind (sigma_bs, sigma_attn) and channel: -sigma (padding: 0), and its deviation from the tile's midrange (padding:
// 0). The factors exp(-sigma z) of a Gaussian at depth z: where the water varies little across the tile (half-range
// times z within the series' bound), one exp of the midrange per kind and channel (`at_depth`) times the series of
// the pixel's deviation, 7 vector operations instead of an exp's 14 (float, AVX-512); else the exp per pixel.
template <typename T>
struct WaterPlanes {
  using V = typename Simd<T>::V;
  static constexpr int kKinds = 2;  // sigma_bs, sigma_attn
  const T* medium = nullptr;  // [H, W, 9]
  const T* ft = nullptr;      // [N, 4]: colour, depth
  int64_t width = 0, stride = 0, plane = 0;
  std::vector<T> neg, dev;  // kKinds x kColor planes each: -sigma, -sigma minus its midrange over the tile
  T mid[kKinds * kColor] = {}, spread = 0;  // midranges of -sigma; the largest half-range
  // the Gaussian whose factors are being taken: its id (-1: none since load), depth, whether the series applies and
  // the factors at the midranges
  int32_t current = -1;
  T z = 0;
  bool series = false;
  T base[kLanes] = {};

  WaterPlanes() = default;
  WaterPlanes(const torch::Tensor& medium_, const torch::Tensor& feats, const Bins& bins, int64_t width_)
      : medium(medium_.data_ptr<T>()), ft(feats.data_ptr<T>()), width(width_),
        stride((bins.tile + kLanes - 1) / kLanes * kLanes), plane(bins.tile * stride) {}

  // Pixel q of the image for tile-plane offset p = r * stride + x.
  int64_t pixel(const TileRect& rect, int64_t r, int64_t x) const { return (rect.y0 + r) * width + rect.x0 + x; }

  void load(const TileRect& rect) {
    neg.assign(kKinds * kColor * plane, static_cast<T>(0));
    dev.assign(kKinds * kColor * plane, static_cast<T>(0));
    T lo[kKinds * kColor], hi[kKinds * kColor];
    std::fill(lo, lo + kKinds * kColor, std::numeric_limits<T>::infinity());
    std::fill(hi, hi + kKinds * kColor, -std::numeric_limits<T>::infinity());
    for (int64_t r = 0; r < rect.h; ++r)
      for (int64_t x = 0; x < rect.w; ++x) {
        const T* med = medium + kMediumValues * pixel(rect, r, x);
        for (int j = 0; j < kKinds * kColor; ++j) {
          const T v = -med[3 + j];
          neg[j * plane + r * stride + x] = v;
          lo[j] = std::min(lo[j], v);
          hi[j] = std::max(hi[j], v);
        }
      }
    spread = 0;
    for (int j = 0; j < kKinds * kColor; ++j) {
      mid[j] = rect.h * rect.w > 0 ? lo[j] + (hi[j] - lo[j]) / 2 : static_cast<T>(0);
      spread = std::max(spread, rect.h * rect.w > 0 ? std::max(hi[j] - mid[j], mid[j] - lo[j]) : static_cast<T>(0));
      for (int64_t r = 0; r < rect.h; ++r)
        for (int64_t x = 0; x < rect.w; ++x) dev[j * plane + r * stride + x] = neg[j * plane + r * stride + x] - mid[j];
    }
    current = -1;
  }

  // The Gaussian `id` (features `ft`) is next: its depth, the series' test and the factors at the midranges.
  void at_gaussian(int32_t id) {
    current = id;
    z = ft[static_cast<int64_t>(id) * kFeats + kColor];
    series = spread * std::abs(z) <= WaterSeries<T>::kBound;
    if (series) {
      V m{};
      for (int j = 0; j < kKinds * kColor; ++j) m[j] = mid[j];
      vstore(base, vexp_floored(V(m * z)));
    }
  }

  // exp(-sigma z) at the kLanes pixels from p of kind k (0: sigma_bs, 1: sigma_attn) and channel c.
  V factor(int k, int c, int64_t p) const {
    const int64_t o = (k * kColor + c) * plane + p;
    if (!series) return vexp_floored(V(vload<V>(&neg[o]) * z));
    const V x = vload<V>(&dev[o]) * z;
    constexpr int n = WaterSeries<T>::kTerms;
    static constexpr InverseFactorials<T, n> coef{};
    V sum = splat<V>(coef.v[n - 1]);
    for (int i = n - 2; i >= 0; --i) sum = vfmadd(sum, x, splat<V>(coef.v[i]));
    return sum * base[k * kColor + c];
  }
};

// The forward's hook: per pixel sum_i w_i c_i exp(-sigma_attn z_i) and sum_i w_i exp(-sigma_bs z_i); at the end of
// a tile, object and water into their images.
template <typename T>
struct WaterForward : WaterPlanes<T> {
  using V = typename Simd<T>::V;
  using Base = WaterPlanes<T>;
  static constexpr int kRow = 0;
  T *object = nullptr, *water = nullptr;  // [H, W, 3]
  std::vector<T> obj, scat;             // 3 planes each

  WaterForward() = default;
  WaterForward(const torch::Tensor& medium_, const torch::Tensor& feats, const Bins& bins, int64_t width_,
               torch::Tensor& object_, torch::Tensor& water_)
      : Base(medium_, feats, bins, width_), object(object_.data_ptr<T>()), water(water_.data_ptr<T>()) {}

  void begin(const TileRect& rect) {
    this->load(rect);
    obj.assign(kColor * this->plane, static_cast<T>(0));
    scat.assign(kColor * this->plane, static_cast<T>(0));
  }

  void blend(int64_t p, const V& w, int32_t id) {
    if (id != this->current) this->at_gaussian(id);  // a Gaussian's chunks come one after another
    const T* f = this->ft + static_cast<int64_t>(id) * kFeats;
    for (int c = 0; c < kColor; ++c) {
      T* o = &obj[c * this->plane + p];
      T* s = &scat[c * this->plane + p];
      vstore(o, V(vload<V>(o) + (this->factor(1, c, p) * f[c]) * w));
      vstore(s, V(vload<V>(s) + this->factor(0, c, p) * w));
    }
  }

  void end(const TileRect& rect) {
    for (int64_t r = 0; r < rect.h; ++r)
      for (int64_t x = 0; x < rect.w; ++x) {
        const int64_t q = this->pixel(rect, r, x), p = r * this->stride + x;
        const T* med = this->medium + kMediumValues * q;
        for (int c = 0; c < kColor; ++c) {
          object[kColor * q + c] = obj[c * this->plane + p];
          water[kColor * q + c] = med[c] * (static_cast<T>(1) - scat[c * this->plane + p]);
        }
      }
  }
};

// The backward's hook. Per (pixel, Gaussian i): dL/dw_i gains sum_c g_obj,c c_i,c exp(-sigma_attn z_i) - g_water,c
// c_med,c exp(-sigma_bs z_i); the colour's gradient w_i g_obj exp(-sigma_attn z_i). Per pixel it sums what the
// medium's gradient needs (sum w e_bs, sum w z e_bs, sum w c z e_attn) and writes it at the end of the tile; per
// slot, 2 more values: the sums of |dL/dmeans2d| over pixels (x, y; absolute-gradient densification).
template <typename T>
struct WaterBackward : WaterPlanes<T> {
  using V = typename Simd<T>::V;
  using Base = WaterPlanes<T>;
  static constexpr int kRow = 2;
  const T *g_obj = nullptr, *g_water = nullptr;  // [H, W, 3]
  T* g_medium = nullptr;                         // [H, W, 9]
  std::vector<T> go, gm, scat, scat_z, att_z;    // 3 planes each; gm = g_water c_med
  T col[kColor] = {};
  V gcol[kColor] = {}, abs_x = {}, abs_y = {};

  WaterBackward() = default;
  WaterBackward(const torch::Tensor& medium_, const torch::Tensor& feats, const Bins& bins, int64_t width_,
                const torch::Tensor& g_obj_, const torch::Tensor& g_water_, torch::Tensor& g_medium_)
      : Base(medium_, feats, bins, width_), g_obj(g_obj_.data_ptr<T>()), g_water(g_water_.data_ptr<T>()),
        g_medium(g_medium_.data_ptr<T>()) {}

  void begin(const TileRect& rect) {
    this->load(rect);
    const int64_t n = kColor * this->plane;
    go.assign(n, static_cast<T>(0));
    gm.assign(n, static_cast<T>(0));
    scat.assign(n, static_cast<T>(0));
    scat_z.assign(n, static_cast<T>(0));
    att_z.assign(n, static_cast<T>(0));
    for (int64_t r = 0; r < rect.h; ++r)
      for (int64_t x = 0; x < rect.w; ++x) {
        const int64_t q = this->pixel(rect, r, x), p = r * this->stride + x;
        for (int c = 0; c < kColor; ++c) {
          go[c * this->plane + p] = g_obj[kColor * q + c];
          gm[c * this->plane + p] = g_water[kColor * q + c] * this->medium[kMediumValues * q + c];
        }
      }
  }

  void gaussian(int32_t id) {
    const T* f = this->ft + static_cast<int64_t>(id) * kFeats;
    for (int c = 0; c < kColor; ++c) {
      col[c] = f[c];
      gcol[c] = V{};
    }
    this->at_gaussian(id);
    abs_x = abs_y = V{};
  }

  V dweight(int64_t p, const V& w) {
    V d{};
    const V wz = w * this->z;
    for (int c = 0; c < kColor; ++c) {
      const int64_t o = c * this->plane + p;
      const V ea = this->factor(1, c, p), eb = this->factor(0, c, p);
      const V g_att = vload<V>(&go[o]) * ea;
      d += g_att * col[c] - vload<V>(&gm[o]) * eb;
      gcol[c] += w * g_att;
      vstore(&scat[o], V(vload<V>(&scat[o]) + w * eb));
      vstore(&scat_z[o], V(vload<V>(&scat_z[o]) + wz * eb));
      vstore(&att_z[o], V(vload<V>(&att_z[o]) + (wz * col[c]) * ea));
    }
    return d;
  }

  void geometry(const V& G, const V& dx, T dy, const GaussRec<T>& g) {
    const V gx = G * (g.a * dx + g.b * dy), gy = G * (g.b * dx + g.c * dy);
    abs_x += gx < static_cast<T>(0) ? -gx : gx;
    abs_y += gy < static_cast<T>(0) ? -gy : gy;
  }

  void finish(T* row) {
    for (int c = 0; c < kColor; ++c) row[6 + c] += hsum<T>(gcol[c]);
    row[6 + kFeats] = hsum<T>(abs_x);
    row[6 + kFeats + 1] = hsum<T>(abs_y);
  }

  void end(const TileRect& rect) {
    for (int64_t r = 0; r < rect.h; ++r)
      for (int64_t x = 0; x < rect.w; ++x) {
        const int64_t q = this->pixel(rect, r, x), p = r * this->stride + x;
        T* gmed = g_medium + kMediumValues * q;
        for (int c = 0; c < kColor; ++c) {
          const int64_t o = c * this->plane + p;
          gmed[c] = g_water[kColor * q + c] * (static_cast<T>(1) - scat[o]);
          gmed[3 + c] = gm[o] * scat_z[o];
          gmed[6 + c] = -go[o] * att_z[o];
        }
      }
  }
};

void check_medium(const torch::Tensor& medium, const torch::Tensor& feats, int64_t width, int64_t height) {
  TORCH_CHECK(medium.dim() == 3 && medium.size(0) == height && medium.size(1) == width &&
                  medium.size(2) == kMediumValues,
              "medium must be [H, W, 9] (c_med, sigma_bs, sigma_attn)");
  TORCH_CHECK(feats.dim() == 2 && feats.size(1) == kFeats,
              "the medium compositor's features are [N, 4]: colour, depth");
  TORCH_CHECK(medium.scalar_type() == feats.scalar_type(), "medium and features must share a dtype");
}

}  // namespace

// Bins and composites with the water. feats [N, 4]: colour, then depth (detached: depths take no gradient); medium
// [H, W, 9]. Returns restored [H, W, 3], depth, alpha [H, W], object, water [H, W, 3], weight_sum [N], pixel_count
// [N] int32, then, when `for_backward`, composite_forward's state for the backward.
std::vector<torch::Tensor> medium_composite_forward(torch::Tensor means2d, torch::Tensor conics,
                                                    torch::Tensor opacities, torch::Tensor feats,
                                                    torch::Tensor depths, torch::Tensor radii, torch::Tensor medium,
                                                    int64_t width, int64_t height, int64_t tile_size,
                                                    double alpha_min, double alpha_max, double t_min,
                                                    bool for_backward) {
  for (auto* p : {&means2d, &conics, &opacities, &feats, &depths, &radii, &medium}) check_cpu(*p, "input");
  check_medium(medium, feats, width, height);
  TORCH_CHECK(tile_size >= 1 && tile_size <= kMaxTile, "tile_size must be in [1, ", kMaxTile, "]");
  auto object = torch::empty({height, width, kColor}, means2d.options());
  auto water = torch::empty({height, width, kColor}, means2d.options());
  ForwardImages images;
  std::vector<torch::Tensor> state;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "medium_composite_forward", [&] {
    using T = scalar_t;
    composite_forward_all<T, kFeats>(
        means2d, conics, opacities, feats, depths, radii, width, height, tile_size, alpha_min, alpha_max, t_min, {},
        for_backward, images, state,
        [&](const Bins& bins) { return WaterForward<T>(medium, feats, bins, width, object, water); });
  });
  std::vector<torch::Tensor> out = {images.render, images.depth, images.alpha, object, water, images.weight_sum,
                                    images.pixel_count};
  out.insert(out.end(), state.begin(), state.end());
  return out;
}

// Takes medium_composite_forward's state and the gradients of its five images (each given, zeros where unused);
// returns the gradients of means2d [N, 2], conics [N, 3], opacities [N], colours [N, 3], the medium [H, W, 9], and
// per Gaussian the sums over pixels of |dL/dmeans2d| [N, 2].
std::vector<torch::Tensor> medium_composite_backward(torch::Tensor means2d, torch::Tensor conics,
                                                     torch::Tensor opacities, torch::Tensor feats,
                                                     torch::Tensor medium, int64_t width, int64_t height,
                                                     int64_t tile_size, double alpha_max,
                                                     std::vector<torch::Tensor> state, torch::Tensor g_restored,
                                                     torch::Tensor g_depth, torch::Tensor g_alpha,
                                                     torch::Tensor g_object, torch::Tensor g_water) {
  for (auto* p : {&means2d, &conics, &opacities, &feats, &medium, &g_restored, &g_depth, &g_alpha, &g_object,
                  &g_water})
    check_cpu(*p, "input");
  check_medium(medium, feats, width, height);
  const ForwardState s = state_of(state, width, height, tile_size, "medium_composite_backward");
  const int64_t row = 6 + kFeats + WaterBackward<float>::kRow;  // the slot rows: TileBackward's, then the hook's
  auto grads = torch::empty({means2d.size(0), row}, means2d.options());
  auto g_medium = torch::empty({height, width, kMediumValues}, means2d.options());
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "medium_composite_backward", [&] {
    using T = scalar_t;
    auto slot_grad = torch::empty({s.bins.sorted_gauss.size(0), row}, means2d.options());
    composite_backward_impl<T, kFeats, true>(
        s.bins, s.trace, records_of<T>(s.recs), feats, width, height, alpha_max, s.final_t, g_restored, g_depth,
        g_alpha, slot_grad, WaterBackward<T>(medium, feats, s.bins, width, g_object, g_water, g_medium));
    reduce_slots<T>(s.bins.gauss_starts, slot_grad, grads);
  });
  using torch::indexing::Slice;
  return {grads.index({Slice(), Slice(0, 2)}), grads.index({Slice(), Slice(2, 5)}), grads.index({Slice(), 5}),
          grads.index({Slice(), Slice(6, 6 + kColor)}), g_medium,
          grads.index({Slice(), Slice(6 + kFeats, 6 + kFeats + 2)})};
}
