// 8-lane float SIMD helpers for the CPU rasterizer.
//
// Two implementations with identical semantics:
//   * AVX2 + FMA intrinsics (built with -mavx2 -mfma),
//   * GCC/Clang generic vector extensions (any other target; fused ops become mul + add, exp is
//     libm's expf per lane).
// Every fused multiply-add is explicit (the kernel is compiled with -ffp-contract=off), so the
// forward and backward passes evaluate bit-identical alphas for the same (pixel, splat) pair.
#pragma once

#include <cstdint>
#include <cstring>

#if defined(__AVX2__) && defined(__FMA__)
#include <immintrin.h>
#define SF_SIMD_AVX2 1
#endif

namespace sf {
namespace simd {

constexpr int W = 8;  // lanes

#ifdef SF_SIMD_AVX2

struct VF {
  __m256 v;
};
struct VM {  // lane mask (all bits set = true)
  __m256 v;
};

inline VF set1(float x) { return {_mm256_set1_ps(x)}; }
inline VF zero() { return {_mm256_setzero_ps()}; }
inline VF load(const float* p) { return {_mm256_load_ps(p)}; }
inline VF loadu(const float* p) { return {_mm256_loadu_ps(p)}; }
inline void store(float* p, VF a) { _mm256_store_ps(p, a.v); }
inline VF iota() { return {_mm256_setr_ps(0, 1, 2, 3, 4, 5, 6, 7)}; }
inline VF operator+(VF a, VF b) { return {_mm256_add_ps(a.v, b.v)}; }
inline VF operator-(VF a, VF b) { return {_mm256_sub_ps(a.v, b.v)}; }
inline VF operator*(VF a, VF b) { return {_mm256_mul_ps(a.v, b.v)}; }
inline VF operator/(VF a, VF b) { return {_mm256_div_ps(a.v, b.v)}; }
inline VF fmadd(VF a, VF b, VF c) { return {_mm256_fmadd_ps(a.v, b.v, c.v)}; }    // a*b + c
inline VF fnmadd(VF a, VF b, VF c) { return {_mm256_fnmadd_ps(a.v, b.v, c.v)}; }  // c - a*b
inline VF vmin(VF a, VF b) { return {_mm256_min_ps(a.v, b.v)}; }
inline VF vmax(VF a, VF b) { return {_mm256_max_ps(a.v, b.v)}; }
inline VF vsqrt(VF a) { return {_mm256_sqrt_ps(a.v)}; }
inline VF vabs(VF a) { return {_mm256_andnot_ps(_mm256_set1_ps(-0.0f), a.v)}; }
inline VM operator<=(VF a, VF b) { return {_mm256_cmp_ps(a.v, b.v, _CMP_LE_OQ)}; }
inline VM operator<(VF a, VF b) { return {_mm256_cmp_ps(a.v, b.v, _CMP_LT_OQ)}; }
inline VM operator>=(VF a, VF b) { return {_mm256_cmp_ps(a.v, b.v, _CMP_GE_OQ)}; }
inline VM operator&(VM a, VM b) { return {_mm256_and_ps(a.v, b.v)}; }
inline VM operator|(VM a, VM b) { return {_mm256_or_ps(a.v, b.v)}; }
inline VM andnot(VM a, VM b) { return {_mm256_andnot_ps(a.v, b.v)}; }  // ~a & b
inline VF select(VM m, VF a, VF b) { return {_mm256_blendv_ps(b.v, a.v, m.v)}; }  // m ? a : b
inline int movemask(VM m) { return _mm256_movemask_ps(m.v); }
inline VM mload(const int32_t* p) { return {_mm256_castsi256_ps(_mm256_load_si256((const __m256i*)p))}; }
inline void mstore(int32_t* p, VM m) { _mm256_store_si256((__m256i*)p, _mm256_castps_si256(m.v)); }
// int32 lanes
struct VI {
  __m256i v;
};
inline VI iload(const int32_t* p) { return {_mm256_load_si256((const __m256i*)p)}; }
inline void istore(int32_t* p, VI a) { _mm256_store_si256((__m256i*)p, a.v); }
inline VI iset1(int32_t x) { return {_mm256_set1_epi32(x)}; }
inline VM igt(VI a, VI b) { return {_mm256_castsi256_ps(_mm256_cmpgt_epi32(a.v, b.v))}; }
inline VI iselect(VM m, VI a, VI b) {
  return {_mm256_castps_si256(_mm256_blendv_ps(_mm256_castsi256_ps(b.v), _mm256_castsi256_ps(a.v), m.v))};
}

// exp(x) for x <= 0 (Cody-Waite reduction + degree-5 polynomial on [-ln2/2, ln2/2], ~1-2 ulp).
inline VF vexp(VF x) {
  __m256 xv = _mm256_max_ps(x.v, _mm256_set1_ps(-87.0f));
  xv = _mm256_min_ps(xv, _mm256_set1_ps(88.0f));
  __m256 n = _mm256_round_ps(_mm256_mul_ps(xv, _mm256_set1_ps(1.44269504088896341f)),
                             _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  __m256 r = _mm256_fnmadd_ps(n, _mm256_set1_ps(0.693359375f), xv);
  r = _mm256_fnmadd_ps(n, _mm256_set1_ps(-2.12194440e-4f), r);
  __m256 p = _mm256_set1_ps(1.9875691500e-4f);
  p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(1.3981999507e-3f));
  p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(8.3334519073e-3f));
  p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(4.1665795894e-2f));
  p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(1.6666665459e-1f));
  p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(5.0000001201e-1f));
  __m256 r2 = _mm256_mul_ps(r, r);
  p = _mm256_fmadd_ps(p, r2, _mm256_add_ps(r, _mm256_set1_ps(1.0f)));
  __m256i e = _mm256_slli_epi32(_mm256_add_epi32(_mm256_cvtps_epi32(n), _mm256_set1_epi32(127)), 23);
  return {_mm256_mul_ps(p, _mm256_castsi256_ps(e))};
}

inline float hsum(VF a) {
  __m128 lo = _mm256_castps256_ps128(a.v);
  __m128 hi = _mm256_extractf128_ps(a.v, 1);
  __m128 s = _mm_add_ps(lo, hi);
  s = _mm_add_ps(s, _mm_movehl_ps(s, s));
  s = _mm_add_ss(s, _mm_shuffle_ps(s, s, 1));
  return _mm_cvtss_f32(s);
}

// out[k] = sum of the lanes of v[k], k = 0..7 (a fixed reduction tree).
inline void hsum8(const VF* v, float* out) {
  __m256 h01 = _mm256_hadd_ps(v[0].v, v[1].v);
  __m256 h23 = _mm256_hadd_ps(v[2].v, v[3].v);
  __m256 h45 = _mm256_hadd_ps(v[4].v, v[5].v);
  __m256 h67 = _mm256_hadd_ps(v[6].v, v[7].v);
  __m256 a = _mm256_hadd_ps(h01, h23);
  __m256 b = _mm256_hadd_ps(h45, h67);
  __m256 s = _mm256_add_ps(_mm256_permute2f128_ps(a, b, 0x20), _mm256_permute2f128_ps(a, b, 0x31));
  _mm256_storeu_ps(out, s);
}

#else  // generic vector extensions

typedef float f8 __attribute__((vector_size(32)));
typedef int32_t i8 __attribute__((vector_size(32)));

struct VF {
  f8 v;
};
struct VM {
  i8 v;
};
struct VI {
  i8 v;
};

inline VF set1(float x) { return {f8{x, x, x, x, x, x, x, x}}; }
inline VF zero() { return set1(0.0f); }
inline VF load(const float* p) {
  VF r;
  std::memcpy(&r.v, p, sizeof(f8));
  return r;
}
inline VF loadu(const float* p) { return load(p); }
inline void store(float* p, VF a) { std::memcpy(p, &a.v, sizeof(f8)); }
inline VF iota() { return {f8{0, 1, 2, 3, 4, 5, 6, 7}}; }
inline VF operator+(VF a, VF b) { return {a.v + b.v}; }
inline VF operator-(VF a, VF b) { return {a.v - b.v}; }
inline VF operator*(VF a, VF b) { return {a.v * b.v}; }
inline VF operator/(VF a, VF b) { return {a.v / b.v}; }
inline VF fmadd(VF a, VF b, VF c) { return {a.v * b.v + c.v}; }
inline VF fnmadd(VF a, VF b, VF c) { return {c.v - a.v * b.v}; }
inline VM operator<=(VF a, VF b) { return {a.v <= b.v}; }
inline VM operator<(VF a, VF b) { return {a.v < b.v}; }
inline VM operator>=(VF a, VF b) { return {a.v >= b.v}; }
inline VM operator&(VM a, VM b) { return {a.v & b.v}; }
inline VM operator|(VM a, VM b) { return {a.v | b.v}; }
inline VM andnot(VM a, VM b) { return {~a.v & b.v}; }
inline VF select(VM m, VF a, VF b) { return {m.v ? a.v : b.v}; }
inline VF vmin(VF a, VF b) { return {a.v < b.v ? a.v : b.v}; }
inline VF vmax(VF a, VF b) { return {a.v > b.v ? a.v : b.v}; }
inline VF vsqrt(VF a) {
  VF r;
  for (int i = 0; i < W; ++i) r.v[i] = __builtin_sqrtf(a.v[i]);
  return r;
}
inline VF vabs(VF a) { return {a.v < 0 ? -a.v : a.v}; }
inline int movemask(VM m) {
  int r = 0;
  for (int i = 0; i < W; ++i) r |= (m.v[i] < 0 ? 1 : 0) << i;
  return r;
}
inline VM mload(const int32_t* p) {
  VM r;
  std::memcpy(&r.v, p, sizeof(i8));
  return r;
}
inline void mstore(int32_t* p, VM m) { std::memcpy(p, &m.v, sizeof(i8)); }
inline VI iload(const int32_t* p) {
  VI r;
  std::memcpy(&r.v, p, sizeof(i8));
  return r;
}
inline void istore(int32_t* p, VI a) { std::memcpy(p, &a.v, sizeof(i8)); }
inline VI iset1(int32_t x) { return {i8{x, x, x, x, x, x, x, x}}; }
inline VM igt(VI a, VI b) { return {a.v > b.v}; }
inline VI iselect(VM m, VI a, VI b) { return {m.v ? a.v : b.v}; }

// Portable path: libm expf per lane (accurate; -ffast-math could reassociate a hand-written
// Cody-Waite reduction without the explicit FMA intrinsics of the AVX2 path).
inline VF vexp(VF x) {
  VF r;
  for (int i = 0; i < W; ++i) {
    const float v = x.v[i] < -87.0f ? -87.0f : (x.v[i] > 88.0f ? 88.0f : x.v[i]);
    r.v[i] = __builtin_expf(v);
  }
  return r;
}

inline float hsum(VF a) {
  float lo0 = a.v[0] + a.v[4], lo1 = a.v[1] + a.v[5], lo2 = a.v[2] + a.v[6], lo3 = a.v[3] + a.v[7];
  return (lo0 + lo2) + (lo1 + lo3);
}
inline void hsum8(const VF* v, float* out) {
  for (int k = 0; k < W; ++k) out[k] = hsum(v[k]);
}

#endif

}  // namespace simd
}  // namespace sf
