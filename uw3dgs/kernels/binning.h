// Binning: (tile, Gaussian) pairs, sorted by tile then depth, and the slots their gradients are written to.
#pragma once

#include "footprint.h"

namespace uw3dgs_kernels {
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
}  // namespace uw3dgs_kernels
