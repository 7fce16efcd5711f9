// 2D Gaussian surfel compositing (2DGS, Huang et al. 2024, Sec. 4.2), forward + hand-written backward,
// CPU/OpenMP, float32 and float64.
//
// Semantics: exactly src/rasterizer/surfel_ref.py (composite_surfels_ref), the oracle it is tested
// against (values and gradients, float64):
//   * inputs per surfel: T [N, 9] (rows T_u, T_v, T_w; homogeneous pixel (x z, y z, z) = T (u, v, 1)),
//     means2d [N, 2] (the low-pass filter's centre c), normals [N, 3], opacities [N], colours [N, C],
//     rects [N, 4] int32 inclusive pixel index ranges (i0, j0, i1, j1), depths [N] (sort key), visible [N];
//   * visible surfels in a stable order of increasing depth; each binned to the 16 x 16 tiles its rect meets;
//   * per pixel (i, j), centre (x, y) = (i + 0.5, j + 0.5), and surfel of its tile's list, in order:
//       skip unless i0 <= i <= i1 and j0 <= j <= j1;
//       k = x T_w - T_u, l = y T_w - T_v, p = k x l; skip if p.z == 0; (u, v) = (p.x / p.z, p.y / p.z);
//       rho3d = u^2 + v^2, rho2d = |c - (x, y)|^2 / sigma^2 (sigma = sqrt(2) / 2: 2DGS Eq. 11);
//       surface = rho3d <= rho2d: rho = rho3d, depth = u T_w.x + v T_w.y + T_w.z; else rho = rho2d,
//       depth = T_w.z; skip if depth < near (0.2);
//       G = exp(-rho / 2), alpha = min(0.99, o G); skip if alpha < 1/255;
//       stop (this surfel and all later ones) if T (1 - alpha) < 1e-4;
//       w = alpha T; colour/normal/depth += w x; m = far / (far - near) (1 - near / depth);
//       distortion += w (m^2 (1 - T) + M2 - 2 m M1); M1 += w m; M2 += w m^2; T *= 1 - alpha.
//   * outputs: colour [H, W, C] (+ T_final bg), alpha = 1 - T_final, depth, normals [H, W, 3], distortion;
//     saved for the backward: T_final, M1, M2 (final), last (list position + 1 of the last blended surfel),
//     the tile offsets and the per-tile lists.
//
// Backward (vector-Jacobian product; the alpha clamp at 0.99 blocks the gradient as torch.clamp does):
// per pixel, back to front from the last blended surfel, reconstructing T_k = T_{k+1} / (1 - alpha_k):
//   g_k   = gC . c_k + gD z_k + gN . n_k + gDist (m_k^2 W - 2 m_k M1 + M2)      (dL/dw_k; W = 1 - T_final,
//           M1, M2 final: d distortion / d w_k = sum_{j != k} w_j (m_k - m_j)^2)
//   dL/dalpha_k = T_k g_k - (S_k + T_final gT) / (1 - alpha_k),  S_k = sum_{i > k} w_i g_i,
//           gT = gC . bg - gAlpha                                                (dL/dT_final)
//   dL/dz_k = gD w_k + gDist 2 w_k (m_k W - M1) dm/dz,  dm/dz = far / (far - near) near / z^2,
// then the chain rule through alpha, G, rho, (u, v), p = k x l, k, l to T, c and o.
// Gradients are accumulated per thread in double and reduced in thread order (deterministic for a
// given thread count).
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numeric>
#include <vector>

namespace {

constexpr int TILE = 16;
constexpr double ALPHA_MAX = 0.99;
constexpr double ALPHA_MIN = 1.0 / 255.0;
constexpr double T_MIN = 1e-4;
constexpr double FILTER_INV_SQ = 2.0;  // 1 / sigma^2, sigma = sqrt(2) / 2
constexpr double NEAR = 0.2;
constexpr double FAR = 100.0;
constexpr int NG = 15;  // gradient slots per surfel besides colours: T (9), c (2), n (3), o (1)

void check(const at::Tensor& t, const char* name, at::ScalarType st, int64_t rows, int64_t cols) {
  TORCH_CHECK(t.device().is_cpu(), "surfel_cpu: ", name, " must be a CPU tensor");
  TORCH_CHECK(t.scalar_type() == st, "surfel_cpu: ", name, " has dtype ", t.scalar_type(), ", expected ", st);
  TORCH_CHECK(t.is_contiguous(), "surfel_cpu: ", name, " must be contiguous");
  if (cols == 0) {
    TORCH_CHECK(t.dim() == 1 && t.size(0) == rows, "surfel_cpu: ", name, " must have shape [", rows, "]");
  } else {
    TORCH_CHECK(t.dim() == 2 && t.size(0) == rows && t.size(1) == cols, "surfel_cpu: ", name,
                " must have shape [", rows, ", ", cols, "]");
  }
}

struct Bins {
  std::vector<int64_t> offsets;  // [tiles + 1]
  std::vector<int32_t> list;     // surfel ids per tile, depth order
};

template <typename S>
Bins bin_surfels(const S* depths, const bool* visible, const int32_t* rects, int64_t n, int gx, int gy) {
  std::vector<int32_t> order;
  order.reserve(n);
  for (int64_t i = 0; i < n; ++i)
    if (visible[i]) order.push_back(static_cast<int32_t>(i));
  std::stable_sort(order.begin(), order.end(),
                   [depths](int32_t a, int32_t b) { return depths[a] < depths[b]; });
  Bins b;
  const int64_t nt = static_cast<int64_t>(gx) * gy;
  std::vector<int64_t> count(nt + 1, 0);
  auto tiles = [&](int32_t id, int& tx0, int& ty0, int& tx1, int& ty1) {
    const int32_t* r = rects + 4 * static_cast<int64_t>(id);
    tx0 = std::max(r[0], 0) / TILE;
    ty0 = std::max(r[1], 0) / TILE;
    tx1 = std::min(r[2] / TILE, gx - 1);
    ty1 = std::min(r[3] / TILE, gy - 1);
  };
  for (int32_t id : order) {
    int tx0, ty0, tx1, ty1;
    tiles(id, tx0, ty0, tx1, ty1);
    for (int ty = ty0; ty <= ty1; ++ty)
      for (int tx = tx0; tx <= tx1; ++tx) ++count[static_cast<int64_t>(ty) * gx + tx + 1];
  }
  for (int64_t t = 0; t < nt; ++t) count[t + 1] += count[t];
  b.offsets = count;
  b.list.resize(count[nt]);
  std::vector<int64_t> fill(count.begin(), count.end() - 1);
  for (int32_t id : order) {
    int tx0, ty0, tx1, ty1;
    tiles(id, tx0, ty0, tx1, ty1);
    for (int ty = ty0; ty <= ty1; ++ty)
      for (int tx = tx0; tx <= tx1; ++tx) b.list[fill[static_cast<int64_t>(ty) * gx + tx]++] = id;
  }
  return b;
}

// One (pixel, surfel) evaluation shared by the forward and the backward.
template <typename S>
struct Pair {
  S kx, ky, kz, lx, ly, lz;  // planes h_x, h_y
  S pz, u, v;                // p.z, intersection (u, v)
  S dx, dy;                  // c - pixel
  bool surface;
  S depth, g, alpha;
  bool clamped;
};

// Per-surfel bound on rho above which alpha < 1/255 for certain: o exp(-rho / 2) < 1/255 iff
// rho > 2 ln(255 o); the margin (1e-4, far above exp's rounding) makes the early skip exact, so the
// decisions stay those of the reference (exp is evaluated wherever alpha may reach 1/255).
template <typename S>
std::vector<S> rho_cutoffs(const S* op, int64_t n) {
  std::vector<S> cut(n);
  for (int64_t i = 0; i < n; ++i)
    cut[i] = op[i] > S(0) ? S(2) * std::log(S(255) * op[i]) + S(1e-4) : -std::numeric_limits<S>::infinity();
  return cut;
}

// Returns false if the pair is skipped (outside, parallel, behind the near plane, alpha < 1/255).
template <typename S>
inline bool eval_pair(const S* T, const S* c, S o, S cut, const int32_t* r, int i, int j, S x, S y, Pair<S>& q) {
  if (i < r[0] || i > r[2] || j < r[1] || j > r[3]) return false;
  q.kx = x * T[6] - T[0];
  q.ky = x * T[7] - T[1];
  q.kz = x * T[8] - T[2];
  q.lx = y * T[6] - T[3];
  q.ly = y * T[7] - T[4];
  q.lz = y * T[8] - T[5];
  const S px = q.ky * q.lz - q.kz * q.ly;
  const S py = q.kz * q.lx - q.kx * q.lz;
  q.pz = q.kx * q.ly - q.ky * q.lx;
  if (q.pz == S(0)) return false;
  q.u = px / q.pz;
  q.v = py / q.pz;
  const S rho3d = q.u * q.u + q.v * q.v;
  q.dx = c[0] - x;
  q.dy = c[1] - y;
  const S rho2d = (q.dx * q.dx + q.dy * q.dy) * S(FILTER_INV_SQ);
  q.surface = rho3d <= rho2d;
  const S rho = q.surface ? rho3d : rho2d;
  if (rho > cut) return false;  // alpha < 1/255 (see rho_cutoffs)
  q.depth = q.surface ? q.u * T[6] + q.v * T[7] + T[8] : T[8];
  if (q.depth < S(NEAR)) return false;
  q.g = std::exp(S(-0.5) * rho);
  const S a = o * q.g;
  q.clamped = a > S(ALPHA_MAX);
  q.alpha = q.clamped ? S(ALPHA_MAX) : a;
  return q.alpha >= S(ALPHA_MIN);
}

// The entries of a tile's list whose rectangle spans row j: list positions and their column ranges, in
// list order (an acceleration only: eval_pair repeats the full rectangle test).
struct RowCandidates {
  std::vector<int64_t> pos;
  std::vector<int32_t> i0, i1;
  void build(const int32_t* list, const int32_t* rects, int64_t beg, int64_t end, int j) {
    pos.clear();
    i0.clear();
    i1.clear();
    for (int64_t k = beg; k < end; ++k) {
      const int32_t* r = rects + 4 * static_cast<int64_t>(list[k]);
      if (j < r[1] || j > r[3]) continue;
      pos.push_back(k);
      i0.push_back(r[0]);
      i1.push_back(r[2]);
    }
  }
};

template <typename S>
inline S ndc(S z) {
  return S(FAR / (FAR - NEAR)) * (S(1) - S(NEAR) / z);
}

template <typename S>
void forward_impl(const S* T, const S* c, const S* nrm, const S* op, const S* col, const int32_t* rects,
                  const S* bg, int64_t n, int C, int W, int H, const Bins& b, S* out_c, S* out_a, S* out_d, S* out_n,
                  S* out_dist, S* t_final, S* m1_out, S* m2_out, int32_t* last) {
  const int gx = (W + TILE - 1) / TILE, gy = (H + TILE - 1) / TILE;
  const int64_t nt = static_cast<int64_t>(gx) * gy;
  const std::vector<S> cut = rho_cutoffs(op, n);
#pragma omp parallel for schedule(dynamic, 1)
  for (int64_t t = 0; t < nt; ++t) {
    const int tx = static_cast<int>(t % gx), ty = static_cast<int>(t / gx);
    const int64_t beg = b.offsets[t], end = b.offsets[t + 1];
    std::vector<S> acc(C);
    RowCandidates row;
    for (int j = ty * TILE; j < std::min((ty + 1) * TILE, H); ++j) {
      row.build(b.list.data(), rects, beg, end, j);
      const int64_t nrow = static_cast<int64_t>(row.pos.size());
      for (int i = tx * TILE; i < std::min((tx + 1) * TILE, W); ++i) {
        const S x = S(i) + S(0.5), y = S(j) + S(0.5);
        std::fill(acc.begin(), acc.end(), S(0));
        S Tr = 1, D = 0, N0 = 0, N1 = 0, N2 = 0, M1 = 0, M2 = 0, dist = 0;
        int32_t lastk = 0;
        for (int64_t e = 0; e < nrow; ++e) {
          if (i < row.i0[e] || i > row.i1[e]) continue;
          const int64_t k = row.pos[e];
          const int64_t id = b.list[k];
          Pair<S> q;
          if (!eval_pair(T + 9 * id, c + 2 * id, op[id], cut[id], rects + 4 * id, i, j, x, y, q)) continue;
          const S test = Tr * (S(1) - q.alpha);
          if (test < S(T_MIN)) break;
          const S w = q.alpha * Tr;
          const S m = ndc(q.depth);
          dist += w * (m * m * (S(1) - Tr) + M2 - S(2) * m * M1);
          M1 += w * m;
          M2 += w * m * m;
          D += w * q.depth;
          N0 += w * nrm[3 * id];
          N1 += w * nrm[3 * id + 1];
          N2 += w * nrm[3 * id + 2];
          for (int ch = 0; ch < C; ++ch) acc[ch] += w * col[id * C + ch];
          Tr = test;
          lastk = static_cast<int32_t>(k - beg + 1);
        }
        const int64_t pix = static_cast<int64_t>(j) * W + i;
        for (int ch = 0; ch < C; ++ch) out_c[pix * C + ch] = acc[ch] + Tr * bg[ch];
        out_a[pix] = S(1) - Tr;
        out_d[pix] = D;
        out_n[3 * pix] = N0;
        out_n[3 * pix + 1] = N1;
        out_n[3 * pix + 2] = N2;
        out_dist[pix] = dist;
        t_final[pix] = Tr;
        m1_out[pix] = M1;
        m2_out[pix] = M2;
        last[pix] = lastk;
      }
    }
  }
}

template <typename S>
void backward_impl(const S* gC, const S* gA, const S* gD, const S* gN, const S* gDist, const S* T, const S* c,
                   const S* nrm, const S* op, const S* col, const int32_t* rects, const S* bg, const S* t_final,
                   const S* m1_all, const S* m2_all, const int32_t* last, const int64_t* offsets,
                   const int32_t* list, int64_t n, int C, int W, int H, S* gT_out, S* gc_out, S* gn_out,
                   S* go_out, S* gcol_out) {
  const int gx = (W + TILE - 1) / TILE, gy = (H + TILE - 1) / TILE;
  const int64_t nt = static_cast<int64_t>(gx) * gy;
  const int64_t stride = NG + C;
  const int nthreads = std::max(1, std::min<int>(omp_get_max_threads(), static_cast<int>(nt)));
  const std::vector<S> cut = rho_cutoffs(op, n);
  std::vector<std::vector<double>> bufs(nthreads, std::vector<double>(static_cast<size_t>(n * stride), 0.0));
#pragma omp parallel num_threads(nthreads)
  {
    std::vector<double>& g = bufs[omp_get_thread_num()];
    std::vector<S> gcol(C);
    RowCandidates row;
#pragma omp for schedule(static)
    for (int64_t t = 0; t < nt; ++t) {
      const int tx = static_cast<int>(t % gx), ty = static_cast<int>(t / gx);
      const int64_t beg = offsets[t];
      for (int j = ty * TILE; j < std::min((ty + 1) * TILE, H); ++j) {
        row.build(list, rects, beg, offsets[t + 1], j);
        for (int i = tx * TILE; i < std::min((tx + 1) * TILE, W); ++i) {
          const int64_t pix = static_cast<int64_t>(j) * W + i;
          const int32_t lastk = last[pix];
          if (lastk == 0) continue;
          const S x = S(i) + S(0.5), y = S(j) + S(0.5);
          const S Tf = t_final[pix];
          const S Wall = S(1) - Tf, M1 = m1_all[pix], M2 = m2_all[pix];
          S gTf = -gA[pix];
          for (int ch = 0; ch < C; ++ch) {
            gcol[ch] = gC[pix * C + ch];
            gTf += gcol[ch] * bg[ch];
          }
          const S gd = gD[pix], gdist = gDist[pix];
          const S gn0 = gN[3 * pix], gn1 = gN[3 * pix + 1], gn2 = gN[3 * pix + 2];
          S Tr = Tf, suffix = 0;
          // the row's candidates before the last blended surfel (positions ascend)
          const int64_t e_end = std::lower_bound(row.pos.begin(), row.pos.end(), beg + lastk) - row.pos.begin();
          for (int64_t e = e_end - 1; e >= 0; --e) {
            const int64_t k = row.pos[e];
            if (i < row.i0[e] || i > row.i1[e]) continue;
            const int64_t id = list[k];
            const S* Ti = T + 9 * id;
            Pair<S> q;
            if (!eval_pair(Ti, c + 2 * id, op[id], cut[id], rects + 4 * id, i, j, x, y, q)) continue;
            const S oma = S(1) - q.alpha;
            Tr = Tr / oma;  // T before this surfel
            const S w = q.alpha * Tr;
            const S m = ndc(q.depth);
            const S* cc = col + id * C;
            const S* nn = nrm + 3 * id;
            S gw = gd * q.depth + gn0 * nn[0] + gn1 * nn[1] + gn2 * nn[2] + gdist * (m * m * Wall - S(2) * m * M1 + M2);
            for (int ch = 0; ch < C; ++ch) gw += gcol[ch] * cc[ch];
            const S galpha = Tr * gw - (suffix + Tf * gTf) / oma;
            suffix += w * gw;
            const S dmdz = S(FAR / (FAR - NEAR) * NEAR) / (q.depth * q.depth);
            const S gz = gd * w + gdist * S(2) * w * (m * Wall - M1) * dmdz;
            double* gi = g.data() + id * stride;
            for (int ch = 0; ch < C; ++ch) gi[NG + ch] += double(w * gcol[ch]);
            gi[11] += double(w * gn0);
            gi[12] += double(w * gn1);
            gi[13] += double(w * gn2);
            S gG = 0;
            if (!q.clamped) {
              gi[14] += double(q.g * galpha);
              gG = op[id] * galpha;
            }
            const S grho = S(-0.5) * q.g * gG;
            if (q.surface) {
              const S gu = S(2) * q.u * grho + gz * Ti[6];
              const S gv = S(2) * q.v * grho + gz * Ti[7];
              gi[6] += double(gz * q.u);
              gi[7] += double(gz * q.v);
              gi[8] += double(gz);
              // (u, v) = (p.x, p.y) / p.z
              const S gpx = gu / q.pz, gpy = gv / q.pz;
              const S gpz = -(gu * q.u + gv * q.v) / q.pz;
              // p = k x l: dL/dk = l x gp, dL/dl = gp x k
              const S gkx = q.ly * gpz - q.lz * gpy, gky = q.lz * gpx - q.lx * gpz, gkz = q.lx * gpy - q.ly * gpx;
              const S glx = gpy * q.kz - gpz * q.ky, gly = gpz * q.kx - gpx * q.kz, glz = gpx * q.ky - gpy * q.kx;
              // k = x T_w - T_u, l = y T_w - T_v
              gi[0] -= double(gkx);
              gi[1] -= double(gky);
              gi[2] -= double(gkz);
              gi[3] -= double(glx);
              gi[4] -= double(gly);
              gi[5] -= double(glz);
              gi[6] += double(x * gkx + y * glx);
              gi[7] += double(x * gky + y * gly);
              gi[8] += double(x * gkz + y * glz);
            } else {
              gi[8] += double(gz);
              gi[9] += double(grho * S(2 * FILTER_INV_SQ) * q.dx);
              gi[10] += double(grho * S(2 * FILTER_INV_SQ) * q.dy);
            }
          }
        }
      }
    }
  }
  // reduce in thread order
  at::parallel_for(0, n, 1024, [&](int64_t lo, int64_t hi) {
    for (int64_t id = lo; id < hi; ++id) {
      std::vector<double> s(stride, 0.0);
      for (int th = 0; th < nthreads; ++th) {
        const double* gi = bufs[th].data() + id * stride;
        for (int64_t e = 0; e < stride; ++e) s[e] += gi[e];
      }
      for (int e = 0; e < 9; ++e) gT_out[9 * id + e] = S(s[e]);
      gc_out[2 * id] = S(s[9]);
      gc_out[2 * id + 1] = S(s[10]);
      gn_out[3 * id] = S(s[11]);
      gn_out[3 * id + 1] = S(s[12]);
      gn_out[3 * id + 2] = S(s[13]);
      go_out[id] = S(s[14]);
      for (int ch = 0; ch < C; ++ch) gcol_out[id * C + ch] = S(s[NG + ch]);
    }
  });
}

at::Tensor vec_tensor_i64(const std::vector<int64_t>& v) {
  at::Tensor t = at::empty({static_cast<int64_t>(v.size())}, at::TensorOptions().dtype(at::kLong));
  std::copy(v.begin(), v.end(), t.data_ptr<int64_t>());
  return t;
}

at::Tensor vec_tensor_i32(const std::vector<int32_t>& v) {
  at::Tensor t = at::empty({static_cast<int64_t>(v.size())}, at::TensorOptions().dtype(at::kInt));
  std::copy(v.begin(), v.end(), t.data_ptr<int32_t>());
  return t;
}

// The per-surfel inputs shared by forward and backward: [N, 9], [N, 2], [N, 3], [N], [N, C], [N, 4] int32, [C].
void check_surfels(const at::Tensor& transforms, const at::Tensor& means2d, const at::Tensor& normals,
                   const at::Tensor& opacities, const at::Tensor& colors, const at::Tensor& rects,
                   const at::Tensor& background, at::ScalarType st, int64_t n, int64_t C) {
  check(transforms, "transforms", st, n, 9);
  check(means2d, "means2d", st, n, 2);
  check(normals, "normals", st, n, 3);
  check(opacities, "opacities", st, n, 0);
  check(colors, "colors", st, n, C);
  check(rects, "rects", at::kInt, n, 4);
  check(background, "background", st, C, 0);
}

// Forward. Returns [color [H, W, C], alpha [H, W], depth [H, W], normals [H, W, 3], distortion [H, W],
// t_final [H, W], m1 [H, W], m2 [H, W], last [H, W] int32, tile offsets [tiles + 1] int64, lists int32].
std::vector<at::Tensor> surfel_forward(at::Tensor transforms, at::Tensor means2d, at::Tensor normals,
                                       at::Tensor opacities, at::Tensor colors, at::Tensor rects,
                                       at::Tensor depths, at::Tensor visible, at::Tensor background,
                                       int64_t width, int64_t height) {
  const auto st = transforms.scalar_type();
  TORCH_CHECK(st == at::kFloat || st == at::kDouble, "surfel_cpu: float32 or float64 only");
  TORCH_CHECK(width > 0 && height > 0, "surfel_cpu: bad image size");
  const int64_t n = transforms.size(0);
  TORCH_CHECK(colors.dim() == 2, "surfel_cpu: colors must be [N, C]");
  const int64_t C = colors.size(1);
  check_surfels(transforms, means2d, normals, opacities, colors, rects, background, st, n, C);
  check(depths, "depths", st, n, 0);
  check(visible, "visible", at::kBool, n, 0);
  const int W = static_cast<int>(width), H = static_cast<int>(height);
  const int gx = (W + TILE - 1) / TILE, gy = (H + TILE - 1) / TILE;
  auto opt = transforms.options();
  at::Tensor out_c = at::empty({H, W, C}, opt), out_a = at::empty({H, W}, opt), out_d = at::empty({H, W}, opt);
  at::Tensor out_n = at::empty({H, W, 3}, opt), out_dist = at::empty({H, W}, opt);
  at::Tensor t_final = at::empty({H, W}, opt), m1 = at::empty({H, W}, opt), m2 = at::empty({H, W}, opt);
  at::Tensor last = at::empty({H, W}, opt.dtype(at::kInt));
  Bins b;
  if (st == at::kFloat) {
    b = bin_surfels(depths.data_ptr<float>(), visible.data_ptr<bool>(), rects.data_ptr<int32_t>(), n, gx, gy);
    forward_impl<float>(transforms.data_ptr<float>(), means2d.data_ptr<float>(), normals.data_ptr<float>(),
                        opacities.data_ptr<float>(), colors.data_ptr<float>(), rects.data_ptr<int32_t>(),
                        background.data_ptr<float>(), n, static_cast<int>(C), W, H, b, out_c.data_ptr<float>(),
                        out_a.data_ptr<float>(), out_d.data_ptr<float>(), out_n.data_ptr<float>(),
                        out_dist.data_ptr<float>(), t_final.data_ptr<float>(), m1.data_ptr<float>(),
                        m2.data_ptr<float>(), last.data_ptr<int32_t>());
  } else {
    b = bin_surfels(depths.data_ptr<double>(), visible.data_ptr<bool>(), rects.data_ptr<int32_t>(), n, gx, gy);
    forward_impl<double>(transforms.data_ptr<double>(), means2d.data_ptr<double>(), normals.data_ptr<double>(),
                         opacities.data_ptr<double>(), colors.data_ptr<double>(), rects.data_ptr<int32_t>(),
                         background.data_ptr<double>(), n, static_cast<int>(C), W, H, b, out_c.data_ptr<double>(),
                         out_a.data_ptr<double>(), out_d.data_ptr<double>(), out_n.data_ptr<double>(),
                         out_dist.data_ptr<double>(), t_final.data_ptr<double>(), m1.data_ptr<double>(),
                         m2.data_ptr<double>(), last.data_ptr<int32_t>());
  }
  return {out_c, out_a, out_d, out_n, out_dist, t_final, m1, m2, last, vec_tensor_i64(b.offsets),
          vec_tensor_i32(b.list)};
}

// Backward. Args: the output gradients (grad_color [H, W, C], grad_alpha, grad_depth [H, W],
// grad_normals [H, W, 3], grad_distortion [H, W]), the forward's inputs and saved state.
// Returns [g_transforms [N, 9], g_means2d [N, 2], g_normals [N, 3], g_opacities [N], g_colors [N, C]].
std::vector<at::Tensor> surfel_backward(at::Tensor grad_color, at::Tensor grad_alpha, at::Tensor grad_depth,
                                        at::Tensor grad_normals, at::Tensor grad_dist, at::Tensor transforms,
                                        at::Tensor means2d, at::Tensor normals, at::Tensor opacities,
                                        at::Tensor colors, at::Tensor rects, at::Tensor background,
                                        at::Tensor t_final, at::Tensor m1, at::Tensor m2, at::Tensor last,
                                        at::Tensor offsets, at::Tensor lists, int64_t width, int64_t height) {
  const auto st = transforms.scalar_type();
  TORCH_CHECK(st == at::kFloat || st == at::kDouble, "surfel_cpu: float32 or float64 only");
  const int64_t n = transforms.size(0);
  const int64_t C = colors.size(1);
  const int W = static_cast<int>(width), H = static_cast<int>(height);
  const int64_t P = static_cast<int64_t>(W) * H;
  check(grad_color, "grad_color", st, P, C);
  check(grad_alpha, "grad_alpha", st, P, 0);
  check(grad_depth, "grad_depth", st, P, 0);
  check(grad_normals, "grad_normals", st, P, 3);
  check(grad_dist, "grad_dist", st, P, 0);
  check_surfels(transforms, means2d, normals, opacities, colors, rects, background, st, n, C);
  check(t_final, "t_final", st, P, 0);
  check(m1, "m1", st, P, 0);
  check(m2, "m2", st, P, 0);
  check(last, "last", at::kInt, P, 0);
  const int gx = (W + TILE - 1) / TILE, gy = (H + TILE - 1) / TILE;
  check(offsets, "offsets", at::kLong, static_cast<int64_t>(gx) * gy + 1, 0);
  TORCH_CHECK(lists.scalar_type() == at::kInt && lists.is_contiguous(), "surfel_cpu: lists must be int32");
  auto opt = transforms.options();
  at::Tensor gT = at::empty({n, 9}, opt), gc = at::empty({n, 2}, opt), gn = at::empty({n, 3}, opt);
  at::Tensor go = at::empty({n}, opt), gcol = at::empty({n, C}, opt);
#define SURFEL_BWD(S)                                                                                         \
  backward_impl<S>(grad_color.data_ptr<S>(), grad_alpha.data_ptr<S>(), grad_depth.data_ptr<S>(),               \
                   grad_normals.data_ptr<S>(), grad_dist.data_ptr<S>(), transforms.data_ptr<S>(),              \
                   means2d.data_ptr<S>(), normals.data_ptr<S>(), opacities.data_ptr<S>(), colors.data_ptr<S>(), \
                   rects.data_ptr<int32_t>(), background.data_ptr<S>(), t_final.data_ptr<S>(), m1.data_ptr<S>(), \
                   m2.data_ptr<S>(), last.data_ptr<int32_t>(), offsets.data_ptr<int64_t>(),                     \
                   lists.data_ptr<int32_t>(), n, static_cast<int>(C), W, H, gT.data_ptr<S>(), gc.data_ptr<S>(),  \
                   gn.data_ptr<S>(), go.data_ptr<S>(), gcol.data_ptr<S>())
  if (st == at::kFloat) {
    SURFEL_BWD(float);
  } else {
    SURFEL_BWD(double);
  }
#undef SURFEL_BWD
  return {gT, gc, gn, go, gcol};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(splatfields_cpu, m) {
  m.def("surfel_forward", &surfel_forward);
  m.def("surfel_backward", &surfel_backward);
}
