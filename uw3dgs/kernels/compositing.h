// Alpha compositing of the depth-sorted Gaussians of each tile, forward and backward, as per-tile structs
// (TileForward, TileBackward) that composite_forward / composite_backward / masked_l1 share, and that a sibling
// compositor (another image formation between the same sorted Gaussians) reuses with the same projection and
// binning. The forward records which pixels each Gaussian blended, so the backward replays exactly those.
#pragma once

#include "binning.h"
#include "simd.h"

namespace uw3dgs_kernels {
struct Trace {
  torch::Tensor pair_codes;               // [pairs] int32: codes of each (tile, Gaussian) pair
  torch::Tensor tile_codes;               // [tiles, 3] int64: thread buffer, first, end
  std::vector<torch::Tensor> codes;       // per thread buffer, int32
};

// What a compositing forward hands its backward (composite_forward's and its siblings'), as the tensors after its
// images: final_t, the tile lists (4), the Gaussian records, pair_codes, tile_codes, then the code buffers.
struct ForwardState {
  torch::Tensor final_t, recs;
  Bins bins;
  Trace trace;
};

inline void push_state(std::vector<torch::Tensor>& out, const torch::Tensor& final_t, const Bins& bins,
                       const torch::Tensor& recs, const Trace& trace) {
  for (const auto& t : {final_t, bins.tile_starts, bins.sorted_gauss, bins.sorted_slot, bins.gauss_starts, recs,
                        trace.pair_codes, trace.tile_codes})
    out.push_back(t);
  for (const auto& t : trace.codes) out.push_back(t);
}

inline ForwardState state_of(const std::vector<torch::Tensor>& state, int64_t width, int64_t height,
                             int64_t tile_size, const char* backward) {
  TORCH_CHECK(state.size() >= 8, backward, ": incomplete forward state");
  ForwardState s;
  s.final_t = state[0];
  s.bins = bins_from(state.data() + 1, width, height, tile_size);
  s.recs = state[5];
  s.trace.pair_codes = state[6];
  s.trace.tile_codes = state[7];
  s.trace.codes.assign(state.begin() + 8, state.end());
  return s;
}

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

// What a sibling compositor adds to the blending of TileForward / TileBackward (another image formation over the
// same weights w = alpha T): nothing here, so 3DGS's compositing compiles as if there were no hook. A sibling's
// hook (medium_compositing.cpp) is copied into each thread's tile and has these members:
//   forward:  begin(rect) before a tile; blend(p, w, gaussian) per blended chunk (tile-plane offset p, the chunk's
//             weights w, 0 in lanes not blended); end(tile) after it, writing its own images;
//   backward: begin(tile) once the tile's planes are loaded; gaussian(id) before a Gaussian's chunks; per chunk
//             dweight(p, w) -> its extra dL/dw per lane, then geometry(G, dx, dy, rec) with dL/dpower G;
//             finish(row) after the Gaussian's chunks: kRow more values per slot row after TileBackward's 6 + F
//             (it may add to the features' gradients there); end(tile) after the tile.
struct NoExtra {
  static constexpr int kRow = 0;
};

// The compositing forward of one tile at a time, with one thread's scratch: what composite_forward and PAUP's
// masked L1 (masked_l1) share. After run(t): Tr holds the tile's final transmittance and acc its F channels then
// the alpha sum (channel-major planes of `plane` values, rows padded to whole chunks, `stride` apart).
template <typename T, int NF, typename Extra = NoExtra>
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
  Extra extra;  // a sibling compositor's blending (NoExtra: none)
  static constexpr bool kExtra = !std::is_same_v<Extra, NoExtra>;

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
        if constexpr (kExtra) extra.blend(p, wgt, ids[j0 + jj]);
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

// `extra`: a sibling compositor's hook (NoExtra: none), copied into each thread's tile; begin(rect) before each
// tile, end(rect) after it (it writes its own images).
template <typename T, int NF, typename Extra = NoExtra>
void composite_forward_impl(const Bins& bins, const GaussRec<T>* recs, const torch::Tensor& feats, int64_t width,
                            int64_t height, double alpha_min, double alpha_max, double t_min,
                            torch::Tensor& render, torch::Tensor& depth, torch::Tensor& alpha_img,
                            torch::Tensor& final_t, torch::Tensor& slot_weight, torch::Tensor& slot_count,
                            Trace* trace, const Extra& extra = Extra()) {
  constexpr bool kExtra = !std::is_same_v<Extra, NoExtra>;
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
    TileForward<T, NF, Extra> tile(bins, recs, feats, width, height, alpha_min, alpha_max, t_min);
    if constexpr (kExtra) tile.extra = extra;
    const int64_t F = tile.F, plane = tile.plane;
    CodeBuf* buf = trace ? &bufs[omp_get_thread_num()] : nullptr;
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      if (buf) {
        tcodes[3 * t] = omp_get_thread_num();
        tcodes[3 * t + 1] = buf->size;
      }
      if constexpr (kExtra) tile.extra.begin(tile_rect(bins, t, width, height));
      tile.run(t, sw, sc, pcodes, buf);
      if constexpr (kExtra) tile.extra.end(tile);
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
template <typename T, int NF, bool kAll, typename Extra = NoExtra>
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
  Extra extra;  // a sibling compositor's blending (NoExtra: none)
  static constexpr bool kExtra = !std::is_same_v<Extra, NoExtra>;

  TileBackward(const Bins& bins_, const GaussRec<T>* recs_, const torch::Tensor& feats, double alpha_max_d)
      : bins(bins_), recs(recs_), ft(feats.data_ptr<T>()), F(NF > 0 ? NF : feats.size(1)), ts(bins_.tile),
        n_cols((ts + kLanes - 1) / kLanes), stride(n_cols * kLanes), plane(ts * stride),
        row(kAll ? 6 + F + Extra::kRow : 1),
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
      if constexpr (kExtra) extra.gaussian(ids[j]);
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
        if constexpr (kExtra) gsum += extra.dweight(p, wgt);
        const V wg = wgt * gsum;
        const V s = vload<V>(&S[p]);
        V G = wg - s * alpha / transmit;
        vstore(&S[p], V(m ? s + wg : s));
        G = (m & (alpha < alpha_max)) ? G : V{};
        m0 += G;
        if constexpr (kExtra) extra.geometry(G, dx, dy, g);
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
        if constexpr (kExtra) extra.finish(out);
      } else {
        out[0] = g_opacity;
      }
    }
  }
};

// `extra`: as composite_forward_impl's (begin after the tile's planes are loaded, end after its run); with one,
// tiles without Gaussians are visited too (their pixels may still have gradients to write).
template <typename T, int NF, bool kAll, typename Extra = NoExtra>
void composite_backward_impl(const Bins& bins, const Trace& trace, const GaussRec<T>* recs,
                             const torch::Tensor& feats, int64_t width, int64_t height, double alpha_max,
                             const torch::Tensor& final_t, const torch::Tensor& grad_render,
                             const torch::Tensor& grad_depth, const torch::Tensor& grad_alpha,
                             torch::Tensor& slot_grad, const Extra& extra = Extra()) {
  constexpr bool kExtra = !std::is_same_v<Extra, NoExtra>;
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
    TileBackward<T, NF, kAll, Extra> tile(bins, recs, feats, alpha_max);
    if constexpr (kExtra) tile.extra = extra;
    const int64_t F = tile.F, plane = tile.plane;
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      if (tstart[t + 1] == tstart[t] && !kExtra) continue;
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
      if constexpr (kExtra) tile.extra.begin(tile);
      tile.run(t, codes[tcodes[3 * t]], tcodes[3 * t + 2], pcodes, sgrad);
      if constexpr (kExtra) tile.extra.end(tile);
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

// Calls fn(std::integral_constant<int, NF>()) with the compiled channel count for F channels (0: any F).
template <typename Fn>
void with_channels(int64_t F, Fn&& fn) {
  if (F == 3) fn(std::integral_constant<int, 3>());
  else if (F == 4) fn(std::integral_constant<int, 4>());
  else if (F == 6) fn(std::integral_constant<int, 6>());
  else if (F == 2) fn(std::integral_constant<int, 2>());
  else fn(std::integral_constant<int, 0>());
}

// A compositing forward's images: render [H, W, F - 1] (the features but the last), depth [H, W] (the last),
// alpha and final transmittance [H, W]; per Gaussian its weight sum [N] and blended pixel count [N] int32.
struct ForwardImages {
  torch::Tensor render, depth, alpha, final_t, weight_sum, pixel_count;
};

// composite_forward's work, shared with its siblings: the Gaussian records, the tile lists (`bins_in`'s when given,
// tile_lists_for), the compositing of feats [N, F] (NF: F as compiled, 0: any) with the hook make_extra(bins)
// returns (NoExtra: none), each Gaussian's weight sum and pixel count. The images into `images`; the backward's
// state appended to `state` when `for_backward` (push_state).
template <typename T, int NF, typename MakeExtra>
void composite_forward_all(const torch::Tensor& means2d, const torch::Tensor& conics, const torch::Tensor& opacities,
                           const torch::Tensor& feats, const torch::Tensor& depths, const torch::Tensor& radii,
                           int64_t width, int64_t height, int64_t tile_size, double alpha_min, double alpha_max,
                           double t_min, const std::vector<torch::Tensor>& bins_in, bool for_backward,
                           ForwardImages& images, std::vector<torch::Tensor>& state, MakeExtra&& make_extra) {
  const int64_t n = means2d.size(0);
  const auto opts = means2d.options();
  images.render = torch::empty({height, width, feats.size(1) - 1}, opts);
  images.depth = torch::empty({height, width}, opts);
  images.alpha = torch::empty({height, width}, opts);
  images.final_t = torch::empty({height, width}, opts);
  images.weight_sum = torch::empty({n}, opts);
  images.pixel_count = torch::empty({n}, opts.dtype(torch::kInt32));
  const torch::Tensor recs =
      gauss_records<T>(means2d, conics, opacities, std::log(alpha_min) - kLogMargin, width, height);
  const Bins bins = tile_lists_for<T>(means2d, depths, radii, records_of<T>(recs), width, height, tile_size, bins_in);
  const int64_t pairs = bins.sorted_gauss.size(0);
  auto slot_weight = torch::empty({pairs}, opts);
  auto slot_count = torch::empty({pairs}, opts.dtype(torch::kInt32));
  Trace trace;
  composite_forward_impl<T, NF>(bins, records_of<T>(recs), feats, width, height, alpha_min, alpha_max, t_min,
                                images.render, images.depth, images.alpha, images.final_t, slot_weight, slot_count,
                                for_backward ? &trace : nullptr, make_extra(bins));
  reduce_slots<T>(bins.gauss_starts, slot_weight, images.weight_sum);
  reduce_slots<int32_t>(bins.gauss_starts, slot_count, images.pixel_count);
  if (for_backward) push_state(state, images.final_t, bins, recs, trace);
}
}  // namespace uw3dgs_kernels
