// The Python module of the compiled CPU kernels: the rasterizer (cpu_rasterizer.cpp), the VM field read
// (vm_field.cpp), the Gaussians' SH colours (sh_colors.cpp), PAUP's phi (floater_mlp.cpp), the D-SSIM loss's SSIM
// (ssim.cpp), UW-3DGS's L_z (depth_consistency.cpp), the medium compositor (medium_compositing.cpp) and the direction
// medium's MLP (direction_mlp.cpp), built together by uw3dgs/render/cpu_backend.py.
#include <torch/extension.h>

#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                           torch::Tensor opacities, torch::Tensor viewmat, torch::Tensor K,
                                           int64_t width, int64_t height, double near, double far, double eps2d,
                                           double alpha_min);
std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                            torch::Tensor viewmat, torch::Tensor K, int64_t width, int64_t height,
                                            double near, double far, double eps2d, torch::Tensor g_means2d,
                                            torch::Tensor g_conics, torch::Tensor g_depths);
std::vector<torch::Tensor> composite_forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                             torch::Tensor feats, torch::Tensor depths, torch::Tensor radii,
                                             int64_t width, int64_t height, int64_t tile_size, double alpha_min,
                                             double alpha_max, double t_min, bool for_backward,
                                             std::vector<torch::Tensor> bins_in);
std::vector<torch::Tensor> composite_backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                              torch::Tensor feats, int64_t width, int64_t height, int64_t tile_size,
                                              double alpha_max, std::vector<torch::Tensor> state,
                                              torch::Tensor grad_render, torch::Tensor grad_depth,
                                              torch::Tensor grad_alpha, bool all_inputs);
std::vector<torch::Tensor> masked_l1(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                     torch::Tensor feats, torch::Tensor depths, torch::Tensor radii, int64_t width,
                                     int64_t height, int64_t tile_size, double alpha_min, double alpha_max,
                                     double t_min, std::vector<torch::Tensor> bins_in, torch::Tensor target);
int num_threads() {
#ifdef _OPENMP
  return omp_get_max_threads();
#else
  return 1;
#endif
}
std::vector<torch::Tensor> vm_fields_forward(torch::Tensor u, std::vector<torch::Tensor> planes,
                                             std::vector<torch::Tensor> lines, std::vector<torch::Tensor> basis,
                                             std::vector<torch::Tensor> bias);
std::vector<std::vector<torch::Tensor>> vm_fields_backward(torch::Tensor u, std::vector<torch::Tensor> planes,
                                                           std::vector<torch::Tensor> lines,
                                                           std::vector<torch::Tensor> basis,
                                                           std::vector<torch::Tensor> bias, torch::Tensor pre,
                                                           torch::Tensor grad_out);
torch::Tensor vm_products_forward(torch::Tensor u, std::vector<torch::Tensor> planes, std::vector<torch::Tensor> lines,
                                  std::vector<int64_t> axes, bool summed);
std::vector<torch::Tensor> vm_products_backward(torch::Tensor u, std::vector<torch::Tensor> planes,
                                                std::vector<torch::Tensor> lines, std::vector<int64_t> axes,
                                                bool summed, torch::Tensor grad_out);
torch::Tensor sh_colors_forward(torch::Tensor means, torch::Tensor center, torch::Tensor dc, torch::Tensor rest,
                                int64_t degree);
std::vector<torch::Tensor> sh_colors_backward(torch::Tensor means, torch::Tensor center, torch::Tensor dc,
                                              torch::Tensor rest, int64_t degree, torch::Tensor grad);
torch::Tensor floater_mlp_forward(torch::Tensor x, torch::Tensor w1, torch::Tensor b1, torch::Tensor w2,
                                  torch::Tensor b2);
std::vector<torch::Tensor> floater_mlp_backward(torch::Tensor x, torch::Tensor w1, torch::Tensor b1, torch::Tensor w2,
                                                torch::Tensor b2, torch::Tensor m, torch::Tensor grad);
std::vector<torch::Tensor> ssim_forward(torch::Tensor pred, torch::Tensor gt, torch::Tensor taps, double c1,
                                        double c2, bool need_grad);
torch::Tensor ssim_backward(torch::Tensor pred, torch::Tensor gt, torch::Tensor grads, torch::Tensor taps,
                            torch::Tensor grad_sum);
std::vector<torch::Tensor> depth_consistency_forward(torch::Tensor radii, torch::Tensor means2d, torch::Tensor means,
                                                     torch::Tensor center, torch::Tensor ranges,
                                                     torch::Tensor weights);
std::vector<torch::Tensor> depth_consistency_backward(torch::Tensor means, torch::Tensor center, torch::Tensor ranges,
                                                      torch::Tensor gauss, torch::Tensor pixel, torch::Tensor coef,
                                                      double grad);
std::vector<torch::Tensor> direction_mlp_forward(torch::Tensor x, torch::Tensor w1, torch::Tensor b1,
                                                 torch::Tensor w2, torch::Tensor b2, double density_bias,
                                                 bool for_backward);
std::vector<torch::Tensor> direction_mlp_backward(torch::Tensor x, torch::Tensor w1, torch::Tensor b1,
                                                  torch::Tensor w2, torch::Tensor b2, torch::Tensor raw,
                                                  torch::Tensor hidden, torch::Tensor grad, double density_bias);
std::vector<torch::Tensor> medium_composite_forward(torch::Tensor means2d, torch::Tensor conics,
                                                    torch::Tensor opacities, torch::Tensor feats,
                                                    torch::Tensor depths, torch::Tensor radii, torch::Tensor medium,
                                                    int64_t width, int64_t height, int64_t tile_size,
                                                    double alpha_min, double alpha_max, double t_min,
                                                    bool for_backward);
std::vector<torch::Tensor> medium_composite_backward(torch::Tensor means2d, torch::Tensor conics,
                                                     torch::Tensor opacities, torch::Tensor feats,
                                                     torch::Tensor medium, int64_t width, int64_t height,
                                                     int64_t tile_size, double alpha_max,
                                                     std::vector<torch::Tensor> state, torch::Tensor g_restored,
                                                     torch::Tensor g_depth, torch::Tensor g_alpha,
                                                     torch::Tensor g_object, torch::Tensor g_water);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("project_forward", &project_forward);
  m.def("project_backward", &project_backward);
  m.def("composite_forward", &composite_forward);
  m.def("composite_backward", &composite_backward);
  m.def("masked_l1", &masked_l1);
  m.def("num_threads", &num_threads);
  m.def("vm_fields_forward", &vm_fields_forward);
  m.def("vm_fields_backward", &vm_fields_backward);
  m.def("vm_products_forward", &vm_products_forward);
  m.def("vm_products_backward", &vm_products_backward);
  m.def("sh_colors_forward", &sh_colors_forward);
  m.def("sh_colors_backward", &sh_colors_backward);
  m.def("floater_mlp_forward", &floater_mlp_forward);
  m.def("floater_mlp_backward", &floater_mlp_backward);
  m.def("ssim_forward", &ssim_forward);
  m.def("ssim_backward", &ssim_backward);
  m.def("depth_consistency_forward", &depth_consistency_forward);
  m.def("depth_consistency_backward", &depth_consistency_backward);
  m.def("direction_mlp_forward", &direction_mlp_forward);
  m.def("direction_mlp_backward", &direction_mlp_backward);
  m.def("medium_composite_forward", &medium_composite_forward);
  m.def("medium_composite_backward", &medium_composite_backward);
}
