// Compiled CPU 3DGS rasterizer: projection, tile binning, sorting, compositing and their hand-written
// backward passes. Numerically mirrors uw3dgs/render/reference.py (see that file for the maths).
// Parallel across Gaussians (projection) and tiles (compositing) with OpenMP; compositing is SIMD across
// the pixels of a tile row (see "SIMD helpers"). The forward records which pixels each Gaussian blended,
// so the backward replays exactly those. Every gradient is written to a per-(tile, Gaussian) slot and
// reduced per Gaussian in a fixed order, so results are bitwise identical run to run and independent of
// the thread count (not of the SIMD width the build was compiled for: sums are split across lanes).
#include <torch/extension.h>

#include "exp_f32.h"
#include "vector_io.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <type_traits>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#else
inline int omp_get_max_threads() { return 1; }
inline int omp_get_thread_num() { return 0; }
#endif
#ifdef __AVX2__
#include <immintrin.h>
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
// Footprints
// ---------------------------------------------------------------------------------------------

// What the tile loops need of one Gaussian, computed once per call (not once per tile it touches) and
// packed so that a (tile, Gaussian) pair reads one record.
//
// The footprint: pixels where the Gaussian can reach alpha_min lie in the ellipse
// {a dx^2 + 2 b dx dy + c dy^2 <= 2 lgap}, lgap = log(opacity) - log(alpha_min) + kLogMargin, whose box spans
// |dx| <= sqrt(2 lgap c / det) and |dy| <= sqrt(2 lgap a / det). These real-arithmetic bounds, widened by a
// pixel, are only used to skip pixels whose alpha is certainly below alpha_min; pixels inside get the
// reference's exact tests.
template <typename T>
struct GaussRec {
  T mx, my, a, b, c, op, logop, ha;  // ha = -a / 2
  int32_t x_lo, x_hi, y_lo, y_hi;    // pixel box (inclusive, clipped to the image); empty when y_lo > y_hi
};

// Pixels i (centre i + 0.5) with |i + 0.5 - centre| <= ext, widened by one, clipped to [0, size).
inline void pixel_range(double centre, double ext, int64_t size, int32_t& lo, int32_t& hi) {
  const double l = std::ceil(centre - ext - 0.5) - 1, u = std::floor(centre + ext - 0.5) + 1;
  // clamped in double first: no overflowing casts
  lo = static_cast<int32_t>(std::max(l, 0.0));
  hi = static_cast<int32_t>(std::min(u, static_cast<double>(size - 1)));
  if (!(l <= u) || lo > hi) { lo = 1; hi = 0; }
}

// The records live in a byte tensor, so that the forward can hand them to the backward.
template <typename T>
torch::Tensor gauss_records(const torch::Tensor& means2d, const torch::Tensor& conics,
                            const torch::Tensor& opacities, double log_cut, int64_t width, int64_t height) {
  const int64_t n = means2d.size(0);
  const T* m2 = means2d.data_ptr<T>();
  const T* cn = conics.data_ptr<T>();
  const T* op = opacities.data_ptr<T>();
  auto out = torch::empty({n * static_cast<int64_t>(sizeof(GaussRec<T>))}, torch::kUInt8);
  GaussRec<T>* recs = reinterpret_cast<GaussRec<T>*>(out.data_ptr<uint8_t>());
#pragma omp parallel for schedule(static) if (n >= kParallelMin)
  for (int64_t i = 0; i < n; ++i) {
    GaussRec<T>& g = recs[i];
    g.mx = m2[2 * i]; g.my = m2[2 * i + 1];
    g.a = cn[3 * i]; g.b = cn[3 * i + 1]; g.c = cn[3 * i + 2];
    g.op = op[i];
    g.ha = static_cast<T>(-0.5) * g.a;
    g.x_lo = 0; g.x_hi = static_cast<int32_t>(width - 1); g.y_lo = 0; g.y_hi = static_cast<int32_t>(height - 1);
    g.logop = std::log(g.op);
    const double a = g.a, b = g.b, c = g.c;
    const double lgap = static_cast<double>(g.logop) - log_cut;
    const double det = a * c - b * b;
    if (!(lgap >= 0)) { g.y_lo = 1; g.y_hi = 0; continue; }  // never reaches alpha_min (also NaN)
    if (!(a > 0) || !(det > 0) || !std::isfinite(det)) continue;  // degenerate conic: every pixel
    pixel_range(g.mx, std::sqrt(2.0 * lgap * c / det), width, g.x_lo, g.x_hi);
    pixel_range(g.my, std::sqrt(2.0 * lgap * a / det), height, g.y_lo, g.y_hi);
    if (g.x_lo > g.x_hi) { g.y_lo = 1; g.y_hi = 0; }
  }
  return out;
}

template <typename T>
const GaussRec<T>* records_of(const torch::Tensor& recs) {
  return reinterpret_cast<const GaussRec<T>*>(recs.data_ptr<uint8_t>());
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

// The tile grid of a width x height image, `tile` pixels a side, its lists not yet made.
inline Bins tile_grid(int64_t width, int64_t height, int64_t tile) {
  Bins b;
  b.tile = tile;
  b.tiles_x = (width + tile - 1) / tile;
  b.tiles_y = (height + tile - 1) / tile;
  return b;
}

// A render's tile lists handed back: lists[0..3] = tile_starts, sorted_gauss, sorted_slot, gauss_starts.
inline Bins bins_from(const torch::Tensor* lists, int64_t width, int64_t height, int64_t tile) {
  Bins b = tile_grid(width, height, tile);
  b.tile_starts = lists[0];
  b.sorted_gauss = lists[1];
  b.sorted_slot = lists[2];
  b.gauss_starts = lists[3];
  return b;
}

template <typename T>
inline void pixel_span(T centre, T radius, int64_t size, int64_t& first, int64_t& last) {
  T f = std::ceil(centre - radius - static_cast<T>(0.5));
  T l = std::floor(centre + radius - static_cast<T>(0.5));
  f = clampv(f, static_cast<T>(0), static_cast<T>(size - 1));
  l = clampv(l, static_cast<T>(0), static_cast<T>(size - 1));
  first = static_cast<int64_t>(f);
  last = static_cast<int64_t>(l);
}

// Stable LSD radix sort of ids by depth (8-bit digits): the order of std::stable_sort by depth, in linear
// time. Keys are the float bits made monotonic; depths of binned Gaussians are finite and positive, and
// + 0 turns a -0 into +0 so that the two compare equal as floats do.
template <typename T>
void sort_by_depth(std::vector<int32_t>& ids, const T* depth) {
  using Key = std::conditional_t<sizeof(T) == 4, uint32_t, uint64_t>;
  const int64_t n = ids.size();
  if (n < 2) return;
  std::vector<Key> keys(n), keys2(n);
  std::vector<int32_t> ids2(n);
  // Each pass is a stable counting sort of blocks of the array in parallel: per-block digit counts, positions in
  // (digit, block) order, each block placed in order; the same permutation as one block, whatever their number.
  const int64_t blocks = n >= kParallelMin ? std::max(1, omp_get_max_threads()) : 1;
  std::vector<int64_t> start(blocks * 256);
#pragma omp parallel for schedule(static) if (blocks > 1)
  for (int64_t i = 0; i < n; ++i) {
    const T d = depth[ids[i]] + static_cast<T>(0);
    Key k;
    std::memcpy(&k, &d, sizeof k);
    const Key sign = Key(1) << (8 * sizeof(Key) - 1);
    keys[i] = (k & sign) ? ~k : (k | sign);
  }
  for (size_t shift = 0; shift < 8 * sizeof(Key); shift += 8) {
#pragma omp parallel for schedule(static, 1) if (blocks > 1)
    for (int64_t b = 0; b < blocks; ++b) {
      int64_t* count = &start[b * 256];
      std::fill(count, count + 256, 0);
      for (int64_t i = n * b / blocks; i < n * (b + 1) / blocks; ++i) ++count[(keys[i] >> shift) & 255];
    }
    const Key first = (keys[0] >> shift) & 255;
    int64_t same = 0;
    for (int64_t b = 0; b < blocks; ++b) same += start[b * 256 + first];
    if (same == n) continue;  // one digit value: order unchanged
    int64_t pos = 0;
    for (int d = 0; d < 256; ++d)
      for (int64_t b = 0; b < blocks; ++b) {
        const int64_t count = start[b * 256 + d];
        start[b * 256 + d] = pos;
        pos += count;
      }
#pragma omp parallel for schedule(static, 1) if (blocks > 1)
    for (int64_t b = 0; b < blocks; ++b) {
      int64_t* next = &start[b * 256];
      for (int64_t i = n * b / blocks; i < n * (b + 1) / blocks; ++i) {
        const int64_t to = next[(keys[i] >> shift) & 255]++;
        keys2[to] = keys[i];
        ids2[to] = ids[i];
      }
    }
    keys.swap(keys2);
    ids.swap(ids2);
  }
}

template <typename T>
Bins bin_impl(const torch::Tensor& means2d, const torch::Tensor& depths, const torch::Tensor& radii,
              const GaussRec<T>* recs, int64_t width, int64_t height, int64_t tile) {
  const int64_t n = means2d.size(0);
  const T* m2 = means2d.data_ptr<T>();
  const T* dp = depths.data_ptr<T>();
  const int32_t* rad = radii.data_ptr<int32_t>();
  Bins b = tile_grid(width, height, tile);
  const int64_t n_tiles = b.tiles_x * b.tiles_y;

  // Visible Gaussians front to back, ties by index (the reference's stable argsort).
  std::vector<int32_t> ids;
  ids.reserve(n);
  for (int64_t i = 0; i < n; ++i)
    if (rad[i] > 0) ids.push_back(static_cast<int32_t>(i));
  sort_by_depth(ids, dp);

  // Tile rectangle of each Gaussian: the tiles of its bounding square (the reference's binning) that its
  // footprint box reaches; the others would composite nothing. Slots are per Gaussian in index order (for
  // the gradient reduction).
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
      const GaussRec<T>& g = recs[i];
      x0 = std::max<int64_t>(x0, g.x_lo); x1 = std::min<int64_t>(x1, g.x_hi);
      y0 = std::max<int64_t>(y0, g.y_lo); y1 = std::min<int64_t>(y1, g.y_hi);
      if (x0 > x1 || y0 > y1) { x0 = y0 = 0; x1 = y1 = -1; }  // footprint empty or outside the square
      x0 /= tile; x1 = x1 < 0 ? -1 : x1 / tile; y0 /= tile; y1 = y1 < 0 ? -1 : y1 / tile;
      rect[4 * i] = x0; rect[4 * i + 1] = x1; rect[4 * i + 2] = y0; rect[4 * i + 3] = y1;
      cnt = std::max<int64_t>(0, x1 - x0 + 1) * std::max<int64_t>(0, y1 - y0 + 1);
    }
    gstart[i + 1] = cnt;
  }
  for (int64_t i = 0; i < n; ++i) gstart[i + 1] += gstart[i];
  const int64_t pairs = gstart[n];

  // Counting sort by tile over the depth-ordered Gaussians: each tile's list ends up front to back. Blocks of the
  // depth order are counted and placed in parallel, each block's pairs of a tile after the blocks before it: the
  // same lists as one block.
  const int64_t n_vis = ids.size();
  const int64_t blocks = pairs >= kParallelMin ? std::max(1, omp_get_max_threads()) : 1;
  std::vector<int64_t> next(blocks * n_tiles, 0);  // per block and tile: its pair count, then its first position
#pragma omp parallel for schedule(static, 1) if (blocks > 1)
  for (int64_t blk = 0; blk < blocks; ++blk) {
    int64_t* count = &next[blk * n_tiles];
    for (int64_t v = n_vis * blk / blocks; v < n_vis * (blk + 1) / blocks; ++v) {
      const int32_t g = ids[v];
      for (int64_t ty = rect[4 * g + 2]; ty <= rect[4 * g + 3]; ++ty)
        for (int64_t tx = rect[4 * g]; tx <= rect[4 * g + 1]; ++tx) count[ty * b.tiles_x + tx]++;
    }
  }
  b.tile_starts = torch::empty({n_tiles + 1}, torch::kInt64);
  int64_t* tstart = b.tile_starts.data_ptr<int64_t>();
  tstart[0] = 0;
  for (int64_t t = 0; t < n_tiles; ++t) {
    int64_t pos = tstart[t];
    for (int64_t blk = 0; blk < blocks; ++blk) {
      const int64_t count = next[blk * n_tiles + t];
      next[blk * n_tiles + t] = pos;
      pos += count;
    }
    tstart[t + 1] = pos;
  }
  b.sorted_gauss = torch::empty({pairs}, torch::kInt32);
  b.sorted_slot = torch::empty({pairs}, torch::kInt64);
  int32_t* sg = b.sorted_gauss.data_ptr<int32_t>();
  int64_t* ss = b.sorted_slot.data_ptr<int64_t>();
#pragma omp parallel for schedule(static, 1) if (blocks > 1)
  for (int64_t blk = 0; blk < blocks; ++blk) {
    int64_t* fill = &next[blk * n_tiles];
    for (int64_t v = n_vis * blk / blocks; v < n_vis * (blk + 1) / blocks; ++v) {
      const int32_t g = ids[v];
      int64_t slot = gstart[g];
      for (int64_t ty = rect[4 * g + 2]; ty <= rect[4 * g + 3]; ++ty)
        for (int64_t tx = rect[4 * g]; tx <= rect[4 * g + 1]; ++tx) {
          const int64_t pos = fill[ty * b.tiles_x + tx]++;
          sg[pos] = g;
          ss[pos] = slot++;
        }
    }
  }
  return b;
}

// ---------------------------------------------------------------------------------------------
// SIMD helpers
// ---------------------------------------------------------------------------------------------

// Compositing works on kLanes consecutive pixels of a tile row at once, written with GCC vector
// extensions so one source serves float and double and compiles to AVX-512, AVX2 or plain SSE. Every
// lane does exactly the scalar per-pixel arithmetic of the reference; masks replace its branches.
#ifdef __AVX512F__
constexpr int kLanes = 16;  // one 512-bit register of floats
#else
constexpr int kLanes = 8;   // one 256-bit register of floats
#endif

template <typename T>
struct Simd;
template <>
struct Simd<float> {
  typedef float V __attribute__((vector_size(kLanes * 4)));
  typedef int32_t I __attribute__((vector_size(kLanes * 4)));
  using Int = int32_t;
};
template <>
struct Simd<double> {
  typedef double V __attribute__((vector_size(kLanes * 8)));
  typedef int64_t I __attribute__((vector_size(kLanes * 8)));
  using Int = int64_t;
};

template <typename V, typename T>
inline V splat(T x) { return V{} + x; }

// Bit i set when lane i of the mask is set.
template <typename I>
inline unsigned mask_bits(const I& m) {
#if defined(__AVX512F__)
  const __m512i* h = reinterpret_cast<const __m512i*>(&m);
  if constexpr (sizeof(m[0]) == 4) {
    return static_cast<unsigned>(_mm512_test_epi32_mask(h[0], h[0]));
  } else {
    return static_cast<unsigned>(_mm512_test_epi64_mask(h[0], h[0])) |
           (static_cast<unsigned>(_mm512_test_epi64_mask(h[1], h[1])) << 8);
  }
#elif defined(__AVX2__)
  if constexpr (sizeof(m[0]) == 4) {
    return static_cast<unsigned>(_mm256_movemask_ps(_mm256_castsi256_ps(reinterpret_cast<const __m256i&>(m))));
  } else {
    const __m256i* h = reinterpret_cast<const __m256i*>(&m);
    return static_cast<unsigned>(_mm256_movemask_pd(_mm256_castsi256_pd(h[0]))) |
           (static_cast<unsigned>(_mm256_movemask_pd(_mm256_castsi256_pd(h[1]))) << 4);
  }
#else
  unsigned bits = 0;
  for (int i = 0; i < kLanes; ++i) bits |= (m[i] != 0 ? 1u : 0u) << i;
  return bits;
#endif
}

// Horizontal sum in a fixed order (deterministic): a pairwise tree, lanes i and i + n / 2 first.
template <typename T, typename V>
inline T hsum(const V& v) {
  T buf[kLanes];
  std::memcpy(buf, &v, sizeof v);
  for (int n = kLanes / 2; n > 0; n /= 2)
    for (int i = 0; i < n; ++i) buf[i] += buf[i + n];
  return buf[0];
}

// exp(x) for x in [-80, 80] (callers clamp), in plain vector arithmetic so it vectorises (exp_f32.h; the double
// version below: Cody-Waite reduction and Sleef's minimax polynomial, about 1 ulp like the Sleef exp torch uses).
inline Simd<float>::V vexp(Simd<float>::V x) {
  using V = Simd<float>::V;
  using I = Simd<float>::I;
  V q;
  const V u = exp_f32_reduced(x, q);
  const I scale = (__builtin_convertvector(q, I) + 127) << 23;  // 2^q, a normal float for |q| <= 126
  return u * (V)scale;  // a vector cast reinterprets the bits
}

inline Simd<double>::V vexp(Simd<double>::V x) {
  using V = Simd<double>::V;
  using I = Simd<double>::I;
  V q = x * 1.442695040888963407359924681001892137;
  q = (q + 6755399441055744.0) - 6755399441055744.0;  // round to nearest: 1.5 * 2^52
  V s = x - q * .69314718055966295651160180568695068359375;
  s = s - q * .28235290563031577122588448175013436025525412068e-12;
  V u = splat<V>(+0.2081276378237164457e-8);
  u = u * s + 0.2511210703042288022e-7;
  u = u * s + 0.2755762628169491192e-6;
  u = u * s + 0.2755723402025388239e-5;
  u = u * s + 0.2480158687479686264e-4;
  u = u * s + 0.0001984126989855865850;
  u = u * s + 0.001388888888914497797;
  u = u * s + 0.008333333333314938210;
  u = u * s + 0.04166666666666602598;
  u = u * s + 0.1666666666666669072;
  u = u * s + 0.5;
  u = 1.0 + ((s * s) * u + s);
  const I scale = (__builtin_convertvector(q, I) + 1023) << 52;
  return u * (V)scale;
}

// ---------------------------------------------------------------------------------------------
// Compositing
// ---------------------------------------------------------------------------------------------

// A tile's Gaussians are composited in batches of kBatch, in two passes:
//  1. for every Gaussian of the batch and every kLanes-pixel chunk of its footprint box (chunks aligned
//     to the tile, so a pixel is always in the same lane), compute the exponent and test it; the chunks
//     with a pixel left are appended to a list without branching;
//  2. walk the list (in Gaussian order, which is all the per-pixel sums need) and blend, skipping the
//     pixels that terminated since pass 1.
// Pass 2 has no data-dependent branch but the rare early termination, so the CPU overlaps consecutive
// chunks instead of stalling on the exp's latency and on mispredicted short loops.
constexpr int64_t kBatch = 16;

// What the forward records for the backward. For every chunk in which a Gaussian blended a pixel, one
// 32-bit code: tile row, chunk column (kRowBits bits each) and the mask of blended lanes (top kLanes bits). Per
// (tile, Gaussian) pair the number of its codes; per tile its codes' thread buffer and range. The backward
// recomputes alpha at exactly those lanes (bit-identical: same code path), so it needs no footprint
// search, no exp of pixels that were not blended and no termination logic. About 4 bytes per blended chunk.
struct CodeBuf {  // growable without zero-filling; the memory is handed to a tensor at the end
  uint32_t* data = nullptr;
  int64_t size = 0, cap = 0;
  void reserve(int64_t n) {
    if (n <= cap) return;
    cap = std::max<int64_t>(n, 2 * cap);
    data = static_cast<uint32_t*>(std::realloc(data, cap * sizeof(uint32_t)));
    TORCH_CHECK(data != nullptr, "out of memory");
  }
  torch::Tensor release() {
    if (size == 0) { std::free(data); data = nullptr; return torch::empty({0}, torch::kInt32); }
    uint32_t* d = data;
    data = nullptr;
    return torch::from_blob(d, {size}, [](void* q) { std::free(q); }, torch::kInt32);
  }
  ~CodeBuf() { std::free(data); }
};
constexpr int kMaskShift = 32 - kLanes, kRowBits = kMaskShift / 2, kMaxTile = 1 << kRowBits;

struct Trace {
  torch::Tensor pair_codes;               // [pairs] int32: codes of each (tile, Gaussian) pair
  torch::Tensor tile_codes;               // [tiles, 3] int64: thread buffer, first, end
  std::vector<torch::Tensor> codes;       // per thread buffer, int32
};

// Pixel box of a Gaussian within a tile, as tile-local rows and chunk columns; false when they miss.
template <typename T>
inline bool tile_box(const GaussRec<T>& g, int64_t x0, int64_t y0, int64_t w, int64_t h, int64_t& r_lo,
                     int64_t& r_hi, int64_t& c_lo, int64_t& c_hi) {
  r_lo = std::max<int64_t>(g.y_lo - y0, 0);
  r_hi = std::min<int64_t>(g.y_hi - y0, h - 1);
  const int64_t xa = std::max<int64_t>(g.x_lo - x0, 0), xb = std::min<int64_t>(g.x_hi - x0, w - 1);
  c_lo = xa / kLanes;
  c_hi = xb / kLanes;
  return r_lo <= r_hi && xa <= xb;
}

// Tile t's origin and size in pixels (tiles of the last row and column may be cut by the image's border).
struct TileRect {
  int64_t x0 = 0, y0 = 0, w = 0, h = 0;
};

inline TileRect tile_rect(const Bins& bins, int64_t t, int64_t width, int64_t height) {
  const int64_t x0 = (t % bins.tiles_x) * bins.tile, y0 = (t / bins.tiles_x) * bins.tile;
  return {x0, y0, std::min(x0 + bins.tile, width) - x0, std::min(y0 + bins.tile, height) - y0};
}

// The compositing forward of one tile at a time, with one thread's scratch: what composite_forward and PAUP's
// masked L1 (masked_l1) share. After run(t): Tr holds the tile's final transmittance and acc its F channels then
// the alpha sum (channel-major planes of `plane` values, rows padded to whole chunks, `stride` apart).
template <typename T, int NF>
struct TileForward : TileRect {  // the last tile's rectangle
  using V = typename Simd<T>::V;
  using I = typename Simd<T>::I;
  using Int = typename Simd<T>::Int;
  struct Chunk {
    V e;          // exponent
    I m;          // pixels to test
    int32_t rc;   // tile row | chunk column << kRowBits
    int32_t jj;   // Gaussian within the batch
  };
  const Bins& bins;
  const GaussRec<T>* recs;
  const T* ft;
  const int64_t F, width, height, ts, n_cols, stride, plane;
  const T alpha_min, alpha_max, t_min, floor_, log_cut;
  V lane;
  // Per pixel of the tile: transmittance, accumulated channels, alive mask (padding and pixels outside the image
  // are dead); per-row terms of the exponent; the batch's chunks to blend and per-Gaussian sums.
  std::vector<T> Tr, acc, dxs, hdx2s, rowcs, bdys;
  std::vector<Int> live;
  std::vector<Chunk> act;
  std::vector<V> wsum;
  std::vector<int32_t> cnt, n_codes;
  std::vector<V> alphas;  // with keep_alphas: each code's blended alphas (0 in other lanes), indexed like buf
  bool keep_alphas = false;

  TileForward(const Bins& bins_, const GaussRec<T>* recs_, const torch::Tensor& feats, int64_t width_,
              int64_t height_, double alpha_min_d, double alpha_max_d, double t_min_d)
      : bins(bins_), recs(recs_), ft(feats.data_ptr<T>()), F(NF > 0 ? NF : feats.size(1)), width(width_),
        height(height_), ts(bins_.tile), n_cols((ts + kLanes - 1) / kLanes), stride(n_cols * kLanes),
        plane(ts * stride), alpha_min(static_cast<T>(alpha_min_d)), alpha_max(static_cast<T>(alpha_max_d)),
        t_min(static_cast<T>(t_min_d)), floor_(static_cast<T>(kExpFloor)),
        log_cut(static_cast<T>(std::log(alpha_min_d) - kLogMargin)), Tr(plane), acc((F + 1) * plane),
        dxs(n_cols * kLanes), hdx2s(n_cols * kLanes), rowcs(n_cols * kLanes), bdys(n_cols * kLanes), live(plane),
        act(kBatch * ts * n_cols), wsum(kBatch), cnt(kBatch), n_codes(kBatch) {
    for (int i = 0; i < kLanes; ++i) lane[i] = static_cast<T>(i);
  }

  // Composite tile t front to back. Per (tile, Gaussian) pair: its weight sum and pixel count into sw / sc and its
  // number of codes into pcodes, each where given (indexed like the tile lists: sw, sc by slot, pcodes by pair);
  // the codes are appended to buf where given (and their alphas to `alphas` with keep_alphas).
  void run(int64_t t, T* sw, int32_t* sc, int32_t* pcodes, CodeBuf* buf) {
    const int64_t* tstart = bins.tile_starts.data_ptr<int64_t>();
    const int32_t* ids = bins.sorted_gauss.data_ptr<int32_t>() + tstart[t];
    const int64_t* ss = bins.sorted_slot.data_ptr<int64_t>() + tstart[t];
    const int64_t k = tstart[t + 1] - tstart[t];
    static_cast<TileRect&>(*this) = tile_rect(bins, t, width, height);
    std::fill(Tr.begin(), Tr.end(), static_cast<T>(1));
    std::fill(acc.begin(), acc.end(), static_cast<T>(0));
    std::fill(live.begin(), live.end(), 0);
    for (int64_t r = 0; r < h; ++r)
      std::fill(live.begin() + r * stride, live.begin() + r * stride + w, static_cast<Int>(-1));
    int64_t n_live = w * h;
    int64_t j0 = 0;
    for (; j0 < k && n_live > 0; j0 += kBatch) {
      const int64_t nb = std::min(kBatch, k - j0);
      // Pass 1.
      int64_t n_act = 0;
      for (int64_t jj = 0; jj < nb; ++jj) {
        if (j0 + jj + 8 < k) {
          __builtin_prefetch(&recs[ids[j0 + jj + 8]]);
          __builtin_prefetch(ft + static_cast<int64_t>(ids[j0 + jj + 8]) * F);
        }
        const GaussRec<T>& g = recs[ids[j0 + jj]];
        int64_t r_lo, r_hi, c_lo, c_hi;
        if (!tile_box(g, x0, y0, w, h, r_lo, r_hi, c_lo, c_hi)) continue;
        // log(opacity) + power exactly as the reference: (-c dy^2/2 + log op) + (-a dx^2/2) + (-b dy) dx,
        // from per-column and per-row terms (computed kLanes columns / rows at a time).
        for (int64_t c = c_lo; c <= c_hi; ++c) {
          const V dx = ((lane + static_cast<T>(x0 + c * kLanes)) + static_cast<T>(0.5)) - g.mx;
          vstore(&dxs[c * kLanes], dx);
          vstore(&hdx2s[c * kLanes], V((g.ha * dx) * dx));
        }
        for (int64_t r = r_lo - r_lo % kLanes; r <= r_hi; r += kLanes) {
          const V dy = ((lane + static_cast<T>(y0 + r)) + static_cast<T>(0.5)) - g.my;
          vstore(&rowcs[r], V((static_cast<T>(-0.5) * g.c * dy) * dy + g.logop));
          vstore(&bdys[r], V(-g.b * dy));
        }
        for (int64_t r = r_lo; r <= r_hi; ++r) {
          for (int64_t c = c_lo; c <= c_hi; ++c) {
            const int64_t p = r * stride + c * kLanes;
            const V e = (rowcs[r] + vload<V>(&hdx2s[c * kLanes])) + bdys[r] * vload<V>(&dxs[c * kLanes]);
            // e < log_cut: alpha certainly below alpha_min; e > log(opacity): power > 0 (also NaN).
            // Terminated pixels are dead in `live`.
            const I m = vload<I>(&live[p]) & (e >= log_cut) & (e <= g.logop);
            act[n_act] = {e, m, static_cast<int32_t>(r | c << kRowBits), static_cast<int32_t>(jj)};
            n_act += mask_bits(m) != 0;
          }
        }
      }
      // Pass 2.
      std::fill(wsum.begin(), wsum.end(), V{});
      std::fill(cnt.begin(), cnt.end(), 0);
      std::fill(n_codes.begin(), n_codes.end(), 0);
      if (buf) buf->reserve(buf->size + n_act);
      if (keep_alphas && static_cast<int64_t>(alphas.size()) < buf->size + n_act) alphas.resize(2 * (buf->size + n_act));
      for (int64_t i = 0; i < n_act; ++i) {
        const int64_t rc = act[i].rc, jj = act[i].jj;
        const int64_t p = (rc & (kMaxTile - 1)) * stride + (rc >> kRowBits) * kLanes;
        const V e = act[i].e;
        I m = act[i].m & vload<I>(&live[p]);  // a pixel may have terminated since pass 1
        const V ec = e < floor_ ? splat<V>(floor_) : (e > static_cast<T>(80) ? splat<V>(static_cast<T>(80)) : e);
        V alpha = vexp(ec);
        alpha = alpha_max < alpha ? splat<V>(alpha_max) : alpha;
        m &= alpha >= alpha_min;
        alpha = m ? alpha : V{};  // skipped lanes blend nothing (and make no denormals)
        const V tr = vload<V>(&Tr[p]);
        const V t_next = tr * (static_cast<T>(1) - alpha);
        // Early termination: this Gaussian and all behind it are dropped for that pixel.
        const I term = m & ~(t_next >= t_min);
        if (const unsigned tb = mask_bits(term)) {
          n_live -= __builtin_popcount(tb);
          vstore(&live[p], I(vload<I>(&live[p]) & ~term));
          m &= ~term;
        }
        const unsigned mb = mask_bits(m);
        cnt[jj] += __builtin_popcount(mb);
        if (buf) {
          buf->data[buf->size] = static_cast<uint32_t>(rc) | mb << kMaskShift;
          if (keep_alphas) alphas[buf->size] = m ? alpha : V{};
          buf->size += mb != 0;
          n_codes[jj] += mb != 0;
        }
        const V wgt = m ? alpha * tr : V{};
        const T* f = ft + static_cast<int64_t>(ids[j0 + jj]) * F;
        // + 0 where not blended: bitwise a no-op (features are finite), cheaper than a blend
        for (int64_t ch = 0; ch < F; ++ch) {
          T* a = &acc[ch * plane + p];
          vstore(a, V(vload<V>(a) + wgt * f[ch]));
        }
        T* a = &acc[F * plane + p];
        vstore(a, V(vload<V>(a) + wgt));
        wsum[jj] += wgt;
        vstore(&Tr[p], V(m ? t_next : tr));
      }
      for (int64_t jj = 0; jj < nb; ++jj) {
        if (sw) sw[ss[j0 + jj]] = hsum<T>(wsum[jj]);
        if (sc) sc[ss[j0 + jj]] = cnt[jj];
        if (pcodes) pcodes[tstart[t] + j0 + jj] = n_codes[jj];
      }
    }
    for (int64_t j = j0; j < k; ++j) {  // behind a fully terminated tile
      if (sw) sw[ss[j]] = 0;
      if (sc) sc[ss[j]] = 0;
      if (pcodes) pcodes[tstart[t] + j] = 0;
    }
  }
};

template <typename T, int NF>
void composite_forward_impl(const Bins& bins, const GaussRec<T>* recs, const torch::Tensor& feats, int64_t width,
                            int64_t height, double alpha_min, double alpha_max, double t_min,
                            torch::Tensor& render, torch::Tensor& depth, torch::Tensor& alpha_img,
                            torch::Tensor& final_t, torch::Tensor& slot_weight, torch::Tensor& slot_count,
                            Trace* trace) {
  T* rend = render.data_ptr<T>();  // [H, W, F - 1]: the features
  T* dimg = depth.data_ptr<T>();   // [H, W]: the last composited channel
  T* aimg = alpha_img.data_ptr<T>();
  T* ftT = final_t.data_ptr<T>();
  T* sw = slot_weight.data_ptr<T>();
  int32_t* sc = slot_count.data_ptr<int32_t>();
  const int64_t n_tiles = bins.tiles_x * bins.tiles_y;
  const int64_t pairs = bins.sorted_gauss.size(0);
  int32_t* pcodes = nullptr;
  int64_t* tcodes = nullptr;
  std::vector<CodeBuf> bufs(trace ? std::max(1, omp_get_max_threads()) : 0);
  if (trace) {
    trace->pair_codes = torch::empty({pairs}, torch::kInt32);
    trace->tile_codes = torch::empty({n_tiles, 3}, torch::kInt64);
    pcodes = trace->pair_codes.data_ptr<int32_t>();
    tcodes = trace->tile_codes.data_ptr<int64_t>();
  }
#pragma omp parallel if (pairs >= kParallelMin)
  {
    TileForward<T, NF> tile(bins, recs, feats, width, height, alpha_min, alpha_max, t_min);
    const int64_t F = tile.F, plane = tile.plane;
    CodeBuf* buf = trace ? &bufs[omp_get_thread_num()] : nullptr;
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      if (buf) {
        tcodes[3 * t] = omp_get_thread_num();
        tcodes[3 * t + 1] = buf->size;
      }
      tile.run(t, sw, sc, pcodes, buf);
      if (buf) tcodes[3 * t + 2] = buf->size;
      for (int64_t r = 0; r < tile.h; ++r)
        for (int64_t x = 0; x < tile.w; ++x) {
          const int64_t p = r * tile.stride + x, q = (tile.y0 + r) * width + tile.x0 + x;
          T* o = rend + q * (F - 1);
          for (int64_t ch = 0; ch < F - 1; ++ch) o[ch] = tile.acc[ch * plane + p];
          dimg[q] = tile.acc[(F - 1) * plane + p];
          aimg[q] = tile.acc[F * plane + p];
          ftT[q] = tile.Tr[p];
        }
    }
  }
  if (trace)
    for (auto& b : bufs) trace->codes.push_back(b.release());
}

// The compositing backward of one tile at a time, with one thread's scratch: what composite_backward and PAUP's
// masked L1 (masked_l1) share. begin(t) zeroes the tile's planes; the caller then writes each pixel's final
// transmittance into Tr and the gradients of its F channels and of alpha into go (channel-major, as TileForward's
// acc); run() replays the forward's codes back to front. kAll: gradients of means2d, conics, opacities and features
// into slot rows of 6 + F values; false: of the opacities only, one value per slot (a render whose Gaussians are
// frozen), which skips the moment and per-channel sums.
template <typename T, int NF, bool kAll>
struct TileBackward : TileRect {  // the tile's rectangle
  using V = typename Simd<T>::V;
  using I = typename Simd<T>::I;
  const Bins& bins;
  const GaussRec<T>* recs;
  const T* ft;
  const int64_t F, ts, n_cols, stride, plane, row;
  const T alpha_max, floor_, tiny;
  V lane;
  I lane_bit;
  // Per pixel: transmittance in front of the current Gaussian, S = sum of w g behind it, the output gradients.
  std::vector<T> Tr, S, go;

  TileBackward(const Bins& bins_, const GaussRec<T>* recs_, const torch::Tensor& feats, double alpha_max_d)
      : bins(bins_), recs(recs_), ft(feats.data_ptr<T>()), F(NF > 0 ? NF : feats.size(1)), ts(bins_.tile),
        n_cols((ts + kLanes - 1) / kLanes), stride(n_cols * kLanes), plane(ts * stride), row(kAll ? 6 + F : 1),
        alpha_max(static_cast<T>(alpha_max_d)), floor_(static_cast<T>(kExpFloor)),
        tiny(std::numeric_limits<T>::min()), Tr(plane), S(plane), go((F + 1) * plane) {
    for (int i = 0; i < kLanes; ++i) {
      lane[i] = static_cast<T>(i);
      lane_bit[i] = 1 << i;
    }
  }

  void begin(int64_t t, int64_t width, int64_t height) {
    static_cast<TileRect&>(*this) = tile_rect(bins, t, width, height);
    std::fill(Tr.begin(), Tr.end(), static_cast<T>(0));
    std::fill(S.begin(), S.end(), static_cast<T>(0));
    std::fill(go.begin(), go.end(), static_cast<T>(0));
  }

  // The tile's codes end at tile_codes[end]; per pair, its code count in pcodes (indexed like the tile lists).
  // `alphas`: the codes' alphas kept by the forward (TileForward::keep_alphas), else recomputed (the same bits).
  void run(int64_t t, const uint32_t* tile_codes, int64_t end, const int32_t* pcodes, T* sgrad,
           const V* alphas = nullptr) {
    const int64_t* tstart = bins.tile_starts.data_ptr<int64_t>();
    const int32_t* ids = bins.sorted_gauss.data_ptr<int32_t>() + tstart[t];
    const int64_t* ss = bins.sorted_slot.data_ptr<int64_t>() + tstart[t];
    const int64_t k = tstart[t + 1] - tstart[t];
    // The forward's blended chunks, back to front, Gaussian by Gaussian.
    for (int64_t j = k - 1; j >= 0; --j) {
      T* out = sgrad + ss[j] * row;
      const int64_t n_codes = pcodes[tstart[t] + j];
      if (n_codes == 0) {  // blended nothing
        std::fill(out, out + row, static_cast<T>(0));
        continue;
      }
      if (j >= 8) {
        __builtin_prefetch(&recs[ids[j - 8]]);
        __builtin_prefetch(ft + static_cast<int64_t>(ids[j - 8]) * F);
      }
      const GaussRec<T>& g = recs[ids[j]];
      const T* f = ft + static_cast<int64_t>(ids[j]) * F;
      // Per-lane sums of dL/dpower G, G dx, G dy, G dx^2, G dx dy, G dy^2 and of w dL/dout per channel.
      V m0 = {}, m1 = {}, m2 = {}, m3 = {}, m4 = {}, m5 = {};
      V gf[NF > 0 ? NF : 64] = {};
      for (int64_t i = end - n_codes; i < end; ++i) {
        const uint32_t code = tile_codes[i];
        const int64_t r = code & (kMaxTile - 1), c = (code >> kRowBits) & (kMaxTile - 1);
        const int64_t p = r * stride + c * kLanes;
        const I m = (splat<I>(static_cast<typename Simd<T>::Int>(code >> kMaskShift)) & lane_bit) != 0;
        const T dy = (static_cast<T>(y0 + r) + static_cast<T>(0.5)) - g.my;
        const V dx = ((lane + static_cast<T>(x0 + c * kLanes)) + static_cast<T>(0.5)) - g.mx;
        V alpha;
        if (alphas) {
          alpha = alphas[i];
        } else {  // alpha exactly as in the forward
          const T rowc = static_cast<T>(-0.5) * g.c * dy * dy + g.logop;
          const T bdy = -g.b * dy;
          const V e = (rowc + V((g.ha * dx) * dx)) + bdy * dx;
          const V ec = e < floor_ ? splat<V>(floor_) : (e > static_cast<T>(80) ? splat<V>(static_cast<T>(80)) : e);
          alpha = vexp(ec);
          alpha = alpha_max < alpha ? splat<V>(alpha_max) : alpha;
          alpha = m ? alpha : V{};  // other lanes: transmit 1, weight 0
        }
        const V transmit = static_cast<T>(1) - alpha;
        const V Tb = vload<V>(&Tr[p]) / transmit;  // transmittance in front of Gaussian j
        vstore(&Tr[p], Tb);
        const V wgt = alpha * Tb;
        V gsum = vload<V>(&go[F * plane + p]);
        for (int64_t ch = 0; ch < F; ++ch) gsum += vload<V>(&go[ch * plane + p]) * f[ch];
        const V wg = wgt * gsum;
        const V s = vload<V>(&S[p]);
        V G = wg - s * alpha / transmit;
        vstore(&S[p], V(m ? s + wg : s));
        G = (m & (alpha < alpha_max)) ? G : V{};
        m0 += G;
        if constexpr (kAll) {
          const V Gdx = G * dx;
          const V Gdy = G * dy;
          m1 += Gdx;
          m2 += Gdy;
          m3 += Gdx * dx;
          m4 += Gdx * dy;
          m5 += Gdy * dy;
          for (int64_t ch = 0; ch < F; ++ch) gf[ch] += m ? wgt * vload<V>(&go[ch * plane + p]) : V{};
        }
      }
      end -= n_codes;
      const T g_opacity = hsum<T>(m0) / std::max(g.op, tiny);
      if constexpr (kAll) {
        const T s1 = hsum<T>(m1), s2 = hsum<T>(m2);
        out[0] = g.a * s1 + g.b * s2;
        out[1] = g.b * s1 + g.c * s2;
        out[2] = static_cast<T>(-0.5) * hsum<T>(m3);
        out[3] = -hsum<T>(m4);
        out[4] = static_cast<T>(-0.5) * hsum<T>(m5);
        out[5] = g_opacity;
        for (int64_t ch = 0; ch < F; ++ch) out[6 + ch] = hsum<T>(gf[ch]);
      } else {
        out[0] = g_opacity;
      }
    }
  }
};

template <typename T, int NF, bool kAll>
void composite_backward_impl(const Bins& bins, const Trace& trace, const GaussRec<T>* recs,
                             const torch::Tensor& feats, int64_t width, int64_t height, double alpha_max,
                             const torch::Tensor& final_t, const torch::Tensor& grad_render,
                             const torch::Tensor& grad_depth, const torch::Tensor& grad_alpha,
                             torch::Tensor& slot_grad) {
  const T* ftT = final_t.data_ptr<T>();
  // Output gradients; an empty tensor stands for zeros (that output was not used).
  const T* grend = grad_render.numel() ? grad_render.data_ptr<T>() : nullptr;
  const T* gdep = grad_depth.numel() ? grad_depth.data_ptr<T>() : nullptr;
  const T* galp = grad_alpha.numel() ? grad_alpha.data_ptr<T>() : nullptr;
  T* sgrad = slot_grad.data_ptr<T>();
  const int64_t* tstart = bins.tile_starts.data_ptr<int64_t>();
  const int32_t* pcodes = trace.pair_codes.data_ptr<int32_t>();
  const int64_t* tcodes = trace.tile_codes.data_ptr<int64_t>();
  std::vector<const uint32_t*> codes;
  for (const auto& c : trace.codes) codes.push_back(reinterpret_cast<const uint32_t*>(c.data_ptr<int32_t>()));
  const int64_t n_tiles = bins.tiles_x * bins.tiles_y;
#pragma omp parallel if (bins.sorted_gauss.size(0) >= kParallelMin)
  {
    TileBackward<T, NF, kAll> tile(bins, recs, feats, alpha_max);
    const int64_t F = tile.F, plane = tile.plane;
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      if (tstart[t + 1] == tstart[t]) continue;
      tile.begin(t, width, height);
      for (int64_t r = 0; r < tile.h; ++r)
        for (int64_t x = 0; x < tile.w; ++x) {
          const int64_t p = r * tile.stride + x, q = (tile.y0 + r) * width + tile.x0 + x;
          tile.Tr[p] = ftT[q];
          if (grend)
            for (int64_t ch = 0; ch < F - 1; ++ch) tile.go[ch * plane + p] = grend[q * (F - 1) + ch];
          if (gdep) tile.go[(F - 1) * plane + p] = gdep[q];
          if (galp) tile.go[F * plane + p] = galp[q];
        }
      tile.run(t, codes[tcodes[3 * t]], tcodes[3 * t + 2], pcodes, sgrad);
    }
  }
}

// masked_l1's tiles: writes image and the opacities' slot gradients (one per slot); returns sum |target - image|.
template <typename T, int NF>
double masked_l1_impl(const Bins& bins, const GaussRec<T>* recs, const torch::Tensor& feats, int64_t width,
                      int64_t height, double alpha_min, double alpha_max, double t_min, const torch::Tensor& target,
                      torch::Tensor& image, torch::Tensor& slot_grad) {
  const int64_t n_tiles = bins.tiles_x * bins.tiles_y, pairs = bins.sorted_gauss.size(0), C = feats.size(1);
  std::vector<int32_t> pcodes(pairs);
  std::vector<double> tile_sums(n_tiles);
  const T* tgt = target.data_ptr<T>();
  T* img = image.data_ptr<T>();
  T* sgrad = slot_grad.data_ptr<T>();
  const T unit = static_cast<T>(1) / static_cast<T>(height * width * C);
#pragma omp parallel if (pairs >= kParallelMin)
  {
    TileForward<T, NF> fwd(bins, recs, feats, width, height, alpha_min, alpha_max, t_min);
    TileBackward<T, NF, false> bwd(bins, recs, feats, alpha_max);
    const int64_t plane = fwd.plane;
    CodeBuf buf;
    fwd.keep_alphas = true;  // in cache for the backward: no exp there
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      buf.size = 0;  // one tile's codes at a time
      fwd.run(t, nullptr, nullptr, pcodes.data(), &buf);
      bwd.begin(t, width, height);
      double sum = 0;
      for (int64_t r = 0; r < fwd.h; ++r)
        for (int64_t x = 0; x < fwd.w; ++x) {
          const int64_t p = r * fwd.stride + x, q = (fwd.y0 + r) * width + fwd.x0 + x;
          bwd.Tr[p] = fwd.Tr[p];
          for (int64_t ch = 0; ch < C; ++ch) {
            const T v = fwd.acc[ch * plane + p], d = tgt[q * C + ch] - v;
            img[q * C + ch] = v;
            sum += std::abs(d);
            // autograd's abs'(d) = sgn(d), then -1 for the subtraction
            bwd.go[ch * plane + p] = d > 0 ? -unit : (d < 0 ? unit : static_cast<T>(0));
          }
        }
      tile_sums[t] = sum;
      bwd.run(t, buf.data, buf.size, pcodes.data(), sgrad, fwd.alphas.data());
    }
  }
  double total = 0;
  for (const double v : tile_sums) total += v;  // in tile order: the same sum for any thread count
  return total;
}

// Sum each Gaussian's slot rows in slot order (deterministic).
template <typename T>
void reduce_slots(const torch::Tensor& gauss_starts, const torch::Tensor& slots, torch::Tensor& out) {
  const int64_t n = out.size(0);
  const int64_t R = out.dim() == 1 ? 1 : out.size(1);
  const int64_t* gs = gauss_starts.data_ptr<int64_t>();
  const T* s = slots.data_ptr<T>();
  T* o = out.data_ptr<T>();
  if (R == 1) {  // weight sums, pixel counts, the frozen backward: the sum in a register (the same order)
#pragma omp parallel for schedule(static) if (n >= kParallelMin)
    for (int64_t i = 0; i < n; ++i) {
      T sum = 0;
      for (int64_t p = gs[i]; p < gs[i + 1]; ++p) sum += s[p];
      o[i] = sum;
    }
    return;
  }
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

// The tile lists of a render: `bins_in` (tile_starts, sorted_gauss, sorted_slot, gauss_starts of an earlier
// composite_forward's state) reused when given, else made by binning. Reuse is exact when this render is the same
// view and geometry with opacities no higher (PAUP's masked render): each tile's own list is then a subsequence of
// the given one in the same order, and a Gaussian in the given list but not in its own can reach alpha_min at no
// pixel of the tile, so it is skipped there as the per-pixel test skips it (the same outputs and gradients, bit for
// bit).
template <typename T>
Bins tile_lists_for(const torch::Tensor& means2d, const torch::Tensor& depths, const torch::Tensor& radii,
                    const GaussRec<T>* recs, int64_t width, int64_t height, int64_t tile_size,
                    const std::vector<torch::Tensor>& bins_in) {
  if (bins_in.empty()) return bin_impl<T>(means2d, depths, radii, recs, width, height, tile_size);
  const Bins grid = tile_grid(width, height, tile_size);
  TORCH_CHECK(bins_in.size() == 4 && bins_in[0].numel() == grid.tiles_x * grid.tiles_y + 1 &&
                  bins_in[3].numel() == means2d.size(0) + 1 && bins_in[1].numel() == bins_in[2].numel() &&
                  bins_in[0].scalar_type() == torch::kInt64 && bins_in[1].scalar_type() == torch::kInt32 &&
                  bins_in[2].scalar_type() == torch::kInt64 && bins_in[3].scalar_type() == torch::kInt64,
              "the reused bins must be the tile lists of a render of this view and these Gaussians");
  for (const auto& t : bins_in) check_cpu(t, "bins");
  return bins_from(bins_in.data(), width, height, tile_size);
}

// Calls fn(std::integral_constant<int, NF>()) with the compiled channel count for F channels (0: any F).
template <typename Fn>
void with_channels(int64_t F, Fn&& fn) {
  if (F == 3) fn(std::integral_constant<int, 3>());
  else if (F == 4) fn(std::integral_constant<int, 4>());
  else if (F == 6) fn(std::integral_constant<int, 6>());
  else if (F == 2) fn(std::integral_constant<int, 2>());
  else fn(std::integral_constant<int, 0>());
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
// pixel_count [N] int32, then, when `for_backward`, the state the backward needs: final_t [H, W],
// tile_starts, sorted_gauss, sorted_slot, gauss_starts, the Gaussian records, pair_codes, tile_codes, and
// the code buffers. `bins_in`: an earlier render's tile lists, or none (tile_lists_for).
std::vector<torch::Tensor> composite_forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                             torch::Tensor feats, torch::Tensor depths, torch::Tensor radii,
                                             int64_t width, int64_t height, int64_t tile_size, double alpha_min,
                                             double alpha_max, double t_min, bool for_backward,
                                             std::vector<torch::Tensor> bins_in) {
  for (auto* p : {&means2d, &conics, &opacities, &feats, &depths, &radii}) check_cpu(*p, "input");
  const int64_t n = means2d.size(0);
  const int64_t F = feats.size(1);
  TORCH_CHECK(F >= 1 && F <= 64, "the CPU rasterizer composites 1 to 64 channels (depth included), got ", F);
  TORCH_CHECK(tile_size >= 1 && tile_size <= kMaxTile, "tile_size must be in [1, ", kMaxTile, "]");
  auto opts = means2d.options();
  auto render = torch::empty({height, width, F - 1}, opts);
  auto depth = torch::empty({height, width}, opts);
  auto alpha = torch::empty({height, width}, opts);
  auto final_t = torch::empty({height, width}, opts);
  auto weight_sum = torch::empty({n}, opts);
  auto pixel_count = torch::empty({n}, opts.dtype(torch::kInt32));
  Bins bins;
  Trace trace;
  torch::Tensor recs;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_forward", [&] {
    recs = gauss_records<scalar_t>(means2d, conics, opacities, std::log(alpha_min) - kLogMargin, width, height);
    bins = tile_lists_for<scalar_t>(means2d, depths, radii, records_of<scalar_t>(recs), width, height, tile_size,
                                    bins_in);
    const int64_t pairs = bins.sorted_gauss.size(0);
    auto slot_weight = torch::empty({pairs}, opts);
    auto slot_count = torch::empty({pairs}, opts.dtype(torch::kInt32));
    with_channels(F, [&](auto nf) {
      composite_forward_impl<scalar_t, decltype(nf)::value>(bins, records_of<scalar_t>(recs), feats, width, height,
                                                            alpha_min, alpha_max, t_min, render, depth, alpha,
                                                            final_t, slot_weight, slot_count,
                                                            for_backward ? &trace : nullptr);
    });
    reduce_slots<scalar_t>(bins.gauss_starts, slot_weight, weight_sum);
    reduce_slots<int32_t>(bins.gauss_starts, slot_count, pixel_count);
  });
  std::vector<torch::Tensor> out = {render, depth, alpha, weight_sum, pixel_count};
  if (for_backward) {
    for (const auto& t : {final_t, bins.tile_starts, bins.sorted_gauss, bins.sorted_slot, bins.gauss_starts, recs,
                          trace.pair_codes, trace.tile_codes})
      out.push_back(t);
    for (const auto& t : trace.codes) out.push_back(t);
  }
  return out;
}

// Takes composite_forward's state; returns grad means2d [N, 2], conics [N, 3], opacities [N], feats [N, F]
// (all_inputs false: only the opacities' gradient, the others are empty tensors).
std::vector<torch::Tensor> composite_backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                              torch::Tensor feats, int64_t width, int64_t height, int64_t tile_size,
                                              double alpha_max, std::vector<torch::Tensor> state,
                                              torch::Tensor grad_render, torch::Tensor grad_depth,
                                              torch::Tensor grad_alpha, bool all_inputs) {
  for (auto* p : {&means2d, &conics, &opacities, &feats, &grad_render, &grad_depth, &grad_alpha})
    check_cpu(*p, "input");
  TORCH_CHECK(state.size() >= 8, "composite_backward: incomplete forward state");
  const int64_t n = means2d.size(0);
  const int64_t F = feats.size(1);
  const torch::Tensor& final_t = state[0];
  const Bins bins = bins_from(state.data() + 1, width, height, tile_size);
  const torch::Tensor& recs = state[5];
  Trace trace;
  trace.pair_codes = state[6];
  trace.tile_codes = state[7];
  trace.codes.assign(state.begin() + 8, state.end());
  auto opts = means2d.options();
  const int64_t row = all_inputs ? 6 + F : 1;
  auto grads = all_inputs ? torch::empty({n, row}, opts) : torch::empty({n}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_backward", [&] {
    auto slot_grad = all_inputs ? torch::empty({bins.sorted_gauss.size(0), row}, opts)
                                : torch::empty({bins.sorted_gauss.size(0)}, opts);
    auto run = [&](auto nf, auto all) {
      composite_backward_impl<scalar_t, decltype(nf)::value, decltype(all)::value>(
          bins, trace, records_of<scalar_t>(recs), feats, width, height, alpha_max, final_t, grad_render, grad_depth,
          grad_alpha, slot_grad);
    };
    with_channels(F, [&](auto nf) {
      if (all_inputs) run(nf, std::true_type());
      else run(nf, std::false_type());
    });
    reduce_slots<scalar_t>(bins.gauss_starts, slot_grad, grads);
  });
  if (!all_inputs) {
    auto none = means2d.new_empty({0});
    return {none, none, grads, none};
  }
  using torch::indexing::Slice;
  return {grads.index({Slice(), Slice(0, 2)}), grads.index({Slice(), Slice(2, 5)}), grads.index({Slice(), 5}),
          grads.index({Slice(), Slice(6, torch::indexing::None)})};
}

// PAUP's masked render I' of frozen Gaussians (colours feats [N, C]) and its L1 distance to target [H, W, C], with
// the backward, in one pass per tile (the tile's codes never leave the cache, and no trace is kept). `bins_in`: the
// full render's tile lists, or none (tile_lists_for). Returns I' [H, W, C], mean |target - I'| (a 0-dim tensor) and
// its gradient in the opacities [N]: the backward of composite_backward (frozen) given dL/dI' = -sgn(target - I') /
// (H W C), as autograd gives it for (target - I').abs().mean().
std::vector<torch::Tensor> masked_l1(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                     torch::Tensor feats, torch::Tensor depths, torch::Tensor radii, int64_t width,
                                     int64_t height, int64_t tile_size, double alpha_min, double alpha_max,
                                     double t_min, std::vector<torch::Tensor> bins_in, torch::Tensor target) {
  for (auto* p : {&means2d, &conics, &opacities, &feats, &depths, &radii, &target}) check_cpu(*p, "input");
  const int64_t n = means2d.size(0), C = feats.size(1);
  TORCH_CHECK(C >= 1 && C <= 63, "masked_l1: 1 to 63 channels, got ", C);
  TORCH_CHECK(tile_size >= 1 && tile_size <= kMaxTile, "tile_size must be in [1, ", kMaxTile, "]");
  TORCH_CHECK(target.dim() == 3 && target.size(0) == height && target.size(1) == width && target.size(2) == C &&
                  target.scalar_type() == feats.scalar_type(),
              "masked_l1: target must be [H, W, C] of the features' dtype");
  auto opts = means2d.options();
  auto image = torch::empty({height, width, C}, opts);
  auto grad = torch::empty({n}, opts);
  double total = 0;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "masked_l1", [&] {
    using T = scalar_t;
    const torch::Tensor recs =
        gauss_records<T>(means2d, conics, opacities, std::log(alpha_min) - kLogMargin, width, height);
    const GaussRec<T>* rp = records_of<T>(recs);
    const Bins bins = tile_lists_for<T>(means2d, depths, radii, rp, width, height, tile_size, bins_in);
    auto slot_grad = torch::empty({bins.sorted_gauss.size(0)}, opts);
    with_channels(C, [&](auto nf) {
      total = masked_l1_impl<T, decltype(nf)::value>(bins, rp, feats, width, height, alpha_min, alpha_max, t_min,
                                                     target, image, slot_grad);
    });
    reduce_slots<T>(bins.gauss_starts, slot_grad, grad);
  });
  return {image, torch::tensor(total / static_cast<double>(height * width * C), opts), grad};
}

int num_threads() {
#ifdef _OPENMP
  return omp_get_max_threads();
#else
  return 1;
#endif
}
