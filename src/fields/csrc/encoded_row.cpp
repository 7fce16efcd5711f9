// The field heads' input row [f, PE(x)] written in one pass (src/fields/encoded_row.py), forward and backward.
//
// row[n] = [f[n, 0..F), x[n, 0..d), sin(2^0 x[n]), cos(2^0 x[n]), ..., sin(2^(L-1) x[n]), cos(2^(L-1) x[n])]
// (the positional encoding's layout, src/fields/encoding.py: level-major, sin then cos, each over all d inputs;
// frequencies 2^l without pi), in f's dtype (float32 or bfloat16, rounded to nearest even). sin and cos of
// 2^l x are ATen's vectorised float32 ones, in place on x 2^l (a product by a power of two: exact), so the
// torch encoding's values bit for bit; they are kept for the backward as sc [2, N, L, d].
// Backward: g_f = g[:, 0..F), g_x[j] = g[F + j] + sum_l 2^l (cos(2^l x_j) g_sin[l, j] - sin(2^l x_j) g_cos[l, j]).

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/cos.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/sin.h>
#include <c10/util/BFloat16.h>
#include <torch/library.h>

#include <cmath>
#include <cstdint>
#include <cstring>
#include <tuple>
#include <type_traits>

#include "bf16_round.h"

namespace {

constexpr int64_t kMaxDims = 8;  // inputs per point (3 for positions)
constexpr int64_t kMaxLevels = 16;

void check_x(const at::Tensor& x, int64_t L) {
  TORCH_CHECK(x.device().is_cpu() && x.scalar_type() == at::kFloat && x.dim() == 2 && x.is_contiguous(),
              "encoded_row: x must be a contiguous float32 CPU tensor [N, d], got ", x.sizes(), " ", x.scalar_type());
  TORCH_CHECK(x.size(1) >= 1 && x.size(1) <= kMaxDims && L >= 1 && L <= kMaxLevels,
              "encoded_row: expected 1..", kMaxDims, " inputs per point and 1..", kMaxLevels, " levels, got ",
              x.size(1), " and ", L);
}

// sin and cos of x 2^l: [2, N, L, d] float32 (ATen's kernels in place on x 2^l, as the torch encoding computes them).
at::Tensor sin_cos(const at::Tensor& x, int64_t L) {
  const int64_t N = x.size(0), d = x.size(1), S = N * L * d;
  at::Tensor sc = at::empty({2, N, L, d}, x.options());
  const float* xp = x.data_ptr<float>();
  float* s = sc.data_ptr<float>();
  float freq[kMaxLevels];  // 2^0 .. 2^(L-1), exact
  for (int64_t l = 0; l < L; ++l) freq[l] = std::ldexp(1.0f, static_cast<int>(l));
  at::parallel_for(0, N, 1024, [&](int64_t begin, int64_t end) {
    for (int64_t n = begin; n < end; ++n)
      for (int64_t l = 0; l < L; ++l)
        for (int64_t j = 0; j < d; ++j) s[(n * L + l) * d + j] = s[S + (n * L + l) * d + j] = xp[n * d + j] * freq[l];
  });
  sc.select(0, 0).sin_();
  sc.select(0, 1).cos_();
  return sc;
}

inline void store_row(float* o, const float* v, int64_t n) { std::memcpy(o, v, sizeof(float) * n); }
inline void store_row(c10::BFloat16* o, const float* v, int64_t n) {
  uint16_t* ob = reinterpret_cast<uint16_t*>(o);
  for (int64_t k = 0; k < n; ++k) ob[k] = to_bf16(v[k]);
}

constexpr int64_t kMaxPe = kMaxDims * (1 + 2 * kMaxLevels);

// DIMS: d known at compile time (3, positions: the gathers unrolled), or 0 (d at run time)
template <typename T, int DIMS>
void forward_rows(const T* f, const float* x, const float* sc, T* out, int64_t N, int64_t F, int64_t d_run, int64_t L) {
  const int64_t d = DIMS > 0 ? DIMS : d_run;
  const int64_t P = d * (1 + 2 * L), D = F + P, S = N * L * d;
  at::parallel_for(0, N, 256, [&](int64_t begin, int64_t end) {
    float pe[kMaxPe];  // one row's PE(x) in float32, converted in one pass
    for (int64_t n = begin; n < end; ++n) {
      T* o = out + n * D;
      if (F > 0) std::memcpy(o, f + n * F, sizeof(T) * F);
      const float* s = sc + n * L * d;
      const float* c = s + S;
      for (int64_t j = 0; j < d; ++j) pe[j] = x[n * d + j];
      for (int64_t l = 0; l < L; ++l)
        for (int64_t j = 0; j < d; ++j) {
          pe[d * (1 + 2 * l) + j] = s[l * d + j];
          pe[d * (2 + 2 * l) + j] = c[l * d + j];
        }
      store_row(o + F, pe, P);
    }
  });
}

template <typename T>
void backward_rows(const T* g, const float* sc, T* g_f, float* g_x, int64_t N, int64_t F, int64_t d, int64_t L) {
  const int64_t D = F + d * (1 + 2 * L), S = N * L * d;
  at::parallel_for(0, N, 256, [&](int64_t begin, int64_t end) {
    for (int64_t n = begin; n < end; ++n) {
      const T* gr = g + n * D;
      if (g_f != nullptr) std::memcpy(g_f + n * F, gr, sizeof(T) * F);
      if (g_x == nullptr) continue;
      const T* gp = gr + F;
      const float* s = sc + n * L * d;
      const float* c = s + S;
      for (int64_t j = 0; j < d; ++j) {
        float acc = static_cast<float>(gp[j]);
        float freq = 1.0f;
        for (int64_t l = 0; l < L; ++l, freq *= 2.0f)
          acc += freq * (c[l * d + j] * static_cast<float>(gp[d * (1 + 2 * l) + j]) -
                         s[l * d + j] * static_cast<float>(gp[d * (2 + 2 * l) + j]));
        g_x[n * d + j] = acc;
      }
    }
  });
}

// f [N, F] (float32 or bfloat16, contiguous), x [N, d] float32, L levels -> (row [N, F + d (1 + 2L)] in f's dtype,
// sc [2, N, L, d]: the sines and cosines, for the backward).
std::tuple<at::Tensor, at::Tensor> encoded_row_forward(const at::Tensor& f, const at::Tensor& x, int64_t L) {
  check_x(x, L);
  TORCH_CHECK(f.device().is_cpu() && f.dim() == 2 && f.is_contiguous() && f.size(0) == x.size(0) &&
                  (f.scalar_type() == at::kFloat || f.scalar_type() == at::kBFloat16),
              "encoded_row: f must be a contiguous float32 or bfloat16 CPU tensor [N, F] with x's N, got ", f.sizes(),
              " ", f.scalar_type());
  const int64_t N = x.size(0), d = x.size(1), F = f.size(1);
  const at::Tensor sc = sin_cos(x, L);
  at::Tensor out = at::empty({N, F + d * (1 + 2 * L)}, f.options());
  auto rows = [&](auto* fp, auto* op) {
    using T = std::remove_pointer_t<decltype(op)>;
    const float *xp = x.data_ptr<float>(), *scp = sc.data_ptr<float>();
    if (d == 3) {
      forward_rows<T, 3>(fp, xp, scp, op, N, F, d, L);
    } else {
      forward_rows<T, 0>(fp, xp, scp, op, N, F, d, L);
    }
  };
  if (f.scalar_type() == at::kFloat) {
    rows(f.data_ptr<float>(), out.data_ptr<float>());
  } else {
    rows(f.data_ptr<c10::BFloat16>(), out.data_ptr<c10::BFloat16>());
  }
  return {out, sc};
}

// g [N, F + d (1 + 2L)] (the row's gradient, the row's dtype), sc [2, N, L, d] from the forward, F -> (g_f [N, F]
// in g's dtype, g_x [N, d] float32); either is an empty tensor where not asked for.
std::tuple<at::Tensor, at::Tensor> encoded_row_backward(const at::Tensor& g, const at::Tensor& sc, int64_t F,
                                                        bool need_f, bool need_x) {
  TORCH_CHECK(sc.device().is_cpu() && sc.scalar_type() == at::kFloat && sc.dim() == 4 && sc.size(0) == 2 &&
                  sc.is_contiguous(),
              "encoded_row: sc must be the forward's contiguous float32 [2, N, L, d], got ", sc.sizes());
  const int64_t N = sc.size(1), L = sc.size(2), d = sc.size(3);
  TORCH_CHECK(g.device().is_cpu() && g.dim() == 2 && g.is_contiguous() && g.size(0) == N &&
                  g.size(1) == F + d * (1 + 2 * L) && (g.scalar_type() == at::kFloat || g.scalar_type() == at::kBFloat16),
              "encoded_row: the row's gradient ", g.sizes(), " ", g.scalar_type(), " does not match sc ", sc.sizes(),
              " and F = ", F);
  at::Tensor g_f = at::empty({need_f ? N : 0, F}, g.options());
  at::Tensor g_x = at::empty({need_x ? N : 0, d}, sc.options());
  float* gx = need_x ? g_x.data_ptr<float>() : nullptr;
  if (g.scalar_type() == at::kFloat) {
    backward_rows<float>(g.data_ptr<float>(), sc.data_ptr<float>(), need_f ? g_f.data_ptr<float>() : nullptr, gx, N,
                         F, d, L);
  } else {
    backward_rows<c10::BFloat16>(g.data_ptr<c10::BFloat16>(), sc.data_ptr<float>(),
                                 need_f ? g_f.data_ptr<c10::BFloat16>() : nullptr, gx, N, F, d, L);
  }
  return {g_f, g_x};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(splatfields_cpu, m) {
  m.def("encoded_row_forward", &encoded_row_forward);
  m.def("encoded_row_backward", &encoded_row_backward);
}
