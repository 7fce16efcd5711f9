// Bilinear sampling of the tri-planes at the query points (src/fields/triplane_sample.py), forward and backward.
//
// The same function as torch's grid_sample(planes, grid, mode="bilinear", padding_mode="zeros",
// align_corners=False) for P planes [C, R, R] read at P point sets, with the result in the layout the field
// heads read, [N, P·C] (plane-major channels). grid_sample's CPU backward scatters one channel at a time into
// the planes; here the planes are first laid out channels-last, so each of a point's 4 corners reads (and in
// the backward adds into) C contiguous floats, and each thread adds into its own copy of the planes' gradient,
// summed once at the end. Coordinates: u indexes a plane's width, v its height, both in [-1, 1] over the
// plane's extent; pixel coordinate x = ((u + 1) R - 1) / 2; corners outside the plane contribute zero.

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

// The 4 corners of a bilinear read: flat pixel index into [R, R] (or -1 outside) and weight.
struct Corners {
  int64_t idx[4];
  float w[4];
};

inline Corners corners(float u, float v, int R) {
  const float x = ((u + 1.0f) * R - 1.0f) * 0.5f, y = ((v + 1.0f) * R - 1.0f) * 0.5f;
  const float x0f = std::floor(x), y0f = std::floor(y);
  const float fx = x - x0f, fy = y - y0f;
  const int x0 = static_cast<int>(x0f), y0 = static_cast<int>(y0f);
  Corners c;
  const float wx[2] = {1.0f - fx, fx}, wy[2] = {1.0f - fy, fy};
  for (int k = 0; k < 4; ++k) {
    const int xi = x0 + (k & 1), yi = y0 + (k >> 1);
    const bool inside = xi >= 0 && xi < R && yi >= 0 && yi < R;
    c.idx[k] = inside ? static_cast<int64_t>(yi) * R + xi : -1;
    c.w[k] = inside ? wx[k & 1] * wy[k >> 1] : 0.0f;
  }
  return c;
}

void check(const at::Tensor& t, int64_t dim, const char* what) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == at::kFloat && t.is_contiguous() && t.dim() == dim,
              "triplane_sample: ", what, " must be a contiguous float32 CPU tensor of ", dim, " dimensions");
}

// Reads of one point on plane p: o[C] = Σ_k w_k src_k[C] (CC > 0: the channel count fixed at compile time).
template <int CC>
inline void read_point(const float* pl, const Corners& c, int64_t C, float* o) {
  const int64_t nc = CC > 0 ? CC : C;
  float acc[CC > 0 ? CC : 1];
  float* a = CC > 0 ? acc : o;
  for (int64_t ch = 0; ch < nc; ++ch) a[ch] = 0.0f;
  for (int k = 0; k < 4; ++k) {
    if (c.idx[k] < 0) continue;
    const float* src = pl + c.idx[k] * nc;
    const float w = c.w[k];
    for (int64_t ch = 0; ch < nc; ++ch) a[ch] += w * src[ch];
  }
  if (CC > 0)
    for (int64_t ch = 0; ch < nc; ++ch) o[ch] = a[ch];
}

// Adds of one point's gradient gi[C] into plane p's gradient (channels-last), weighted by the corners.
template <int CC>
inline void add_point(float* pl, const Corners& c, int64_t C, const float* gi) {
  const int64_t nc = CC > 0 ? CC : C;
  for (int k = 0; k < 4; ++k) {
    if (c.idx[k] < 0) continue;
    float* dst = pl + c.idx[k] * nc;
    const float w = c.w[k];
    for (int64_t ch = 0; ch < nc; ++ch) dst[ch] += w * gi[ch];
  }
}

template <int CC>
void forward_points(const float* pl, const float* uvp, float* op, int64_t P, int64_t C, int64_t R, int64_t N) {
  const int nt = std::max(1, at::get_num_threads());
#pragma omp parallel for num_threads(nt) schedule(static)
  for (int64_t n = 0; n < N; ++n)
    for (int64_t p = 0; p < P; ++p) {
      const float* q = uvp + (p * N + n) * 2;
      read_point<CC>(pl + p * R * R * C, corners(q[0], q[1], static_cast<int>(R)), C, op + n * P * C + p * C);
    }
}

template <int CC>
void backward_points(float* acc, int64_t plane_elems, const float* gp, const float* uvp, int64_t P, int64_t C,
                     int64_t R, int64_t N, int nt) {
#pragma omp parallel num_threads(nt)
  {
    float* a = acc + static_cast<size_t>(omp_get_thread_num()) * plane_elems;
#pragma omp for schedule(static)
    for (int64_t n = 0; n < N; ++n)
      for (int64_t p = 0; p < P; ++p) {
        const float* q = uvp + (p * N + n) * 2;
        add_point<CC>(a + p * R * R * C, corners(q[0], q[1], static_cast<int>(R)), C, gp + n * P * C + p * C);
      }
  }
}

// planes [P, C, R, R], uv [P, N, 2] -> features [N, P·C].
at::Tensor triplane_sample_forward(const at::Tensor& planes, const at::Tensor& uv) {
  check(planes, 4, "planes");
  check(uv, 3, "uv");
  const int64_t P = planes.size(0), C = planes.size(1), R = planes.size(2), N = uv.size(1);
  TORCH_CHECK(planes.size(3) == R && uv.size(0) == P && uv.size(2) == 2,
              "triplane_sample: expected planes [P, C, R, R] and uv [P, N, 2], got ", planes.sizes(), " and ", uv.sizes());
  const at::Tensor cl = planes.permute({0, 2, 3, 1}).contiguous();  // [P, R, R, C]
  at::Tensor out = at::empty({N, P * C}, planes.options());
  if (C == 16) {  // the paper's plane channels (B.2): fixed-size loops the compiler vectorises
    forward_points<16>(cl.data_ptr<float>(), uv.data_ptr<float>(), out.data_ptr<float>(), P, C, R, N);
  } else {
    forward_points<0>(cl.data_ptr<float>(), uv.data_ptr<float>(), out.data_ptr<float>(), P, C, R, N);
  }
  return out;
}

// g [N, P·C] (gradient of the features), uv [P, N, 2], R -> gradient of the planes [P, C, R, R].
at::Tensor triplane_sample_backward(const at::Tensor& g, const at::Tensor& uv, int64_t R) {
  check(g, 2, "g");
  check(uv, 3, "uv");
  const int64_t P = uv.size(0), N = uv.size(1), C = g.size(1) / std::max<int64_t>(P, 1);
  TORCH_CHECK(g.size(0) == N && g.size(1) == P * C && R > 0, "triplane_sample: g ", g.sizes(), " does not match uv ",
              uv.sizes());
  const int nt = std::max(1, at::get_num_threads());
  const int64_t plane_elems = P * R * R * C;
  std::vector<float> acc(static_cast<size_t>(nt) * plane_elems, 0.0f);  // per thread [P, R, R, C]
  if (C == 16) {
    backward_points<16>(acc.data(), plane_elems, g.data_ptr<float>(), uv.data_ptr<float>(), P, C, R, N, nt);
  } else {
    backward_points<0>(acc.data(), plane_elems, g.data_ptr<float>(), uv.data_ptr<float>(), P, C, R, N, nt);
  }
  at::Tensor cl = at::zeros({P, R, R, C}, g.options());
  float* out = cl.data_ptr<float>();
  for (int t = 0; t < nt; ++t) {
    const float* a = acc.data() + static_cast<size_t>(t) * plane_elems;
    for (int64_t i = 0; i < plane_elems; ++i) out[i] += a[i];
  }
  return cl.permute({0, 3, 1, 2}).contiguous();  // [P, C, R, R]
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(splatfields_cpu, m) {
  m.def("triplane_sample_forward", &triplane_sample_forward);
  m.def("triplane_sample_backward", &triplane_sample_backward);
}
