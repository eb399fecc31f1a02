// Semi-static floating-point filters in front of CGAL's dD predicates.
//
// CGAL 5.5's Epick_d evaluates Orientation_d and Side_of_oriented_sphere_d
// with interval arithmetic first (exact Mpzf arithmetic when the intervals
// cannot decide). Profiling the 4D build (benchmarks/cgal_build_peer.cpp
// under perf) put ~40% of the time in those interval determinants and their
// wrapper. Here each predicate first evaluates its determinant in plain
// doubles and compares it with a proven bound on the rounding error; only
// when |det| is within that bound does it call CGAL's own predicate, so
// every answer is exact and equal to CGAL's.
//
// Error bound (Higham, "Accuracy and Stability of Numerical Algorithms",
// Sec. 3.1): the determinant is the Leibniz sum evaluated by a Laplace
// expansion over column subsets. A rounded evaluation of a sum of products
// with at most `depth` roundings along any path from an input to the result
// is off by at most gamma_depth times the same sum evaluated on absolute
// values, which is at most N! * prod_j max_i |a_ij| (one entry per column in
// every term). The entries (differences of input coordinates, and their
// squared norms for the lifted column) carry relative errors of their own,
// counted in `input_depth`. Every constant gets a factor 2 of margin. Column
// maxima outside [kMinScale, kMaxScale] (tiny or huge coordinates, where
// underflow would void the relative error model) go straight to CGAL.
#pragma once

#include <CGAL/Epick_d.h>

#include <algorithm>
#include <cmath>
#include <utility>

namespace flatserve {
namespace pred {

constexpr double kMinScale = 1e-30;
constexpr double kMaxScale = 1e30;
constexpr double kUnitRoundoff = 1.1102230246251565e-16;  // 2^-53

constexpr double factorial(int n) { return n <= 1 ? 1.0 : n * factorial(n - 1); }

// Relative bound (times prod of column maxima) for an N x N determinant
// whose entries carry `input_depth` roundings per term.
constexpr double det_error_factor(int N, int input_depth) {
  // N(N+1)/2 roundings in the expansion below, input_depth in the entries,
  // a few for the product of the maxima and the comparison; factor 2 margin.
  return 2.0 * (N * (N + 1) / 2 + input_depth + 4) * kUnitRoundoff * factorial(N);
}

// Determinant of the row-major N x N matrix `a` (N <= 7): Laplace expansion
// along successive rows over column subsets, minors shared (N 2^(N-1)
// multiplications), unrolled at compile time. m[S] is the minor of rows
// 0..|S|-1 and the columns in S; subsets come before their supersets.
template <int N, unsigned Mask, int J = 0, int Pos = 0>
inline double laplace_terms(const double (&a)[N][N], const double* m) {
  if constexpr (J == N) {
    return 0.0;
  } else if constexpr (!(Mask & (1u << J))) {
    return laplace_terms<N, Mask, J + 1, Pos>(a, m);
  } else {
    constexpr int row = __builtin_popcount(Mask) - 1;
    const double t = a[row][J] * m[Mask & ~(1u << J)];
    const double rest = laplace_terms<N, Mask, J + 1, Pos + 1>(a, m);
    return ((row + Pos) & 1) ? rest - t : rest + t;
  }
}

template <int N, unsigned... S>
inline void laplace_fill(const double (&a)[N][N], double* m, std::integer_sequence<unsigned, S...>) {
  ((m[S + 1] = laplace_terms<N, S + 1>(a, m)), ...);  // left to right
}

template <int N>
inline double determinant(const double (&a)[N][N]) {
  static_assert(N >= 1 && N <= 7, "semi-static filter for N <= 7 only");
  double m[1u << N];
  m[0] = 1.0;
  laplace_fill<N>(a, m, std::make_integer_sequence<unsigned, (1u << N) - 1>());
  return m[(1u << N) - 1];
}

// Product of the column maxima, or 0 when a column is out of the safe range.
template <int N>
inline double column_scale(const double (&a)[N][N], int columns_checked) {
  double prod = 1.0;
  for (int j = 0; j < N; ++j) {
    double mx = 0.0;
    for (int i = 0; i < N; ++i) mx = std::max(mx, std::abs(a[i][j]));
    if (j < columns_checked && !(mx >= kMinScale && mx <= kMaxScale)) return 0.0;
    prod *= mx;
  }
  return prod;
}

// -1, +1, or 0 when the filter cannot decide.
template <int N>
inline int filtered_sign(const double (&a)[N][N], int columns_checked, double factor) {
  const double scale = column_scale<N>(a, columns_checked);
  if (!(scale > 0.0)) return 0;
  const double det = determinant<N>(a);
  const double bound = factor * scale;
  return det > bound ? 1 : det < -bound ? -1 : 0;
}

// Epick_d<Dimension_tag<D>> with filtered Orientation_d and
// Side_of_oriented_sphere_d; everything else is Epick_d's.
template <int D>
struct FilteredEpick : CGAL::Epick_d<CGAL::Dimension_tag<D>> {
  using Base = CGAL::Epick_d<CGAL::Dimension_tag<D>>;
  using Point_d = typename Base::Point_d;
  using Base::Base;

  // Sign of det[p_i - p_0]_{i=1..D}, as CGAL's Orientation_of_points.
  struct Orientation_d {
    using Exact = typename Base::Orientation_d;
    using result_type = CGAL::Orientation;
    static constexpr double kFactor = det_error_factor(D, D);
    Exact exact;
    explicit Orientation_d(const FilteredEpick& k) : exact(k.Base::orientation_d_object()) {}

    template <class Iter>
    result_type operator()(Iter f, Iter e) const {
      double x[D + 1][D];
      int n = 0;
      for (Iter it = f; it != e; ++it) {
        if (n > D) return exact(f, e);
        const Point_d& p = *it;
        for (int j = 0; j < D; ++j) x[n][j] = p[j];
        ++n;
      }
      if (n != D + 1) return exact(f, e);
      double a[D][D];
      for (int i = 0; i < D; ++i)
        for (int j = 0; j < D; ++j) a[i][j] = x[i + 1][j] - x[0][j];
      const int s = filtered_sign<D>(a, D, kFactor);
      if (s > 0) return CGAL::POSITIVE;
      if (s < 0) return CGAL::NEGATIVE;
      return exact(f, e);
    }
  };

  // CGAL's Side_of_oriented_sphere(f, e, p0): rows (p_i - p0, |p_i - p0|^2)
  // for the D+1 points; sign of the determinant, negated for odd D.
  struct Side_of_oriented_sphere_d {
    using Exact = typename Base::Side_of_oriented_sphere_d;
    using result_type = CGAL::Oriented_side;
    // entries: differences (1 rounding each), squared norms (D + 2)
    static constexpr double kFactor = det_error_factor(D + 1, 2 * D + 2);
    Exact exact;
    explicit Side_of_oriented_sphere_d(const FilteredEpick& k)
        : exact(k.Base::side_of_oriented_sphere_d_object()) {}

    template <class Iter>
    result_type operator()(Iter f, Iter e, const Point_d& q) const {
      double a[D + 1][D + 1];
      int n = 0;
      for (Iter it = f; it != e; ++it) {
        if (n > D) return exact(f, e, q);
        const Point_d& pi = *it;
        double sq = 0.0;
        for (int j = 0; j < D; ++j) {
          const double x = pi[j] - q[j];
          a[n][j] = x;
          sq += x * x;
        }
        a[n][D] = sq;
        ++n;
      }
      if (n != D + 1) return exact(f, e, q);
      int s = filtered_sign<D + 1>(a, D, kFactor);
      if (s == 0) return exact(f, e, q);
      if (D % 2) s = -s;
      return s > 0 ? CGAL::ON_POSITIVE_SIDE : CGAL::ON_NEGATIVE_SIDE;
    }
  };

  Orientation_d orientation_d_object() const { return Orientation_d(*this); }
  Side_of_oriented_sphere_d side_of_oriented_sphere_d_object() const {
    return Side_of_oriented_sphere_d(*this);
  }
};

}  // namespace pred

// The kernel of a triangulation: filtered predicates in static dimensions.
template <class DimTag>
struct KernelFor {
  using type = CGAL::Epick_d<DimTag>;
};
template <int D>
struct KernelFor<CGAL::Dimension_tag<D>> {
  using type = pred::FilteredEpick<D>;
};

}  // namespace flatserve
