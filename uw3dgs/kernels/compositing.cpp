// The compositing stage's entry points: composite_forward / composite_backward (3DGS alpha blending of any number
// of feature channels) and masked_l1 (PAUP's masked render of frozen Gaussians with its L1, in one pass).
#include "compositing.h"

using namespace uw3dgs_kernels;

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
  const int64_t F = feats.size(1);
  TORCH_CHECK(F >= 1 && F <= 64, "the CPU rasterizer composites 1 to 64 channels (depth included), got ", F);
  TORCH_CHECK(tile_size >= 1 && tile_size <= kMaxTile, "tile_size must be in [1, ", kMaxTile, "]");
  ForwardImages images;
  std::vector<torch::Tensor> state;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_forward", [&] {
    with_channels(F, [&](auto nf) {
      composite_forward_all<scalar_t, decltype(nf)::value>(
          means2d, conics, opacities, feats, depths, radii, width, height, tile_size, alpha_min, alpha_max, t_min,
          bins_in, for_backward, images, state, [](const Bins&) { return NoExtra(); });
    });
  });
  std::vector<torch::Tensor> out = {images.render, images.depth, images.alpha, images.weight_sum,
                                    images.pixel_count};
  out.insert(out.end(), state.begin(), state.end());
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
  const int64_t n = means2d.size(0);
  const int64_t F = feats.size(1);
  const ForwardState saved = state_of(state, width, height, tile_size, "composite_backward");
  const torch::Tensor &final_t = saved.final_t, &recs = saved.recs;
  const Bins& bins = saved.bins;
  const Trace& trace = saved.trace;
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
