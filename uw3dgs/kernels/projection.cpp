// Projection of 3D Gaussians to the screen (means2d, conics, depths, opacity-aware radii) and its hand-written
// backward, one Gaussian per iteration, parallel across Gaussians.
#include "common.h"

namespace uw3dgs_kernels {
namespace {
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

}  // namespace
}  // namespace uw3dgs_kernels

using namespace uw3dgs_kernels;

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
