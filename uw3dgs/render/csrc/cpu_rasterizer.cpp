// Compiled CPU 3DGS rasterizer: projection, tile binning, sorting, compositing and their hand-written
// backward passes. Numerically mirrors uw3dgs/render/reference.py (see that file for the maths).
// Parallel across Gaussians (projection) and tiles (compositing) with OpenMP. Every gradient is
// written to a per-(tile, Gaussian) slot and reduced per Gaussian in a fixed order, so results are
// bitwise identical run to run and independent of the thread count.
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <numeric>
#include <type_traits>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace {

constexpr double kFovClamp = 1.3;
constexpr double kExpFloor = -80.0;
// exp(e) < alpha_min is certain when e < log(alpha_min) - kLogMargin (exp's error is far below 1%), so
// such pixels are skipped before the exp; the exact alpha_min test decides the rest, as in the reference.
constexpr double kLogMargin = 0.01;
// Below this many Gaussians / (tile, Gaussian) pairs a loop runs on one thread: waking a team costs more,
// and far more on a loaded machine, where a descheduled thread stalls the whole region.
constexpr int64_t kParallelMin = 4096;

template <typename T>
inline T clampv(T v, T lo, T hi) { return v < lo ? lo : (v > hi ? hi : v); }

// ---------------------------------------------------------------------------------------------
// Projection
// ---------------------------------------------------------------------------------------------

template <typename T>
struct Cam {
  T W[9];
  T t[3];
  T fx, fy, cx, cy;
  T lim_x, lim_y;
};

template <typename T>
Cam<T> make_cam(const torch::Tensor& viewmat, const torch::Tensor& K, int64_t width, int64_t height) {
  auto vm = viewmat.to(torch::kFloat64).contiguous();
  auto k = K.to(torch::kFloat64).contiguous();
  const double* v = vm.data_ptr<double>();
  const double* kk = k.data_ptr<double>();
  Cam<T> c;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) c.W[i * 3 + j] = static_cast<T>(v[i * 4 + j]);
    c.t[i] = static_cast<T>(v[i * 4 + 3]);
  }
  c.fx = static_cast<T>(kk[0]);
  c.fy = static_cast<T>(kk[4]);
  c.cx = static_cast<T>(kk[2]);
  c.cy = static_cast<T>(kk[5]);
  // Same operation order as the reference (in the input dtype): FOV_CLAMP * 0.5 * width / fx.
  // The reference evaluates `python_float / fx` as reciprocal(fx) * python_float, in the input dtype.
  c.lim_x = (static_cast<T>(1) / c.fx) * static_cast<T>(kFovClamp * 0.5 * static_cast<double>(width));
  c.lim_y = (static_cast<T>(1) / c.fy) * static_cast<T>(kFovClamp * 0.5 * static_cast<double>(height));
  return c;
}

template <typename T>
inline void quat_rotmat(const T* q, T R[9], T qn[4], T& norm) {
  norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  T d = std::max(norm, static_cast<T>(1e-12));
  T w = q[0] / d, x = q[1] / d, y = q[2] / d, z = q[3] / d;
  qn[0] = w; qn[1] = x; qn[2] = y; qn[3] = z;
  R[0] = 1 - 2 * (y * y + z * z); R[1] = 2 * (x * y - w * z); R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z); R[4] = 1 - 2 * (x * x + z * z); R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y); R[7] = 2 * (y * z + w * x); R[8] = 1 - 2 * (x * x + y * y);
}

// Intermediate quantities of one Gaussian's projection (recomputed in the backward).
template <typename T>
struct ProjLocal {
  T p[3];        // camera-space centre with z replaced by z_safe
  T z;           // true depth
  bool in_range;
  T tx, ty;      // clamped (tx, ty)
  bool clamp_x, clamp_y;
  T sx, sy;      // clamp sign (+1 / -1) when clamped
  T J[6];
  T R[9], qn[4], qnorm;
  T M[9];        // R S
  T JW[6];       // J W
  T Tm[6];       // J W M
  T a, b, c, det;
  bool det_ok;
};

template <typename T>
inline void project_one(const Cam<T>& cam, const T* m, const T* q, const T* s, T near, T far, T eps2d,
                        ProjLocal<T>& L) {
  const T* W = cam.W;
  T p0 = W[0] * m[0] + W[1] * m[1] + W[2] * m[2] + cam.t[0];
  T p1 = W[3] * m[0] + W[4] * m[1] + W[5] * m[2] + cam.t[1];
  T p2 = W[6] * m[0] + W[7] * m[1] + W[8] * m[2] + cam.t[2];
  L.z = p2;
  L.in_range = (p2 >= near) && (p2 <= far);
  T zs = L.in_range ? p2 : static_cast<T>(1);
  L.p[0] = p0; L.p[1] = p1; L.p[2] = zs;
  T rx = p0 / zs, ry = p1 / zs;
  L.clamp_x = !(rx >= -cam.lim_x && rx <= cam.lim_x);
  L.clamp_y = !(ry >= -cam.lim_y && ry <= cam.lim_y);
  L.sx = rx > 0 ? 1 : -1;
  L.sy = ry > 0 ? 1 : -1;
  L.tx = clampv(rx, -cam.lim_x, cam.lim_x) * zs;
  L.ty = clampv(ry, -cam.lim_y, cam.lim_y) * zs;
  L.J[0] = cam.fx / zs; L.J[1] = 0; L.J[2] = -cam.fx * L.tx / (zs * zs);
  L.J[3] = 0; L.J[4] = cam.fy / zs; L.J[5] = -cam.fy * L.ty / (zs * zs);
  quat_rotmat(q, L.R, L.qn, L.qnorm);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) L.M[i * 3 + j] = L.R[i * 3 + j] * s[j];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      L.JW[i * 3 + j] = L.J[i * 3 + 0] * W[0 * 3 + j] + L.J[i * 3 + 1] * W[1 * 3 + j] + L.J[i * 3 + 2] * W[2 * 3 + j];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      L.Tm[i * 3 + j] = L.JW[i * 3 + 0] * L.M[0 * 3 + j] + L.JW[i * 3 + 1] * L.M[1 * 3 + j] + L.JW[i * 3 + 2] * L.M[2 * 3 + j];
  const T* A = L.Tm;
  L.a = A[0] * A[0] + A[1] * A[1] + A[2] * A[2] + eps2d;
  L.b = A[0] * A[3] + A[1] * A[4] + A[2] * A[5];
  L.c = A[3] * A[3] + A[4] * A[4] + A[5] * A[5] + eps2d;
  L.det = L.a * L.c - L.b * L.b;
  L.det_ok = L.det > 0;
}

template <typename T>
void project_forward_impl(const torch::Tensor& means, const torch::Tensor& quats, const torch::Tensor& scales,
                          const torch::Tensor& opacities, const Cam<T>& cam, int64_t width, int64_t height,
                          double near_d, double far_d, double eps2d_d, double alpha_min_d, torch::Tensor& means2d,
                          torch::Tensor& conics, torch::Tensor& depths, torch::Tensor& radii) {
  const int64_t n = means.size(0);
  const T* m = means.data_ptr<T>();
  const T* q = quats.data_ptr<T>();
  const T* s = scales.data_ptr<T>();
  const T* op = opacities.data_ptr<T>();
  T* m2 = means2d.data_ptr<T>();
  T* cn = conics.data_ptr<T>();
  T* dp = depths.data_ptr<T>();
  int32_t* rad = radii.data_ptr<int32_t>();
  const T near = static_cast<T>(near_d), far = static_cast<T>(far_d), eps2d = static_cast<T>(eps2d_d);
  const T inv_alpha_min = static_cast<T>(1) / static_cast<T>(alpha_min_d);
#pragma omp parallel for schedule(static) if (n >= kParallelMin)
  for (int64_t i = 0; i < n; ++i) {
    ProjLocal<T> L;
    project_one(cam, m + 3 * i, q + 4 * i, s + 3 * i, near, far, eps2d, L);
    dp[i] = L.z;
    T u = L.p[0] / L.p[2] * cam.fx + cam.cx;
    T v = L.p[1] / L.p[2] * cam.fy + cam.cy;
    m2[2 * i] = u;
    m2[2 * i + 1] = v;
    T dsafe = L.det_ok ? L.det : static_cast<T>(1);
    cn[3 * i] = L.c / dsafe;
    cn[3 * i + 1] = -L.b / dsafe;
    cn[3 * i + 2] = L.a / dsafe;
    // Radius: the reference's _radii, operation for operation.
    T mid = static_cast<T>(0.5) * (L.a + L.c);
    T lambda_max = mid + std::sqrt(std::max(mid * mid - L.det, static_cast<T>(0)));
    // torch divides by a Python scalar as a multiplication by its reciprocal.
    T ratio = std::max(op[i] * inv_alpha_min, static_cast<T>(1));
    T extent = std::sqrt(static_cast<T>(2) * std::log(ratio));
    T radius = std::ceil(extent * std::sqrt(std::max(lambda_max, static_cast<T>(0))));
    if (std::isnan(radius)) radius = 0;
    radius = std::min(radius, static_cast<T>(1073741824.0));
    bool on_screen = (u + radius >= static_cast<T>(0.5)) && (u - radius <= static_cast<T>(width) - static_cast<T>(0.5)) &&
                     (v + radius >= static_cast<T>(0.5)) && (v - radius <= static_cast<T>(height) - static_cast<T>(0.5));
    int32_t r = on_screen ? static_cast<int32_t>(radius) : 0;
    bool valid = L.in_range && L.det_ok && r > 0;
    rad[i] = valid ? r : 0;
  }
}

template <typename T>
void project_backward_impl(const torch::Tensor& means, const torch::Tensor& quats, const torch::Tensor& scales,
                           const Cam<T>& cam, double near_d, double far_d, double eps2d_d,
                           const torch::Tensor& g_means2d, const torch::Tensor& g_conics,
                           const torch::Tensor& g_depths, torch::Tensor& g_means, torch::Tensor& g_quats,
                           torch::Tensor& g_scales) {
  const int64_t n = means.size(0);
  const T* m = means.data_ptr<T>();
  const T* q = quats.data_ptr<T>();
  const T* s = scales.data_ptr<T>();
  const T* gm2 = g_means2d.data_ptr<T>();
  const T* gcn = g_conics.data_ptr<T>();
  const T* gdp = g_depths.data_ptr<T>();
  T* gm = g_means.data_ptr<T>();
  T* gq = g_quats.data_ptr<T>();
  T* gs = g_scales.data_ptr<T>();
  const T near = static_cast<T>(near_d), far = static_cast<T>(far_d), eps2d = static_cast<T>(eps2d_d);
  const T* W = cam.W;
#pragma omp parallel for schedule(static) if (n >= kParallelMin)
  for (int64_t i = 0; i < n; ++i) {
    ProjLocal<T> L;
    project_one(cam, m + 3 * i, q + 4 * i, s + 3 * i, near, far, eps2d, L);
    const T x = L.p[0], y = L.p[1], z = L.p[2];
    T gp[3] = {0, 0, 0};
    // means2d = (x / z * fx + cx, y / z * fy + cy)
    const T gu = gm2[2 * i], gv = gm2[2 * i + 1];
    gp[0] += gu * cam.fx / z;
    gp[1] += gv * cam.fy / z;
    T gz = -(gu * cam.fx * x + gv * cam.fy * y) / (z * z);
    // conics = (c, -b, a) / D with D = det (or 1 when det <= 0)
    const T gA = gcn[3 * i], gB = gcn[3 * i + 1], gC = gcn[3 * i + 2];
    T ga, gb, gc;
    if (L.det_ok) {
      const T a = L.a, b = L.b, c = L.c, D = L.det, D2 = D * D;
      // d(c/D), d(-b/D), d(a/D) w.r.t. a, b, c
      ga = gA * (-c * c / D2) + gB * (b * c / D2) + gC * (-b * b / D2);
      gb = gA * (2 * b * c / D2) + gB * (-(a * c + b * b) / D2) + gC * (2 * a * b / D2);
      gc = gA * (-b * b / D2) + gB * (a * b / D2) + gC * (-a * a / D2);
    } else {
      ga = gC; gb = -gB; gc = gA;
    }
    // cov = Tm Tm^T: a = T0.T0 + eps, b = T0.T1, c = T1.T1 + eps
    T gT[6];
    for (int j = 0; j < 3; ++j) {
      gT[j] = 2 * ga * L.Tm[j] + gb * L.Tm[3 + j];
      gT[3 + j] = gb * L.Tm[j] + 2 * gc * L.Tm[3 + j];
    }
    // Tm = JW M: gM = JW^T gT, gJW = gT M^T
    T gM[9], gJW[6], gJ[6];
    for (int r = 0; r < 3; ++r)
      for (int cidx = 0; cidx < 3; ++cidx) gM[r * 3 + cidx] = L.JW[r] * gT[cidx] + L.JW[3 + r] * gT[3 + cidx];
    for (int r = 0; r < 2; ++r)
      for (int k = 0; k < 3; ++k)
        gJW[r * 3 + k] = gT[r * 3 + 0] * L.M[k * 3 + 0] + gT[r * 3 + 1] * L.M[k * 3 + 1] + gT[r * 3 + 2] * L.M[k * 3 + 2];
    // JW = J W: gJ = gJW W^T
    for (int r = 0; r < 2; ++r)
      for (int k = 0; k < 3; ++k)
        gJ[r * 3 + k] = gJW[r * 3 + 0] * W[k * 3 + 0] + gJW[r * 3 + 1] * W[k * 3 + 1] + gJW[r * 3 + 2] * W[k * 3 + 2];
    // M = R diag(s)
    T gR[9];
    for (int r = 0; r < 3; ++r)
      for (int j = 0; j < 3; ++j) gR[r * 3 + j] = gM[r * 3 + j] * s[3 * i + j];
    for (int j = 0; j < 3; ++j)
      gs[3 * i + j] = gM[0 * 3 + j] * L.R[0 * 3 + j] + gM[1 * 3 + j] * L.R[1 * 3 + j] + gM[2 * 3 + j] * L.R[2 * 3 + j];
    // R(q_hat)
    {
      const T w = L.qn[0], qx = L.qn[1], qy = L.qn[2], qz = L.qn[3];
      const T* G = gR;
      T gw = 2 * (-qz * G[1] + qy * G[2] + qz * G[3] - qx * G[5] - qy * G[6] + qx * G[7]);
      T gx = 2 * (qy * G[1] + qz * G[2] + qy * G[3] - 2 * qx * G[4] - w * G[5] + qz * G[6] + w * G[7] - 2 * qx * G[8]);
      T gy = 2 * (-2 * qy * G[0] + qx * G[1] + w * G[2] + qx * G[3] + qz * G[5] - w * G[6] + qz * G[7] - 2 * qy * G[8]);
      T gzq = 2 * (-2 * qz * G[0] - w * G[1] + qx * G[2] + w * G[3] - 2 * qz * G[4] + qy * G[5] + qx * G[6] + qy * G[7]);
      T gh[4] = {gw, gx, gy, gzq};
      T d = std::max(L.qnorm, static_cast<T>(1e-12));
      if (L.qnorm > static_cast<T>(1e-12)) {
        T dot = L.qn[0] * gh[0] + L.qn[1] * gh[1] + L.qn[2] * gh[2] + L.qn[3] * gh[3];
        for (int k = 0; k < 4; ++k) gq[4 * i + k] = (gh[k] - L.qn[k] * dot) / d;
      } else {
        for (int k = 0; k < 4; ++k) gq[4 * i + k] = gh[k] / d;
      }
    }
    // J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]], tx = clamp(x/z) z
    {
      const T z2 = z * z, z3 = z2 * z;
      T gtx = gJ[2] * (-cam.fx / z2);
      T gty = gJ[5] * (-cam.fy / z2);
      gz += gJ[0] * (-cam.fx / z2) + gJ[2] * (2 * cam.fx * L.tx / z3);
      gz += gJ[4] * (-cam.fy / z2) + gJ[5] * (2 * cam.fy * L.ty / z3);
      if (!L.clamp_x) {
        gp[0] += gtx;  // tx = (x / z) z: d/dx = 1, d/dz = 0
      } else {
        gz += gtx * L.sx * cam.lim_x;
      }
      if (!L.clamp_y) {
        gp[1] += gty;
      } else {
        gz += gty * L.sy * cam.lim_y;
      }
    }
    if (L.in_range) gp[2] += gz;  // z_safe is the constant 1 for culled Gaussians
    gp[2] += gdp[i];
    for (int j = 0; j < 3; ++j) gm[3 * i + j] = W[0 * 3 + j] * gp[0] + W[1 * 3 + j] * gp[1] + W[2 * 3 + j] * gp[2];
  }
}

// ---------------------------------------------------------------------------------------------
// Binning
// ---------------------------------------------------------------------------------------------

struct Bins {
  int64_t tiles_x, tiles_y, tile;
  torch::Tensor tile_starts;   // [tiles + 1] int64
  torch::Tensor sorted_gauss;  // [pairs] int32, Gaussian per sorted pair (tile, then depth)
  torch::Tensor sorted_slot;   // [pairs] int64, unsorted pair slot of each sorted pair
  torch::Tensor gauss_starts;  // [N + 1] int64, each Gaussian's contiguous range of unsorted slots
};

template <typename T>
inline void pixel_span(T centre, T radius, int64_t size, int64_t& first, int64_t& last) {
  T f = std::ceil(centre - radius - static_cast<T>(0.5));
  T l = std::floor(centre + radius - static_cast<T>(0.5));
  f = clampv(f, static_cast<T>(0), static_cast<T>(size - 1));
  l = clampv(l, static_cast<T>(0), static_cast<T>(size - 1));
  first = static_cast<int64_t>(f);
  last = static_cast<int64_t>(l);
}

template <typename T>
Bins bin_impl(const torch::Tensor& means2d, const torch::Tensor& depths, const torch::Tensor& radii, int64_t width,
              int64_t height, int64_t tile) {
  const int64_t n = means2d.size(0);
  const T* m2 = means2d.data_ptr<T>();
  const T* dp = depths.data_ptr<T>();
  const int32_t* rad = radii.data_ptr<int32_t>();
  Bins b;
  b.tile = tile;
  b.tiles_x = (width + tile - 1) / tile;
  b.tiles_y = (height + tile - 1) / tile;
  const int64_t n_tiles = b.tiles_x * b.tiles_y;

  // Visible Gaussians front to back, ties by index (the reference's stable argsort).
  std::vector<int32_t> ids;
  ids.reserve(n);
  for (int64_t i = 0; i < n; ++i)
    if (rad[i] > 0) ids.push_back(static_cast<int32_t>(i));
  std::sort(ids.begin(), ids.end(), [dp](int32_t x, int32_t y) { return dp[x] < dp[y] || (dp[x] == dp[y] && x < y); });

  // Tile rectangle of each Gaussian; slots are per Gaussian in index order (for the gradient reduction).
  std::vector<int64_t> rect(4 * n, 0);
  b.gauss_starts = torch::zeros({n + 1}, torch::kInt64);
  int64_t* gstart = b.gauss_starts.data_ptr<int64_t>();
#pragma omp parallel for schedule(static) if (n >= kParallelMin)
  for (int64_t i = 0; i < n; ++i) {
    int64_t cnt = 0;
    if (rad[i] > 0) {
      T r = static_cast<T>(rad[i]);
      int64_t x0, x1, y0, y1;
      pixel_span(m2[2 * i], r, width, x0, x1);
      pixel_span(m2[2 * i + 1], r, height, y0, y1);
      x0 /= tile; x1 /= tile; y0 /= tile; y1 /= tile;
      rect[4 * i] = x0; rect[4 * i + 1] = x1; rect[4 * i + 2] = y0; rect[4 * i + 3] = y1;
      cnt = std::max<int64_t>(0, x1 - x0 + 1) * std::max<int64_t>(0, y1 - y0 + 1);
    }
    gstart[i + 1] = cnt;
  }
  for (int64_t i = 0; i < n; ++i) gstart[i + 1] += gstart[i];
  const int64_t pairs = gstart[n];

  b.tile_starts = torch::zeros({n_tiles + 1}, torch::kInt64);
  int64_t* tstart = b.tile_starts.data_ptr<int64_t>();
  for (int32_t g : ids)
    for (int64_t ty = rect[4 * g + 2]; ty <= rect[4 * g + 3]; ++ty)
      for (int64_t tx = rect[4 * g]; tx <= rect[4 * g + 1]; ++tx) tstart[ty * b.tiles_x + tx + 1]++;
  for (int64_t t = 0; t < n_tiles; ++t) tstart[t + 1] += tstart[t];

  // Counting sort by tile over the depth-ordered Gaussians: each tile's list ends up front to back.
  b.sorted_gauss = torch::empty({pairs}, torch::kInt32);
  b.sorted_slot = torch::empty({pairs}, torch::kInt64);
  int32_t* sg = b.sorted_gauss.data_ptr<int32_t>();
  int64_t* ss = b.sorted_slot.data_ptr<int64_t>();
  std::vector<int64_t> fill(tstart, tstart + n_tiles);
  for (int32_t g : ids) {
    int64_t slot = gstart[g];
    for (int64_t ty = rect[4 * g + 2]; ty <= rect[4 * g + 3]; ++ty)
      for (int64_t tx = rect[4 * g]; tx <= rect[4 * g + 1]; ++tx) {
        int64_t pos = fill[ty * b.tiles_x + tx]++;
        sg[pos] = g;
        ss[pos] = slot++;
      }
  }
  return b;
}

// ---------------------------------------------------------------------------------------------
// Compositing
// ---------------------------------------------------------------------------------------------

// One tile's Gaussians gathered contiguously.
template <typename T>
struct TileData {
  std::vector<T> mx, my, a, b, c, op, logop, feat;
  void load(const int32_t* ids, int64_t k, const T* m2, const T* cn, const T* opac, const T* feats, int64_t F) {
    mx.resize(k); my.resize(k); a.resize(k); b.resize(k); c.resize(k); op.resize(k); logop.resize(k);
    feat.resize(k * F);
    for (int64_t j = 0; j < k; ++j) {
      const int64_t g = ids[j];
      mx[j] = m2[2 * g]; my[j] = m2[2 * g + 1];
      a[j] = cn[3 * g]; b[j] = cn[3 * g + 1]; c[j] = cn[3 * g + 2];
      op[j] = opac[g];
      logop[j] = std::log(opac[g]);
      for (int64_t f = 0; f < F; ++f) feat[j * F + f] = feats[g * F + f];
    }
  }
};

// Pixels of a tile a Gaussian can reach alpha_min in, row by row: exact real-arithmetic bounds of
// {log(opacity) + power >= log(alpha_min) - kLogMargin}, widened by a pixel. Pixels outside are never
// evaluated (their alpha is certainly below alpha_min); pixels inside get the reference's exact tests.
struct Footprint {
  int64_t y_lo, y_hi;  // rows [y_lo, y_hi], empty when y_lo > y_hi
  bool full;           // degenerate conic: evaluate the whole tile
  double mx, my, a, b, lgap, inv_a = 0;
  void init(double mx_, double my_, double a_, double b_, double c_, double logop, double log_cut, int64_t y0,
            int64_t y1) {
    mx = mx_; my = my_; a = a_; b = b_;
    lgap = logop - log_cut;
    full = false;
    y_lo = y0; y_hi = y1 - 1;
    if (!(lgap >= 0)) { y_lo = 1; y_hi = 0; return; }  // never reaches alpha_min (also NaN)
    const double detc = a * c_ - b * b;
    if (!(a > 0) || !(detc > 0) || !std::isfinite(detc)) { full = true; return; }
    const double ext = std::sqrt(2.0 * lgap * a / detc);
    y_lo = std::max<int64_t>(y0, static_cast<int64_t>(std::ceil(my - ext - 0.5)) - 1);
    y_hi = std::min<int64_t>(y1 - 1, static_cast<int64_t>(std::floor(my + ext - 0.5)) + 1);
    cc = c_;
    inv_a = 1.0 / a;
  }
  double cc = 0;
  // Columns [x_lo, x_hi] of row y; false when empty.
  bool row(int64_t y, int64_t x0, int64_t x1, int64_t& x_lo, int64_t& x_hi) const {
    if (full) { x_lo = x0; x_hi = x1 - 1; return true; }
    const double dy = static_cast<double>(y) + 0.5 - my;
    const double disc = (b * dy) * (b * dy) + 2.0 * a * (lgap - 0.5 * cc * dy * dy);
    if (!(disc >= 0)) return false;
    const double sq = std::sqrt(disc);
    const double centre = mx - b * dy * inv_a - 0.5, half = sq * inv_a;
    x_lo = std::max<int64_t>(x0, static_cast<int64_t>(std::ceil(centre - half)) - 1);
    x_hi = std::min<int64_t>(x1 - 1, static_cast<int64_t>(std::floor(centre + half)) + 1);
    return x_lo <= x_hi;
  }
};

template <typename T, int NF>
void composite_forward_impl(const Bins& bins, const torch::Tensor& means2d, const torch::Tensor& conics,
                            const torch::Tensor& opacities, const torch::Tensor& feats, int64_t width, int64_t height,
                            double alpha_min_d, double alpha_max_d, double t_min_d, torch::Tensor& render,
                            torch::Tensor& depth, torch::Tensor& alpha_img,
                            torch::Tensor& final_t, torch::Tensor& n_contrib, torch::Tensor& slot_weight,
                            torch::Tensor& slot_count) {
  const int64_t F = NF > 0 ? NF : feats.size(1);  // compile-time channel count for the common cases
  const int64_t C = F + 1;  // feats then alpha
  const T* m2 = means2d.data_ptr<T>();
  const T* cn = conics.data_ptr<T>();
  const T* opac = opacities.data_ptr<T>();
  const T* ft = feats.data_ptr<T>();
  T* rend = render.data_ptr<T>();  // [H, W, F - 1]: the features
  T* dimg = depth.data_ptr<T>();   // [H, W]: the last composited channel
  T* aimg = alpha_img.data_ptr<T>();
  T* ftT = final_t.data_ptr<T>();
  int32_t* nc = n_contrib.data_ptr<int32_t>();
  T* sw = slot_weight.data_ptr<T>();
  int32_t* sc = slot_count.data_ptr<int32_t>();
  const int64_t* tstart = bins.tile_starts.data_ptr<int64_t>();
  const int32_t* sg = bins.sorted_gauss.data_ptr<int32_t>();
  const int64_t* ss = bins.sorted_slot.data_ptr<int64_t>();
  const T alpha_min = static_cast<T>(alpha_min_d), alpha_max = static_cast<T>(alpha_max_d);
  const T t_min = static_cast<T>(t_min_d), floor_ = static_cast<T>(kExpFloor);
  const double log_cut_d = std::log(alpha_min_d) - kLogMargin;
  const T log_cut = static_cast<T>(log_cut_d);
  const int64_t n_tiles = bins.tiles_x * bins.tiles_y;
  const int64_t ts = bins.tile;
#pragma omp parallel if (bins.sorted_gauss.size(0) >= kParallelMin)
  {
    TileData<T> d;
    std::vector<T> Tr(ts * ts), acc(ts * ts * C);
    std::vector<int32_t> last(ts * ts);
    std::vector<uint8_t> done(ts * ts);
    std::vector<int32_t> row_alive(ts);  // pixels of each row not terminated yet
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      const int64_t k = tstart[t + 1] - tstart[t];
      const int64_t tx = t % bins.tiles_x, ty = t / bins.tiles_x;
      const int64_t x0 = tx * ts, y0 = ty * ts;
      const int64_t x1 = std::min(x0 + ts, width), y1 = std::min(y0 + ts, height);
      const int64_t n_pix = (x1 - x0) * (y1 - y0);
      std::fill(Tr.begin(), Tr.end(), static_cast<T>(1));
      std::fill(acc.begin(), acc.end(), static_cast<T>(0));
      std::fill(last.begin(), last.end(), 0);
      std::fill(done.begin(), done.end(), 0);
      if (k > 0) d.load(sg + tstart[t], k, m2, cn, opac, ft, F);
      for (int64_t j = 0; j < k; ++j) {  // pairs behind a fully terminated tile keep these zeros
        sw[ss[tstart[t] + j]] = 0;
        sc[ss[tstart[t] + j]] = 0;
      }
      int64_t n_done = 0;
      std::fill(row_alive.begin(), row_alive.end(), static_cast<int32_t>(x1 - x0));
      for (int64_t j = 0; j < k && n_done < n_pix; ++j) {
        Footprint fp;
        fp.init(d.mx[j], d.my[j], d.a[j], d.b[j], d.c[j], d.logop[j], log_cut_d, y0, y1);
        T wsum = 0;
        int32_t cnt = 0;
        const T* f = &d.feat[j * F];
        const T mxj = d.mx[j], myj = d.my[j], bj = d.b[j], cj = d.c[j], lop = d.logop[j];
        const T ha = static_cast<T>(-0.5) * d.a[j];
        for (int64_t y = fp.y_lo; y <= fp.y_hi; ++y) {
          int64_t xa, xb;
          if (row_alive[y - y0] == 0 || !fp.row(y, x0, x1, xa, xb)) continue;
          // log(opacity) + power exactly as the reference: (-c dy^2/2 + log op) + (-a dx^2/2) + (-b dy) dx.
          const T dy = (static_cast<T>(y) + static_cast<T>(0.5)) - myj;
          const T rowc = static_cast<T>(-0.5) * cj * dy * dy + lop;
          const T bdy = -bj * dy;
          const int64_t prow = (y - y0) * ts - x0;
          for (int64_t x = xa; x <= xb; ++x) {
            const int64_t p = prow + x;
            if (done[p]) continue;
            const T dx = (static_cast<T>(x) + static_cast<T>(0.5)) - mxj;
            const T e = (rowc + ha * dx * dx) + bdy * dx;
            if (e < log_cut) continue;  // alpha certainly below alpha_min: skip the exp
            if (!(e <= lop)) continue;  // power > 0
            const T alpha = std::min(std::exp(std::max(e, floor_)), alpha_max);
            if (!(alpha >= alpha_min)) continue;
            const T t_next = Tr[p] * (1 - alpha);
            if (!(t_next >= t_min)) {  // early termination: this one and all behind are dropped
              done[p] = 1;
              ++n_done;
              --row_alive[y - y0];
              continue;
            }
            const T w = alpha * Tr[p];
            T* a = &acc[p * C];
            for (int64_t ch = 0; ch < F; ++ch) a[ch] += w * f[ch];
            a[F] += w;
            wsum += w;
            cnt += 1;
            Tr[p] = t_next;
            last[p] = static_cast<int32_t>(j + 1);
          }
        }
        const int64_t slot = ss[tstart[t] + j];
        sw[slot] = wsum;
        sc[slot] = cnt;
      }
      for (int64_t y = y0; y < y1; ++y)
        for (int64_t x = x0; x < x1; ++x) {
          const int64_t p = (y - y0) * ts + (x - x0);
          T* o = rend + (y * width + x) * (F - 1);
          for (int64_t ch = 0; ch < F - 1; ++ch) o[ch] = acc[p * C + ch];
          dimg[y * width + x] = acc[p * C + F - 1];
          aimg[y * width + x] = acc[p * C + F];
          ftT[y * width + x] = Tr[p];
          nc[y * width + x] = last[p];
        }
    }
  }
}

template <typename T, int NF>
void composite_backward_impl(const Bins& bins, const torch::Tensor& means2d, const torch::Tensor& conics,
                             const torch::Tensor& opacities, const torch::Tensor& feats, int64_t width,
                             int64_t height, double alpha_min_d, double alpha_max_d, const torch::Tensor& final_t,
                             const torch::Tensor& n_contrib, const torch::Tensor& grad_render,
                             const torch::Tensor& grad_depth, const torch::Tensor& grad_alpha, torch::Tensor& slot_grad) {
  const int64_t F = NF > 0 ? NF : feats.size(1);
  const int64_t C = F + 1;
  const int64_t R = 6 + F;  // mean x, mean y, conic a, b, c, opacity, feats
  const T* m2 = means2d.data_ptr<T>();
  const T* cn = conics.data_ptr<T>();
  const T* opac = opacities.data_ptr<T>();
  const T* ft = feats.data_ptr<T>();
  const T* ftT = final_t.data_ptr<T>();
  const int32_t* nc = n_contrib.data_ptr<int32_t>();
  // Output gradients; an empty tensor stands for zeros (that output was not used).
  const T* grend = grad_render.numel() ? grad_render.data_ptr<T>() : nullptr;
  const T* gdep = grad_depth.numel() ? grad_depth.data_ptr<T>() : nullptr;
  const T* galp = grad_alpha.numel() ? grad_alpha.data_ptr<T>() : nullptr;
  T* sgrad = slot_grad.data_ptr<T>();
  const int64_t* tstart = bins.tile_starts.data_ptr<int64_t>();
  const int32_t* sg = bins.sorted_gauss.data_ptr<int32_t>();
  const int64_t* ss = bins.sorted_slot.data_ptr<int64_t>();
  const T alpha_min = static_cast<T>(alpha_min_d), alpha_max = static_cast<T>(alpha_max_d);
  const T floor_ = static_cast<T>(kExpFloor);
  const double log_cut_d = std::log(alpha_min_d) - kLogMargin;
  const T log_cut = static_cast<T>(log_cut_d);
  const int64_t n_tiles = bins.tiles_x * bins.tiles_y;
  const int64_t ts = bins.tile;
  const T tiny = std::numeric_limits<T>::min();
#pragma omp parallel if (bins.sorted_gauss.size(0) >= kParallelMin)
  {
    TileData<T> d;
    std::vector<T> Tr(ts * ts), S(ts * ts), go(ts * ts * C), mo(6 + F);
    std::vector<int32_t> last(ts * ts), row_last(ts);
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      const int64_t k = tstart[t + 1] - tstart[t];
      if (k == 0) continue;
      const int64_t tx = t % bins.tiles_x, ty = t / bins.tiles_x;
      const int64_t x0 = tx * ts, y0 = ty * ts;
      const int64_t x1 = std::min(x0 + ts, width), y1 = std::min(y0 + ts, height);
      d.load(sg + tstart[t], k, m2, cn, opac, ft, F);
      int32_t max_last = 0;
      std::fill(row_last.begin(), row_last.end(), 0);
      for (int64_t y = y0; y < y1; ++y)
        for (int64_t x = x0; x < x1; ++x) {
          const int64_t p = (y - y0) * ts + (x - x0);
          Tr[p] = ftT[y * width + x];
          S[p] = 0;
          last[p] = nc[y * width + x];
          max_last = std::max(max_last, last[p]);
          row_last[y - y0] = std::max(row_last[y - y0], last[p]);
          const int64_t q = y * width + x;
          for (int64_t ch = 0; ch < F - 1; ++ch) go[p * C + ch] = grend ? grend[q * (F - 1) + ch] : static_cast<T>(0);
          go[p * C + F - 1] = gdep ? gdep[q] : static_cast<T>(0);
          go[p * C + F] = galp ? galp[q] : static_cast<T>(0);
        }
      for (int64_t j = k - 1; j >= 0; --j) {
        std::fill(mo.begin(), mo.end(), static_cast<T>(0));
        if (j < max_last) {
          Footprint fp;
          fp.init(d.mx[j], d.my[j], d.a[j], d.b[j], d.c[j], d.logop[j], log_cut_d, y0, y1);
          const T* f = &d.feat[j * F];
          const T mxj = d.mx[j], myj = d.my[j], bj = d.b[j], cj = d.c[j], lop = d.logop[j];
          const T ha = static_cast<T>(-0.5) * d.a[j];
          T m0 = 0, m1 = 0, m2s = 0, m3 = 0, m4 = 0, m5 = 0;
          for (int64_t y = fp.y_lo; y <= fp.y_hi; ++y) {
            int64_t xa, xb;
            if (j >= row_last[y - y0] || !fp.row(y, x0, x1, xa, xb)) continue;
            const T dy = (static_cast<T>(y) + static_cast<T>(0.5)) - myj;
            const T rowc = static_cast<T>(-0.5) * cj * dy * dy + lop;
            const T bdy = -bj * dy;
            const int64_t prow = (y - y0) * ts - x0;
            for (int64_t x = xa; x <= xb; ++x) {
              const int64_t p = prow + x;
              if (j >= last[p]) continue;
              const T dx = (static_cast<T>(x) + static_cast<T>(0.5)) - mxj;
              const T e = (rowc + ha * dx * dx) + bdy * dx;
              if (e < log_cut) continue;
              if (!(e <= lop)) continue;
              const T alpha = std::min(std::exp(std::max(e, floor_)), alpha_max);
              if (!(alpha >= alpha_min)) continue;
              const T transmit = 1 - alpha;
              const T Tb = Tr[p] / transmit;  // transmittance in front of Gaussian j
              Tr[p] = Tb;
              const T w = alpha * Tb;
              const T* g_o = &go[p * C];
              T g = g_o[F];
              for (int64_t ch = 0; ch < F; ++ch) g += g_o[ch] * f[ch];
              const T wg = w * g;
              T G = wg - S[p] * alpha / transmit;
              S[p] += wg;
              if (!(alpha < alpha_max)) G = 0;
              m0 += G;
              m1 += G * dx;
              m2s += G * dy;
              m3 += G * dx * dx;
              m4 += G * dx * dy;
              m5 += G * dy * dy;
              for (int64_t ch = 0; ch < F; ++ch) mo[6 + ch] += w * g_o[ch];
            }
          }
          mo[0] = m0; mo[1] = m1; mo[2] = m2s; mo[3] = m3; mo[4] = m4; mo[5] = m5;
        }
        T* out = sgrad + ss[tstart[t] + j] * R;
        out[0] = d.a[j] * mo[1] + d.b[j] * mo[2];
        out[1] = d.b[j] * mo[1] + d.c[j] * mo[2];
        out[2] = static_cast<T>(-0.5) * mo[3];
        out[3] = -mo[4];
        out[4] = static_cast<T>(-0.5) * mo[5];
        out[5] = mo[0] / std::max(d.op[j], tiny);
        for (int64_t ch = 0; ch < F; ++ch) out[6 + ch] = mo[6 + ch];
      }
    }
  }
}

// Sum each Gaussian's slot rows in slot order (deterministic).
template <typename T>
void reduce_slots(const torch::Tensor& gauss_starts, const torch::Tensor& slots, torch::Tensor& out) {
  const int64_t n = out.size(0);
  const int64_t R = out.dim() == 1 ? 1 : out.size(1);
  const int64_t* gs = gauss_starts.data_ptr<int64_t>();
  const T* s = slots.data_ptr<T>();
  T* o = out.data_ptr<T>();
#pragma omp parallel for schedule(static) if (n >= kParallelMin)
  for (int64_t i = 0; i < n; ++i) {
    for (int64_t r = 0; r < R; ++r) o[i * R + r] = 0;
    for (int64_t p = gs[i]; p < gs[i + 1]; ++p)
      for (int64_t r = 0; r < R; ++r) o[i * R + r] += s[p * R + r];
  }
}

void check_cpu(const torch::Tensor& t, const char* name) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
}

}  // namespace

// Returns means2d [N, 2], conics [N, 3], depths [N], radii [N] int32.
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                           torch::Tensor opacities, torch::Tensor viewmat, torch::Tensor K,
                                           int64_t width, int64_t height, double near, double far, double eps2d,
                                           double alpha_min) {
  for (auto* p : {&means, &quats, &scales, &opacities}) check_cpu(*p, "input");
  const int64_t n = means.size(0);
  auto opts = means.options();
  auto means2d = torch::empty({n, 2}, opts);
  auto conics = torch::empty({n, 3}, opts);
  auto depths = torch::empty({n}, opts);
  auto radii = torch::empty({n}, opts.dtype(torch::kInt32));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_forward", [&] {
    auto cam = make_cam<scalar_t>(viewmat, K, width, height);
    project_forward_impl<scalar_t>(means, quats, scales, opacities, cam, width, height, near, far, eps2d, alpha_min,
                                   means2d, conics, depths, radii);
  });
  return {means2d, conics, depths, radii};
}

std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                            torch::Tensor viewmat, torch::Tensor K, int64_t width, int64_t height,
                                            double near, double far, double eps2d, torch::Tensor g_means2d,
                                            torch::Tensor g_conics, torch::Tensor g_depths) {
  for (auto* p : {&means, &quats, &scales, &g_means2d, &g_conics, &g_depths}) check_cpu(*p, "input");
  auto g_means = torch::empty_like(means);
  auto g_quats = torch::empty_like(quats);
  auto g_scales = torch::empty_like(scales);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_backward", [&] {
    auto cam = make_cam<scalar_t>(viewmat, K, width, height);
    project_backward_impl<scalar_t>(means, quats, scales, cam, near, far, eps2d, g_means2d, g_conics, g_depths,
                                    g_means, g_quats, g_scales);
  });
  return {g_means, g_quats, g_scales};
}

// Bins and composites. Returns render [H, W, F-1], depth [H, W], alpha [H, W], weight_sum [N],
// pixel_count [N] int32, and the state
// the backward needs: final_t [H, W], n_contrib [H, W] int32, tile_starts, sorted_gauss, sorted_slot,
// gauss_starts.
std::vector<torch::Tensor> composite_forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                             torch::Tensor feats, torch::Tensor depths, torch::Tensor radii,
                                             int64_t width, int64_t height, int64_t tile_size, double alpha_min,
                                             double alpha_max, double t_min) {
  for (auto* p : {&means2d, &conics, &opacities, &feats, &depths, &radii}) check_cpu(*p, "input");
  const int64_t n = means2d.size(0);
  const int64_t F = feats.size(1);
  TORCH_CHECK(F >= 1 && F <= 64, "the CPU rasterizer composites 1 to 64 channels (depth included), got ", F);
  auto opts = means2d.options();
  auto render = torch::empty({height, width, F - 1}, opts);
  auto depth = torch::empty({height, width}, opts);
  auto alpha = torch::empty({height, width}, opts);
  auto final_t = torch::empty({height, width}, opts);
  auto n_contrib = torch::empty({height, width}, opts.dtype(torch::kInt32));
  auto weight_sum = torch::empty({n}, opts);
  auto pixel_count = torch::empty({n}, opts.dtype(torch::kInt32));
  Bins bins;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_forward", [&] {
    bins = bin_impl<scalar_t>(means2d, depths, radii, width, height, tile_size);
    const int64_t pairs = bins.sorted_gauss.size(0);
    auto slot_weight = torch::empty({pairs}, opts);
    auto slot_count = torch::empty({pairs}, opts.dtype(torch::kInt32));
    auto run = [&](auto nf) {
      composite_forward_impl<scalar_t, decltype(nf)::value>(bins, means2d, conics, opacities, feats, width, height,
                                                            alpha_min, alpha_max, t_min, render, depth, alpha, final_t, n_contrib,
                                                            slot_weight, slot_count);
    };
    if (F == 4) run(std::integral_constant<int, 4>());
    else if (F == 2) run(std::integral_constant<int, 2>());
    else run(std::integral_constant<int, 0>());
    reduce_slots<scalar_t>(bins.gauss_starts, slot_weight, weight_sum);
    reduce_slots<int32_t>(bins.gauss_starts, slot_count, pixel_count);
  });
  return {render, depth, alpha, weight_sum, pixel_count, final_t, n_contrib, bins.tile_starts, bins.sorted_gauss,
          bins.sorted_slot, bins.gauss_starts};
}

// Returns grad means2d [N, 2], conics [N, 3], opacities [N], feats [N, F].
std::vector<torch::Tensor> composite_backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                              torch::Tensor feats, int64_t width, int64_t height, int64_t tile_size,
                                              double alpha_min, double alpha_max, torch::Tensor final_t,
                                              torch::Tensor n_contrib, torch::Tensor tile_starts,
                                              torch::Tensor sorted_gauss, torch::Tensor sorted_slot,
                                              torch::Tensor gauss_starts, torch::Tensor grad_render,
                                              torch::Tensor grad_depth, torch::Tensor grad_alpha) {
  for (auto* p : {&means2d, &conics, &opacities, &feats, &grad_render, &grad_depth, &grad_alpha})
    check_cpu(*p, "input");
  const int64_t n = means2d.size(0);
  const int64_t F = feats.size(1);
  Bins bins;
  bins.tile = tile_size;
  bins.tiles_x = (width + tile_size - 1) / tile_size;
  bins.tiles_y = (height + tile_size - 1) / tile_size;
  bins.tile_starts = tile_starts;
  bins.sorted_gauss = sorted_gauss;
  bins.sorted_slot = sorted_slot;
  bins.gauss_starts = gauss_starts;
  auto opts = means2d.options();
  auto grads = torch::empty({n, 6 + F}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_backward", [&] {
    auto slot_grad = torch::empty({sorted_gauss.size(0), 6 + F}, opts);
    auto run = [&](auto nf) {
      composite_backward_impl<scalar_t, decltype(nf)::value>(bins, means2d, conics, opacities, feats, width, height,
                                                             alpha_min, alpha_max, final_t, n_contrib, grad_render,
                                                             grad_depth, grad_alpha,
                                                             slot_grad);
    };
    if (F == 4) run(std::integral_constant<int, 4>());
    else if (F == 2) run(std::integral_constant<int, 2>());
    else run(std::integral_constant<int, 0>());
    reduce_slots<scalar_t>(gauss_starts, slot_grad, grads);
  });
  using torch::indexing::Slice;
  return {grads.index({Slice(), Slice(0, 2)}), grads.index({Slice(), Slice(2, 5)}), grads.index({Slice(), 5}),
          grads.index({Slice(), Slice(6, torch::indexing::None)})};
}

int num_threads() {
#ifdef _OPENMP
  return omp_get_max_threads();
#else
  return 1;
#endif
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("project_forward", &project_forward);
  m.def("project_backward", &project_backward);
  m.def("composite_forward", &composite_forward);
  m.def("composite_backward", &composite_backward);
  m.def("num_threads", &num_threads);
}
