// The hidden layers of one field head as ONE kernel on AMX-BF16 tiles (src/fields/head_chain.py).
//
// A head's hidden layers are a chain of equal-width ReLU layers,
//
//     h_0 = ReLU(x_0),   h_l = ReLU(h_{l-1} W_lᵀ + a_l)   (l = 1..L),
//
// where a_l is the layer's bias [W] or, at a skip layer, its precomputed input part [N, W] (fused.py).
// Evaluated layer by layer through oneDNN, every layer writes and re-reads [N, W] activations and the
// backward runs separate passes for the ReLU mask, the bias sum and two products, whose weight-gradient
// product oneDNN runs at a third of its forward rate (docs/benchmarks.md). Here a block of 32 splats goes
// through ALL layers while it sits in cache: per layer two 16-row AMX tiles against the packed weight,
// the bias (or skip part) and the ReLU applied on the float32 tile result, rounded to bf16 as the next
// layer's input; only the activations h_0..h_L leave the cache (bf16, [L+1, N, W]), for the backward.
// The backward walks the same blocks from h_L down to h_0: mask, bias sum, the weight gradient
// (gᵀ h, accumulated in float32 per thread over its blocks) and the input gradient (g W), all in cache.
//
// Layouts (bf16 stored as uint16): activations row-major [N, W]; a weight for the forward product is
// packed "VNNI over its input" [W/2][W][2] (p[k][o][j] = W[o][2k+j]), for the backward input-gradient
// product "VNNI over its output" [W/2][W][2] (p[k][i][j] = W[2k+j][i]). Products round their operands to
// bf16 and accumulate in float32, as oneDNN's bf16 products do under CPU autocast. W must be a multiple of 32.

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>
#include <omp.h>

#include <immintrin.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <vector>

namespace {

constexpr int kRows = 32;  // splats per block: two 16-row tiles

struct alignas(64) TileConfig {
  uint8_t palette_id;
  uint8_t start_row;
  uint8_t reserved[14];
  uint16_t colsb[16];
  uint8_t rows[16];
};

// Every tile 16 rows x 64 bytes: C tiles 16 x 16 float32, A tiles 16 x 32 bf16, B tiles 16 pair-rows x 16 x 2 bf16.
void load_tile_config() {
  TileConfig cfg;
  std::memset(&cfg, 0, sizeof(cfg));
  cfg.palette_id = 1;
  for (int t = 0; t < 8; ++t) {
    cfg.colsb[t] = 64;
    cfg.rows[t] = 16;
  }
  _tile_loadconfig(&cfg);
}

// Linux asks a process to request the AMX tile state before its first tile instruction.
bool request_amx_permission() {
  constexpr long kArchReqXcompPerm = 0x1023;
  constexpr long kXfeatureXtiledata = 18;
  return syscall(SYS_arch_prctl, kArchReqXcompPerm, kXfeatureXtiledata) == 0;
}

inline __m512 load16(const float* p) { return _mm512_loadu_ps(p); }
inline __m512 load16(const uint16_t* p) {
  __m256i v = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(p));
  return _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_cvtepu16_epi32(v), 16));
}
// 16 bf16 at p, each zero-extended into a 32-bit lane
inline __m512i load16_u32(const uint16_t* p) {
  return _mm512_cvtepu16_epi32(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(p)));
}

// In-register transpose of a 16 x 16 float32 block (r[i] holds row i; afterwards column i).
inline void transpose16x16(__m512 r[16]) {
  __m512 t[16];
  for (int i = 0; i < 8; ++i) {
    t[2 * i] = _mm512_unpacklo_ps(r[2 * i], r[2 * i + 1]);
    t[2 * i + 1] = _mm512_unpackhi_ps(r[2 * i], r[2 * i + 1]);
  }
  for (int i = 0; i < 4; ++i) {
    r[4 * i] = _mm512_shuffle_ps(t[4 * i], t[4 * i + 2], _MM_SHUFFLE(1, 0, 1, 0));
    r[4 * i + 1] = _mm512_shuffle_ps(t[4 * i], t[4 * i + 2], _MM_SHUFFLE(3, 2, 3, 2));
    r[4 * i + 2] = _mm512_shuffle_ps(t[4 * i + 1], t[4 * i + 3], _MM_SHUFFLE(1, 0, 1, 0));
    r[4 * i + 3] = _mm512_shuffle_ps(t[4 * i + 1], t[4 * i + 3], _MM_SHUFFLE(3, 2, 3, 2));
  }
  for (int i = 0; i < 4; ++i) {
    t[i] = _mm512_shuffle_f32x4(r[i], r[i + 4], 0x88);
    t[i + 4] = _mm512_shuffle_f32x4(r[i], r[i + 4], 0xdd);
    t[i + 8] = _mm512_shuffle_f32x4(r[i + 8], r[i + 12], 0x88);
    t[i + 12] = _mm512_shuffle_f32x4(r[i + 8], r[i + 12], 0xdd);
  }
  for (int i = 0; i < 8; ++i) {
    r[i] = _mm512_shuffle_f32x4(t[i], t[i + 8], 0x88);
    r[i + 8] = _mm512_shuffle_f32x4(t[i], t[i + 8], 0xdd);
  }
}

// 32 floats (lo then hi) -> 32 bf16 at p, round to nearest even
inline void store32_bf16(uint16_t* p, __m512 lo, __m512 hi) {
  __m512bh v = _mm512_cvtne2ps_pbh(hi, lo);
  _mm512_storeu_si512(reinterpret_cast<void*>(p), reinterpret_cast<__m512i&>(v));
}

// C[M][N] (=, or += when acc) A[M][K] B, A row-major bf16 (lda), B packed [K/2][N][2] bf16, C float32 (ldc).
// M, N, K multiples of 32. Tiles: 0-3 C (2 x 2), 4-5 A, 6-7 B.
inline void gemm(const uint16_t* A, int lda, const uint16_t* B, int K, int N, float* C, int ldc, int M, bool acc) {
  for (int m = 0; m < M; m += 32) {
    for (int n = 0; n < N; n += 32) {
      float* c = C + static_cast<size_t>(m) * ldc + n;
      if (acc) {
        _tile_loadd(0, c, ldc * 4);
        _tile_loadd(1, c + 16, ldc * 4);
        _tile_loadd(2, c + 16 * ldc, ldc * 4);
        _tile_loadd(3, c + 16 * ldc + 16, ldc * 4);
      } else {
        _tile_zero(0);
        _tile_zero(1);
        _tile_zero(2);
        _tile_zero(3);
      }
      for (int k = 0; k < K; k += 32) {
        const uint16_t* a = A + static_cast<size_t>(m) * lda + k;
        const uint16_t* b = B + static_cast<size_t>(k / 2) * N * 2 + n * 2;
        _tile_loadd(4, a, lda * 2);
        _tile_loadd(5, a + 16 * lda, lda * 2);
        _tile_loadd(6, b, N * 4);
        _tile_loadd(7, b + 32, N * 4);
        _tile_dpbf16ps(0, 4, 6);
        _tile_dpbf16ps(1, 4, 7);
        _tile_dpbf16ps(2, 5, 6);
        _tile_dpbf16ps(3, 5, 7);
      }
      _tile_stored(0, c, ldc * 4);
      _tile_stored(1, c + 16, ldc * 4);
      _tile_stored(2, c + 16 * ldc, ldc * 4);
      _tile_stored(3, c + 16 * ldc + 16, ldc * 4);
    }
  }
}

// Row r of a [N, W] float32 or bf16 tensor (row stride in elements).
struct RowSource {
  const float* f32 = nullptr;
  const uint16_t* b16 = nullptr;
  int64_t stride = 0;
  explicit RowSource(const at::Tensor& t) : stride(t.stride(0)) {
    if (t.scalar_type() == at::kFloat) {
      f32 = t.data_ptr<float>();
    } else {
      b16 = reinterpret_cast<const uint16_t*>(t.data_ptr<at::BFloat16>());
    }
  }
  inline __m512 load(int64_t row, int col) const {
    return f32 ? load16(f32 + row * stride + col) : load16(b16 + row * stride + col);
  }
};

// True when this CPU has AVX512-BF16 and Linux granted this process the AMX tile state (asked once).
bool head_chain_available() {
  static const bool ok = [] {
    if (!__builtin_cpu_supports("avx512bf16")) return false;
    return request_amx_permission();
  }();
  return ok;
}

void check_input(const at::Tensor& t, const char* what, int64_t n, int64_t w) {
  TORCH_CHECK(t.device().is_cpu(), what, ": expected a CPU tensor");
  TORCH_CHECK(t.dim() == 2 && t.size(0) == n && t.size(1) == w, what, ": expected [", n, ", ", w, "], got ",
              t.sizes());
  TORCH_CHECK(t.stride(1) == 1, what, ": expected contiguous rows");
  TORCH_CHECK(t.scalar_type() == at::kFloat || t.scalar_type() == at::kBFloat16, what,
              ": expected float32 or bfloat16");
}

const uint16_t* bf16_ptr(const at::Tensor& t) { return reinterpret_cast<const uint16_t*>(t.data_ptr<at::BFloat16>()); }
uint16_t* bf16_ptr_mut(at::Tensor& t) { return reinterpret_cast<uint16_t*>(t.data_ptr<at::BFloat16>()); }

// Forward: x0 [N, W] (float32/bf16, pre-activation of h_0); w_in[l] [W/2, W, 2] bf16 (VNNI over input);
// adds[l]: bias [W] float32 or skip part [N, W] float32/bf16. Returns h_0..h_L, L+1 tensors [N, W] bf16 (one
// allocation per layer: sizes the allocator reuses between steps, where one [L+1, N, W] block would be mapped afresh).
std::vector<at::Tensor> head_chain_forward(const at::Tensor& x0, std::vector<at::Tensor> w_in, std::vector<at::Tensor> adds) {
  TORCH_CHECK(head_chain_available(), "head_chain_forward: this CPU or process cannot use AMX-BF16 tiles");
  const int64_t N = x0.size(0);
  const int W = static_cast<int>(x0.size(1));
  const int L = static_cast<int>(w_in.size());
  TORCH_CHECK(W % 32 == 0 && W <= 256, "head_chain_forward: width ", W, " must be a multiple of 32, at most 256");
  TORCH_CHECK(static_cast<int>(adds.size()) == L, "head_chain_forward: ", L, " weights but ", adds.size(), " adds");
  check_input(x0, "head_chain_forward x0", N, W);
  std::vector<const uint16_t*> wp(L);
  std::vector<const float*> bias(L, nullptr);
  std::vector<RowSource> skip;
  std::vector<int> skip_of(L, -1);
  for (int l = 0; l < L; ++l) {
    TORCH_CHECK(w_in[l].scalar_type() == at::kBFloat16 && w_in[l].is_contiguous() && w_in[l].numel() == W * W,
                "head_chain_forward: weight ", l, " must be a contiguous bf16 [W/2, W, 2] pack");
    wp[l] = bf16_ptr(w_in[l]);
    if (adds[l].dim() == 1) {
      TORCH_CHECK(adds[l].scalar_type() == at::kFloat && adds[l].is_contiguous() && adds[l].size(0) == W,
                  "head_chain_forward: bias ", l, " must be a contiguous float32 [W]");
      bias[l] = adds[l].data_ptr<float>();
    } else {
      check_input(adds[l], "head_chain_forward skip part", N, W);
      skip_of[l] = static_cast<int>(skip.size());
      skip.emplace_back(adds[l]);
    }
  }
  std::vector<at::Tensor> H(L + 1);
  std::vector<uint16_t*> Hp(L + 1);
  for (int l = 0; l <= L; ++l) {
    H[l] = at::empty({N, W}, x0.options().dtype(at::kBFloat16));
    Hp[l] = bf16_ptr_mut(H[l]);
  }
  const RowSource xs(x0);
  const int64_t n_blocks = (N + kRows - 1) / kRows;
  const __m512 zero = _mm512_setzero_ps();
  const int nt = std::max(1, at::get_num_threads());  // torch's thread count (threads=1 runs stay on one core)
#pragma omp parallel num_threads(nt)
  {
    load_tile_config();
    alignas(64) uint16_t hb[kRows * 256];  // current activations [32, W] bf16 (W <= 256)
    alignas(64) float cf[kRows * 256];     // product result [32, W] float32
#pragma omp for schedule(static)
    for (int64_t b = 0; b < n_blocks; ++b) {
      const int64_t r0 = b * kRows;
      const int nr = static_cast<int>(std::min<int64_t>(kRows, N - r0));
      for (int r = 0; r < kRows; ++r) {
        for (int o = 0; o < W; o += 32) {
          __m512 lo = zero, hi = zero;
          if (r < nr) {
            lo = _mm512_max_ps(xs.load(r0 + r, o), zero);
            hi = _mm512_max_ps(xs.load(r0 + r, o + 16), zero);
          }
          store32_bf16(hb + r * W + o, lo, hi);
        }
        if (r < nr) std::memcpy(Hp[0] + (r0 + r) * W, hb + r * W, W * 2);
      }
      for (int l = 0; l < L; ++l) {
        gemm(hb, W, wp[l], W, W, cf, W, kRows, false);
        uint16_t* Hl = Hp[l + 1];
        for (int r = 0; r < kRows; ++r) {
          for (int o = 0; o < W; o += 32) {
            __m512 lo = load16(cf + r * W + o), hi = load16(cf + r * W + o + 16);
            if (bias[l]) {
              lo = _mm512_add_ps(lo, load16(bias[l] + o));
              hi = _mm512_add_ps(hi, load16(bias[l] + o + 16));
            } else if (r < nr) {
              lo = _mm512_add_ps(lo, skip[skip_of[l]].load(r0 + r, o));
              hi = _mm512_add_ps(hi, skip[skip_of[l]].load(r0 + r, o + 16));
            }
            store32_bf16(hb + r * W + o, _mm512_max_ps(lo, zero), _mm512_max_ps(hi, zero));
          }
          if (r < nr) std::memcpy(Hl + (r0 + r) * W, hb + r * W, W * 2);
        }
      }
    }
    _tile_release();
  }
  return H;
}

// Rows r0 .. r0+nr of out [N, W]: the float32 block g, or its bf16 rounding gb when out is bf16.
void store_rows(at::Tensor& out, int64_t r0, int nr, int W, const float* g, const uint16_t* gb) {
  if (out.scalar_type() == at::kBFloat16) {
    std::memcpy(bf16_ptr_mut(out) + r0 * W, gb, sizeof(uint16_t) * nr * W);
  } else {
    std::memcpy(out.data_ptr<float>() + r0 * W, g, sizeof(float) * nr * W);
  }
}

// Backward: g_out [N, W] (gradient of h_L), H from the forward, w_out[l] [W/2, W, 2] bf16 (VNNI over output),
// is_skip[l] (1: a skip layer, 0: a bias layer), out_bf16: g_x0 and the skip gradients in bf16 (else float32).
// Returns (g_x0 [N, W], g_w [L, W, W] float32, g_add [L] list: [W] float32 bias or [N, W] skip gradient).
std::tuple<at::Tensor, at::Tensor, std::vector<at::Tensor>> head_chain_backward(
    const at::Tensor& g_out, std::vector<at::Tensor> H, std::vector<at::Tensor> w_out, std::vector<int64_t> is_skip,
    bool out_bf16) {
  TORCH_CHECK(head_chain_available(), "head_chain_backward: this CPU or process cannot use AMX-BF16 tiles");
  const int L = static_cast<int>(w_out.size());
  TORCH_CHECK(static_cast<int>(H.size()) == L + 1, "head_chain_backward: expected ", L + 1, " activations");
  const int64_t N = H[0].size(0);
  const int W = static_cast<int>(H[0].size(1));
  std::vector<const uint16_t*> Hp(L + 1);
  for (int l = 0; l <= L; ++l) {
    TORCH_CHECK(H[l].dim() == 2 && H[l].size(0) == N && H[l].size(1) == W && H[l].scalar_type() == at::kBFloat16 &&
                H[l].is_contiguous(), "head_chain_backward: activation ", l, " must be the forward's bf16 [N, W]");
    Hp[l] = bf16_ptr(H[l]);
  }
  TORCH_CHECK(static_cast<int>(is_skip.size()) == L, "head_chain_backward: is_skip has the wrong length");
  TORCH_CHECK(W % 32 == 0 && W <= 256, "head_chain_backward: width ", W, " must be a multiple of 32, at most 256");
  check_input(g_out, "head_chain_backward g_out", N, W);
  std::vector<const uint16_t*> wp(L);
  for (int l = 0; l < L; ++l) {
    TORCH_CHECK(w_out[l].scalar_type() == at::kBFloat16 && w_out[l].is_contiguous() && w_out[l].numel() == W * W,
                "head_chain_backward: weight ", l, " must be a contiguous bf16 [W/2, W, 2] pack");
    wp[l] = bf16_ptr(w_out[l]);
  }
  const auto fopts = g_out.options().dtype(at::kFloat);
  const auto gopts = g_out.options().dtype(out_bf16 ? at::kBFloat16 : at::kFloat);
  at::Tensor g_x0 = at::empty({N, W}, gopts);
  std::vector<at::Tensor> g_add(L);
  for (int l = 0; l < L; ++l) g_add[l] = is_skip[l] ? at::empty({N, W}, gopts) : at::Tensor();
  const int n_threads = std::max(1, at::get_num_threads());  // torch's thread count, as in the forward
  const int64_t per_thread = static_cast<int64_t>(L) * W * W + static_cast<int64_t>(L) * W;
  std::vector<float> acc(static_cast<size_t>(n_threads) * per_thread, 0.0f);  // per thread: g_w [L,W,W], g_b [L,W]
  const RowSource gs(g_out);
  const int64_t n_blocks = (N + kRows - 1) / kRows;
  const __m512 zero = _mm512_setzero_ps();
#pragma omp parallel num_threads(n_threads)
  {
    load_tile_config();
    float* gw_t = acc.data() + static_cast<size_t>(omp_get_thread_num()) * per_thread;
    float* gb_t = gw_t + static_cast<int64_t>(L) * W * W;
    alignas(64) float g[kRows * 256];         // gradient of the current layer's output [32, W] float32
    alignas(64) uint16_t gpb[kRows * 256];    // masked gradient, bf16 row-major [32, W]
    alignas(64) uint16_t gpt[256 * kRows];    // masked gradient, bf16 transposed [W, 32]
    alignas(64) uint16_t hv[kRows * 256];     // layer input, VNNI over rows [16, W, 2]
#pragma omp for schedule(static)
    for (int64_t b = 0; b < n_blocks; ++b) {
      const int64_t r0 = b * kRows;
      const int nr = static_cast<int>(std::min<int64_t>(kRows, N - r0));
      for (int r = 0; r < kRows; ++r)
        for (int o = 0; o < W; o += 16) _mm512_storeu_ps(g + r * W + o, r < nr ? gs.load(r0 + r, o) : zero);
      for (int l = L; l >= 0; --l) {
        const uint16_t* Hl = Hp[l];
        // mask by h_l > 0 (pad rows: zero): float32 in place in g, bf16-rounded in gpb
        for (int r = 0; r < kRows; ++r) {
          for (int o = 0; o < W; o += 32) {
            __m512 lo = zero, hi = zero;
            if (r < nr) {
              __m512 y0 = load16(Hl + (r0 + r) * W + o), y1 = load16(Hl + (r0 + r) * W + o + 16);
              lo = _mm512_maskz_mov_ps(_mm512_cmp_ps_mask(y0, zero, _CMP_GT_OQ), load16(g + r * W + o));
              hi = _mm512_maskz_mov_ps(_mm512_cmp_ps_mask(y1, zero, _CMP_GT_OQ), load16(g + r * W + o + 16));
            }
            _mm512_storeu_ps(g + r * W + o, lo);
            _mm512_storeu_ps(g + r * W + o + 16, hi);
            store32_bf16(gpb + r * W + o, lo, hi);
          }
        }
        if (l == 0) {  // gradient of x0
          store_rows(g_x0, r0, nr, W, g, gpb);
          break;
        }
        const int li = l - 1;  // weight index of the layer producing h_l
        if (is_skip[li]) {
          store_rows(g_add[li], r0, nr, W, g, gpb);
        } else {
          float* gb = gb_t + static_cast<int64_t>(li) * W;
          for (int o = 0; o < W; o += 16) {
            __m512 s = load16(gb + o);
            for (int r = 0; r < nr; ++r) s = _mm512_add_ps(s, load16(g + r * W + o));
            _mm512_storeu_ps(gb + o, s);
          }
        }
        // transpose the masked gradient to [W, 32], bf16 (16 x 16 float32 blocks)
        for (int ob = 0; ob < W; ob += 16) {
          __m512 lo[16], hi[16];
          for (int r = 0; r < 16; ++r) {
            lo[r] = load16(g + r * W + ob);
            hi[r] = load16(g + (r + 16) * W + ob);
          }
          transpose16x16(lo);
          transpose16x16(hi);
          for (int o = 0; o < 16; ++o) store32_bf16(gpt + (ob + o) * kRows, lo[o], hi[o]);
        }
        // layer input h_{l-1}, VNNI over rows: hv[k][i][j] = h[2k+j][i]
        const uint16_t* Hin = Hp[l - 1];
        for (int k = 0; k < kRows / 2; ++k) {
          const int ra = 2 * k, rb = 2 * k + 1;
          for (int i = 0; i < W; i += 16) {
            const __m512i a = ra < nr ? load16_u32(Hin + (r0 + ra) * W + i) : _mm512_setzero_si512();
            const __m512i c = rb < nr ? load16_u32(Hin + (r0 + rb) * W + i) : _mm512_setzero_si512();
            _mm512_storeu_si512(reinterpret_cast<void*>(hv + (k * W + i) * 2), _mm512_or_si512(a, _mm512_slli_epi32(c, 16)));
          }
        }
        gemm(gpt, kRows, hv, kRows, W, gw_t + static_cast<int64_t>(li) * W * W, W, W, true);  // g_W += gᵀ h
        gemm(gpb, W, wp[li], W, W, g, W, kRows, false);                                      // g_h = g W
      }
    }
    _tile_release();
  }
  at::Tensor g_w = at::zeros({L, W, W}, fopts);
  at::Tensor g_b = at::zeros({L, W}, fopts);
  float* gwp = g_w.data_ptr<float>();
  float* gbp = g_b.data_ptr<float>();
  for (int t = 0; t < n_threads; ++t) {
    const float* a = acc.data() + static_cast<size_t>(t) * per_thread;
    for (int64_t i = 0; i < static_cast<int64_t>(L) * W * W; ++i) gwp[i] += a[i];
    for (int64_t i = 0; i < static_cast<int64_t>(L) * W; ++i) gbp[i] += a[static_cast<int64_t>(L) * W * W + i];
  }
  for (int l = 0; l < L; ++l)
    if (!is_skip[l]) g_add[l] = g_b[l];
  return {g_x0, g_w, g_add};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(splatfields_cpu, m) {
  m.def("head_chain_forward", &head_chain_forward);
  m.def("head_chain_backward", &head_chain_backward);
  m.def("head_chain_available", &head_chain_available);
}
