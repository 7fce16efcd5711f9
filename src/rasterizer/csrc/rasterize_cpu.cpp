// CPU (OpenMP + 8-lane SIMD) Gaussian-splat rasterizer with a hand-written backward.
//
// Semantics: the original 3DGS CUDA rasterizer, as implemented by src/rasterizer/torch_ref.py:
//   * visible splats are composited front to back in a stable depth order;
//   * a splat touches the 16x16 tiles of its 3DGS getRect (centre means2d - 0.5, radius);
//   * pixel (i, j) is sampled at its centre (i + 0.5, j + 0.5);
//   * power = -0.5 (a dx^2 + c dy^2) - b dx dy with d = pixel - mean; power > 0 is skipped;
//   * alpha = min(0.99, o exp(power)), skipped if alpha < 1/255;
//   * a pixel stops before the splat that would take its transmittance T below 1e-4.
// With the accumulated features acc = sum_j f_j alpha_j T_j ([H, W, NF]; NF = colour channels + 1
// for depth), the outputs are colour = acc[..., :C] + T_final bg, alpha = 1 - T_final and
// depth = acc[..., C], computed exactly as torch_ref does (same float32 operations).
//
// Pipeline (forward): per-splat records and 3DGS getRect tile rects (float32, bit-identical to
// torch's tile_rects; original order, sequential) -> the first depth window: the visible splats
// nearer than a sampled depth quantile, stable LSD radix sort -> binning (a half-row mask per
// (splat, tile); stable counting sort by tile, O(pairs)) and compositing -> the splats behind it
// whose rect still meets a tile with a half-row compositing (one sequential scan of the rects),
// stably sorted -> further windows of geometrically growing size, each: records gathered into
// depth order (one cache line each), binning restricted to the tiles' half-rows still compositing,
// compositing, with per-tile state carried across windows. Once a tile's pixels have all
// terminated (T < 1e-4 would be crossed), no later splat is binned onto it: in scenes that
// saturate, most splats behind the opaque front are neither sorted, binned nor stored, and their
// (splat, tile) pairs are visited by neither the forward, the backward nor the reduction. The
// result is bit-identical to sorting and binning everything at once (tested, with depth ties).
//
// Work decomposition: one OpenMP task per 16x16 tile (dynamic schedule, longest lists first).
// Inside a tile, splats are the outer loop and pixels the inner loop: 32 "half-rows" of 8 pixels,
// one SIMD vector each. Exact culling (identical results, only fewer evaluations):
//   * only half-rows whose pixel-centre x-range meets the chord of the splat's alpha >= 1/255
//     ellipse  d^T conic d <= 2 ln(255 o)  (inflated to cover float rounding) on that row are
//     evaluated; a tile of the rect where no half-row qualifies is not binned at all;
//   * forward: half-rows whose 8 pixels have all terminated are skipped, and a tile stops when all
//     its pixels have; backward: half-rows whose last contributor is before the splat are skipped;
//   * in both, a half-row whose pixels inside the splat's (inflated) ellipse have all terminated
//     (forward) or all have their last contributor before the splat (backward) is skipped after
//     evaluating the power only (no exp): at an object's silhouette most half-rows never terminate
//     as a whole, while the splats behind the surface evaluated there blend nowhere.
// Skipped (pixel, splat) pairs would have had alpha = 0 (masked), so images and gradients are
// bit-identical with culling on or off (tested).
//
// Backward: per tile, the list is walked back to front from the last contributor as in the 3DGS
// CUDA backward (T recovered by division; D = sum over later splats of w (g . f) + dL/dT_final
// T_final carries the accumulated-colour and background terms). Each processed (splat, tile)
// slot gets a record of partial sums over the tile's pixels; records are then reduced per splat
// in a fixed (tile) order: bit-identical results for any thread count or schedule, no atomics.
// Memory is O(pixels + splats + tile pairs).
//
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <limits>
#include <vector>

#include "simd.h"

namespace {

using namespace sf::simd;

constexpr int TILE = 16;
constexpr int TPIX = TILE * TILE;  // pixels per tile
constexpr int NHR = 32;            // half-rows (8-pixel vectors) per tile
constexpr float ALPHA_MAX = 0.99f;
constexpr float ALPHA_MIN = 1.0f / 255.0f;
constexpr float T_MIN = 1e-4f;
constexpr int PREFETCH = 8;  // splats ahead in a tile list (and in the gradient reduction's gather)
constexpr int64_t MIN_PAIRS_PARALLEL = 1024;  // fewer (splat, tile) pairs: one thread (~0.1 ms of work)
constexpr int64_t MIN_SORT_CHUNK = 16384;  // depth sort / key selection: elements per thread at least
// Depth windows of the forward: the first holds ~max(WINDOW_MIN, M / WINDOW_FIRST_DIV) of the M
// visible splats, each next one twice as many rows (at most ~log2(WINDOW_FIRST_DIV) + 1 windows) ...
constexpr int64_t WINDOW_MIN = 16384;
constexpr int64_t WINDOW_FIRST_DIV = 16;
// ... unless fewer than 1 / WINDOW_DEAD_DIV of the image's half-rows have terminated after a window:
// then the rest is binned in one window.
constexpr int64_t WINDOW_DEAD_DIV = 8;
// The first window is the splats nearer than a depth quantile estimated from ~WINDOW_SAMPLE keys.
constexpr int64_t WINDOW_SAMPLE = 8192;
constexpr int NSTATS = 17;  // see forward()

// Packed per-splat record (depth-sorted order), one cache line.
struct alignas(64) Geo {
  float mx, my;    // means2d (pixel coordinates, centres at i + 0.5)
  float a, b, c;   // conic: power = -0.5 (a dx^2 + c dy^2) - b dx dy
  float o;         // opacity
  float thr;       // cull threshold on Q = d^T conic d (inflated 2 ln(255 o)); <0: never blends; inf: no cull
  float det;       // a c - b^2 (computed in double)
  float inv_a;     // 1 / a
  int16_t rect[4]; // 3DGS tile rect x0, y0, x1, y1
  float f[4];      // features when NF == 4 (colour + depth), else unused
  float ry;        // half-height of the cull ellipse (pixels, inflated); < 0: empty
};
static_assert(sizeof(Geo) == 64, "Geo must be one cache line");

template <typename T>
struct AlignedBuf {
  T* p = nullptr;
  explicit AlignedBuf(size_t n) {
    size_t bytes = ((n * sizeof(T) + 63) / 64) * 64;
    p = static_cast<T*>(std::aligned_alloc(64, bytes > 0 ? bytes : 64));
    TORCH_CHECK(p != nullptr, "rasterize_cpu: out of memory");
  }
  ~AlignedBuf() { std::free(p); }
  AlignedBuf(const AlignedBuf&) = delete;
  AlignedBuf& operator=(const AlignedBuf&) = delete;
};

// Grow-only scratch buffer kept per calling thread across calls: the per-splat buffers of every
// render are this large, and fresh allocations of that size cost a page fault per 4 KiB on each
// call. Holds at most the largest request so far (never shrinks while the thread lives).
template <typename T>
struct Scratch {
  T* p = nullptr;
  size_t cap = 0;
  T* get(size_t n) {
    if (n > cap) {
      std::free(p);
      cap = std::max<size_t>(n, 1);
      const size_t bytes = ((cap * sizeof(T) + 63) / 64) * 64;
      p = static_cast<T*>(std::aligned_alloc(64, bytes));
      TORCH_CHECK(p != nullptr, "rasterize_cpu: out of memory");
    }
    return p;
  }
  Scratch() = default;
  Scratch(const Scratch&) = delete;
  Scratch& operator=(const Scratch&) = delete;
  ~Scratch() { std::free(p); }
};

// Prevents -ffast-math reassociation: the compiler cannot see through the empty asm, so the value is
// computed exactly as written before it (kept in a vector register on x86, else in memory).
inline float opaque(float x) {
#if defined(__SSE__)
  asm volatile("" : "+x"(x));
#else
  asm volatile("" : "+m"(x));
#endif
  return x;
}

int num_threads() { return std::max(1, at::get_num_threads()); }

// Wall-clock and process CPU time stamps (seconds) for the stage statistics.
struct Stamp {
  double wall, cpu;
};
inline Stamp now() {
  timespec ts;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return {omp_get_wtime(), static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec)};
}
// stats[k] = wall ms, stats[k + 6] = CPU ms (all threads) of the interval(s)
inline void put_ms(double* st, int k, double wall, double cpu) {
  st[k] = 1e3 * wall;
  st[k + 6] = 1e3 * cpu;
}

// ---------------------------------------------------------------------------------------------
// Depth order: stable LSD radix sort of the depth keys, equal to torch.argsort(depths[vis],
// stable=True) mapped back to indices.

// Order-preserving unsigned key of a float depth (IEEE order -> unsigned order; handles
// negatives too, although visible depths are > 0.2).
inline uint32_t depth_key(float d) {
  uint32_t u;
  std::memcpy(&u, &d, 4);
  return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}

// Threads for n elements split into chunks of at least MIN_SORT_CHUNK (1 .. nt).
inline int sort_team(int nt, int64_t n) {
  return static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(nt, n / MIN_SORT_CHUNK)));
}

// Stable LSD radix sort (8-bit digits) of idx by key; both are permuted. Passes whose digit is the
// same for every element are skipped. Each pass splits the array into nt contiguous chunks: a
// histogram per chunk, offsets digit-major then chunk-minor (so equal digits keep their order:
// stable, and the same permutation for any nt), then every chunk scatters its elements.
void radix_sort(std::vector<uint32_t>& key, std::vector<int32_t>& idx, int nt) {
  constexpr int BITS = 8;
  constexpr uint32_t RADIX = 1u << BITS;
  constexpr int PASSES = 32 / BITS;
  const size_t m = key.size();
  if (m == 0) return;
  nt = sort_team(nt, static_cast<int64_t>(m));
  // the digits that vary: the bits where some key differs from the first (a pass over a constant
  // digit moves nothing)
  uint32_t differ = 0;
  for (size_t i = 1; i < m; ++i) differ |= key[i] ^ key[0];
  std::vector<int> passes;
  for (int p = 0; p < PASSES; ++p)
    if ((differ >> (p * BITS)) & (RADIX - 1)) passes.push_back(p);
  if (passes.empty()) return;
  std::vector<uint32_t> key2(m);
  std::vector<int32_t> idx2(m);
  std::vector<uint32_t> cnt(static_cast<size_t>(nt) * RADIX);  // [chunk][digit]
  for (size_t q = 0; q < passes.size(); ++q) {
    const int shift = passes[q] * BITS;
    const bool last_pass = q + 1 == passes.size();  // no later pass reads the keys
    const uint32_t* kin = key.data();
    const int32_t* iin = idx.data();
#pragma omp parallel num_threads(nt)
    {
#pragma omp for schedule(static, 1)
      for (int t = 0; t < nt; ++t) {
        uint32_t* c = cnt.data() + static_cast<size_t>(t) * RADIX;
        std::fill(c, c + RADIX, 0u);
        for (size_t i = m * t / nt, hi = m * (t + 1) / nt; i < hi; ++i) c[(kin[i] >> shift) & (RADIX - 1)]++;
      }
#pragma omp single
      {
        uint32_t sum = 0;
        for (uint32_t r = 0; r < RADIX; ++r)
          for (int t = 0; t < nt; ++t) {
            uint32_t& c = cnt[static_cast<size_t>(t) * RADIX + r];
            const uint32_t n = c;
            c = sum;
            sum += n;
          }
      }  // implicit barrier
#pragma omp for schedule(static, 1)
      for (int t = 0; t < nt; ++t) {
        uint32_t* c = cnt.data() + static_cast<size_t>(t) * RADIX;
        const size_t lo = m * t / nt, hi = m * (t + 1) / nt;
        if (last_pass) {
          for (size_t i = lo; i < hi; ++i) idx2[c[(kin[i] >> shift) & (RADIX - 1)]++] = iin[i];
        } else {
          for (size_t i = lo; i < hi; ++i) {
            const uint32_t pos = c[(kin[i] >> shift) & (RADIX - 1)]++;
            key2[pos] = kin[i];
            idx2[pos] = iin[i];
          }
        }
      }
    }
    if (!last_pass) key.swap(key2);
    idx.swap(idx2);
  }
}

// The visible splats s with lo <= depth_key(depth[s]) < hi and keep(s), as (key, index) pairs in
// the original order: nt contiguous chunks scanned in parallel, then concatenated in order.
template <typename Keep>
void select_keys(const float* depth, const bool* visible, int64_t n, uint64_t lo, uint64_t hi, const Keep& keep,
                 int nt, std::vector<uint32_t>& key, std::vector<int32_t>& idx) {
  nt = sort_team(nt, n);
  key.resize(static_cast<size_t>(n));  // chunk t compacts into [n t / nt, ...) (branch-free writes)
  idx.resize(static_cast<size_t>(n));
  std::vector<int64_t> kept(nt);
#pragma omp parallel for num_threads(nt) schedule(static, 1)
  for (int t = 0; t < nt; ++t) {
    const int64_t s0 = n * t / nt, s1 = n * (t + 1) / nt;
    uint32_t* kp = key.data() + s0;
    int32_t* ip = idx.data() + s0;
    int64_t c = 0;
    for (int64_t s = s0; s < s1; ++s) {
      const uint32_t k = depth_key(depth[s]);
      kp[c] = k;
      ip[c] = static_cast<int32_t>(s);
      c += visible[s] & (k >= lo) & (k < hi) & keep(s);
    }
    kept[t] = c;
  }
  int64_t o = kept[0];  // close the gaps between the chunks, in order
  for (int t = 1; t < nt; ++t) {
    const int64_t s0 = n * t / nt;
    std::copy(key.begin() + s0, key.begin() + s0 + kept[t], key.begin() + o);
    std::copy(idx.begin() + s0, idx.begin() + s0 + kept[t], idx.begin() + o);
    o += kept[t];
  }
  key.resize(static_cast<size_t>(o));
  idx.resize(static_cast<size_t>(o));
}

// The visible splats (original indices) whose depth key k satisfies lo <= k < hi, in stable depth
// order (ties keep the original order). [0, 2^32) selects every visible splat.
std::vector<int32_t> depth_order_range(const float* depth, const bool* visible, int64_t n, uint64_t lo,
                                       uint64_t hi, int nt) {
  std::vector<uint32_t> key;
  std::vector<int32_t> idx;
  select_keys(depth, visible, n, lo, hi, [](int64_t) { return true; }, nt, key, idx);
  radix_sort(key, idx, nt);
  return idx;
}

// Stable depth order of the visible splats (original indices).
std::vector<int32_t> depth_order(const float* depth, const bool* visible, int64_t n, int nt) {
  return depth_order_range(depth, visible, n, 0, uint64_t(1) << 32, nt);
}

// A depth key below which roughly `target` of the m visible splats lie: the matching quantile of
// a strided sample of the keys (any value gives the same image; it only sizes the first window),
// and above the nearest sampled key. Returns 2^32 (every splat) when target >= m.
uint64_t window_threshold(const float* depth, const bool* visible, int64_t n, int64_t m, int64_t target) {
  if (target >= m) return uint64_t(1) << 32;
  const int64_t stride = std::max<int64_t>(1, n / WINDOW_SAMPLE);
  std::vector<uint32_t> sample;
  for (int64_t i = 0; i < n; i += stride)
    if (visible[i]) sample.push_back(depth_key(depth[i]));
  if (sample.empty()) return uint64_t(1) << 32;
  const size_t k = std::min(sample.size() - 1, static_cast<size_t>(
      static_cast<double>(sample.size()) * static_cast<double>(target) / static_cast<double>(m)));
  std::nth_element(sample.begin(), sample.begin() + static_cast<ptrdiff_t>(k), sample.end());
  const uint32_t lowest = *std::min_element(sample.begin(), sample.begin() + static_cast<ptrdiff_t>(k) + 1);
  // at least the splats at the nearest sampled depth (ties there would empty the window)
  return std::max<uint64_t>(sample[k], uint64_t(lowest) + 1);
}

// The x-extent of the splat's cull ellipse on the 16 pixel rows of one tile row (rows ty0 + 0.5 ..
// ty0 + 15.5, two vectors of 8 rows): [xlo, xhi] (inflated) where ok; computed once per tile row
// and shared by all tiles of the rect in that row.
struct RowSpans {
  VF xlo[2], xhi[2];
  VM ok[2];
  bool live[2];  // the 8-row block meets the ellipse's y-extent
  bool all;      // no culling (thr = inf): every half-row
};
inline RowSpans ellipse_spans(const Geo& g, float ty0) {
  RowSpans sp;
  sp.all = !(g.thr < std::numeric_limits<float>::infinity());
  if (sp.all) return sp;
  const VF a = set1(g.a), thr = set1(g.thr), det = set1(g.det), ia = set1(g.inv_a), nb = set1(-g.b);
  const VF mx = set1(g.mx);
  const VF amx = set1(std::fabs(g.mx));
  const VF athr = a * thr;
  for (int k = 0; k < 2; ++k) {
    const float yb = ty0 + 8.0f * k;  // rows yb + 0.5 .. yb + 7.5
    sp.live[k] = yb + 7.5f >= g.my - g.ry && yb + 0.5f <= g.my + g.ry;
    if (!sp.live[k]) continue;
    VF dy = (set1(yb + 0.5f) + iota()) - set1(g.my);
    VF disc = fnmadd(det * dy, dy, athr);
    sp.ok[k] = disc >= zero();
    VF s = vsqrt(vmax(disc, zero())) * ia;
    VF off = nb * dy * ia;
    VF cen = mx + off;
    VF marg = set1(1e-3f) + set1(2e-6f) * (amx + vabs(off) + s);
    sp.xlo[k] = cen - s - marg;
    sp.xhi[k] = cen + s + marg;
  }
  return sp;
}

// Half-row mask of the splat's cull ellipse over the tile at x0 = tx0 of the spans' tile row: bit
// (h * 16 + r) set if half-row h (pixels x0 + 8h .. x0 + 8h + 7) of row r may hold a pixel with
// Q <= thr.
inline uint32_t span_mask(const RowSpans& sp, float tx0) {
  if (sp.all) return 0xFFFFFFFFu;
  const VF lo0 = set1(tx0 + 0.5f), hi0 = set1(tx0 + 7.5f), lo1 = set1(tx0 + 8.5f), hi1 = set1(tx0 + 15.5f);
  uint32_t m0 = 0, m1 = 0;
  for (int k = 0; k < 2; ++k) {
    if (!sp.live[k]) continue;
    int l = movemask(sp.ok[k] & (sp.xhi[k] >= lo0) & (sp.xlo[k] <= hi0));
    int r = movemask(sp.ok[k] & (sp.xhi[k] >= lo1) & (sp.xlo[k] <= hi1));
    m0 |= static_cast<uint32_t>(l) << (8 * k);
    m1 |= static_cast<uint32_t>(r) << (8 * k);
  }
  return m0 | (m1 << 16);
}

// power and alpha of one splat on one 8-pixel vector: the single definition shared by the forward
// and backward so that both take identical decisions.
struct Eval {
  VF dx, power, G, alpha;
};
inline Eval eval_power(const Geo& g, VF px, float dy) {
  Eval e;
  e.dx = px - set1(g.mx);
  const float nbdy = -g.b * dy;
  const float hcdy2 = ((-0.5f * g.c) * dy) * dy;
  VF t = fmadd(set1(-0.5f * g.a), e.dx, set1(nbdy));
  e.power = fmadd(t, e.dx, set1(hcdy2));
  return e;
}
inline void eval_alpha(const Geo& g, Eval& e) {
  e.G = vexp(e.power);
  e.alpha = vmin(set1(g.o) * e.G, set1(ALPHA_MAX));
}
// Lanes that may blend: power <= 0 inside the (inflated) alpha >= 1/255 ellipse Q <= thr, i.e.
// power >= -thr / 2. alpha >= 1/255 implies both, so the blending mask is this & (alpha >= 1/255)
// and a vector with no such lane is skipped exactly.
inline VM may_blend(const Eval& e, VF neg_half_thr) {
  const VF zf = zero();
  return (e.power <= zf) & (e.power >= neg_half_thr);
}

// ---------------------------------------------------------------------------------------------
// A 1-D array living in an (uninitialised) at::Tensor, so the binning's arrays are handed to
// Python (saved for the backward) without copies. V = int32_t / uint32_t (kInt) or int64_t (kLong).
template <typename V>
struct TVec {
  at::Tensor t;
  V* p = nullptr;
  void resize(int64_t n) {
    static_assert(sizeof(V) == 4 || sizeof(V) == 8, "4- or 8-byte elements");
    t = at::empty({n}, sizeof(V) == 8 ? at::kLong : at::kInt);
    p = reinterpret_cast<V*>(t.data_ptr());
  }
  void assign(int64_t n, V v) {
    resize(n);
    std::fill(p, p + n, v);
  }
  V& operator[](int64_t i) { return p[i]; }
  const V& operator[](int64_t i) const { return p[i]; }
  const V* data() const { return p; }
};

struct Binning {
  int gx = 0, gy = 0, ntiles = 0;
  TVec<int64_t> tile_off;    // [ntiles + 1]
  TVec<int32_t> tile_list;   // [P] sorted splat index per slot
  TVec<uint32_t> tile_mask;  // [P] half-row cull mask per slot
  static Binning empty(int gx, int gy) {
    Binning b;
    b.gx = gx;
    b.gy = gy;
    b.ntiles = gx * gy;
    b.tile_off.assign(b.ntiles + 1, 0);
    b.tile_list.resize(0);
    b.tile_mask.resize(0);
    return b;
  }
};

struct Rect {
  int x0, y0, x1, y1;
};

struct TileMask {
  int32_t splat, tile;
  uint32_t mask;
};

// 3DGS getRect on p = means2d - 0.5 with float32 arithmetic exactly as torch's tile_rects.
Rect tile_rect(float mx, float my, int radius, int gx, int gy) {
  const float r = static_cast<float>(radius);
  auto lo = [&](float p, int gmax) {
    float v = opaque(p - r);
    v = opaque(v / 16.0f);
    v = std::trunc(v);
    v = std::min(std::max(v, 0.0f), static_cast<float>(gmax));
    return static_cast<int>(v);
  };
  auto hi = [&](float p, int gmax) {
    float v = opaque(p + r);
    v = opaque(v + 15.0f);
    v = opaque(v / 16.0f);
    v = std::trunc(v);
    v = std::min(std::max(v, 0.0f), static_cast<float>(gmax));
    return static_cast<int>(v);
  };
  const float px = opaque(mx - 0.5f), py = opaque(my - 0.5f);
  return {lo(px, gx), lo(py, gy), hi(px, gx), hi(py, gy)};
}

// The forward's inputs in the original splat order (float32 / int32, contiguous).
struct SplatInputs {
  const float *m2, *cn, *op, *col, *dep;  // means2d [N,2], conics [N,3], opacities [N], colors [N,C], depths [N]
  const int32_t* rad;                     // radii [N]
  int C, gx, gy;
  bool cull;

  Rect rect(int64_t s) const { return tile_rect(m2[2 * s], m2[2 * s + 1], rad[s], gx, gy); }

  // Raw record of splat s with tile rect rc: mean, conic, opacity, rect, features; the derived
  // fields are filled in by finish() for splats that reach a tile still compositing.
  Geo raw(int64_t s, const Rect& rc) const {
    Geo g;
    g.mx = m2[2 * s];
    g.my = m2[2 * s + 1];
    g.a = cn[3 * s];
    g.b = cn[3 * s + 1];
    g.c = cn[3 * s + 2];
    g.o = op[s];
    g.rect[0] = static_cast<int16_t>(rc.x0);
    g.rect[1] = static_cast<int16_t>(rc.y0);
    g.rect[2] = static_cast<int16_t>(rc.x1);
    g.rect[3] = static_cast<int16_t>(rc.y1);
    if (C == 3) {
      for (int c2 = 0; c2 < 3; ++c2) g.f[c2] = col[s * 3 + c2];
      g.f[3] = dep[s];
    } else {
      for (int c2 = 0; c2 < 4; ++c2) g.f[c2] = 0.0f;
    }
    return g;
  }

  // The derived fields of a raw record: det = a c - b^2, 1/a, the cull threshold thr on
  // Q = d^T conic d and the cull ellipse's half-height ry.
  void finish(Geo& g) const {
    const double a = g.a, b = g.b, c = g.c;
    const double det = a * c - b * b;
    g.det = static_cast<float>(det);
    g.inv_a = static_cast<float>(1.0 / a);
    if (!cull || !(det > 0.0) || !(a > 0.0) || !(c > 0.0) || !std::isfinite(det)) {
      g.thr = std::numeric_limits<float>::infinity();
    } else if (!(g.o >= ALPHA_MIN)) {
      g.thr = -1.0f;  // o exp(power) <= o < 1/255 everywhere
    } else {
      // alpha >= 1/255  <=>  Q <= 2 ln(255 o); inflated for the float rounding of the kernel's
      // power (relative error ~ eps x condition of the conic) and of the fast exp.
      const double t = 2.0 * static_cast<double>(std::log(g.o * 255.0f));
      const double kappa = (std::fabs(a) + std::fabs(c) + 2.0 * std::fabs(b)) * (a + c) / det;
      const double thr = t * (1.0 + 1e-3 + 1e-5 * kappa) + 1e-3;
      g.thr = thr < 1e30 ? static_cast<float>(thr) : std::numeric_limits<float>::infinity();
    }
    if (std::isinf(g.thr)) {
      g.ry = std::numeric_limits<float>::infinity();
    } else if (g.thr < 0.0f) {
      g.ry = -1.0f;
    } else {  // max |dy| on Q = thr is sqrt(thr a / det)
      g.ry = static_cast<float>(std::sqrt(static_cast<double>(g.thr) * a / det) * (1.0 + 1e-4) + 1e-3);
    }
  }

  // Features [colors, depth] of splat s (when C != 3; else they ride in Geo::f).
  void features(int64_t s, float* out) const {
    for (int c = 0; c < C; ++c) out[c] = col[s * C + c];
    out[C] = dep[s];
  }
};

// A 3DGS tile rect [x0, x1) x [y0, y1) in tiles (also kept apart from the records, 8 bytes per splat,
// for the scan that selects the splats behind the first window).
struct TileRect {
  int16_t x0, y0, x1, y1;
};

// The tiles with a half-row still compositing, for testing whether a tile rect meets one in O(1)
// and without data-dependent branches (the test runs on every splat behind the first window, and
// about half pass: a loop over the rect's rows mispredicted most of them): a summed-area table
// S[y][x] = number of live tiles in [0, x) x [0, y), built from alive [tiles] (half-row masks)
// after each window.
struct LiveTiles {
  int gx;
  std::vector<int32_t> sat;  // [(gy + 1) * (gx + 1)]
  LiveTiles(const uint32_t* alive, int gx_, int gy) : gx(gx_), sat(static_cast<size_t>(gy + 1) * (gx_ + 1), 0) {
    const int w = gx + 1;
    for (int ty = 0; ty < gy; ++ty) {
      int32_t run = 0;
      for (int tx = 0; tx < gx; ++tx) {
        run += alive[ty * gx + tx] != 0;
        sat[(ty + 1) * w + tx + 1] = sat[ty * w + tx + 1] + run;
      }
    }
  }
  // rect coordinates are within [0, gx] x [0, gy] (tile_rect clamps them)
  bool meets(const TileRect& r) const {
    const int w = gx + 1;
    const int32_t* S = sat.data();
    const int32_t live = S[r.y1 * w + r.x1] - S[r.y0 * w + r.x1] - S[r.y1 * w + r.x0] + S[r.y0 * w + r.x0];
    return (r.x1 > r.x0) & (r.y1 > r.y0) & (live > 0);
  }
};

// The visible splats with depth key >= lo whose rect meets a tile still compositing (alive), in
// stable depth order: behind the first window, the only splats that can still be binned (alive
// only loses half-rows as compositing proceeds). One sequential pass over the 8-byte rects (not
// the 64-byte records) in nth chunks, then a stable radix sort of what passed.
std::vector<int32_t> depth_order_survivors(const TileRect* rects, const float* depth, const bool* visible,
                                           int64_t n, uint64_t lo, const LiveTiles& live, int nth) {
  std::vector<uint32_t> key;
  std::vector<int32_t> idx;
  select_keys(depth, visible, n, lo, uint64_t(1) << 32, [&](int64_t s) { return live.meets(rects[s]); }, nth,
              key, idx);
  radix_sort(key, idx, nth);
  return idx;
}

// Binning of one depth window, rows [lo, hi) of the depth-sorted splats (order[row] = original
// index; "depth index" below = row): for every splat and every tile
// of its rect, the half-row mask of its cull ellipse on that tile, restricted to the tile's
// half-rows that are still compositing (alive[tile]; a half-row whose 8 pixels have all terminated
// never composites a later splat); pairs with an empty mask are dropped (exact: no pixel there can
// reach alpha >= 1/255 or take part). Stable counting sort by tile: tile lists stay in depth order.
// Records: a splat (depth index i) with at least one pair gets geo[i] = geo_orig[order[i]] (one
// random line read per splat, nothing else) with its derived fields (finish(), computed only for
// splats that reach a live tile), feat[i] and src[i] = order[i] (its original index);
// the others src[i] = -1 (row unused, never in a tile list). Tile lists hold depth indices.
Binning bin_window(const SplatInputs& in, const Geo* geo_orig, const int32_t* order, Geo* geo, float* feat,
                   int32_t* src, int64_t lo_w, int64_t hi_w, const uint32_t* alive, int nth) {
  const LiveTiles live(alive, in.gx, in.gy);
  const int gx = in.gx, gy = in.gy, NF = in.C + 1;
  Binning b;
  b.gx = gx;
  b.gy = gy;
  b.ntiles = gx * gy;
  const int T = b.ntiles;
  const int64_t M = hi_w - lo_w;
  nth = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(nth, M / 4096 + 1)));
  // per (chunk, tile): the chunk's pair count, then (below) its first slot in that tile's list
  std::vector<int64_t> cursor(static_cast<size_t>(nth) * T, 0);
  // per chunk: the (depth index, tile, mask) pairs, in depth order
  std::vector<std::vector<TileMask>> found(nth);
  // pass 1: masks and per-(chunk, tile) counts over nth contiguous splat chunks (a loop over the
  // chunks, so every chunk runs whatever team size OpenMP grants)
#pragma omp parallel for num_threads(nth) schedule(static, 1)
  for (int t = 0; t < nth; ++t) {
    const int64_t lo = lo_w + M * t / nth, hi = lo_w + M * (t + 1) / nth;
    // thread-local histogram and pair list (per-thread rows of shared arrays would share cache
    // lines between threads: measured 2-4x slower)
    std::vector<int64_t> h(T, 0);
    std::vector<TileMask> fd;
    fd.reserve(static_cast<size_t>(hi - lo));
    for (int64_t i = lo; i < hi; ++i) {
      if (i + PREFETCH < hi) __builtin_prefetch(geo_orig + order[i + PREFETCH]);
      const int32_t s = order[i];
      Geo g = geo_orig[s];
      const Rect rc = {g.rect[0], g.rect[1], g.rect[2], g.rect[3]};
      src[i] = -1;
      // every tile of the rect has terminated
      if (!live.meets(TileRect{g.rect[0], g.rect[1], g.rect[2], g.rect[3]})) continue;
      in.finish(g);
      const size_t before = fd.size();
      for (int ty = rc.y0; ty < rc.y1; ++ty) {
        const uint32_t* arow = alive + ty * gx;
        uint32_t anyr = 0;
        for (int tx = rc.x0; tx < rc.x1; ++tx) anyr |= arow[tx];
        if (!anyr) continue;  // every tile of this rect row has terminated
        const RowSpans sp = ellipse_spans(g, static_cast<float>(ty * TILE));
        for (int tx = rc.x0; tx < rc.x1; ++tx) {
          const uint32_t m = arow[tx] ? span_mask(sp, static_cast<float>(tx * TILE)) & arow[tx] : 0u;
          if (m) {
            const int tile = ty * gx + tx;
            fd.push_back({static_cast<int32_t>(i), tile, m});
            h[tile]++;
          }
        }
      }
      if (fd.size() > before) {
        geo[i] = g;
        src[i] = s;
        if (NF != 4) in.features(s, feat + i * NF);
      }
    }
    std::copy(h.begin(), h.end(), cursor.begin() + static_cast<ptrdiff_t>(t) * T);
    found[t] = std::move(fd);
  }
  // offsets: tiles in order, threads (= depth chunks) in order inside a tile -> stable
  b.tile_off.assign(T + 1, 0);
  int64_t run = 0;
  for (int tile = 0; tile < T; ++tile) {
    b.tile_off[tile] = run;
    for (int t = 0; t < nth; ++t) {
      const int64_t count = cursor[static_cast<size_t>(t) * T + tile];
      cursor[static_cast<size_t>(t) * T + tile] = run;
      run += count;
    }
  }
  b.tile_off[T] = run;
  const int64_t P = run;
  TORCH_CHECK(P < (int64_t(1) << 31), "rasterize_cpu: too many (splat, tile) pairs: ", P);
  b.tile_list.resize(P);
  b.tile_mask.resize(P);
  // pass 2: scatter each chunk's pairs into the tile lists
#pragma omp parallel for num_threads(nth) schedule(static, 1)
  for (int t = 0; t < nth; ++t) {
    std::vector<int64_t> cur(cursor.begin() + static_cast<ptrdiff_t>(t) * T,
                             cursor.begin() + static_cast<ptrdiff_t>(t + 1) * T);
    int32_t* __restrict tl = b.tile_list.p;
    uint32_t* __restrict tm = b.tile_mask.p;
    for (const TileMask& fd : found[t]) {
      const int64_t slot = cur[fd.tile]++;
      tl[slot] = fd.splat;
      tm[slot] = fd.mask;
    }
  }
  return b;
}

// The tile lists of several depth windows concatenated per tile (window order = depth order).
Binning concat_windows(std::vector<Binning>& wins, int gx, int gy) {
  if (wins.size() == 1) return std::move(wins[0]);
  Binning b;
  b.gx = gx;
  b.gy = gy;
  b.ntiles = gx * gy;
  const int T = b.ntiles;
  b.tile_off.assign(T + 1, 0);
  int64_t run = 0;
  for (int tile = 0; tile < T; ++tile) {
    b.tile_off[tile] = run;
    for (const Binning& w : wins) run += w.tile_off[tile + 1] - w.tile_off[tile];
  }
  b.tile_off[T] = run;
  TORCH_CHECK(run < (int64_t(1) << 31), "rasterize_cpu: too many (splat, tile) pairs: ", run);
  b.tile_list.resize(run);
  b.tile_mask.resize(run);
#pragma omp parallel for schedule(static) if (run >= MIN_PAIRS_PARALLEL)
  for (int tile = 0; tile < T; ++tile) {
    int64_t dst = b.tile_off[tile];
    for (const Binning& w : wins) {
      const int64_t s0 = w.tile_off[tile], n = w.tile_off[tile + 1] - s0;
      std::copy(w.tile_list.p + s0, w.tile_list.p + s0 + n, b.tile_list.p + dst);
      std::copy(w.tile_mask.p + s0, w.tile_mask.p + s0 + n, b.tile_mask.p + dst);
      dst += n;
    }
  }
  return b;
}

// Tiles ordered by decreasing work (longest-processing-time first) for the dynamic schedule.
std::vector<int32_t> tile_schedule(const std::vector<int64_t>& work) {
  std::vector<int32_t> order(work.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = static_cast<int32_t>(i);
  std::stable_sort(order.begin(), order.end(), [&](int32_t x, int32_t y) { return work[x] > work[y]; });
  return order;
}

// Per-tile pixel geometry: first pixel, valid extent, half-rows with at least one valid pixel.
struct TileGeom {
  int tx0, ty0, nx, ny;
  uint32_t valid_rows;
};
inline TileGeom tile_geom(int tile, int gx, int W, int H) {
  TileGeom t;
  t.tx0 = (tile % gx) * TILE;
  t.ty0 = (tile / gx) * TILE;
  t.nx = std::min(TILE, W - t.tx0);
  t.ny = std::min(TILE, H - t.ty0);
  const uint32_t rows = (t.ny >= 16) ? 0xFFFFu : ((1u << t.ny) - 1u);
  t.valid_rows = rows | (t.nx > 8 ? rows << 16 : 0u);
  return t;
}

// Output images of the forward ([H, W] or [H, W, C] with C = NF - 1; depth is feature NF - 1).
struct ImageOut {
  float* color;
  float* alpha;
  float* depth;
  float* T;
  int32_t* last;
  const float* bg;  // [C]
};
// Incoming gradients of the backward.
struct ImageGrad {
  const float* color;
  const float* alpha;
  const float* depth;
  const float* bg;
};

// ---------------------------------------------------------------------------------------------
// Compositing state of one tile, kept across depth windows (pixel p = r * 16 + 8 h + lane, half-row
// bit h * 16 + r): transmittance T, done (-1: terminated or outside the image), last contributor
// (tile-list position), accumulated features acc [NF][256].
struct TileView {
  float* T;
  int32_t* done;
  int32_t* last;
  float* acc;
};

inline void tile_begin(const TileGeom& tg, int NF, const TileView& s) {
  for (int p = 0; p < TPIX; ++p) {
    const int r = p / TILE, x = p % TILE;
    s.T[p] = 1.0f;
    s.last[p] = -1;
    s.done[p] = (r < tg.ny && x < tg.nx) ? 0 : -1;
  }
  for (int k = 0; k < NF * TPIX; ++k) s.acc[k] = 0.0f;
}

// Forward kernel on one tile over one segment of its list (n slots whose tile-list positions start
// at jbase); updates the tile's state and its mask of half-rows still compositing (alive).
template <int NFT, bool COUNT>
void forward_tile(const Geo* __restrict__ geo, const float* __restrict__ feat, int nf,
                  const int32_t* __restrict__ list, const uint32_t* __restrict__ lmask, int64_t n,
                  int64_t jbase, const TileGeom& tg, const TileView& s, uint32_t& alive_io,
                  int64_t* stats) {
  const int NF = NFT > 0 ? NFT : nf;
  float* __restrict__ T = s.T;
  int32_t* __restrict__ done = s.done;
  int32_t* __restrict__ last = s.last;
  float* __restrict__ acc = s.acc;
  uint32_t alive = alive_io;
  const float fx0 = static_cast<float>(tg.tx0), fy0 = static_cast<float>(tg.ty0);
  const VF px_h[2] = {set1(fx0 + 0.5f) + iota(), set1(fx0 + 8.5f) + iota()};
  const VF one = set1(1.0f), amin = set1(ALPHA_MIN), tmin = set1(T_MIN), zf = zero();
  const VM all = zf <= zf;
  int64_t n_contrib = 0, n_eval = 0;
  for (int64_t jl = 0; jl < n && alive; ++jl) {
    if (jl + PREFETCH < n) __builtin_prefetch(geo + list[jl + PREFETCH]);
    uint32_t rows = lmask[jl] & alive;
    if (!rows) continue;
    const int32_t gi = list[jl];
    const Geo& g = geo[gi];
    const float* f = NFT == 4 ? g.f : feat + static_cast<int64_t>(gi) * NF;
    const VI jv = iset1(static_cast<int32_t>(jbase + jl));
    const VF nht = set1(-0.5f * g.thr);
    do {
      const int hr = __builtin_ctz(rows);
      rows &= rows - 1;
      const int h = hr >> 4, r = hr & 15;
      const int p0 = r * TILE + 8 * h;
      const float dy = (fy0 + static_cast<float>(r) + 0.5f) - g.my;
      Eval e = eval_power(g, px_h[h], dy);
      const VM dn = mload(done + p0);
      const VM cand = may_blend(e, nht) & andnot(dn, all);  // live pixels that may blend
      if (!movemask(cand)) continue;
      eval_alpha(g, e);
      const VM m = cand & (e.alpha >= amin);
      const VF Tv = load(T + p0);
      const VF testT = Tv * (one - e.alpha);
      const VM term = m & (testT < tmin);
      const VM contrib = andnot(term, m);
      const VF w = select(contrib, e.alpha, zf) * Tv;
      for (int c = 0; c < NF; ++c) {
        float* ac = acc + c * TPIX + p0;
        store(ac, fmadd(w, set1(f[c]), load(ac)));
      }
      store(T + p0, select(contrib, testT, Tv));
      istore(last + p0, iselect(contrib, jv, iload(last + p0)));
      const VM nd = dn | term;
      mstore(done + p0, nd);
      if (movemask(nd) == 0xFF) alive &= ~(1u << hr);
      if (COUNT) {
        n_contrib += __builtin_popcount(movemask(contrib));
        n_eval += 1;
      }
    } while (rows);
  }
  alive_io = alive;
  if (COUNT) {
    stats[0] += n_contrib;
    stats[1] += n_eval;
  }
}

// Writes one tile's final state into the output images.
inline void tile_end(const TileGeom& tg, int W, int NF, const TileView& s, const ImageOut& out) {
  for (int r = 0; r < tg.ny; ++r) {
    for (int x = 0; x < tg.nx; ++x) {
      const int p = r * TILE + x;
      const int64_t o = static_cast<int64_t>(tg.ty0 + r) * W + (tg.tx0 + x);
      const float Tp = s.T[p];
      out.T[o] = Tp;
      out.alpha[o] = 1.0f - Tp;
      out.last[o] = s.last[p];
      for (int c = 0; c < NF - 1; ++c) out.color[o * (NF - 1) + c] = s.acc[c * TPIX + p] + Tp * out.bg[c];
      out.depth[o] = s.acc[(NF - 1) * TPIX + p];
    }
  }
}

// Writes the outputs of a tile that no splat reached (T = 1, colour = background).
inline void tile_end_empty(const TileGeom& tg, int W, int NF, const ImageOut& out) {
  for (int r = 0; r < tg.ny; ++r) {
    for (int x = 0; x < tg.nx; ++x) {
      const int64_t o = static_cast<int64_t>(tg.ty0 + r) * W + (tg.tx0 + x);
      out.T[o] = 1.0f;
      out.alpha[o] = 0.0f;
      out.last[o] = -1;
      for (int c = 0; c < NF - 1; ++c) out.color[o * (NF - 1) + c] = out.bg[c];
      out.depth[o] = 0.0f;
    }
  }
}

// Backward kernel on one tile: walks the list back to front from the tile's last contributor and
// writes, per processed slot, R = 6 + NF partial sums over the tile's pixels:
// [sum dpow dx, sum dpow dy, sum dpow dx^2, sum dpow dx dy, sum dpow dy^2, sum G dalpha, sum w g_c...]
// (dpow = dL/dpower, w = alpha T, g = dL/dacc). Returns the number of processed slots.
template <int NFT, bool COUNT>
int64_t backward_tile(const Geo* __restrict__ geo, const float* __restrict__ feat, int nf,
                      const int32_t* __restrict__ list, const uint32_t* __restrict__ lmask,
                      const TileGeom& tg, int W, const float* __restrict__ in_T,
                      const int32_t* __restrict__ in_last, const ImageGrad& gin,
                      float* __restrict__ T, float* __restrict__ D,
                      int32_t* __restrict__ last, float* __restrict__ gpix, VF* __restrict__ accv,
                      float* __restrict__ rec, int64_t* stats) {
  const int NF = NFT > 0 ? NFT : nf;
  const int R = 6 + NF;
  for (int p = 0; p < TPIX; ++p) {
    T[p] = 1.0f;
    D[p] = 0.0f;
    last[p] = -1;
  }
  for (int k = 0; k < NF * TPIX; ++k) gpix[k] = 0.0f;
  int32_t jmax = -1;
  for (int r = 0; r < tg.ny; ++r) {
    for (int x = 0; x < tg.nx; ++x) {
      const int p = r * TILE + x;
      const int64_t o = static_cast<int64_t>(tg.ty0 + r) * W + (tg.tx0 + x);
      T[p] = in_T[o];
      // dL/dT_final (colour = acc + T_final bg, alpha = 1 - T_final) times T_final: the
      // background/alpha term of dL/dalpha_j
      float gT = -gin.alpha[o];
      for (int c = 0; c < NF - 1; ++c) {
        const float gc = gin.color[o * (NF - 1) + c];
        gpix[c * TPIX + p] = gc;
        gT += gin.bg[c] * gc;
      }
      gpix[(NF - 1) * TPIX + p] = gin.depth[o];
      D[p] = gT * in_T[o];
      last[p] = in_last[o];
      jmax = std::max(jmax, in_last[o]);
    }
  }
  if (jmax < 0) return 0;
  // half-rows sorted by their last contributor (descending): they become active as jl reaches it
  int32_t hr_last[NHR], hr_order[NHR];
  for (int hr = 0; hr < NHR; ++hr) {
    const int h = hr >> 4, r = hr & 15, p0 = r * TILE + 8 * h;
    int32_t mx = -1;
    for (int l = 0; l < 8; ++l) mx = std::max(mx, last[p0 + l]);
    hr_last[hr] = mx;
    hr_order[hr] = hr;
  }
  std::sort(hr_order, hr_order + NHR, [&](int32_t x, int32_t y) {
    return hr_last[x] != hr_last[y] ? hr_last[x] > hr_last[y] : x < y;
  });
  int next = 0;
  uint32_t active = 0;
  const float fx0 = static_cast<float>(tg.tx0), fy0 = static_cast<float>(tg.ty0);
  const VF px_h[2] = {set1(fx0 + 0.5f) + iota(), set1(fx0 + 8.5f) + iota()};
  const VF one = set1(1.0f), amin = set1(ALPHA_MIN), amax = set1(ALPHA_MAX), zf = zero();
  int64_t n_eval = 0;
  for (int32_t jl = jmax; jl >= 0; --jl) {
    while (next < NHR && hr_last[hr_order[next]] >= jl) active |= 1u << hr_order[next++];
    if (jl >= PREFETCH) __builtin_prefetch(geo + list[jl - PREFETCH]);
    float* out = rec + static_cast<int64_t>(jl) * R;
    uint32_t rows = lmask[jl] & active;
    if (!rows) {
      for (int k = 0; k < R; ++k) out[k] = 0.0f;
      continue;
    }
    const int32_t gi = list[jl];
    const Geo& g = geo[gi];
    const float* f = NFT == 4 ? g.f : feat + static_cast<int64_t>(gi) * NF;
    for (int k = 0; k < R; ++k) accv[k] = zf;
    const VI jm1 = iset1(jl - 1);
    const VF o = set1(g.o);
    const VF nht = set1(-0.5f * g.thr);
    do {
      const int hr = __builtin_ctz(rows);
      rows &= rows - 1;
      const int h = hr >> 4, r = hr & 15;
      const int p0 = r * TILE + 8 * h;
      const float dy = (fy0 + static_cast<float>(r) + 0.5f) - g.my;
      Eval e = eval_power(g, px_h[h], dy);
      // pixels whose last contributor is this splat or later that may blend
      const VM cand = may_blend(e, nht) & igt(iload(last + p0), jm1);
      if (!movemask(cand)) continue;
      eval_alpha(g, e);
      const VM m = cand & (e.alpha >= amin);
      const VF am = select(m, e.alpha, zf);
      const VF rcp = one / (one - am);
      const VF Tj = load(T + p0) * rcp;  // transmittance before this splat
      const VF Dv = load(D + p0);
      VF gf = zf;
      for (int c = 0; c < NF; ++c) gf = fmadd(load(gpix + c * TPIX + p0), set1(f[c]), gf);
      const VF dalpha = fnmadd(Dv, rcp, Tj * gf);  // T_j g.f - D / (1 - alpha)
      const VF w = am * Tj;
      store(D + p0, fmadd(w, gf, Dv));
      store(T + p0, Tj);
      const VM unclamped = m & ((o * e.G) <= amax);
      const VF dpow = select(unclamped, am * dalpha, zf);
      const VF dGo = select(unclamped, e.G * dalpha, zf);
      const VF dy_v = set1(dy);
      const VF pdx = dpow * e.dx, pdy = dpow * dy_v;
      accv[0] = accv[0] + pdx;
      accv[1] = accv[1] + pdy;
      accv[2] = fmadd(pdx, e.dx, accv[2]);
      accv[3] = fmadd(pdx, dy_v, accv[3]);
      accv[4] = fmadd(pdy, dy_v, accv[4]);
      accv[5] = accv[5] + dGo;
      for (int c = 0; c < NF; ++c) accv[6 + c] = fmadd(w, load(gpix + c * TPIX + p0), accv[6 + c]);
      if (COUNT) n_eval += 1;
    } while (rows);
    int k = 0;
    for (; k + 8 <= R; k += 8) hsum8(accv + k, out + k);
    for (; k < R; ++k) out[k] = hsum(accv[k]);
  }
  if (COUNT) stats[2] += n_eval;
  return static_cast<int64_t>(jmax) + 1;
}

struct TileScratch {
  AlignedBuf<float> f;
  AlignedBuf<int32_t> i;
  AlignedBuf<VF> v;
  explicit TileScratch(int nf) : f(static_cast<size_t>(TPIX) * (3 + nf)), i(2 * TPIX), v(6 + nf + 8) {}
};

// ---------------------------------------------------------------------------------------------
// Python entry points.

void check_f32(const at::Tensor& t, const char* name, int64_t dim) {
  TORCH_CHECK(t.device().is_cpu(), "rasterize_cpu: ", name, " must be a CPU tensor, got ", t.device());
  TORCH_CHECK(t.scalar_type() == at::kFloat, "rasterize_cpu: ", name, " must be float32, got ",
              t.scalar_type());
  TORCH_CHECK(t.dim() == dim, "rasterize_cpu: ", name, " must have ", dim, " dims, got ", t.dim());
  TORCH_CHECK(t.is_contiguous(), "rasterize_cpu: ", name, " must be contiguous");
}

template <typename V>
at::Tensor to_tensor(const std::vector<V>& v, at::ScalarType st) {
  auto t = at::empty({static_cast<int64_t>(v.size())}, st);
  if (!v.empty()) std::memcpy(t.data_ptr(), v.data(), v.size() * sizeof(V));
  return t;
}

// Forward.
// Args: means2d [N,2], conics [N,3], opacities [N], colors [N,C], depths [N] (sort key and the
//       last feature channel: features = [colors, depths], NF = C + 1), radii [N] int32,
//       visible [N] bool, background [C]; width, height; cull
//       (exact culling on/off); count (pair statistics); first_window (about this many splats,
//       the nearest, in the first depth window, each next one twice as many rows;
//       <= 0: max(WINDOW_MIN, M / WINDOW_FIRST_DIV)).
// Returns: color [H,W,NF-1] (= acc + T_final background), alpha [H,W] (= 1 - T_final), depth [H,W]
//          (accumulated feature NF-1), T_final [H,W], last [H,W] int32 (tile-list position of the
//          last contributor, -1 if none), then the state for the backward, with one row per
//          sorted splat (R <= M rows in depth order; splats behind the first window whose rect
//          met no live tile have none): src [R] int32 (the original index of a binned splat, -1
//          for a row never binned, whose geo and feat are unset), geo [R,16], feat_sorted [R,NF]
//          (or [0,NF] when NF == 4: features ride in geo), tile_off [T+1] int64, tile_list [P]
//          int32 (rows), tile_mask [P] int32, and stats [NSTATS] float64: contrib pairs,
//          evaluated fwd vectors, evaluated bwd vectors, tile pairs, wall times in ms of: sort
//          (including the scan selecting the splats behind the first window), pack, binning,
//          raster fwd, raster bwd, bwd reduction, then the process CPU times of the same six
//          stages, then the number of depth windows.
std::vector<at::Tensor> forward(at::Tensor means2d, at::Tensor conics, at::Tensor opacities,
                                   at::Tensor colors, at::Tensor depths, at::Tensor radii,
                                   at::Tensor visible, at::Tensor background, int64_t width,
                                   int64_t height, bool cull, bool count, int64_t first_window) {
  check_f32(means2d, "means2d", 2);
  check_f32(conics, "conics", 2);
  check_f32(opacities, "opacities", 1);
  check_f32(colors, "colors", 2);
  check_f32(depths, "depths", 1);
  check_f32(background, "background", 1);
  const int64_t N = means2d.size(0);
  TORCH_CHECK(means2d.size(1) == 2, "rasterize_cpu: means2d must be [N, 2]");
  TORCH_CHECK(conics.size(0) == N && conics.size(1) == 3, "rasterize_cpu: conics must be [N, 3]");
  TORCH_CHECK(opacities.size(0) == N, "rasterize_cpu: opacities must be [N]");
  TORCH_CHECK(colors.size(0) == N, "rasterize_cpu: colors must be [N, C]");
  TORCH_CHECK(depths.size(0) == N, "rasterize_cpu: depths must be [N]");
  TORCH_CHECK(background.size(0) == colors.size(1),
              "rasterize_cpu: background must have C = ", colors.size(1), " channels");
  TORCH_CHECK(radii.device().is_cpu() && radii.scalar_type() == at::kInt && radii.dim() == 1 &&
                  radii.size(0) == N && radii.is_contiguous(),
              "rasterize_cpu: radii must be a contiguous CPU int32 [N] tensor");
  TORCH_CHECK(visible.device().is_cpu() && visible.scalar_type() == at::kBool && visible.dim() == 1 &&
                  visible.size(0) == N && visible.is_contiguous(),
              "rasterize_cpu: visible must be a contiguous CPU bool [N] tensor");
  TORCH_CHECK(width > 0 && height > 0 && width <= 65536 && height <= 65536,
              "rasterize_cpu: bad image size ", width, "x", height);
  const int W = static_cast<int>(width), H = static_cast<int>(height);
  const int C = static_cast<int>(colors.size(1));
  const int NF = C + 1;  // features: colours, then depth
  const int nth = num_threads();
  const Stamp t0 = now();

  const int gx = (W + TILE - 1) / TILE, gy = (H + TILE - 1) / TILE;
  SplatInputs in{means2d.data_ptr<float>(), conics.data_ptr<float>(), opacities.data_ptr<float>(),
                 colors.data_ptr<float>(), depths.data_ptr<float>(), radii.data_ptr<int32_t>(),
                 C, gx, gy, cull};
  // raw per-splat records (with their tile rects) in the original order: a sequential pass over
  // the inputs; binning then reads one random line per splat instead of five
  thread_local Scratch<Geo> geo_scratch;
  Geo* geo_orig = geo_scratch.get(static_cast<size_t>(N));  // [N] records (visible splats only)
  thread_local Scratch<TileRect> rect_scratch;
  TileRect* rects = rect_scratch.get(static_cast<size_t>(N));  // [N] their tile rects
  {
    const bool* vis = visible.data_ptr<bool>();
    at::parallel_for(0, N, 16384, [&](int64_t lo, int64_t hi) {
      for (int64_t s = lo; s < hi; ++s)
        if (vis[s]) {
          const Rect rc = in.rect(s);
          geo_orig[s] = in.raw(s, rc);
          rects[s] = {static_cast<int16_t>(rc.x0), static_cast<int16_t>(rc.y0), static_cast<int16_t>(rc.x1),
                      static_cast<int16_t>(rc.y1)};
        } else {
          rects[s] = {0, 0, 0, 0};  // empty: meets no tile (the survivor scan tests every splat)
        }
    });
  }
  const Stamp t1 = now();
  // The first depth window: the visible splats nearer than a sampled depth quantile, depth-sorted.
  // The later ones are sorted after it has been composited, and only those whose rect still meets
  // a live tile (depth_order_survivors); order[row] = original index of the splat in that row.
  const float* dp = depths.data_ptr<float>();
  const bool* vis = visible.data_ptr<bool>();
  const int64_t M = std::count(vis, vis + N, true);  // visible splats: an upper bound on the rows
  const int64_t w0 = first_window > 0 ? first_window : std::max<int64_t>(WINDOW_MIN, M / WINDOW_FIRST_DIV);
  uint64_t near = window_threshold(dp, vis, N, M, w0);
  std::vector<int32_t> order = depth_order_range(dp, vis, N, 0, near, nth);
  if (order.empty() && M > 0) {  // nothing nearer than the sampled quantile (ties): one window
    near = uint64_t(1) << 32;
    order = depth_order(dp, vis, N, nth);
  }
  const int64_t M1 = static_cast<int64_t>(order.size());
  const Stamp t2 = now();
  auto geo_t = at::empty({M, 16}, at::kFloat);
  auto feat_t = at::empty({NF == 4 ? 0 : M, NF}, at::kFloat);
  Geo* geo = reinterpret_cast<Geo*>(geo_t.data_ptr<float>());
  TORCH_CHECK(reinterpret_cast<uintptr_t>(geo) % 64 == 0 || M == 0, "rasterize_cpu: misaligned buffer");
  auto color_t = at::empty({H, W, NF - 1}, at::kFloat);
  auto alpha_t = at::empty({H, W}, at::kFloat);
  auto depth_t = at::empty({H, W}, at::kFloat);
  auto Tf_t = at::empty({H, W}, at::kFloat);
  auto last_t = at::empty({H, W}, at::kInt);
  auto stats_t = at::zeros({NSTATS}, at::kDouble);
  auto src_t = at::empty({M}, at::kInt);  // per row: original splat index, -1 if not binned
  const int T = gx * gy;
  // per-tile compositing state (O(pixels)), kept across the depth windows
  AlignedBuf<float> s_T(static_cast<size_t>(T) * TPIX), s_acc(static_cast<size_t>(T) * NF * TPIX);
  AlignedBuf<int32_t> s_done(static_cast<size_t>(T) * TPIX), s_last(static_cast<size_t>(T) * TPIX);
  auto view = [&](int tile) {
    const size_t o = static_cast<size_t>(tile) * TPIX;
    return TileView{s_T.p + o, s_done.p + o, s_last.p + o, s_acc.p + o * NF};
  };
  std::vector<uint32_t> alive(T);  // per tile: half-rows still compositing
  std::vector<int64_t> len(T, 0);  // per tile: list length so far (0: state not yet set up)
  for (int tile = 0; tile < T; ++tile) alive[tile] = tile_geom(tile, gx, W, H).valid_rows;
  std::vector<int64_t> tstats(static_cast<size_t>(nth) * 8, 0);
  // Depth windows [lo, hi) of geometrically growing size: each is gathered into depth order,
  // binned onto the half-rows still compositing and composited; once a tile's pixels have all
  // terminated, later splats are neither binned onto it nor stored (the image, the last
  // contributors and hence the backward are those of one full binning; tested bit for bit).
  std::vector<Binning> wins;
  const Stamp t3 = now();
  double bin_w = 0, bin_c = 0, ras_w = 0, ras_c = 0, sort_w = t2.wall - t1.wall, sort_c = t2.cpu - t1.cpu;
  int64_t n_windows = 0;
  const float* fs = feat_t.data_ptr<float>();
  int64_t all_rows = 0;  // half-rows of the image
  for (int t = 0; t < T; ++t) all_rows += __builtin_popcount(alive[t]);
  int64_t wsize = M1;
  bool rest_sorted = M1 == M;  // the splats behind the first window are in `order`
  for (int64_t lo = 0, hi = 0; lo < static_cast<int64_t>(order.size()); lo = hi) {
    hi = std::min(static_cast<int64_t>(order.size()), lo + wsize);
    const Stamp w1 = now();
    wins.push_back(bin_window(in, geo_orig, order.data(), geo, feat_t.data_ptr<float>(),
                              src_t.data_ptr<int32_t>(), lo, hi, alive.data(), nth));
    const Binning& bw = wins.back();
    const Stamp w2 = now();
    std::vector<int64_t> work(T);
    for (int t = 0; t < T; ++t) work[t] = bw.tile_off[t + 1] - bw.tile_off[t];
    const std::vector<int32_t> sched = tile_schedule(work);
    const int64_t Pw = bw.tile_off[T];
    const int nth_tiles = Pw < MIN_PAIRS_PARALLEL ? 1 : nth;
#pragma omp parallel num_threads(nth_tiles)
    {
      int64_t* st = tstats.data() + 8 * omp_get_thread_num();
#pragma omp for schedule(dynamic, 1)
      for (int k = 0; k < T; ++k) {
        const int tile = sched[k];
        const int64_t n = work[tile];
        if (n == 0) continue;
        const TileGeom tg = tile_geom(tile, gx, W, H);
        if (len[tile] == 0) tile_begin(tg, NF, view(tile));  // first work for this tile
        const int32_t* list = bw.tile_list.data() + bw.tile_off[tile];
        const uint32_t* lmask = bw.tile_mask.data() + bw.tile_off[tile];
#define SF_FWD(NFT, CNT) \
  forward_tile<NFT, CNT>(geo, fs, NF, list, lmask, n, len[tile], tg, view(tile), alive[tile], st)
        if (NF == 4) {
          if (count) SF_FWD(4, true); else SF_FWD(4, false);
        } else {
          if (count) SF_FWD(0, true); else SF_FWD(0, false);
        }
#undef SF_FWD
      }
    }
    for (int t = 0; t < T; ++t) len[t] += work[t];
    // next window: twice as large, or all the rest when too few half-rows have terminated for
    // later windows to skip enough work to pay for themselves (scenes that never saturate)
    int64_t live_rows = 0;
    for (int t = 0; t < T; ++t) live_rows += __builtin_popcount(alive[t]);
    const bool few_dead = (all_rows - live_rows) * WINDOW_DEAD_DIV < all_rows;
    const Stamp w3 = now();
    if (!rest_sorted) {  // after the first window: the splats behind it that can still be binned
      // (where few half-rows have terminated, testing the rects would keep almost all of them)
      std::vector<int32_t> rest =
          few_dead ? depth_order_range(dp, vis, N, near, uint64_t(1) << 32, nth)
                   : depth_order_survivors(rects, dp, vis, N, near, LiveTiles(alive.data(), gx, gy), nth);
      order.insert(order.end(), rest.begin(), rest.end());
      rest_sorted = true;
    }
    const int64_t rows = static_cast<int64_t>(order.size());
    wsize = (few_dead && first_window <= 0) ? rows - hi : 2 * wsize;
    const Stamp w4 = now();
    bin_w += w2.wall - w1.wall;
    bin_c += w2.cpu - w1.cpu;
    ras_w += w3.wall - w2.wall;
    ras_c += w3.cpu - w2.cpu;
    sort_w += w4.wall - w3.wall;
    sort_c += w4.cpu - w3.cpu;
    ++n_windows;
  }
  const int64_t Mr = static_cast<int64_t>(order.size());  // rows used
  const Stamp t4 = now();
  Binning bins = wins.empty() ? Binning::empty(gx, gy) : concat_windows(wins, gx, gy);
  wins.clear();
  const int64_t P = bins.tile_off[T];
  {
    const ImageOut iout{color_t.data_ptr<float>(), alpha_t.data_ptr<float>(), depth_t.data_ptr<float>(),
                        Tf_t.data_ptr<float>(), last_t.data_ptr<int32_t>(), background.data_ptr<float>()};
#pragma omp parallel for schedule(static) num_threads(P < MIN_PAIRS_PARALLEL ? 1 : nth)
    for (int tile = 0; tile < T; ++tile) {
      const TileGeom tg = tile_geom(tile, gx, W, H);
      if (len[tile] > 0) {
        tile_end(tg, W, NF, view(tile), iout);
      } else {  // no splat: T = 1
        tile_end_empty(tg, W, NF, iout);
      }
    }
  }
  const Stamp t5 = now();
  double* st = stats_t.data_ptr<double>();
  for (int t = 0; t < nth; ++t) {
    st[0] += static_cast<double>(tstats[8 * t]);
    st[1] += static_cast<double>(tstats[8 * t + 1]);
  }
  st[3] = static_cast<double>(P);
  put_ms(st, 4, sort_w, sort_c);  // depth sorts (first window, then the splats behind it)
  put_ms(st, 5, (t1.wall - t0.wall) + (t3.wall - t2.wall) + (t5.wall - t4.wall),
         (t1.cpu - t0.cpu) + (t3.cpu - t2.cpu) + (t5.cpu - t4.cpu));  // records, tile state, write-out
  put_ms(st, 6, bin_w, bin_c);  // records + binning
  put_ms(st, 7, ras_w, ras_c);  // raster fwd
  st[16] = static_cast<double>(n_windows);

  return {color_t,
          alpha_t,
          depth_t,
          Tf_t,
          last_t,
          src_t.narrow(0, 0, Mr),
          geo_t.narrow(0, 0, Mr),
          NF == 4 ? feat_t : feat_t.narrow(0, 0, Mr),
          bins.tile_off.t,
          bins.tile_list.t,
          bins.tile_mask.t,
          stats_t};
}

// Backward. grad_color [H,W,NF-1], grad_alpha [H,W], grad_depth [H,W], background [NF-1] plus the
// forward's saved tensors. Returns the gradients (zero for culled splats) g_geo [N, 6] w.r.t.
// means2d (cols 0-1), conics (2-4) and depths (5), g_opacity [N] and g_color [N, NF - 1].
// Writes the evaluated backward vectors and the times into stats[2], stats[8], stats[9].
std::vector<at::Tensor> backward(at::Tensor grad_color, at::Tensor grad_alpha, at::Tensor grad_depth,
                                    at::Tensor background, at::Tensor T_final,
                                    at::Tensor last, at::Tensor src, at::Tensor geo_t,
                                    at::Tensor feat_t, at::Tensor tile_off, at::Tensor tile_list,
                                    at::Tensor tile_mask, at::Tensor stats,
                                    int64_t n_splats, bool count) {
  check_f32(grad_color, "grad_color", 3);
  check_f32(grad_alpha, "grad_alpha", 2);
  check_f32(grad_depth, "grad_depth", 2);
  check_f32(background, "background", 1);
  check_f32(T_final, "T_final", 2);
  const int H = static_cast<int>(T_final.size(0)), W = static_cast<int>(T_final.size(1));
  const int NF = static_cast<int>(feat_t.size(1));
  TORCH_CHECK(grad_color.size(0) == H && grad_color.size(1) == W && grad_color.size(2) == NF - 1,
              "rasterize_cpu: grad_color shape mismatch");
  TORCH_CHECK(grad_alpha.size(0) == H && grad_alpha.size(1) == W, "rasterize_cpu: grad_alpha shape mismatch");
  TORCH_CHECK(grad_depth.size(0) == H && grad_depth.size(1) == W, "rasterize_cpu: grad_depth shape mismatch");
  TORCH_CHECK(background.size(0) == NF - 1, "rasterize_cpu: background shape mismatch");
  const int64_t N = n_splats, M = src.size(0);  // M records
  const int gx = (W + TILE - 1) / TILE, gy = (H + TILE - 1) / TILE;
  const int T = gx * gy;
  const int nth = num_threads();
  const Stamp t0 = now();
  const int R = 6 + NF;
  const int64_t P = tile_list.size(0);
  // records [P, R] in slot order: only the slots up to each tile's last contributor are written
  // and read
  thread_local Scratch<float> rec_scratch;  // reused across calls (no page faults per render)
  float* const rec = rec_scratch.get(static_cast<size_t>(P) * R);
  std::vector<int64_t> nproc(T, 0);
  const int64_t* toff = tile_off.data_ptr<int64_t>();
  const int32_t* tl = tile_list.data_ptr<int32_t>();
  const uint32_t* tm = reinterpret_cast<const uint32_t*>(tile_mask.data_ptr<int32_t>());
  const int32_t* lastp = last.data_ptr<int32_t>();
  std::vector<int64_t> work(T);
  for (int t = 0; t < T; ++t) {
    const TileGeom tg = tile_geom(t, gx, W, H);
    int32_t jm = -1;
    for (int r = 0; r < tg.ny; ++r) {
      const int32_t* row = lastp + static_cast<int64_t>(tg.ty0 + r) * W + tg.tx0;
      for (int x = 0; x < tg.nx; ++x) jm = std::max(jm, row[x]);
    }
    work[t] = jm + 1;
  }
  const std::vector<int32_t> sched = tile_schedule(work);
  std::vector<int64_t> tstats(static_cast<size_t>(nth) * 8, 0);
  const int nth_tiles = P < MIN_PAIRS_PARALLEL ? 1 : nth;
  {
    const Geo* gp = reinterpret_cast<const Geo*>(geo_t.data_ptr<float>());
    const float* fs = feat_t.data_ptr<float>();
    const float* inT = T_final.data_ptr<float>();
    const ImageGrad gin{grad_color.data_ptr<float>(), grad_alpha.data_ptr<float>(),
                        grad_depth.data_ptr<float>(), background.data_ptr<float>()};
    float* recp = rec;
#pragma omp parallel num_threads(nth_tiles)
    {
      TileScratch s(NF);
      int64_t* st = tstats.data() + 8 * omp_get_thread_num();
#pragma omp for schedule(dynamic, 1)
      for (int k = 0; k < T; ++k) {
        const int tile = sched[k];
        if (work[tile] == 0) continue;
        const TileGeom tg = tile_geom(tile, gx, W, H);
        float* Tb = s.f.p;
        float* Db = s.f.p + TPIX;
        float* gpix = s.f.p + 2 * TPIX;
        int32_t* lastb = s.i.p;
#define SF_BWD(NFT, CNT)                                                                            \
  nproc[tile] = backward_tile<NFT, CNT>(gp, fs, NF, tl + toff[tile], tm + toff[tile], tg, W, inT, lastp, \
                                        gin, Tb, Db, lastb, gpix, s.v.p, recp + toff[tile] * R, st)
        if (NF == 4) {
          if (count) SF_BWD(4, true); else SF_BWD(4, false);
        } else {
          if (count) SF_BWD(0, true); else SF_BWD(0, false);
        }
#undef SF_BWD
      }
    }
  }
  const Stamp t1 = now();
  // Per-splat reduction over its tiles in a fixed (tile) order, in three phases (barriers between):
  //  1. each thread owns a range of rows (depth order) and walks its run of the processed slots of
  //     every tile in tile order (sequential reads), accumulating its rows' slot records into a
  //     row-order buffer sums [M, R] (each tile's run visits rows in increasing order), then maps
  //     them to gradients there (its rows, reading their records in order);
  //  2. rows of the original order: row_of[s] = the row of splat s, or -1 if it has none;
  //  3. each thread writes its share of the outputs in the original order (sequential writes),
  //     gathering sums[row_of[s]] (prefetched reads) or zeros.
  // Every splat's sum is taken in the same order for any thread count (deterministic, no atomics),
  // and the outputs are written once, not read-modified-written per slot at random. Outputs
  // (original order; zero for splats not visible or never binned): g_geo [N, 6] = [dL/dmeans2d
  // (2), dL/dconic (3), dL/ddepth], g_opacity [N], g_color [N, NF - 1] (separate contiguous
  // tensors: autograd takes the last two as they are, without copies).
  const int C = NF - 1;
  auto g_geo = at::empty({N, 6}, at::kFloat);
  auto g_op = at::empty({N}, at::kFloat);
  auto g_col = at::empty({N, C}, at::kFloat);
  {
    const Geo* gp = reinterpret_cast<const Geo*>(geo_t.data_ptr<float>());
    const int32_t* srcp = src.data_ptr<int32_t>();
    float* og = g_geo.data_ptr<float>();
    float* oo = g_op.data_ptr<float>();
    float* oc = g_col.data_ptr<float>();
    const float* recp = rec;
    // sums [M, R] per row, layout of the records: [means2d (2), conic (3), opacity, features (NF;
    // depth last)]; after phase 1: [dL/dmeans2d (2), dL/dconic (3), dL/dopacity, dL/dfeatures]
    thread_local Scratch<float> sum_scratch;
    float* const sums = sum_scratch.get(static_cast<size_t>(std::max<int64_t>(M, 1)) * R);
    thread_local Scratch<int32_t> row_scratch;
    int32_t* const row_of = row_scratch.get(static_cast<size_t>(std::max<int64_t>(N, 1)));
    const int nth_red = P < MIN_PAIRS_PARALLEL ? 1 : nth;
#pragma omp parallel num_threads(nth_red)
    {
      const int t = omp_get_thread_num(), nt = omp_get_num_threads();
      const int64_t lo = M * t / nt, hi = M * (t + 1) / nt;  // this thread's rows
      const int64_t s0 = N * t / nt, s1 = N * (t + 1) / nt;  // and splats (original order)
      std::fill(sums + lo * R, sums + hi * R, 0.0f);
      std::fill(row_of + s0, row_of + s1, -1);
      for (int tile = 0; tile < T; ++tile) {
        // processed slots; a tile list holds rows in increasing (depth) order, so this thread's
        // rows [lo, hi) are one contiguous run of it
        const int32_t* first = tl + toff[tile];
        const int32_t* end = first + nproc[tile];
        const int32_t* b0 = std::lower_bound(first, end, static_cast<int32_t>(lo));
        const int32_t* b1 = std::lower_bound(b0, end, static_cast<int32_t>(hi));  // rows < 2^31
        for (int64_t slot = b0 - tl, e = b1 - tl; slot < e; ++slot) {
          const float* r = recp + slot * R;
          float* acc = sums + static_cast<int64_t>(tl[slot]) * R;
          for (int q = 0; q < R; ++q) acc[q] += r[q];
        }
      }
      for (int64_t i = lo; i < hi; ++i) {  // sums of power derivatives -> dL/dmeans2d, dL/dconic
        if (srcp[i] < 0) continue;  // unused row (the splat was never binned): geo unset
        const Geo& g = gp[i];
        float* o = sums + i * R;
        const float d0 = o[0], d1 = o[1];
        o[0] = g.a * d0 + g.b * d1;
        o[1] = g.b * d0 + g.c * d1;
        o[2] = -0.5f * o[2];
        o[3] = -o[3];
        o[4] = -0.5f * o[4];
      }
#pragma omp barrier
#pragma omp for schedule(static)
      for (int64_t i = 0; i < M; ++i)
        if (srcp[i] >= 0) row_of[srcp[i]] = static_cast<int32_t>(i);  // after every thread's fill
      // implicit barrier
      for (int64_t s = s0; s < s1; ++s) {
        if (s + PREFETCH < s1 && row_of[s + PREFETCH] >= 0)
          __builtin_prefetch(sums + static_cast<int64_t>(row_of[s + PREFETCH]) * R);
        const int32_t i = row_of[s];
        float* dg = og + s * 6;
        float* dc = oc + s * C;
        if (i < 0) {  // not visible or never binned
          std::fill(dg, dg + 6, 0.0f);
          oo[s] = 0.0f;
          std::fill(dc, dc + C, 0.0f);
          continue;
        }
        const float* o = sums + static_cast<int64_t>(i) * R;
        for (int q = 0; q < 5; ++q) dg[q] = o[q];
        dg[5] = o[6 + C];
        oo[s] = o[5];
        for (int q = 0; q < C; ++q) dc[q] = o[6 + q];
      }
    }
  }
  const Stamp t2 = now();
  double* st = stats.data_ptr<double>();
  int64_t ev = 0;
  for (int t = 0; t < nth; ++t) ev += tstats[8 * t + 2];
  st[2] = static_cast<double>(ev);
  put_ms(st, 8, t1.wall - t0.wall, t1.cpu - t0.cpu);  // raster bwd
  put_ms(st, 9, t2.wall - t1.wall, t2.cpu - t1.cpu);  // reduction
  return {g_geo, g_op, g_col};
}

// Test helpers.
at::Tensor fast_exp(at::Tensor x) {
  check_f32(x, "x", 1);
  auto y = at::empty({x.size(0)}, at::kFloat);
  const int64_t n = x.size(0);
  const float* xp = x.data_ptr<float>();
  float* yp = y.data_ptr<float>();
  alignas(32) float buf[8];
  for (int64_t i = 0; i < n; i += 8) {
    for (int l = 0; l < 8; ++l) buf[l] = i + l < n ? xp[i + l] : 0.0f;
    store(buf, vexp(load(buf)));
    for (int l = 0; l < 8 && i + l < n; ++l) yp[i + l] = buf[l];
  }
  return y;
}

at::Tensor depth_order_py(at::Tensor depths, at::Tensor visible) {
  check_f32(depths, "depths", 1);
  TORCH_CHECK(visible.scalar_type() == at::kBool && visible.is_contiguous() &&
                  visible.size(0) == depths.size(0),
              "visible must be a contiguous bool tensor like depths");
  auto o = depth_order(depths.data_ptr<float>(), visible.data_ptr<bool>(), depths.size(0), num_threads());
  auto t = at::empty({static_cast<int64_t>(o.size())}, at::kLong);
  std::copy(o.begin(), o.end(), t.data_ptr<int64_t>());
  return t;
}

bool has_avx2() {
#ifdef SF_SIMD_AVX2
  return true;
#else
  return false;
#endif
}

}  // namespace

TORCH_LIBRARY(splatfields_cpu, m) {
  m.def("forward", &forward);
  m.def("backward", &backward);
  m.def("fast_exp", &fast_exp);
  m.def("depth_order", &depth_order_py);
  m.def("has_avx2", &has_avx2);
}
