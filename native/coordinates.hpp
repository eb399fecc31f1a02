// Coordinates of lines in R^3 in a basis of five flats (paper Sec. 4, Fig. 8,
// Eq. 9 and 12) plus the round trip (Sec. 2.3): the hot path of
// flatserve.coordinates.coordinates_rays for k = 1, d = 3, m = 5.
//
// Pure C++/Eigen, no Python.  The NumPy implementation in
// flatserve/coordinates.py is the reference; tests compare the two.
//
// Per ray (one pass, no heap allocation):
//   a = v / |v|, r+ = o - (a.o) a, normals n1, n2 by the branchless
//   orthonormal basis of Duff et al. (2017) (any orthonormal completion gives
//   the same solution: rotating n1, n2 mixes rows within each block);
//   rows n_j^T Q_l a (Eq. 9), n_j^T (Q_l r+ - r_l) (Eq. 12), ones;
//   the system is solved as in solve_system(): w = 1/5 + H z with H the
//   Helmert basis of {sum = 0} and B z = c, B = M_o H (4x4), c = -M_o 1/5;
//   singular when sigma_min(B) <= rcond sigma_max(B) (2-norm; closed-form
//   inverse in the common case, JacobiSVD near the threshold), then the truncated
//   pseudo-inverse solution;
//   round trip: Q* = sum w_l Q_l, r* = sum w_l r_l, eigen-decomposition
//   (ascending), Q~ = N N^T, r~ = N diag(1/lambda_N) N^T r* (pseudo-inverse),
//   residual = max(|Q~ - Q+|_F, |r~ - r+|), gap = lambda_2 - lambda_1.
#pragma once

#include <Eigen/Dense>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <exception>
#include <limits>
#include <thread>
#include <vector>

namespace flatserve {

struct CoordinateTolerances {
  double roundtrip_tol;  // ROUNDTRIP_TOL
  double rcond;          // SINGULAR_RCOND
  double gap_tol;        // GAP_TOL
  double pinv_rcond;     // PINV_RCOND
};

// Exported to Python as flatserve._core.CoordinateStatus (bindings.cpp); the
// reasons shown to users are in flatserve/coordinates.py (REASONS).
// COORD_NO_SAMPLES is never written by the kernels here: a field answers it
// for a query flat whose coordinates round-trip in a chart (or in every chart
// of an atlas that holds it) whose samples do not yet span a simplex.
enum CoordinateStatus : std::int8_t { COORD_OK = 0, COORD_NOT_REPRESENTABLE = 1,
                                      COORD_SINGULAR = 2, COORD_AMBIGUOUS = 3,
                                      COORD_NO_SAMPLES = 4 };

// Rows per thread below which extra threads do not pay for their start-up
// (threads <= 0 picks min(cores, n / kCoordRowsPerThread), at least 1).
constexpr std::size_t kCoordRowsPerThread = 16384;
constexpr std::size_t kCoordMaxThreads = 256;  // explicit requests are capped here

// Qb: 5 row-major 3x3 matrices; rb: 5x3; origins, directions: n x 3 (row-major,
// validated: finite, non-zero directions).  Outputs: w n x 5, status n,
// residual n.  One thread; see coordinates_rays3_mt.
inline void coordinates_rays3(const double* Qb, const double* rb, const double* origins,
                              const double* directions, std::size_t n,
                              const CoordinateTolerances& tol, double* w_out,
                              std::int8_t* status_out, double* residual_out) {
  using Eigen::Matrix3d;
  using Eigen::Vector3d;
  using Mat45 = Eigen::Matrix<double, 4, 5>;
  using Mat54 = Eigen::Matrix<double, 5, 4>;
  using Eigen::Matrix4d;
  using Eigen::Vector4d;
  using Vec5 = Eigen::Matrix<double, 5, 1>;
  constexpr int m = 5;

  Matrix3d Q[m];
  Vector3d r[m];
  for (int l = 0; l < m; ++l) {
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) Q[l](i, j) = Qb[l * 9 + i * 3 + j];
      r[l](i) = rb[l * 3 + i];
    }
  }
  // Helmert basis (same as flatserve.embedding.regular_simplex(5)).
  Mat54 H = Mat54::Zero();
  for (int j = 1; j < m; ++j) {
    const double s = 1.0 / std::sqrt(double(j) * (j + 1.0));
    for (int i = 0; i < j; ++i) H(i, j - 1) = s;
    H(j, j - 1) = -double(j) * s;
  }
  const double inf = std::numeric_limits<double>::infinity();

  for (std::size_t t = 0; t < n; ++t) {
    const Vector3d o(origins[3 * t], origins[3 * t + 1], origins[3 * t + 2]);
    Vector3d a(directions[3 * t], directions[3 * t + 1], directions[3 * t + 2]);
    a /= a.norm();
    const Vector3d rt = o - a.dot(o) * a;
    // Duff et al., "Building an orthonormal basis, revisited" (JCGT 2017).
    const double sg = std::copysign(1.0, a.z());
    const double aa = -1.0 / (sg + a.z());
    const double bb = a.x() * a.y() * aa;
    const Vector3d n1(1.0 + sg * a.x() * a.x() * aa, sg * bb, -sg * a.x());
    const Vector3d n2(bb, sg + a.y() * a.y() * aa, -a.y());

    Mat45 Mo;
    for (int l = 0; l < m; ++l) {
      const Vector3d Qa = Q[l] * a;
      const Vector3d off = Q[l] * rt - r[l];
      Mo(0, l) = n1.dot(Qa);
      Mo(1, l) = n2.dot(Qa);
      Mo(2, l) = n1.dot(off);
      Mo(3, l) = n2.dot(off);
    }
    const Matrix4d B = Mo * H;
    const Vector4d c = -Mo.rowwise().sum() / double(m);
    // Fast path: Eigen's closed-form 4x4 inverse plus one step of iterative
    // refinement.  kF = 1 / (|B|_F |B^-1|_F) satisfies
    // kF <= sigma_min / sigma_max <= 4 kF (4x4), so only when kF <= 4 rcond
    // (or B^-1 is not finite) is the exact 2-norm test needed (JacobiSVD, which
    // also gives the truncated pseudo-inverse solution of the reference).
    const Matrix4d Bi = B.inverse();
    const double kF = 1.0 / (B.norm() * Bi.norm());
    bool singular = false;
    Vector4d z;
    if (kF > 4.0 * tol.rcond && std::isfinite(kF)) {
      z = Bi * c;
      z += Bi * (c - B * z);
    } else {
      Eigen::JacobiSVD<Matrix4d> svd(B, Eigen::ComputeFullU | Eigen::ComputeFullV);
      const Vector4d s = svd.singularValues();
      singular = !(s(3) > tol.rcond * s(0));
      Vector4d y = svd.matrixU().transpose() * c;
      for (int i = 0; i < 4; ++i) y(i) = (s(i) > tol.rcond * s(0)) ? y(i) / s(i) : 0.0;
      z = svd.matrixV() * y;
    }
    const Vec5 w = Vec5::Constant(1.0 / m) + H * z;

    // Round trip (Sec. 2.3).
    Matrix3d Qs = Matrix3d::Zero();
    Vector3d rs = Vector3d::Zero();
    for (int l = 0; l < m; ++l) {
      Qs.noalias() += w(l) * Q[l];
      rs.noalias() += w(l) * r[l];
    }
    // Closed-form 3x3 eigen-decomposition: the smallest eigenvalue is isolated
    // (gap checked below), so its eigenvector, and with it span(N), is accurate.
    Eigen::SelfAdjointEigenSolver<Matrix3d> es;
    es.computeDirect(Qs);
    const Vector3d lam = es.eigenvalues();
    const Matrix3d& V = es.eigenvectors();
    const double gap = lam(1) - lam(0);
    const double scale = lam.cwiseAbs().maxCoeff();
    Vector3d rr = Vector3d::Zero();
    Matrix3d Qt = Matrix3d::Zero();
    for (int j = 1; j < 3; ++j) {
      const Vector3d v = V.col(j);
      Qt.noalias() += v * v.transpose();
      if (std::abs(lam(j)) > tol.pinv_rcond * scale) rr += v * (v.dot(rs) / lam(j));
    }
    const Matrix3d Qp = Matrix3d::Identity() - a * a.transpose();
    double res = std::max((Qt - Qp).norm(), (rr - rt).norm());
    if (!std::isfinite(res)) res = inf;

    std::int8_t st = res <= tol.roundtrip_tol ? COORD_OK : COORD_NOT_REPRESENTABLE;
    if (!(gap >= tol.gap_tol)) st = COORD_AMBIGUOUS;
    if (singular) st = COORD_SINGULAR;
    for (int l = 0; l < m; ++l) w_out[t * m + l] = w(l);
    status_out[t] = st;
    residual_out[t] = res;
  }
}

// coordinates_rays3 on `threads` std::threads (<= 0: all cores for big
// batches, one for small ones) taking contiguous blocks of kCoordBlock rows
// from a shared counter (load balance when a core is busy elsewhere).  Rows
// are independent and every row runs the same instructions, so the result is
// bit-identical for any thread count.  Call without the GIL.
constexpr std::size_t kCoordBlock = 4096;

inline void coordinates_rays3_mt(const double* Qb, const double* rb, const double* origins,
                                 const double* directions, std::size_t n,
                                 const CoordinateTolerances& tol, double* w_out,
                                 std::int8_t* status_out, double* residual_out, int threads) {
  std::size_t T;
  if (threads > 0) {
    T = static_cast<std::size_t>(threads);
  } else {
    const unsigned hw = std::thread::hardware_concurrency();
    T = std::min<std::size_t>(hw ? hw : 1, n / kCoordRowsPerThread);
  }
  const std::size_t nblocks = (n + kCoordBlock - 1) / kCoordBlock;
  T = std::max<std::size_t>(1, std::min({T, nblocks, kCoordMaxThreads}));
  if (T == 1) {
    coordinates_rays3(Qb, rb, origins, directions, n, tol, w_out, status_out, residual_out);
    return;
  }
  std::atomic<std::size_t> next{0};
  std::vector<std::exception_ptr> errors(T);
  auto work = [&](std::size_t t) {
    try {
      for (std::size_t c = next++; c < nblocks; c = next++) {
        const std::size_t b = c * kCoordBlock, e = std::min(n, b + kCoordBlock);
        coordinates_rays3(Qb, rb, origins + 3 * b, directions + 3 * b, e - b, tol, w_out + 5 * b,
                          status_out + b, residual_out + b);
      }
    } catch (...) {
      errors[t] = std::current_exception();
    }
  };
  std::vector<std::thread> pool;
  pool.reserve(T - 1);
  for (std::size_t t = 1; t < T; ++t) {
    try {
      pool.emplace_back(work, t);
    } catch (...) {  // no more threads to be had: the others share the blocks
      break;
    }
  }
  work(0);
  for (auto& th : pool) th.join();
  for (auto& err : errors)
    if (err) std::rethrow_exception(err);
}

}  // namespace flatserve
