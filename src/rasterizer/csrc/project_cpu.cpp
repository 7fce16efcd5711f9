// Fused EWA projection of 3D Gaussians (forward + hand-written backward), CPU/OpenMP.
//
// Semantics: exactly src/rasterizer/projection.py (project_splats), the 3DGS CUDA rules:
//   * OpenCV camera (x right, y down, z forward), world_to_cam [4, 4] = [R | t];
//   * quaternions (w, x, y, z), normalised here; scales are linear standard deviations;
//   * splats with camera depth z <= near are culled (their z is replaced by 1 in the formulas);
//   * the Jacobian is evaluated at x/z, y/z clamped to frustum_clamp x the image extent on each
//     side of the principal point;
//   * Sigma2D = J W Sigma W^T J^T + eps2d I (low-pass filter, pixels^2), culled if det <= 0;
//   * antialiased entry points (project_forward_aa / project_backward_aa; Mip-Splatting's 2D Mip
//     filter, eps2d its variance): also ratio = clamp(det0 / det, min=aa_ratio_min), det0 the
//     determinant before the filter (det where culled replaced by 1, as for the conic); the caller
//     takes torch.sqrt of it (the opacity compensation; torch's sqrt, which on MKL builds is not
//     always correctly rounded, so the compensation stays bit-identical to the torch projection's),
//     and the ratio's gradient joins the conic's chain rule;
//   * means2d = (fx x / z + cx, fy y / z + cy) (pixel centres at i + 0.5);
//   * radius = ceil(3 sqrt(lambda_max)), lambda_max = mid + sqrt(max(mid^2 - det, 0.1));
//   * visible additionally needs a non-empty 3DGS tile rect (centre means2d - 0.5) and finite means2d;
//     radius 0 if not visible.
// The forward repeats torch's float operations one by one in the same order and precision (this
// file is built WITHOUT -ffast-math and with -ffp-contract=off, see src/kernels/build.py), so means2d, conics,
// depths, radii and visible are bit-identical to the torch projection in float32 and float64.
// Torch idioms reproduced: `fx / z` is reciprocal(z) * fx (Tensor.__rtruediv__), Python scalars
// are cast to the tensor dtype, the quaternion norm sums squares sequentially, `.to(int32)` of
// NaN / inf / out-of-range floats gives INT32_MIN (x86 cvtt), clamp backward passes at the bounds.
//
// The backward recomputes the forward intermediates per splat (in the input dtype, so the culling
// and clamp decisions are the forward's) and evaluates the chain rule of the torch graph in double,
// including its where/clamp masks: gradients of culled splats are those torch autograd gives (the
// camera depth replaced by 1 and det by 1 where culled; the masked branch contributes 0 x its
// inputs as in torch). The camera is not differentiated.
//
// Work: splats are processed in SIMD packs (GCC vector extensions: 8 floats or 4 doubles per pack
// in the forward, 4 lanes in the backward, whose chain rule runs on 4 doubles), with a scalar tail
// running the same template code; every lane does the same IEEE operations as the scalar code.
// On AVX2 the forward's 8-float packs read their [8, 3] / [8, 4] input rows and write their
// [8, 3] / [8, 2] output rows as block transposes (load_rows / store_rows: contiguous loads,
// blends, lane permutes) instead of lane-by-lane gathers: 4.8 -> 2.6 ms single-threaded for 200k
// splats, bit-identical (pure data movement).
// One OpenMP loop over packs per pass; no reductions across splats, so results are deterministic
// for any thread count. Packs whose splats all have zero incoming gradients (occluded splats of a
// render) skip the chain rule when that is exact (see backward_pack). The incoming gradients may
// be strided column views (GradIn), e.g. of the CPU rasterizer's [N, 6 + NF] gradient buffer.
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <type_traits>
#include <vector>

#if defined(__AVX__)
#include <immintrin.h>
#endif

#if defined(__FAST_MATH__)
#error "project_cpu.cpp must be compiled without -ffast-math (bit-exact parity with torch)"
#endif

namespace {

constexpr int64_t MIN_SPLATS_PARALLEL = 4096;  // fewer splats: one thread

// ---------------------------------------------------------------------------------------------
// Lane packs. The per-splat code is written once as a template over V, either a scalar (float,
// double) or a GCC vector-extension type of L lanes (L splats at once); arithmetic, comparisons
// (-> lane masks) and `m ? a : b` selects have the same IEEE per-lane semantics in both, so the
// vector body and the scalar tail give bit-identical results.

template <typename T, int L>
struct VecT {
  typedef T type __attribute__((vector_size(sizeof(T) * L)));
};
template <typename T, int L>
using vec_t = typename VecT<T, L>::type;

template <typename V>
struct Tr {  // scalars
  using S = V;
  static constexpr int L = 1;
};
template <typename T, int N>
struct TrVec {
  using S = T;
  static constexpr int L = N;
};
template <>
struct Tr<vec_t<float, 8>> : TrVec<float, 8> {};
template <>
struct Tr<vec_t<float, 4>> : TrVec<float, 4> {};
template <>
struct Tr<vec_t<double, 4>> : TrVec<double, 4> {};

template <typename V>
inline typename Tr<V>::S lane(const V& v, int l) {
  if constexpr (Tr<V>::L == 1) {
    (void)l;
    return v;
  } else {
    return v[l];
  }
}
template <typename V>
inline void set_lane(V& v, int l, typename Tr<V>::S x) {
  if constexpr (Tr<V>::L == 1) {
    (void)l;
    v = x;
  } else {
    v[l] = x;
  }
}
template <typename M>
inline bool mlane(const M& m, int l) {
  if constexpr (std::is_arithmetic_v<M>) {  // scalar masks: bool, or int after `&`
    (void)l;
    return m;
  } else {
    return m[l] != 0;
  }
}
template <typename V>
inline V bc(typename Tr<V>::S x) {  // broadcast
  return V{} + x;
}
// Gathers component c of L consecutive splats from an [N, stride] row-major array.
template <typename V>
inline V gather(const typename Tr<V>::S* p, int64_t stride, int c) {
  V v;
  for (int l = 0; l < Tr<V>::L; ++l) set_lane(v, l, p[stride * l + c]);
  return v;
}
template <typename V>
inline void scatter(typename Tr<V>::S* p, int stride, int c, const V& v) {
  for (int l = 0; l < Tr<V>::L; ++l) p[stride * l + c] = lane(v, l);
}

// All K components of L consecutive rows of an [N, K] row-major array (rows(p)[c] = component
// c), and the inverse store: the per-component gather/scatter above, or, for 8 float lanes on
// AVX2, a block transpose of K contiguous 8-float loads (blends and lane permutes; pure data
// movement, so results are bit-identical either way).
template <typename V, int K>
inline void load_rows(const typename Tr<V>::S* p, V (&out)[K]) {
  for (int c = 0; c < K; ++c) out[c] = gather<V>(p, K, c);
}
template <typename V, int K>
inline void store_rows(typename Tr<V>::S* p, const V (&in)[K]) {
  for (int c = 0; c < K; ++c) scatter<V>(p, K, c, in[c]);
}
#if defined(__AVX2__)
using F8 = vec_t<float, 8>;
// [8, 3] rows <-> 3 vectors. Element e of the 24 floats sits in load e / 8, lane e % 8; component
// c of row l is e = 3 l + c. Blending the three loads so that lane k takes the load holding
// component c in lane k leaves the 8 values of component c in the order P3[c]; a lane permute
// restores row order (and its inverse undoes it for the store).
alignas(32) constexpr int32_t P3_GATHER[3][8] = {{0, 3, 6, 1, 4, 7, 2, 5}, {1, 4, 7, 2, 5, 0, 3, 6},
                                                  {2, 5, 0, 3, 6, 1, 4, 7}};
alignas(32) constexpr int32_t P3_SCATTER[3][8] = {{0, 3, 6, 1, 4, 7, 2, 5}, {5, 0, 3, 6, 1, 4, 7, 2},
                                                   {2, 5, 0, 3, 6, 1, 4, 7}};
// blend masks (bit k: lane k from the second operand): component c's lanes in load 0 / 1 / 2
constexpr int B3_LOAD1[3] = {0x92, 0x24, 0x49};  // lanes of load 1 holding component c
constexpr int B3_LOAD2[3] = {0x24, 0x49, 0x92};  // lanes of load 2 holding component c
template <>
inline void load_rows<F8, 3>(const float* p, F8 (&out)[3]) {
  const __m256 r0 = _mm256_loadu_ps(p), r1 = _mm256_loadu_ps(p + 8), r2 = _mm256_loadu_ps(p + 16);
  const __m256 t[3] = {_mm256_blend_ps(_mm256_blend_ps(r0, r1, B3_LOAD1[0]), r2, B3_LOAD2[0]),
                       _mm256_blend_ps(_mm256_blend_ps(r0, r1, B3_LOAD1[1]), r2, B3_LOAD2[1]),
                       _mm256_blend_ps(_mm256_blend_ps(r0, r1, B3_LOAD1[2]), r2, B3_LOAD2[2])};
  for (int c = 0; c < 3; ++c)
    out[c] = (F8)_mm256_permutevar8x32_ps(t[c], _mm256_load_si256((const __m256i*)P3_GATHER[c]));
}
template <>
inline void store_rows<F8, 3>(float* p, const F8 (&in)[3]) {
  __m256 t[3];
  for (int c = 0; c < 3; ++c)
    t[c] = _mm256_permutevar8x32_ps((__m256)in[c], _mm256_load_si256((const __m256i*)P3_SCATTER[c]));
  // load j takes component c on the lanes where load j holds it
  _mm256_storeu_ps(p, _mm256_blend_ps(_mm256_blend_ps(t[0], t[1], 0x92), t[2], 0x24));
  _mm256_storeu_ps(p + 8, _mm256_blend_ps(_mm256_blend_ps(t[0], t[1], 0x24), t[2], 0x49));
  _mm256_storeu_ps(p + 16, _mm256_blend_ps(_mm256_blend_ps(t[0], t[1], 0x49), t[2], 0x92));
}
// [8, 4] rows -> 4 vectors: 4x4 transposes within 128-bit halves, then rows (0 2 4 6 | 1 3 5 7)
// back into order.
template <>
inline void load_rows<F8, 4>(const float* p, F8 (&out)[4]) {
  const __m256 r0 = _mm256_loadu_ps(p), r1 = _mm256_loadu_ps(p + 8), r2 = _mm256_loadu_ps(p + 16),
               r3 = _mm256_loadu_ps(p + 24);  // rows (0 | 1), (2 | 3), (4 | 5), (6 | 7)
  const __m256 a = _mm256_unpacklo_ps(r0, r1), b = _mm256_unpackhi_ps(r0, r1);
  const __m256 c = _mm256_unpacklo_ps(r2, r3), d = _mm256_unpackhi_ps(r2, r3);
  const __m256i order = _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7);
  out[0] = (F8)_mm256_permutevar8x32_ps(_mm256_shuffle_ps(a, c, 0x44), order);
  out[1] = (F8)_mm256_permutevar8x32_ps(_mm256_shuffle_ps(a, c, 0xEE), order);
  out[2] = (F8)_mm256_permutevar8x32_ps(_mm256_shuffle_ps(b, d, 0x44), order);
  out[3] = (F8)_mm256_permutevar8x32_ps(_mm256_shuffle_ps(b, d, 0xEE), order);
}
// 2 vectors -> [8, 2] rows.
template <>
inline void store_rows<F8, 2>(float* p, const F8 (&in)[2]) {
  const __m256 lo = _mm256_unpacklo_ps((__m256)in[0], (__m256)in[1]);  // rows 0 1 | 4 5
  const __m256 hi = _mm256_unpackhi_ps((__m256)in[0], (__m256)in[1]);  // rows 2 3 | 6 7
  _mm256_storeu_ps(p, _mm256_permute2f128_ps(lo, hi, 0x20));
  _mm256_storeu_ps(p + 8, _mm256_permute2f128_ps(lo, hi, 0x31));
}
#endif

// Exact rounding functions (IEEE sqrt, ceil, trunc) per lane.
inline float vsqrt(float x) { return std::sqrt(x); }
inline double vsqrt(double x) { return std::sqrt(x); }
inline float vceil(float x) { return std::ceil(x); }
inline double vceil(double x) { return std::ceil(x); }
inline float vtrunc(float x) { return std::trunc(x); }
inline double vtrunc(double x) { return std::trunc(x); }
#if defined(__AVX__)
inline vec_t<float, 8> vsqrt(vec_t<float, 8> x) { return (vec_t<float, 8>)_mm256_sqrt_ps((__m256)x); }
inline vec_t<double, 4> vsqrt(vec_t<double, 4> x) { return (vec_t<double, 4>)_mm256_sqrt_pd((__m256d)x); }
inline vec_t<float, 4> vsqrt(vec_t<float, 4> x) { return (vec_t<float, 4>)_mm_sqrt_ps((__m128)x); }
inline vec_t<float, 8> vceil(vec_t<float, 8> x) {
  return (vec_t<float, 8>)_mm256_round_ps((__m256)x, _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC);
}
inline vec_t<double, 4> vceil(vec_t<double, 4> x) {
  return (vec_t<double, 4>)_mm256_round_pd((__m256d)x, _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC);
}
inline vec_t<float, 8> vtrunc(vec_t<float, 8> x) {
  return (vec_t<float, 8>)_mm256_round_ps((__m256)x, _MM_FROUND_TO_ZERO | _MM_FROUND_NO_EXC);
}
inline vec_t<double, 4> vtrunc(vec_t<double, 4> x) {
  return (vec_t<double, 4>)_mm256_round_pd((__m256d)x, _MM_FROUND_TO_ZERO | _MM_FROUND_NO_EXC);
}
#else
template <typename V>
inline V lanewise_sqrt(V x) {
  for (int l = 0; l < Tr<V>::L; ++l) x[l] = std::sqrt(x[l]);
  return x;
}
template <typename V>
inline V lanewise_ceil(V x) {
  for (int l = 0; l < Tr<V>::L; ++l) x[l] = std::ceil(x[l]);
  return x;
}
template <typename V>
inline V lanewise_trunc(V x) {
  for (int l = 0; l < Tr<V>::L; ++l) x[l] = std::trunc(x[l]);
  return x;
}
inline vec_t<float, 8> vsqrt(vec_t<float, 8> x) { return lanewise_sqrt(x); }
inline vec_t<double, 4> vsqrt(vec_t<double, 4> x) { return lanewise_sqrt(x); }
inline vec_t<float, 4> vsqrt(vec_t<float, 4> x) { return lanewise_sqrt(x); }
inline vec_t<float, 8> vceil(vec_t<float, 8> x) { return lanewise_ceil(x); }
inline vec_t<double, 4> vceil(vec_t<double, 4> x) { return lanewise_ceil(x); }
inline vec_t<float, 8> vtrunc(vec_t<float, 8> x) { return lanewise_trunc(x); }
inline vec_t<double, 4> vtrunc(vec_t<double, 4> x) { return lanewise_trunc(x); }
#endif

// Value / mask conversion between packs of the same lane count (float -> double for the backward).
template <typename VA, typename VT>
inline VA cvt(const VT& v) {
  if constexpr (Tr<VT>::L == 1)
    return static_cast<VA>(v);
  else
    return __builtin_convertvector(v, VA);
}
template <typename MA, typename MT>
inline MA mcvt(const MT& m) {
  if constexpr (std::is_arithmetic_v<MT>)
    return static_cast<bool>(m);
  else
    return __builtin_convertvector(m, MA);
}

template <typename V>
using mask_t = decltype(V{} < V{});

// torch.clamp(x, lo, hi): NaN propagates.
template <typename V>
inline V clampv(V x, V lo, V hi) {
  return (x < lo) ? lo : ((x > hi) ? hi : x);
}

// ---------------------------------------------------------------------------------------------
// Camera constants in the computation dtype T, as torch sees them.
template <typename T>
struct Cam {
  T R[3][3];
  T t[3];
  T fx, fy, cx, cy;  // Python floats cast to T
  T mfx, mfy;        // -fx, -fy (Python negation, then cast)
  T xlo, xhi, ylo, yhi;  // clamp bounds of x/z and y/z
  T near, eps2d;
  T tile, gx, gy;  // tile size, tile grid size
  bool aa;         // antialiased: compute the 2D Mip filter's determinant ratio
  T aa_min;        // floor of det0 / det (under the compensation's square root)
};

template <typename T>
Cam<T> make_cam(const at::Tensor& viewmat, double fx, double fy, double cx, double cy, int64_t width,
                int64_t height, double near, double frustum_clamp, double eps2d, int64_t tile,
                bool antialiased = false, double aa_ratio_min = 0.0) {
  Cam<T> c;
  const T* m = viewmat.data_ptr<T>();
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) c.R[i][j] = m[4 * i + j];
    c.t[i] = m[4 * i + 3];
  }
  c.fx = static_cast<T>(fx);
  c.fy = static_cast<T>(fy);
  c.cx = static_cast<T>(cx);
  c.cy = static_cast<T>(cy);
  c.mfx = static_cast<T>(-fx);
  c.mfy = static_cast<T>(-fy);
  // projection.py: lim = FRUSTUM_CLAMP * (width - cx) / fx etc. in double, clamp(-lim_neg, lim_pos)
  const double lxp = frustum_clamp * (static_cast<double>(width) - cx) / fx;
  const double lxn = frustum_clamp * cx / fx;
  const double lyp = frustum_clamp * (static_cast<double>(height) - cy) / fy;
  const double lyn = frustum_clamp * cy / fy;
  c.xlo = static_cast<T>(-lxn);
  c.xhi = static_cast<T>(lxp);
  c.ylo = static_cast<T>(-lyn);
  c.yhi = static_cast<T>(lyp);
  c.near = static_cast<T>(near);
  c.eps2d = static_cast<T>(eps2d);
  c.tile = static_cast<T>(tile);
  c.gx = static_cast<T>((width + tile - 1) / tile);
  c.gy = static_cast<T>((height + tile - 1) / tile);
  c.aa = antialiased;
  c.aa_min = static_cast<T>(aa_ratio_min);
  return c;
}

// Per-splat forward intermediates (everything the backward needs), L splats per pack V.
template <typename V>
struct Fwd {
  using M = mask_t<V>;
  V tx, ty, tz, zs;  // camera-space centre, z or 1 where culled
  M vis_z;           // z > near
  V xr, yr, xz, yz;  // x/z, y/z before and after the clamp
  V inv, j00, j02, j11, j12;  // Jacobian
  V n, q[4];         // quaternion norm, normalised quaternion (w, x, y, z)
  V r[3][3];         // rotation
  V s[3];            // scales
  V m[3][3];         // R S
  V T0[3], T1[3];    // J W
  V u[3], v[3];      // T0 Sigma, T1 Sigma
  V a0, c0;            // Sigma2D diagonal before the filter
  V a, b, c, det, ds;  // Sigma2D (+ eps2d), determinant, det or 1 where culled
  M vis;               // vis_z && det > 0
  V det0, ratio, rc;  // antialiased only: det before the filter, det0 / ds, ratio clamped
};

// The forward of projection.py up to the conic's inputs, op by op, for the L splats starting at
// means/quats/scales (row-major [., 3], [., 4], [., 3]).
template <typename V>
inline void fwd_core(const Cam<typename Tr<V>::S>& k, const typename Tr<V>::S* means,
                     const typename Tr<V>::S* quats, const typename Tr<V>::S* scales, Fwd<V>& f) {
  using T = typename Tr<V>::S;
  V mv[3];
  load_rows<V, 3>(means, mv);
  const V px = mv[0], py = mv[1], pz = mv[2];
  f.tx = ((k.R[0][0] * px + k.R[0][1] * py) + k.R[0][2] * pz) + k.t[0];
  f.ty = ((k.R[1][0] * px + k.R[1][1] * py) + k.R[1][2] * pz) + k.t[1];
  f.tz = ((k.R[2][0] * px + k.R[2][1] * py) + k.R[2][2] * pz) + k.t[2];
  const V one = bc<V>(T(1));
  f.vis_z = f.tz > bc<V>(k.near);
  f.zs = f.vis_z ? f.tz : one;
  f.xr = f.tx / f.zs;
  f.yr = f.ty / f.zs;
  f.xz = clampv(f.xr, bc<V>(k.xlo), bc<V>(k.xhi));
  f.yz = clampv(f.yr, bc<V>(k.ylo), bc<V>(k.yhi));
  f.inv = one / f.zs;
  f.j00 = f.inv * k.fx;
  f.j02 = (k.mfx * f.xz) / f.zs;
  f.j11 = f.inv * k.fy;
  f.j12 = (k.mfy * f.yz) / f.zs;

  V qv[4];
  load_rows<V, 4>(quats, qv);
  const V qw = qv[0], qx = qv[1], qy = qv[2], qz = qv[3];
  f.n = vsqrt(((qw * qw + qx * qx) + qy * qy) + qz * qz);
  const V w = qw / f.n, x = qx / f.n, y = qy / f.n, z = qz / f.n;
  f.q[0] = w;
  f.q[1] = x;
  f.q[2] = y;
  f.q[3] = z;
  auto& r = f.r;
  r[0][0] = one - T(2) * (y * y + z * z);
  r[0][1] = T(2) * (x * y - w * z);
  r[0][2] = T(2) * (x * z + w * y);
  r[1][0] = T(2) * (x * y + w * z);
  r[1][1] = one - T(2) * (x * x + z * z);
  r[1][2] = T(2) * (y * z - w * x);
  r[2][0] = T(2) * (x * z - w * y);
  r[2][1] = T(2) * (y * z + w * x);
  r[2][2] = one - T(2) * (x * x + y * y);
  auto& m = f.m;
  load_rows<V, 3>(scales, f.s);
  for (int j = 0; j < 3; ++j) {
    for (int i = 0; i < 3; ++i) m[i][j] = r[i][j] * f.s[j];
  }
  const V c00 = (m[0][0] * m[0][0] + m[0][1] * m[0][1]) + m[0][2] * m[0][2];
  const V c01 = (m[0][0] * m[1][0] + m[0][1] * m[1][1]) + m[0][2] * m[1][2];
  const V c02 = (m[0][0] * m[2][0] + m[0][1] * m[2][1]) + m[0][2] * m[2][2];
  const V c11 = (m[1][0] * m[1][0] + m[1][1] * m[1][1]) + m[1][2] * m[1][2];
  const V c12 = (m[1][0] * m[2][0] + m[1][1] * m[2][1]) + m[1][2] * m[2][2];
  const V c22 = (m[2][0] * m[2][0] + m[2][1] * m[2][1]) + m[2][2] * m[2][2];

  for (int j = 0; j < 3; ++j) {
    f.T0[j] = f.j00 * k.R[0][j] + f.j02 * k.R[2][j];
    f.T1[j] = f.j11 * k.R[1][j] + f.j12 * k.R[2][j];
  }
  const V* t0 = f.T0;
  const V* t1 = f.T1;
  f.u[0] = (t0[0] * c00 + t0[1] * c01) + t0[2] * c02;
  f.u[1] = (t0[0] * c01 + t0[1] * c11) + t0[2] * c12;
  f.u[2] = (t0[0] * c02 + t0[1] * c12) + t0[2] * c22;
  f.v[0] = (t1[0] * c00 + t1[1] * c01) + t1[2] * c02;
  f.v[1] = (t1[0] * c01 + t1[1] * c11) + t1[2] * c12;
  f.v[2] = (t1[0] * c02 + t1[1] * c12) + t1[2] * c22;
  f.a0 = (f.u[0] * t0[0] + f.u[1] * t0[1]) + f.u[2] * t0[2];
  f.b = (f.u[0] * t1[0] + f.u[1] * t1[1]) + f.u[2] * t1[2];
  f.c0 = (f.v[0] * t1[0] + f.v[1] * t1[1]) + f.v[2] * t1[2];
  f.a = f.a0 + k.eps2d;
  f.c = f.c0 + k.eps2d;
  f.det = f.a * f.c - f.b * f.b;
  f.vis = f.vis_z & (f.det > V{});
  f.ds = f.vis ? f.det : one;
  if (k.aa) {
    f.det0 = f.a0 * f.c0 - f.b * f.b;
    f.ratio = f.det0 / f.ds;
    const V lo = bc<V>(k.aa_min);
    f.rc = (f.ratio < lo) ? lo : f.ratio;  // clamp(min=aa_min); NaN propagates
  }
}

// True if every lane of the mask is set.
template <typename M>
inline bool all_lanes(const M& m, int L) {
  for (int l = 0; l < L; ++l)
    if (!mlane(m, l)) return false;
  return true;
}

// 0 in every lane where all forward intermediates of the chain rule (and the scales) and the
// reciprocals of its divisors are finite, NaN elsewhere (x * 0 is NaN for x = +-inf or NaN; no -ffast-math here, so it is not folded).
template <typename V>
inline V finite_probe(const Fwd<V>& f, const V* s, bool aa) {
  const V z{};
  V acc = (f.tx * z + f.ty * z) + (f.tz * z + f.zs * z);
  acc += (f.xr * z + f.yr * z) + (f.inv * z + f.j00 * z) + (f.j02 * z + f.j11 * z) + f.j12 * z;
  acc += f.n * z;
  for (int j = 0; j < 4; ++j) acc += f.q[j] * z;
  for (int p = 0; p < 3; ++p) {
    for (int j = 0; j < 3; ++j) acc += f.r[p][j] * z + f.m[p][j] * z;
    acc += (f.T0[p] * z + f.T1[p] * z) + (f.u[p] * z + f.v[p] * z) + s[p] * z;
  }
  acc += (f.a * z + f.b * z) + (f.c * z + f.ds * z);
  // the chain rule's divisors (in VT: an underflow to 0 here only makes the probe conservative)
  const V one = z + 1;
  acc += (one / (f.ds * f.ds)) * z + (one / (f.zs * f.zs)) * z + (one / f.n) * z;
  if (aa) acc += (f.det0 * z + f.ratio * z) + f.rc * z;
  return acc;
}

// Backward of the L splats starting at splat i: forward intermediates in VT (the input dtype, so
// every mask is the forward's), chain rule in VA (double lanes).
// trunc(v / tile).clamp(0, g) followed by nan_to_num(nan=0) (tile_rects).
template <typename V>
inline V rect_coord(V v, V tile, V g) {
  const V r = clampv(vtrunc(v / tile), V{}, g);
  return (r == r) ? r : V{};
}

// Forward of the L splats starting at splat i.
template <typename V>
inline void forward_pack(const Cam<typename Tr<V>::S>& k, int64_t i, const typename Tr<V>::S* means,
                         const typename Tr<V>::S* quats, const typename Tr<V>::S* scales,
                         typename Tr<V>::S* means2d, typename Tr<V>::S* conics, typename Tr<V>::S* depths,
                         int32_t* radii, bool* visible, bool* finite, typename Tr<V>::S* ratio) {
  using T = typename Tr<V>::S;
  constexpr int L = Tr<V>::L;
  Fwd<V> f;
  fwd_core<V>(k, means + 3 * i, quats + 4 * i, scales + 3 * i, f);
  {
    const auto fin = finite_probe<V>(f, f.s, k.aa) == V{};
    for (int l = 0; l < L; ++l) finite[i + l] = mlane(fin, l);
  }
  const V conic[3] = {f.c / f.ds, (-f.b) / f.ds, f.a / f.ds};
  store_rows<V, 3>(conics + 3 * i, conic);
  const V u = (k.fx * f.tx) / f.zs + k.cx;
  const V v = (k.fy * f.ty) / f.zs + k.cy;
  const V uv[2] = {u, v};
  store_rows<V, 2>(means2d + 2 * i, uv);
  scatter<V>(depths + i, 1, 0, f.tz);
  if (k.aa) scatter<V>(ratio + i, 1, 0, f.rc);
  // radius (no_grad block of projection.py)
  const V mid = T(0.5) * (f.a + f.c);
  V disc = mid * mid - f.det;
  disc = (disc < bc<V>(T(0.1))) ? bc<V>(T(0.1)) : disc;  // clamp(min=0.1); NaN propagates
  const V lam = mid + vsqrt(disc);
  const V rad = vceil(T(3) * vsqrt(lam));
  // .to(int32) on x86: NaN, inf and out-of-range values give INT32_MIN; rr = float(radius)
  const V int_min = bc<V>(T(-2147483648.0));
  const V rr = ((rad >= int_min) & (rad < bc<V>(T(2147483648.0)))) ? rad : int_min;
  // 3DGS getRect of (means2d - 0.5, radius)
  const V pu = u - T(0.5), pv = v - T(0.5);
  const V tile = bc<V>(k.tile), gx = bc<V>(k.gx), gy = bc<V>(k.gy);
  const V x0 = rect_coord(pu - rr, tile, gx);
  const V y0 = rect_coord(pv - rr, tile, gy);
  const V x1 = rect_coord(((pu + rr) + k.tile) - T(1), tile, gx);
  const V y1 = rect_coord(((pv + rr) + k.tile) - T(1), tile, gy);
  const auto vis = f.vis & (x1 > x0) & (y1 > y0) & ((u - u) == V{}) & ((v - v) == V{});  // finite u, v
  for (int l = 0; l < L; ++l) {
    const bool vl = mlane(vis, l);
    visible[i + l] = vl;
    radii[i + l] = vl ? static_cast<int32_t>(lane(rr, l)) : 0;  // rr is integral and in range
  }
}

template <typename T>
void forward_impl(const Cam<T>& k, const T* means, const T* quats, const T* scales, int64_t N,
                  T* means2d, T* conics, T* depths, int32_t* radii, bool* visible, bool* finite, T* ratio) {
  using V = vec_t<T, 32 / sizeof(T)>;  // 8 floats or 4 doubles
  constexpr int L = Tr<V>::L;
  const int64_t nb = N / L;
  const int nt = std::max(1, at::get_num_threads());
#pragma omp parallel for schedule(static) num_threads(nt) if (N >= MIN_SPLATS_PARALLEL)
  for (int64_t b = 0; b < nb; ++b)
    forward_pack<V>(k, b * L, means, quats, scales, means2d, conics, depths, radii, visible, finite, ratio);
  for (int64_t i = nb * L; i < N; ++i)
    forward_pack<T>(k, i, means, quats, scales, means2d, conics, depths, radii, visible, finite, ratio);
}

// Incoming gradients of the backward: rows of means2d [N, 2], conics [N, 3], depths [N] and (the
// antialiased mode only, else null) the clamped determinant ratio [N] with row strides (elements) sm2, scn, sdp,
// scp, so strided views (e.g. columns of the rasterizer's [N, R] gradient) are read in place.
template <typename S>
struct GradIn {
  const S* m2;
  const S* cn;
  const S* dp;
  int64_t sm2, scn, sdp;
  const S* cp = nullptr;
  int64_t scp = 1;
};

template <typename VT, typename VA>
inline void backward_pack(const Cam<typename Tr<VT>::S>& k, int64_t i, const typename Tr<VT>::S* means,
                          const typename Tr<VT>::S* quats, const typename Tr<VT>::S* scales,
                          const GradIn<typename Tr<VT>::S>& gi, typename Tr<VT>::S* g_means,
                          typename Tr<VT>::S* g_quats, typename Tr<VT>::S* g_scales) {
  using A = typename Tr<VA>::S;
  using MA = mask_t<VA>;
  static_assert(Tr<VT>::L == Tr<VA>::L, "lane counts must match");
  Fwd<VT> f;
  const auto* sc = scales + 3 * i;
  fwd_core<VT>(k, means + 3 * i, quats + 4 * i, sc, f);
  auto up = [](const VT& v) { return cvt<VA>(v); };
  const auto* gm2 = gi.m2 + gi.sm2 * i;
  const auto* gcn = gi.cn + gi.scn * i;
  {
    // Splats whose incoming gradients are all zero (in a render, the occluded ones: 60-75 % of a
    // dense scene) get zero gradients without the chain rule where that is exact: every step of
    // it is linear in the incoming gradients with coefficients from the forward intermediates
    // (divisors zs, n, ds nonzero), so it yields +-0 exactly when all of those are finite
    // (finite_probe); where one is not, the full chain rule runs (0 x inf = NaN, as torch
    // autograd gives). Per pack: all L lanes must qualify.
    constexpr int L = Tr<VT>::L;
    const VT zt{};
    const auto zero_g = (gather<VT>(gm2, gi.sm2, 0) == zt) & (gather<VT>(gm2, gi.sm2, 1) == zt) &
                        (gather<VT>(gcn, gi.scn, 0) == zt) & (gather<VT>(gcn, gi.scn, 1) == zt) &
                        (gather<VT>(gcn, gi.scn, 2) == zt) &
                        (gather<VT>(gi.dp + gi.sdp * i, gi.sdp, 0) == zt);
    const bool zero_cp = !k.aa || all_lanes(gather<VT>(gi.cp + gi.scp * i, gi.scp, 0) == zt, L);
    if (zero_cp && all_lanes(zero_g, L)) {
      if (all_lanes(finite_probe<VT>(f, f.s, k.aa) == zt, L)) {
        for (int j = 0; j < 4; ++j) scatter<VT>(g_quats + 4 * i, 4, j, zt);
        for (int j = 0; j < 3; ++j) {
          scatter<VT>(g_scales + 3 * i, 3, j, zt);
          scatter<VT>(g_means + 3 * i, 3, j, zt);
        }
        return;
      }
    }
  }
  const VA gu = up(gather<VT>(gm2, gi.sm2, 0)), gv = up(gather<VT>(gm2, gi.sm2, 1));
  const VA gA = up(gather<VT>(gcn, gi.scn, 0)), gB = up(gather<VT>(gcn, gi.scn, 1)),
           gC = up(gather<VT>(gcn, gi.scn, 2));
  const VA a = up(f.a), b = up(f.b), c = up(f.c), ds = up(f.ds);
  const VA zero{};

  // conics = (c, -b, a) / ds; ds = det = a c - b^2 where visible, else the constant 1 (torch.where:
  // the det branch gets a zero gradient, which is still multiplied through det's inputs)
  VA ga = gC / ds, gb = -gB / ds, gc = gA / ds;
  VA gds_in = -(gA * c - gB * b + gC * a) / (ds * ds);
  if (k.aa) {
    // rc = clamp(ratio, min), ratio = det0 / ds, det0 = a0 c0 - b^2 (a = a0 + eps2d: the gradients
    // of a0 and a are the same, likewise c)
    const VA grc = up(gather<VT>(gi.cp + gi.scp * i, gi.scp, 0));
    const auto pass = f.ratio >= bc<VT>(k.aa_min);  // clamp backward: passes at and above the bound
    const VA gratio = mcvt<MA>(pass) ? grc : zero;
    const VA gdet0 = gratio / ds;
    gds_in -= gratio * up(f.ratio) / ds;
    ga += gdet0 * up(f.c0);
    gc += gdet0 * up(f.a0);
    gb -= A(2) * gdet0 * b;
  }
  const VA gds = mcvt<MA>(f.vis) ? gds_in : zero;
  ga += gds * c;
  gc += gds * a;
  gb -= A(2) * gds * b;
  // a = T0 Sigma T0^T, b = T0 Sigma T1^T, c = T1 Sigma T1^T (+ eps)
  VA t0[3], t1[3], gT0[3], gT1[3];
  for (int j = 0; j < 3; ++j) {
    t0[j] = up(f.T0[j]);
    t1[j] = up(f.T1[j]);
    const VA uj = up(f.u[j]), vj = up(f.v[j]);
    gT0[j] = A(2) * ga * uj + gb * vj;
    gT1[j] = gb * uj + A(2) * gc * vj;
  }
  // dL/dSigma (full 3x3) G = ga T0 T0^T + gb T0 T1^T + gc T1 T1^T; Sigma = M M^T -> dL/dM = (G + G^T) M
  VA Gs[3][3];
  for (int p = 0; p < 3; ++p)
    for (int q = 0; q < 3; ++q) {
      const VA gpq = ga * t0[p] * t0[q] + gb * t0[p] * t1[q] + gc * t1[p] * t1[q];
      const VA gqp = ga * t0[q] * t0[p] + gb * t0[q] * t1[p] + gc * t1[q] * t1[p];
      Gs[p][q] = gpq + gqp;
    }
  VA mm[3][3], rr[3][3], s[3];
  for (int p = 0; p < 3; ++p)
    for (int j = 0; j < 3; ++j) {
      mm[p][j] = up(f.m[p][j]);
      rr[p][j] = up(f.r[p][j]);
    }
  for (int j = 0; j < 3; ++j) s[j] = up(f.s[j]);
  // M = R diag(s)
  VA gr[3][3];
  VA gs[3] = {zero, zero, zero};
  for (int p = 0; p < 3; ++p)
    for (int j = 0; j < 3; ++j) {
      const VA gm = Gs[p][0] * mm[0][j] + Gs[p][1] * mm[1][j] + Gs[p][2] * mm[2][j];
      gr[p][j] = gm * s[j];
      gs[j] += gm * rr[p][j];
    }
  // R(q) of the normalised quaternion (w, x, y, z)
  const VA w = up(f.q[0]), x = up(f.q[1]), y = up(f.q[2]), z = up(f.q[3]);
  const VA gw = A(2) * (-z * gr[0][1] + y * gr[0][2] + z * gr[1][0] - x * gr[1][2] - y * gr[2][0] +
                        x * gr[2][1]);
  const VA gx = A(2) * (y * gr[0][1] + z * gr[0][2] + y * gr[1][0] - A(2) * x * gr[1][1] - w * gr[1][2] +
                        z * gr[2][0] + w * gr[2][1] - A(2) * x * gr[2][2]);
  const VA gy = A(2) * (-A(2) * y * gr[0][0] + x * gr[0][1] + w * gr[0][2] + x * gr[1][0] + z * gr[1][2] -
                        w * gr[2][0] + z * gr[2][1] - A(2) * y * gr[2][2]);
  const VA gz = A(2) * (-A(2) * z * gr[0][0] - w * gr[0][1] + x * gr[0][2] + w * gr[1][0] -
                        A(2) * z * gr[1][1] + y * gr[1][2] + x * gr[2][0] + y * gr[2][1]);
  // q = Q / |Q|
  const VA dot = w * gw + x * gx + y * gy + z * gz;
  const VA n = up(f.n);
  auto down = [](const VA& v) { return cvt<VT>(v); };
  scatter<VT>(g_quats + 4 * i, 4, 0, down((gw - w * dot) / n));
  scatter<VT>(g_quats + 4 * i, 4, 1, down((gx - x * dot) / n));
  scatter<VT>(g_quats + 4 * i, 4, 2, down((gy - y * dot) / n));
  scatter<VT>(g_quats + 4 * i, 4, 3, down((gz - z * dot) / n));
  for (int j = 0; j < 3; ++j) scatter<VT>(g_scales + 3 * i, 3, j, down(gs[j]));

  // T0 = j00 R_0 + j02 R_2, T1 = j11 R_1 + j12 R_2 (camera rotation rows)
  VA gj00 = zero, gj02 = zero, gj11 = zero, gj12 = zero;
  for (int j = 0; j < 3; ++j) {
    gj00 += gT0[j] * A(k.R[0][j]);
    gj02 += gT0[j] * A(k.R[2][j]);
    gj11 += gT1[j] * A(k.R[1][j]);
    gj12 += gT1[j] * A(k.R[2][j]);
  }
  const VA zs = up(f.zs), inv = up(f.inv);
  const A fx = k.fx, fy = k.fy;
  // j00 = fx / zs, j11 = fy / zs
  VA gzs = -((gj00 * fx + gj11 * fy) * inv * inv);
  // j02 = -fx xz / zs, j12 = -fy yz / zs
  const VA gxz = gj02 * A(k.mfx) / zs;
  const VA gyz = gj12 * A(k.mfy) / zs;
  gzs -= (gj02 * up(f.j02) + gj12 * up(f.j12)) / zs;
  // clamp: the gradient passes where lo <= x/z <= hi (torch's clamp backward)
  const auto in_x = (f.xr >= bc<VT>(k.xlo)) & (f.xr <= bc<VT>(k.xhi));
  const auto in_y = (f.yr >= bc<VT>(k.ylo)) & (f.yr <= bc<VT>(k.yhi));
  const VA gxr = mcvt<MA>(in_x) ? gxz : zero;
  const VA gyr = mcvt<MA>(in_y) ? gyz : zero;
  VA gtx = gxr / zs;
  VA gty = gyr / zs;
  gzs -= (gxr * up(f.xr) + gyr * up(f.yr)) / zs;
  // means2d = (fx tx / zs + cx, fy ty / zs + cy)
  gtx += gu * fx / zs;
  gty += gv * fy / zs;
  gzs -= (gu * fx * up(f.tx) + gv * fy * up(f.ty)) / (zs * zs);
  // depths = tz; zs = tz where z > near
  const VA gtz = up(gather<VT>(gi.dp + gi.sdp * i, gi.sdp, 0)) + (mcvt<MA>(f.vis_z) ? gzs : zero);
  // t = R p + t
  for (int j = 0; j < 3; ++j)
    scatter<VT>(g_means + 3 * i, 3, j,
                down(A(k.R[0][j]) * gtx + A(k.R[1][j]) * gty + A(k.R[2][j]) * gtz));
}

// Backward over the live splats only: those with a non-zero incoming gradient or a non-finite
// forward intermediate (finite[i] false; there torch's chain rule yields NaN). Every other splat's
// gradient is exactly zero and written as such during the scan (outputs need no fill). Live
// splats are staged L at a time into contiguous rows, so packs stay full however sparse they are;
// lanes do not interact, so each splat's result is the same in any pack (any thread count).
template <typename T>
void backward_impl(const Cam<T>& k, const T* means, const T* quats, const T* scales, const bool* finite,
                   int64_t N, const GradIn<T>& gi, T* g_means, T* g_quats, T* g_scales) {
  using VT = vec_t<T, 4>;
  using VA = vec_t<double, 4>;
  constexpr int L = 4;
  const int nt = N >= MIN_SPLATS_PARALLEL ? std::max(1, at::get_num_threads()) : 1;
  // nt contiguous chunks, each scanned for its live splats and evaluated by one thread
#pragma omp parallel for schedule(static, 1) num_threads(nt)
  for (int t = 0; t < nt; ++t) {
    std::vector<int64_t> live;
    live.reserve(static_cast<size_t>(N / nt + 1));
    for (int64_t i = N * t / nt; i < N * (t + 1) / nt; ++i) {
      const T* m2 = gi.m2 + gi.sm2 * i;
      const T* cn = gi.cn + gi.scn * i;
      const bool zero = m2[0] == T(0) && m2[1] == T(0) && cn[0] == T(0) && cn[1] == T(0) &&
                        cn[2] == T(0) && gi.dp[gi.sdp * i] == T(0) && (!k.aa || gi.cp[gi.scp * i] == T(0));
      if (!(zero && finite[i])) {
        live.push_back(i);
      } else {  // exactly zero gradients (outputs are not pre-filled)
        for (int j = 0; j < 3; ++j) {
          g_means[3 * i + j] = T(0);
          g_scales[3 * i + j] = T(0);
        }
        for (int j = 0; j < 4; ++j) g_quats[4 * i + j] = T(0);
      }
    }
    const int64_t nl = static_cast<int64_t>(live.size()), nb = nl / L;
    for (int64_t b = 0; b < nb; ++b) {
      T lm[3 * L], lq[4 * L], ls[3 * L], lg2[2 * L], lgc[3 * L], lgd[L], lgp[L], om[3 * L], oq[4 * L],
          os[3 * L];
      for (int l = 0; l < L; ++l) {
        const int64_t i = live[b * L + l];
        for (int j = 0; j < 3; ++j) {
          lm[3 * l + j] = means[3 * i + j];
          ls[3 * l + j] = scales[3 * i + j];
          lgc[3 * l + j] = gi.cn[gi.scn * i + j];
        }
        for (int j = 0; j < 4; ++j) lq[4 * l + j] = quats[4 * i + j];
        lg2[2 * l] = gi.m2[gi.sm2 * i];
        lg2[2 * l + 1] = gi.m2[gi.sm2 * i + 1];
        lgd[l] = gi.dp[gi.sdp * i];
        lgp[l] = k.aa ? gi.cp[gi.scp * i] : T(0);
      }
      const GradIn<T> gl{lg2, lgc, lgd, 2, 3, 1, k.aa ? lgp : nullptr, 1};
      backward_pack<VT, VA>(k, 0, lm, lq, ls, gl, om, oq, os);
      for (int l = 0; l < L; ++l) {
        const int64_t i = live[b * L + l];
        for (int j = 0; j < 3; ++j) {
          g_means[3 * i + j] = om[3 * l + j];
          g_scales[3 * i + j] = os[3 * l + j];
        }
        for (int j = 0; j < 4; ++j) g_quats[4 * i + j] = oq[4 * l + j];
      }
    }
    for (int64_t b = nb * L; b < nl; ++b)
      backward_pack<T, double>(k, live[b], means, quats, scales, gi, g_means, g_quats, g_scales);
  }
}

// ---------------------------------------------------------------------------------------------
// Python entry points.

// Device, dtype and shape ([n] if cols == 0, else [n, cols]) of an input or incoming gradient.
void check_device_dtype_shape(const at::Tensor& t, const char* name, at::ScalarType st, int64_t n,
                              int64_t cols) {
  TORCH_CHECK(t.device().is_cpu(), "project_cpu: ", name, " must be a CPU tensor, got ", t.device());
  TORCH_CHECK(t.scalar_type() == st, "project_cpu: ", name, " must be ", st, " like means, got ",
              t.scalar_type());
  if (cols == 0) {
    TORCH_CHECK(t.dim() == 1 && t.size(0) == n, "project_cpu: ", name, " must be [", n, "], got ",
                t.sizes());
  } else {
    TORCH_CHECK(t.dim() == 2 && t.size(0) == n && t.size(1) == cols, "project_cpu: ", name,
                " must be [", n, ", ", cols, "], got ", t.sizes());
  }
}

void check_input(const at::Tensor& t, const char* name, at::ScalarType st, int64_t n, int64_t cols) {
  check_device_dtype_shape(t, name, st, n, cols);
  TORCH_CHECK(t.is_contiguous(), "project_cpu: ", name, " must be contiguous");
}

void check_common(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                  const at::Tensor& viewmat, int64_t width, int64_t height, int64_t tile) {
  TORCH_CHECK(means.dim() == 2, "project_cpu: means must be [N, 3], got ", means.sizes());
  const auto st = means.scalar_type();
  TORCH_CHECK(st == at::kFloat || st == at::kDouble, "project_cpu: means must be float32 or float64, got ",
              st);
  const int64_t N = means.size(0);
  check_input(means, "means", st, N, 3);
  check_input(quats, "quats", st, N, 4);
  check_input(scales, "scales", st, N, 3);
  check_input(viewmat, "viewmat", st, 4, 4);
  TORCH_CHECK(width > 0 && height > 0, "project_cpu: bad image size ", width, "x", height);
  TORCH_CHECK(tile > 0, "project_cpu: bad tile size ", tile);
}

// Forward.
// Args: means [N,3], quats [N,4] (w,x,y,z, any norm), scales [N,3] (linear), viewmat [4,4]
//       world-to-camera (OpenCV), all float32 or all float64, contiguous; fx, fy, cx, cy (pixels);
//       width, height; near_plane, frustum_clamp, eps2d, tile (projection.py constants).
// Returns: means2d [N,2], conics [N,3] (a, b, c of the inverse 2D covariance), depths [N]
//          (camera z, also of culled splats), radii [N] int32 (0 if culled), visible [N] bool,
//          finite [N] bool (every intermediate the backward's chain rule uses is finite).
std::vector<at::Tensor> forward_entry(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                      const at::Tensor& viewmat, double fx, double fy, double cx, double cy,
                                      int64_t width, int64_t height, double near_plane, double frustum_clamp,
                                      double eps2d, int64_t tile, bool antialiased, double aa_ratio_min) {
  check_common(means, quats, scales, viewmat, width, height, tile);
  const int64_t N = means.size(0);
  auto opts = means.options();
  at::Tensor means2d = at::empty({N, 2}, opts);
  at::Tensor conics = at::empty({N, 3}, opts);
  at::Tensor depths = at::empty({N}, opts);
  at::Tensor radii = at::empty({N}, opts.dtype(at::kInt));
  at::Tensor visible = at::empty({N}, opts.dtype(at::kBool));
  at::Tensor finite = at::empty({N}, opts.dtype(at::kBool));
  at::Tensor ratio = at::empty({antialiased ? N : 0}, opts);
  auto run = [&](auto zero) {
    using T = decltype(zero);
    const Cam<T> k = make_cam<T>(viewmat, fx, fy, cx, cy, width, height, near_plane, frustum_clamp,
                                 eps2d, tile, antialiased, aa_ratio_min);
    forward_impl<T>(k, means.data_ptr<T>(), quats.data_ptr<T>(), scales.data_ptr<T>(), N,
                    means2d.data_ptr<T>(), conics.data_ptr<T>(), depths.data_ptr<T>(),
                    radii.data_ptr<int32_t>(), visible.data_ptr<bool>(), finite.data_ptr<bool>(),
                    antialiased ? ratio.data_ptr<T>() : nullptr);
  };
  if (means.scalar_type() == at::kFloat)
    run(float(0));
  else
    run(double(0));
  if (antialiased) return {means2d, conics, depths, radii, visible, finite, ratio};
  return {means2d, conics, depths, radii, visible, finite};
}

std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                        at::Tensor viewmat, double fx, double fy, double cx, double cy,
                                        int64_t width, int64_t height, double near_plane,
                                        double frustum_clamp, double eps2d, int64_t tile) {
  return forward_entry(means, quats, scales, viewmat, fx, fy, cx, cy, width, height, near_plane,
                       frustum_clamp, eps2d, tile, false, 0.0);
}

// Antialiased forward (Mip-Splatting's 2D Mip filter; eps2d is the filter's variance): the same
// outputs, then ratio [N] = clamp(det0 / det, min=aa_ratio_min) (det0: the 2D covariance's
// determinant before the filter; det replaced by 1 where culled); the opacity compensation is its
// square root.
std::vector<at::Tensor> project_forward_aa(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                           at::Tensor viewmat, double fx, double fy, double cx, double cy,
                                           int64_t width, int64_t height, double near_plane,
                                           double frustum_clamp, double eps2d, int64_t tile,
                                           double aa_ratio_min) {
  return forward_entry(means, quats, scales, viewmat, fx, fy, cx, cy, width, height, near_plane,
                       frustum_clamp, eps2d, tile, true, aa_ratio_min);
}

// Incoming gradient of the backward: [N] or [N, cols] in the splats' dtype whose elements within a
// row are contiguous (any row stride, e.g. a column slice of a wider gradient buffer).
void check_grad(const at::Tensor& t, const char* name, at::ScalarType st, int64_t n, int64_t cols) {
  check_device_dtype_shape(t, name, st, n, cols);
  TORCH_CHECK(cols == 0 || t.stride(1) == 1, "project_cpu: ", name, " must have contiguous rows");
  TORCH_CHECK(t.stride(0) >= 0, "project_cpu: ", name, " has a negative stride");
}

// Backward (vector-Jacobian product of project_forward's differentiable outputs).
// Args: the forward's inputs, then v_means2d [N,2], v_conics [N,3], v_depths [N] (same dtype;
//       elements within a row contiguous, rows at any stride: see check_grad), and the forward's
//       finite [N] bool (splats with zero incoming gradients and finite[i] get zero gradients
//       without evaluating their chain rule).
// Returns: v_means [N,3], v_quats [N,4] (w.r.t. the unnormalised input), v_scales [N,3].
std::vector<at::Tensor> backward_entry(const at::Tensor& means, const at::Tensor& quats,
                                       const at::Tensor& scales, const at::Tensor& viewmat, double fx,
                                       double fy, double cx, double cy, int64_t width, int64_t height,
                                       double near_plane, double frustum_clamp, double eps2d, int64_t tile,
                                       const at::Tensor& v_means2d, const at::Tensor& v_conics,
                                       const at::Tensor& v_depths, const at::Tensor* v_ratio,
                                       const at::Tensor& finite, double aa_ratio_min) {
  check_common(means, quats, scales, viewmat, width, height, tile);
  const int64_t N = means.size(0);
  const auto st = means.scalar_type();
  const bool antialiased = v_ratio != nullptr;
  check_grad(v_means2d, "v_means2d", st, N, 2);
  check_grad(v_conics, "v_conics", st, N, 3);
  check_grad(v_depths, "v_depths", st, N, 0);
  if (antialiased) check_grad(*v_ratio, "v_ratio", st, N, 0);
  check_input(finite, "finite", at::kBool, N, 0);
  auto opts = means.options();
  at::Tensor g_means = at::empty({N, 3}, opts);  // every row written by backward_impl
  at::Tensor g_quats = at::empty({N, 4}, opts);
  at::Tensor g_scales = at::empty({N, 3}, opts);
  auto run = [&](auto zero) {
    using T = decltype(zero);
    const Cam<T> k = make_cam<T>(viewmat, fx, fy, cx, cy, width, height, near_plane, frustum_clamp,
                                 eps2d, tile, antialiased, aa_ratio_min);
    const GradIn<T> gi{v_means2d.data_ptr<T>(), v_conics.data_ptr<T>(), v_depths.data_ptr<T>(),
                       v_means2d.stride(0), v_conics.stride(0), v_depths.stride(0),
                       antialiased ? v_ratio->data_ptr<T>() : nullptr, antialiased ? v_ratio->stride(0) : 1};
    backward_impl<T>(k, means.data_ptr<T>(), quats.data_ptr<T>(), scales.data_ptr<T>(),
                     finite.data_ptr<bool>(), N, gi,
                     g_means.data_ptr<T>(), g_quats.data_ptr<T>(), g_scales.data_ptr<T>());
  };
  if (st == at::kFloat)
    run(float(0));
  else
    run(double(0));
  return {g_means, g_quats, g_scales};
}

std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                         at::Tensor viewmat, double fx, double fy, double cx,
                                         double cy, int64_t width, int64_t height, double near_plane,
                                         double frustum_clamp, double eps2d, int64_t tile,
                                         at::Tensor v_means2d, at::Tensor v_conics,
                                         at::Tensor v_depths, at::Tensor finite) {
  return backward_entry(means, quats, scales, viewmat, fx, fy, cx, cy, width, height, near_plane,
                        frustum_clamp, eps2d, tile, v_means2d, v_conics, v_depths, nullptr, finite, 0.0);
}

// Antialiased backward: as project_backward, plus v_ratio [N] (the incoming gradient of
// project_forward_aa's ratio; rows at any stride), and aa_ratio_min as in the forward.
std::vector<at::Tensor> project_backward_aa(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                            at::Tensor viewmat, double fx, double fy, double cx,
                                            double cy, int64_t width, int64_t height, double near_plane,
                                            double frustum_clamp, double eps2d, int64_t tile,
                                            double aa_ratio_min, at::Tensor v_means2d, at::Tensor v_conics,
                                            at::Tensor v_depths, at::Tensor v_ratio,
                                            at::Tensor finite) {
  return backward_entry(means, quats, scales, viewmat, fx, fy, cx, cy, width, height, near_plane,
                        frustum_clamp, eps2d, tile, v_means2d, v_conics, v_depths, &v_ratio, finite,
                        aa_ratio_min);
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(splatfields_cpu, m) {
  m.def("project_forward", &project_forward);
  m.def("project_backward", &project_backward);
  m.def("project_forward_aa", &project_forward_aa);
  m.def("project_backward_aa", &project_backward_aa);
}
