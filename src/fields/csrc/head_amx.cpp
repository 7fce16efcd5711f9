// A field head's layers as ONE kernel on AMX-BF16 tiles (src/fields/head_kernel.py).
//
// A head reads its input x = [f, PE(x)] [N, K] at its first linear and at each skip linear, runs equal-width
// ReLU layers and ends in a linear output (a head's 3 colours, 1 opacity, 3 scales or 4 quaternion terms; a flow
// trunk's features):
//
//     h_0 = ReLU(x A_0ᵀ + b_0),   h_l = ReLU(h_{l-1} W_lᵀ [+ x A_lᵀ at a skip layer] + b_l)   (l = 1..L),
//     y   = h_L W_outᵀ + b_out                                                              [N, O] float32.
//
// Evaluated layer by layer through oneDNN, every layer writes and re-reads [N, W] activations, the input
// layers write one wide [N, S] product that the backward gathers again, the output layer runs on a float32
// copy of h_L, and the backward runs separate passes for masks, bias sums and products. Here a block of
// splats (block_rows: 32..256) goes through ALL layers while it sits in cache: per layer 16-row AMX tiles against the packed
// weights, starting from the bias (a skip layer's two products into the same tiles), ReLU applied on the float32
// tile result, rounded to bf16 as the next layer's input; a narrow output layer (O < 32) in float32 FMAs on the
// bf16 h_L, a wide one as one more tile product (its width padded to 32). Only the activations h_0..h_L leave the
// cache (bf16, one [N, W] tensor per layer, streamed out with non-temporal stores), for the backward. The
// backward walks the same blocks from y down to x: output
// layer, then per layer the mask, the bias sum, the weight gradients (gᵀ h and gᵀ x, accumulated in float32
// per thread over its blocks) and the input gradients (g W, and g A into the block's x gradient), all in cache.
//
// Layouts (bf16 stored as uint16): activations row-major [N, W]; x row-major [N, K] (float32 or bf16, row
// stride free), zero-padded in cache to Kp (a multiple of 32); a weight for a forward product is packed
// "VNNI over its input" [in/2][out][2] (p[k][o][j] = W[o][2k+j]), for the backward input-gradient product
// "VNNI over its output" [out/2][in][2] (p[k][i][j] = W[2k+j][i]). Products round their operands to bf16 and
// accumulate in float32, as oneDNN's bf16 products do under CPU autocast. W must be a multiple of 32.

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
#include <cstdlib>
#include <cstring>
#include <vector>

#include "bf16_round.h"

namespace {


// 64-byte aligned per-thread scratch of n elements of T, freed at scope exit.
template <typename T>
struct Scratch {
  T* p;
  explicit Scratch(size_t n) : p(static_cast<T*>(std::aligned_alloc(64, (n * sizeof(T) + 63) / 64 * 64))) {}
  ~Scratch() { std::free(p); }
  Scratch(const Scratch&) = delete;
  Scratch& operator=(const Scratch&) = delete;
  operator T*() const { return p; }
};

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

// Tiles 0-3 (a 32 x 32 float32 C block at rows m, columns n: 2 x 2 tiles) += A[m .. m+32][0 .. K] B[0 .. K][n .. n+32],
// A row-major bf16 (lda), B packed [K/2][N][2] bf16. Tiles 4-5 hold A, 6-7 B.
inline void tiles_accumulate(const uint16_t* A, int lda, const uint16_t* B, int K, int N, int m, int n) {
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
}

// Tiles 0-3 into the 32 x 32 float32 block at c (row stride ldc).
inline void tiles_store(float* c, int ldc) {
  _tile_stored(0, c, ldc * 4);
  _tile_stored(1, c + 16, ldc * 4);
  _tile_stored(2, c + 16 * ldc, ldc * 4);
  _tile_stored(3, c + 16 * ldc + 16, ldc * 4);
}

// C[M][N] (=, or += when acc) A[M][K] B, A row-major bf16 (lda), B packed [K/2][N][2] bf16, C float32 (ldc).
// M, N, K multiples of 32.
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
      tiles_accumulate(A, lda, B, K, N, m, n);
      tiles_store(c, ldc);
    }
  }
}

// Forward product with its bias: C[M][N] = C0 + A1 B1 (+ A2 B2 where A2 is given; no A1 B1 where A1 is null),
// A row-major bf16, B packed [K/2][N][2] bf16, C0 [16][N] float32 (the bias, one row repeated 16 times: each 16-row
// C tile starts from it), C float32 (ldc). M, N, K multiples of 32. Both products accumulate in the same tiles (no
// store and reload between).
inline void gemm_bias(const uint16_t* A1, int lda1, const uint16_t* B1, int K1, const uint16_t* A2, int lda2,
                      const uint16_t* B2, int K2, const float* C0, int N, float* C, int ldc, int M) {
  for (int m = 0; m < M; m += 32) {
    for (int n = 0; n < N; n += 32) {
      _tile_loadd(0, C0 + n, N * 4);
      _tile_loadd(1, C0 + n + 16, N * 4);
      _tile_loadd(2, C0 + n, N * 4);
      _tile_loadd(3, C0 + n + 16, N * 4);
      if (A1 != nullptr) tiles_accumulate(A1, lda1, B1, K1, N, m, n);
      if (A2 != nullptr) tiles_accumulate(A2, lda2, B2, K2, N, m, n);
      tiles_store(C + static_cast<size_t>(m) * ldc + n, ldc);
    }
  }
}

// One weight w [out, in] (float32, any strides) as a bf16 pack of [rows, cols] >= [out, in] (the rows past `out`
// and the columns past `in` zero): over_input, "VNNI over its input" [cols/2][rows][2] (p[k][o][j] = w[o][2k+j]);
// else "VNNI over its output" [rows/2][cols][2] (p[k][i][j] = w[2k+j][i]). rows and cols even.
void pack_weight(const at::Tensor& w, int rows, int cols, bool over_input, uint16_t* p) {
  const int out = static_cast<int>(w.size(0)), in = static_cast<int>(w.size(1));
  const float* wp = w.data_ptr<float>();
  const int64_t so = w.stride(0), si = w.stride(1);
  auto elem = [&](int o, int i) { return o < out && i < in ? to_bf16(wp[o * so + i * si]) : static_cast<uint16_t>(0); };
  if (over_input) {
    for (int k = 0; k < cols / 2; ++k)
      for (int o = 0; o < rows; ++o) {
        p[(k * rows + o) * 2] = elem(o, 2 * k);
        p[(k * rows + o) * 2 + 1] = elem(o, 2 * k + 1);
      }
  } else {
    for (int k = 0; k < rows / 2; ++k)
      for (int i = 0; i < cols; ++i) {
        p[(k * cols + i) * 2] = elem(2 * k, i);
        p[(k * cols + i) * 2 + 1] = elem(2 * k + 1, i);
      }
  }
}

// Outputs from which the output layer runs as a tile product, its width padded to Ot (a multiple of 32; bf16
// operands, float32 accumulation: its weight rounded to bf16 as the hidden layers' are); below, float32 dot
// products on the bf16 h_L (a head's few values).
constexpr int kTileOutput = 32;
inline int tile_outputs(int O) { return O >= kTileOutput ? (O + 31) / 32 * 32 : O; }

// 16 floats -> 16 bf16 at p, round to nearest even
inline void store16_bf16(uint16_t* p, __m512 v) {
  __m256bh b = _mm512_cvtneps_pbh(v);
  _mm256_storeu_si256(reinterpret_cast<__m256i*>(p), reinterpret_cast<__m256i&>(b));
}

// Row r, columns ob .. ob+15 of the gradient g [rows, W] masked by its layer's output h > 0 (h: [rows, W] bf16);
// zero for a pad row (r >= nr).
inline __m512 masked_gradient(const float* g, const uint16_t* h, int W, int r, int nr, int ob) {
  if (r >= nr) return _mm512_setzero_ps();
  const __m512 y = load16(h + r * W + ob);
  return _mm512_maskz_mov_ps(_mm512_cmp_ps_mask(y, _mm512_setzero_ps(), _CMP_GT_OQ), _mm512_loadu_ps(g + r * W + ob));
}

// src [rows, cols] float32 (row stride ld) -> dst [cols, rows] bf16: 16 x 16 blocks, 32 rows at a time.
// rows a multiple of 32, cols of 16.
void transpose_bf16(const float* src, int ld, int rows, int cols, uint16_t* dst) {
  for (int ob = 0; ob < cols; ob += 16) {
    for (int rp = 0; rp < rows; rp += 32) {
      __m512 lo[16], hi[16];
      for (int r = 0; r < 16; ++r) {
        lo[r] = _mm512_loadu_ps(src + (rp + r) * ld + ob);
        hi[r] = _mm512_loadu_ps(src + (rp + r + 16) * ld + ob);
      }
      transpose16x16(lo);
      transpose16x16(hi);
      for (int o = 0; o < 16; ++o) store32_bf16(dst + (ob + o) * rows + rp, lo[o], hi[o]);
    }
  }
}

// Row r of a [N, C] float32 or bf16 tensor (row stride in elements).
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
  // the n <= 16 elements from column col as float32 (the rest zero; nothing past them is read)
  inline __m512 load(int64_t row, int col, int n = 16) const {
    const __mmask16 m = n >= 16 ? static_cast<__mmask16>(0xffff) : static_cast<__mmask16>((1u << n) - 1u);
    if (f32) return _mm512_maskz_loadu_ps(m, f32 + row * stride + col);
    __m256i v = _mm256_maskz_loadu_epi16(m, b16 + row * stride + col);
    return _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_cvtepu16_epi32(v), 16));
  }
};

// True when this CPU has AVX512-BF16 and Linux granted this process the AMX tile state (asked once).
bool head_available() {
  static const bool ok = [] {
    if (!__builtin_cpu_supports("avx512bf16")) return false;
    return request_amx_permission();
  }();
  return ok;
}

const uint16_t* bf16_ptr(const at::Tensor& t) { return reinterpret_cast<const uint16_t*>(t.data_ptr<at::BFloat16>()); }
uint16_t* bf16_ptr_mut(at::Tensor& t) { return reinterpret_cast<uint16_t*>(t.data_ptr<at::BFloat16>()); }

inline float hsum(__m512 v) { return _mm512_reduce_add_ps(v); }

// Rows r0 .. r0+nr of x [N, K] into xb [rows, Kp] bf16 (columns K..Kp and rows nr..rows zero).
void load_x_block(const RowSource& xs, int64_t r0, int nr, int rows, int K, int Kp, uint16_t* xb) {
  const __m512 zero = _mm512_setzero_ps();
  for (int r = 0; r < rows; ++r) {
    for (int c = 0; c < Kp; c += 32) {
      __m512 lo = zero, hi = zero;
      if (r < nr) {
        if (c < K) lo = xs.load(r0 + r, c, K - c);
        if (c + 16 < K) hi = xs.load(r0 + r, c + 16, K - c - 16);
      }
      store32_bf16(xb + r * Kp + c, lo, hi);
    }
  }
}

// VNNI over rows of a [rows, C] bf16 block (row stride ld, rows >= nr zero): dst[k][i][j] = src[2k+j][i].
void vnni_rows(const uint16_t* src, int64_t ld, int nr, int rows, int C, uint16_t* dst) {
  for (int k = 0; k < rows / 2; ++k) {
    const int ra = 2 * k, rb = 2 * k + 1;
    for (int i = 0; i < C; i += 16) {
      const __m512i a = ra < nr ? load16_u32(src + ra * ld + i) : _mm512_setzero_si512();
      const __m512i c = rb < nr ? load16_u32(src + rb * ld + i) : _mm512_setzero_si512();
      _mm512_storeu_si512(reinterpret_cast<void*>(dst + (k * C + i) * 2), _mm512_or_si512(a, _mm512_slli_epi32(c, 16)));
    }
  }
}

// Rows r0 .. r0+nr of g [N, K] (float32, or bf16 rounded to nearest even) from the block gb [rows, Kp] float32.
// Rows r0 .. r0+nr of g [N, K] (float32 or bf16) from the block's float32 gradient gb [rows, Kp]: written, or with
// add = true added to what g holds (bf16: the sum rounded once, to nearest even).
void store_x_rows(at::Tensor& g, int64_t r0, int nr, int K, int Kp, const float* gb, bool add) {
  if (g.scalar_type() == at::kFloat) {
    float* gp = g.data_ptr<float>();
    for (int r = 0; r < nr; ++r) {
      float* dst = gp + (r0 + r) * K;
      if (add) {
        for (int c = 0; c < K; ++c) dst[c] += gb[r * Kp + c];
      } else {
        std::memcpy(dst, gb + r * Kp, sizeof(float) * K);
      }
    }
    return;
  }
  uint16_t* gp = bf16_ptr_mut(g);
  for (int r = 0; r < nr; ++r) {
    for (int c = 0; c < K; c += 32) {
      const int n = std::min(32, K - c);
      const __mmask32 m = n >= 32 ? ~static_cast<__mmask32>(0) : (static_cast<__mmask32>(1) << n) - 1;
      uint16_t* dst = gp + (r0 + r) * K + c;
      __m512 lo = load16(gb + r * Kp + c), hi = load16(gb + r * Kp + c + 16);
      if (add) {  // the held bf16 values widened to float32 (a bf16 is the top half of a float32)
        const __m512i held = _mm512_maskz_loadu_epi16(m, dst);
        lo = _mm512_add_ps(lo, _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_cvtepu16_epi32(_mm512_castsi512_si256(held)), 16)));
        hi = _mm512_add_ps(hi, _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_cvtepu16_epi32(_mm512_extracti64x4_epi64(held, 1)), 16)));
      }
      __m512bh v = _mm512_cvtne2ps_pbh(hi, lo);
      _mm512_mask_storeu_epi16(dst, m, reinterpret_cast<__m512i&>(v));
    }
  }
}

struct Shape {
  int64_t N;
  int K, Kp, W, L, O;
};

// Checks shared by forward and backward; returns the head's shape.
Shape check_head(const at::Tensor& x, int64_t n_x, int64_t L, const std::vector<int64_t>& reads_x, const at::Tensor& w_out,
                 const char* fn) {
  TORCH_CHECK(head_available(), fn, ": this CPU or process cannot use AMX-BF16 tiles");
  TORCH_CHECK(x.device().is_cpu() && x.dim() == 2 && x.stride(1) == 1, fn, ": x must be a CPU [N, K] tensor with contiguous rows");
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kBFloat16, fn, ": x must be float32 or bfloat16");
  TORCH_CHECK(w_out.dim() == 2 && w_out.scalar_type() == at::kFloat && w_out.is_contiguous(), fn,
              ": w_out must be a contiguous float32 [O, W]");
  Shape s{x.size(0), static_cast<int>(x.size(1)), 0, static_cast<int>(w_out.size(1)), static_cast<int>(L),
          static_cast<int>(w_out.size(0))};
  s.Kp = (s.K + 31) / 32 * 32;
  TORCH_CHECK(s.W % 32 == 0 && s.W <= 256, fn, ": width ", s.W, " must be a multiple of 32, at most 256");
  TORCH_CHECK(s.K >= 1 && s.Kp <= 256, fn, ": input width ", s.K, " must be 1..256");
  TORCH_CHECK(s.O >= 1 && s.O <= 256, fn, ": output width ", s.O, " must be 1..256");
  TORCH_CHECK(static_cast<int64_t>(reads_x.size()) == L + 1 && reads_x[0] == 0, fn,
              ": reads_x must name an input weight for each of the L + 1 layers, the first layer's being 0");
  for (int64_t l = 0; l <= L; ++l)
    TORCH_CHECK(reads_x[l] >= -1 && reads_x[l] < n_x, fn, ": reads_x[", l, "] = ", reads_x[l], " is not an input weight");
  return s;
}

// Splats per block: a multiple of 32 (pairs of 16-row tiles), at most 256.
int check_rows(int64_t block_rows, const char* fn) {
  TORCH_CHECK(block_rows >= 32 && block_rows <= 256 && block_rows % 32 == 0, fn, ": block_rows ", block_rows,
              " must be 32, 64, ..., 256");
  return static_cast<int>(block_rows);
}

void check_pack(const at::Tensor& p, int64_t numel, const char* fn, const char* what, int64_t i) {
  TORCH_CHECK(p.scalar_type() == at::kBFloat16 && p.is_contiguous() && p.numel() == numel, fn, ": ", what, " ", i,
              " must be a contiguous bf16 pack of ", numel, " elements, got ", p.numel());
}

// Forward. x [N, K]; a_in[s] [Kp/2, W, 2] the input weights (first layer, skip layers; zero-padded to Kp);
// w_in[l] [W/2, W, 2] the hidden weights (l = 1..L stored at l-1); bias [L+1, W] float32; reads_x[l]: the
// input weight layer l adds (-1: none); w_out [O, W], b_out [O] float32.
// Returns (y [N, O] float32, h_0..h_L: L+1 tensors [N, W] bf16, one allocation per layer: sizes the allocator
// reuses between steps, where one [L+1, N, W] block would be mapped afresh).
std::tuple<at::Tensor, std::vector<at::Tensor>> head_forward(
    const at::Tensor& x, std::vector<at::Tensor> a_in, std::vector<at::Tensor> w_in, const at::Tensor& bias,
    std::vector<int64_t> reads_x, const at::Tensor& w_out, const at::Tensor& b_out, int64_t block_rows) {
  const char* fn = "head_forward";
  const int rows = check_rows(block_rows, fn);
  const Shape s = check_head(x, static_cast<int64_t>(a_in.size()), static_cast<int64_t>(w_in.size()), reads_x, w_out, fn);
  const int64_t N = s.N;
  const int K = s.K, Kp = s.Kp, W = s.W, L = s.L, O = s.O;
  std::vector<const uint16_t*> ap(a_in.size()), wp(L);
  for (size_t i = 0; i < a_in.size(); ++i) {
    check_pack(a_in[i], static_cast<int64_t>(Kp) * W, fn, "input weight", static_cast<int64_t>(i));
    ap[i] = bf16_ptr(a_in[i]);
  }
  for (int l = 0; l < L; ++l) {
    check_pack(w_in[l], static_cast<int64_t>(W) * W, fn, "hidden weight", l);
    wp[l] = bf16_ptr(w_in[l]);
  }
  TORCH_CHECK(bias.scalar_type() == at::kFloat && bias.is_contiguous() && bias.numel() == static_cast<int64_t>(L + 1) * W,
              fn, ": bias must be a contiguous float32 [L + 1, W]");
  TORCH_CHECK(b_out.scalar_type() == at::kFloat && b_out.is_contiguous() && b_out.numel() == O, fn,
              ": b_out must be a contiguous float32 [O]");
  const float* bp = bias.data_ptr<float>();
  std::vector<float> bias16(static_cast<size_t>(L + 1) * 16 * W);  // [L+1][16][W]: each layer's bias in 16 rows
  for (int l = 0; l <= L; ++l)
    for (int r = 0; r < 16; ++r) std::memcpy(bias16.data() + (l * 16 + r) * W, bp + l * W, sizeof(float) * W);
  const float* wo = w_out.data_ptr<float>();
  const float* bo = b_out.data_ptr<float>();
  const int Ot = tile_outputs(O);
  const bool tile_out = O >= kTileOutput;
  std::vector<uint16_t> wo_pack;  // a tiled output layer's weight, VNNI over its input [W/2][Ot][2] (rows >= O zero)
  std::vector<float> bias16_out;  // its bias in 16 rows [16][Ot]
  if (tile_out) {
    wo_pack.resize(static_cast<size_t>(W) * Ot);
    pack_weight(w_out, Ot, W, true, wo_pack.data());
    bias16_out.assign(static_cast<size_t>(16) * Ot, 0.0f);
    for (int r = 0; r < 16; ++r) std::memcpy(bias16_out.data() + r * Ot, bo, sizeof(float) * O);
  }
  std::vector<at::Tensor> H(L + 1);
  std::vector<uint16_t*> Hp(L + 1);
  for (int l = 0; l <= L; ++l) {
    H[l] = at::empty({N, W}, x.options().dtype(at::kBFloat16));
    Hp[l] = bf16_ptr_mut(H[l]);
  }
  bool h_aligned = true;  // every H row starts on a 64-byte line (W a multiple of 32): streaming stores apply
  for (int l = 0; l <= L; ++l) h_aligned = h_aligned && reinterpret_cast<uintptr_t>(Hp[l]) % 64 == 0;
  at::Tensor y = at::empty({N, O}, x.options().dtype(at::kFloat));
  float* yp = y.data_ptr<float>();
  const RowSource xs(x);
  const int64_t n_blocks = (N + rows - 1) / rows;
  const __m512 zero = _mm512_setzero_ps();
  const int nt = std::max(1, at::get_num_threads());  // torch's thread count (threads=1 runs stay on one core)
#pragma omp parallel num_threads(nt)
  {
    load_tile_config();
    Scratch<uint16_t> xb(rows * 256);  // the block's input [rows, Kp] bf16
    Scratch<uint16_t> hb(rows * 256);  // current activations [rows, W] bf16 (W <= 256)
    Scratch<float> cf(rows * 256);     // product result [rows, W] float32
#pragma omp for schedule(static)
    for (int64_t b = 0; b < n_blocks; ++b) {
      const int64_t r0 = b * rows;
      const int nr = static_cast<int>(std::min<int64_t>(rows, N - r0));
      load_x_block(xs, r0, nr, rows, K, Kp, xb);
      for (int l = 0; l <= L; ++l) {
        const int s_x = reads_x[l];
        gemm_bias(l > 0 ? static_cast<const uint16_t*>(hb) : nullptr, W, l > 0 ? wp[l - 1] : nullptr, W,
                  s_x >= 0 ? static_cast<const uint16_t*>(xb) : nullptr, Kp, s_x >= 0 ? ap[s_x] : nullptr, Kp,
                  bias16.data() + static_cast<size_t>(l) * 16 * W, W, cf, W, rows);
        // ReLU, rounded to bf16: into hb (the next layer's input, in cache) and streamed into H (not read again
        // before the backward: non-temporal stores skip reading the destination's lines first)
        uint16_t* h_dst = Hp[l] + r0 * W;
        for (int r = 0; r < rows; ++r)
          for (int o = 0; o < W; o += 32) {
            __m512bh v = _mm512_cvtne2ps_pbh(_mm512_max_ps(load16(cf + r * W + o + 16), zero),
                                             _mm512_max_ps(load16(cf + r * W + o), zero));
            const __m512i vi = reinterpret_cast<__m512i&>(v);
            _mm512_storeu_si512(reinterpret_cast<void*>(hb + r * W + o), vi);
            if (r < nr) {
              if (h_aligned) {
                _mm512_stream_si512(reinterpret_cast<__m512i*>(h_dst + r * W + o), vi);
              } else {
                _mm512_storeu_si512(reinterpret_cast<void*>(h_dst + r * W + o), vi);
              }
            }
          }
      }
      if (tile_out) {  // y = h_L W_outᵀ + b_out as a tile product
        gemm_bias(hb, W, wo_pack.data(), W, nullptr, 0, nullptr, 0, bias16_out.data(), Ot, cf, Ot, rows);
        for (int r = 0; r < nr; ++r) std::memcpy(yp + (r0 + r) * O, cf + r * Ot, sizeof(float) * O);
      } else {  // y = h_L W_outᵀ + b_out, float32 on the bf16 h_L
        for (int r = 0; r < nr; ++r) {
          for (int o = 0; o < O; ++o) {
            __m512 acc = zero;
            for (int i = 0; i < W; i += 16) acc = _mm512_fmadd_ps(load16(hb + r * W + i), load16(wo + o * W + i), acc);
            yp[(r0 + r) * O + o] = hsum(acc) + bo[o];
          }
        }
      }
    }
    _mm_sfence();  // the streamed H visible before the region ends
    _tile_release();
  }
  return {y, H};
}

// Backward. g_y [N, O] float32; x, H (h_0..h_L) from the forward; a_out[s] [W/2, Kp, 2] the input weights packed
// over their output; w_out_packs[l] [W/2, W, 2] the hidden weights packed over their output; reads_x as in the
// forward; w_out [O, W] float32; g_x_into: none, or a contiguous [N, K] tensor in x's dtype that this head's x
// gradient is added into (the heads that read one input row sum their gradients there, each block once in
// cache). Returns (g_x [N, K] in x's dtype: g_x_into itself when given, g_a [S, W, Kp], g_w [L, W, W],
// g_bias [L+1, W], g_w_out [O, W], g_b_out [O]), all but g_x float32.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> head_backward(
    const at::Tensor& g_y, const at::Tensor& x, std::vector<at::Tensor> H, std::vector<at::Tensor> a_out,
    std::vector<at::Tensor> w_packs, std::vector<int64_t> reads_x, const at::Tensor& w_out, int64_t block_rows,
    const c10::optional<at::Tensor>& g_x_into) {
  const char* fn = "head_backward";
  const int rows = check_rows(block_rows, fn);
  const Shape s = check_head(x, static_cast<int64_t>(a_out.size()), static_cast<int64_t>(w_packs.size()), reads_x, w_out, fn);
  const int64_t N = s.N;
  const int K = s.K, Kp = s.Kp, W = s.W, L = s.L, O = s.O;
  const int S = static_cast<int>(a_out.size());
  TORCH_CHECK(static_cast<int>(H.size()) == L + 1, fn, ": expected ", L + 1, " activations");
  std::vector<const uint16_t*> Hp(L + 1);
  for (int l = 0; l <= L; ++l) {
    TORCH_CHECK(H[l].dim() == 2 && H[l].size(0) == N && H[l].size(1) == W && H[l].scalar_type() == at::kBFloat16 &&
                H[l].is_contiguous(), fn, ": activation ", l, " must be the forward's bf16 [N, W]");
    Hp[l] = bf16_ptr(H[l]);
  }
  TORCH_CHECK(g_y.scalar_type() == at::kFloat && g_y.is_contiguous() && g_y.dim() == 2 && g_y.size(0) == N &&
              g_y.size(1) == O, fn, ": g_y must be a contiguous float32 [N, O]");
  std::vector<const uint16_t*> ap(S), wp(L);
  for (int i = 0; i < S; ++i) {
    check_pack(a_out[i], static_cast<int64_t>(Kp) * W, fn, "input weight", i);
    ap[i] = bf16_ptr(a_out[i]);
  }
  for (int l = 0; l < L; ++l) {
    check_pack(w_packs[l], static_cast<int64_t>(W) * W, fn, "hidden weight", l);
    wp[l] = bf16_ptr(w_packs[l]);
  }
  const float* gyp = g_y.data_ptr<float>();
  const float* wo = w_out.data_ptr<float>();
  const auto fopts = g_y.options().dtype(at::kFloat);
  const bool add = g_x_into.has_value() && g_x_into->defined();
  if (add)
    TORCH_CHECK(g_x_into->scalar_type() == x.scalar_type() && g_x_into->is_contiguous() && g_x_into->dim() == 2 &&
                g_x_into->size(0) == N && g_x_into->size(1) == K, fn, ": g_x_into must be a contiguous [", N, ", ", K,
                "] tensor in x's dtype");
  at::Tensor g_x = add ? *g_x_into : at::empty({N, K}, x.options().memory_format(at::MemoryFormat::Contiguous));
  const int n_threads = std::max(1, at::get_num_threads());  // torch's thread count, as in the forward
  const int Ot = tile_outputs(O);
  const bool tile_out = O >= kTileOutput;
  std::vector<uint16_t> wo_pack;  // a tiled output layer's weight, VNNI over its output [Ot/2][W][2] (rows >= O zero)
  if (tile_out) {
    wo_pack.resize(static_cast<size_t>(Ot) * W);
    pack_weight(w_out, Ot, W, false, wo_pack.data());
  }
  // per thread, float32: g_a [S, W, Kp], g_w [L, W, W], g_bias [L+1, W], g_w_out [Ot, W], g_b_out [O]
  const int64_t n_a = static_cast<int64_t>(S) * W * Kp, n_w = static_cast<int64_t>(L) * W * W;
  const int64_t n_b = static_cast<int64_t>(L + 1) * W, n_wo = static_cast<int64_t>(Ot) * W;
  const int64_t per_thread = n_a + n_w + n_b + n_wo + O;
  std::vector<float> acc(static_cast<size_t>(n_threads) * per_thread, 0.0f);
  const RowSource xs(x);
  const int64_t n_blocks = (N + rows - 1) / rows;
  const __m512 zero = _mm512_setzero_ps();
#pragma omp parallel num_threads(n_threads)
  {
    load_tile_config();
    float* ga_t = acc.data() + static_cast<size_t>(omp_get_thread_num()) * per_thread;
    float* gw_t = ga_t + n_a;
    float* gb_t = gw_t + n_w;
    float* gwo_t = gb_t + n_b;
    float* gbo_t = gwo_t + n_wo;
    Scratch<float> g(rows * 256);         // gradient of the current layer's output [rows, W] float32
    Scratch<uint16_t> gpb(rows * 256);    // masked gradient, bf16 row-major [rows, W]
    Scratch<uint16_t> gpt(256 * rows);    // masked gradient, bf16 transposed [W, rows]
    Scratch<uint16_t> hv(rows * 256);     // a layer's input, VNNI over rows [rows / 2, W, 2]
    Scratch<uint16_t> xb(rows * 256);     // the block's x [rows, Kp] bf16
    Scratch<uint16_t> xv(rows * 256);     // x VNNI over rows [rows / 2, Kp, 2]
    Scratch<float> gx(rows * 256);        // the block's x gradient [rows, Kp] float32
    Scratch<float> gyf(rows * 256);       // a tiled output layer's g_y [rows, Ot] float32 (zero-padded)
    Scratch<uint16_t> gyb(rows * 256);    // ... bf16 row-major [rows, Ot]
    Scratch<uint16_t> gyt(256 * rows);    // ... bf16 transposed [Ot, rows]
#pragma omp for schedule(static)
    for (int64_t b = 0; b < n_blocks; ++b) {
      const int64_t r0 = b * rows;
      const int nr = static_cast<int>(std::min<int64_t>(rows, N - r0));
      const uint16_t* HL = Hp[L] + r0 * W;
      // output layer: g = g_y W_out (rows >= nr zero), g_W_out += g_yᵀ h_L, g_b_out += Σ g_y
      if (tile_out) {  // both products on tiles, g_y rounded to bf16
        for (int r = 0; r < rows; ++r) {
          for (int o = 0; o < Ot; ++o) gyf[r * Ot + o] = r < nr && o < O ? gyp[(r0 + r) * O + o] : 0.0f;
          for (int o = 0; o < Ot; o += 32) store32_bf16(gyb + r * Ot + o, load16(gyf + r * Ot + o), load16(gyf + r * Ot + o + 16));
        }
        transpose_bf16(gyf, Ot, rows, Ot, gyt);
        vnni_rows(HL, W, nr, rows, W, hv);
        gemm(gyt, rows, hv, rows, W, gwo_t, W, Ot, true);              // g_W_out += g_yᵀ h_L
        gemm(gyb, Ot, wo_pack.data(), Ot, W, g, W, rows, false);       // g = g_y W_out
      } else {
        for (int r = 0; r < rows; ++r) {
          for (int i = 0; i < W; i += 16) {
            __m512 v = zero;
            if (r < nr)
              for (int o = 0; o < O; ++o) v = _mm512_fmadd_ps(_mm512_set1_ps(gyp[(r0 + r) * O + o]), load16(wo + o * W + i), v);
            _mm512_storeu_ps(g + r * W + i, v);
          }
        }
        for (int o = 0; o < O; ++o) {
          for (int i = 0; i < W; i += 16) {
            __m512 v = load16(gwo_t + o * W + i);
            for (int r = 0; r < nr; ++r) v = _mm512_fmadd_ps(_mm512_set1_ps(gyp[(r0 + r) * O + o]), load16(HL + r * W + i), v);
            _mm512_storeu_ps(gwo_t + o * W + i, v);
          }
        }
      }
      for (int o = 0; o < O; ++o) {
        float sb = 0.0f;
        for (int r = 0; r < nr; ++r) sb += gyp[(r0 + r) * O + o];
        gbo_t[o] += sb;
      }
      load_x_block(xs, r0, nr, rows, K, Kp, xb);
      vnni_rows(xb, Kp, rows, rows, Kp, xv);
      std::memset(gx, 0, sizeof(float) * rows * Kp);
      for (int l = L; l >= 0; --l) {
        const uint16_t* Hl = Hp[l] + r0 * W;
        // one pass over g in 32-row x 16-column blocks: the mask by h_l > 0 (pad rows: zero), the bias sum, the
        // masked gradient rounded to bf16 row-major (gpb) and, transposed in registers, as [W, rows] (gpt)
        float* gb = gb_t + static_cast<int64_t>(l) * W;
        for (int ob = 0; ob < W; ob += 16) {
          __m512 bsum = load16(gb + ob);
          for (int rp = 0; rp < rows; rp += 32) {
            __m512 lo[16], hi[16];  // rows rp .. rp+15 and rp+16 .. rp+31 of columns ob .. ob+15
            for (int r = 0; r < 16; ++r) {
              lo[r] = masked_gradient(g, Hl, W, rp + r, nr, ob);
              hi[r] = masked_gradient(g, Hl, W, rp + r + 16, nr, ob);
              bsum = _mm512_add_ps(bsum, _mm512_add_ps(lo[r], hi[r]));
              store16_bf16(gpb + (rp + r) * W + ob, lo[r]);
              store16_bf16(gpb + (rp + r + 16) * W + ob, hi[r]);
            }
            transpose16x16(lo);
            transpose16x16(hi);
            for (int o = 0; o < 16; ++o) store32_bf16(gpt + (ob + o) * rows + rp, lo[o], hi[o]);
          }
          _mm512_storeu_ps(gb + ob, bsum);
        }
        if (reads_x[l] >= 0) {
          const int si = static_cast<int>(reads_x[l]);
          gemm(gpt, rows, xv, rows, Kp, ga_t + static_cast<int64_t>(si) * W * Kp, Kp, W, true);  // g_A += gᵀ x
          gemm(gpb, W, ap[si], W, Kp, gx, Kp, rows, true);                                      // g_x += g A
        }
        if (l == 0) break;
        vnni_rows(Hp[l - 1] + r0 * W, W, nr, rows, W, hv);
        gemm(gpt, rows, hv, rows, W, gw_t + static_cast<int64_t>(l - 1) * W * W, W, W, true);  // g_W += gᵀ h
        gemm(gpb, W, wp[l - 1], W, W, g, W, rows, false);                                      // g_h = g W
      }
      store_x_rows(g_x, r0, nr, K, Kp, gx, add);
    }
    _tile_release();
  }
  at::Tensor g_all = at::zeros({per_thread}, fopts);
  float* gp = g_all.data_ptr<float>();
  for (int t = 0; t < n_threads; ++t) {
    const float* a = acc.data() + static_cast<size_t>(t) * per_thread;
    for (int64_t i = 0; i < per_thread; ++i) gp[i] += a[i];
  }
  int64_t off = 0;
  auto take = [&](int64_t n, at::IntArrayRef shape) {
    at::Tensor t = g_all.narrow(0, off, n).view(shape);
    off += n;
    return t;
  };
  at::Tensor g_a = take(n_a, {S, W, Kp});
  at::Tensor g_w = take(n_w, {L, W, W});
  at::Tensor g_b = take(n_b, {L + 1, W});
  at::Tensor g_wo = take(n_wo, {Ot, W}).narrow(0, 0, O);
  at::Tensor g_bo = take(O, {O});
  return {g_x, g_a, g_w, g_b, g_wo, g_bo};
}

// A head's weight packs for the kernel, built in one call: a[s] [W, K] the input weights (zero-padded to Kp, K
// rounded up to 32) and hidden[l] [W, W], float32 with any strides. over_input: the forward's packs ([S, Kp/2, W, 2]
// and [L, W/2, W, 2]); else the backward's ([S, W/2, Kp, 2] and [L, W/2, W, 2]). Equals pack_in / pack_out of
// src/fields/head_kernel.py on the stacked, padded weights.
std::tuple<at::Tensor, at::Tensor> head_pack(std::vector<at::Tensor> a, std::vector<at::Tensor> hidden, bool over_input) {
  const char* fn = "head_pack";
  TORCH_CHECK(!a.empty() && a[0].dim() == 2, fn, ": needs at least one input weight [W, K]");
  const int W = static_cast<int>(a[0].size(0)), K = static_cast<int>(a[0].size(1)), Kp = (K + 31) / 32 * 32;
  TORCH_CHECK(W % 2 == 0, fn, ": the width ", W, " must be even");
  auto check = [&](const at::Tensor& w, int in, const char* what, size_t i) {
    TORCH_CHECK(w.device().is_cpu() && w.scalar_type() == at::kFloat && w.dim() == 2 && w.size(0) == W && w.size(1) == in,
                fn, ": ", what, " ", i, " must be a float32 CPU [", W, ", ", in, "], got ", w.sizes(), " ", w.scalar_type());
  };
  for (size_t i = 0; i < a.size(); ++i) check(a[i], K, "input weight", i);
  for (size_t i = 0; i < hidden.size(); ++i) check(hidden[i], W, "hidden weight", i);
  const auto opts = a[0].options().dtype(at::kBFloat16);
  const int64_t S = static_cast<int64_t>(a.size()), L = static_cast<int64_t>(hidden.size());
  at::Tensor pa = over_input ? at::empty({S, Kp / 2, W, 2}, opts) : at::empty({S, W / 2, Kp, 2}, opts);
  at::Tensor ph = at::empty({L, W / 2, W, 2}, opts);
  uint16_t* pap = bf16_ptr_mut(pa);
  uint16_t* php = bf16_ptr_mut(ph);
  for (int64_t i = 0; i < S; ++i) pack_weight(a[i], W, Kp, over_input, pap + i * Kp * W);
  for (int64_t i = 0; i < L; ++i) pack_weight(hidden[i], W, W, over_input, php + i * W * W);
  return {pa, ph};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(splatfields_cpu, m) {
  m.def("head_forward", &head_forward);
  m.def("head_backward", &head_backward);
  m.def("head_available", &head_available);
  m.def("head_pack", &head_pack);
}
