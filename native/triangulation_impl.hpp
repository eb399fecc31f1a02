// The CGAL side of triangulation.hpp: the class template, included only by
// triangulation.cpp (one translation unit per dimension, so that editing the
// bindings never recompiles CGAL and the dimensions compile in parallel).
#pragma once

#include <CGAL/Delaunay_triangulation.h>
#include <CGAL/Epick_d.h>
#include <CGAL/Spatial_sort_traits_adapter_d.h>
#include <CGAL/Triangulation_full_cell.h>
#include <CGAL/Triangulation_vertex.h>
#include <CGAL/property_map.h>
#include <CGAL/spatial_sort.h>

#include <Eigen/Dense>
#include <boost/iterator/indirect_iterator.hpp>

#include <optional>

#include "fast_predicates.hpp"
#include "triangulation.hpp"

namespace flatserve {

// Walk tolerances (see Triangulation::locate_one).
constexpr double kLambdaEps = 1e-10;   // |barycentric| below this (relative) -> exact predicate
constexpr double kPivotRatio = 1e-8;   // LU pivot ratio below this -> exact predicates only
constexpr std::size_t kMaxFloatSteps = 4096;

// Hilbert index of a point quantised to `bits` bits per axis (Skilling,
// "Programming the Hilbert curve", AIP Conf. Proc. 707, 2004), as a key of
// D*bits <= 64 bits. N > 0 fixes the number of axes at compile time (the
// loops unroll and X stays in registers); N = 0 takes it from `n_axes`.
template <int N = 0>
inline std::uint64_t hilbert_key(std::uint32_t* X, int bits, int n_axes) {
  const int n = N > 0 ? N : n_axes;
  const std::uint32_t M = 1u << (bits - 1);
  for (std::uint32_t Q = M; Q > 1; Q >>= 1) {
    const std::uint32_t P = Q - 1;
    for (int i = 0; i < n; ++i) {  // branch-free: invert if bit Q set, else exchange
      const std::uint32_t set = 0u - ((X[i] & Q) != 0);
      const std::uint32_t t = (X[0] ^ X[i]) & P & ~set;
      X[0] ^= (P & set) | t;
      X[i] ^= t;
    }
  }
  for (int i = 1; i < n; ++i) X[i] ^= X[i - 1];
  std::uint32_t t = 0;
  for (std::uint32_t Q = M; Q > 1; Q >>= 1)
    if (X[n - 1] & Q) t ^= Q - 1;
  for (int i = 0; i < n; ++i) X[i] ^= t;
  std::uint64_t key = 0;
  for (int b = bits - 1; b >= 0; --b)
    for (int i = 0; i < n; ++i) key = (key << 1) | ((X[i] >> b) & 1u);
  return key;
}

// Query order along a Hilbert curve. Each axis is quantised through its
// empirical quantiles (a deterministic sample of up to kQuantiles values), so
// heavy-tailed data (embedded ray coordinates span 1e-2 .. 1e5) still spreads
// over the grid. Keys are computed and sorted in parallel; ties broken by
// index, so the order is unique (independent of the thread count).
constexpr std::size_t kQuantiles = 1024;

inline std::vector<std::uint32_t> hilbert_order(const double* q, std::size_t n, int D,
                                                int threads) {
  const int axes = std::min(D, 64);  // beyond 64 axes only the first 64 count
  // a few bits per axis beyond what separates n points (the quantiles make
  // the marginals uniform, so no bits are wasted on empty ranges)
  int need = 0;
  while (need < 63 && (std::size_t(1) << need) < n) ++need;
  const int bits = std::max(1, std::min({16, 64 / axes, (need + axes - 1) / axes + 3}));
  const double cells = std::ldexp(1.0, bits);
  const std::size_t ns = std::min(n, kQuantiles);
  std::size_t np2 = 1;
  while (np2 < ns) np2 *= 2;
  std::vector<std::vector<double>> table(axes);
  for (int k = 0; k < axes; ++k) {
    auto& t = table[k];
    t.resize(ns);
    for (std::size_t j = 0; j < ns; ++j) t[j] = q[(j * n / ns) * D + k];
    std::sort(t.begin(), t.end());
    t.resize(np2, std::numeric_limits<double>::infinity());  // pad for the branch-free search
  }
  // x -> position in [0, cells): bin of the sorted sample, interpolated inside
  auto quantise = [&](int k, double x) -> std::uint32_t {
    const double* t = table[k].data();
    std::size_t j = 0;  // number of sample values <= x (upper bound), branch-free
    for (std::size_t step = np2 / 2; step; step /= 2) j += (t[j + step - 1] <= x) ? step : 0;
    j += (j < ns && t[j] <= x) ? 1 : 0;
    double pos;
    if (j == 0) {
      pos = 0.0;
    } else if (j >= ns) {
      pos = static_cast<double>(ns);
    } else {
      double lo = t[j - 1], hi = t[j];
      pos = static_cast<double>(j) + (hi > lo ? (x - lo) / (hi - lo) : 0.0);
    }
    double c = pos * (cells / static_cast<double>(ns + 1));
    return static_cast<std::uint32_t>(std::min(c, cells - 1));
  };
  std::vector<std::pair<std::uint64_t, std::uint32_t>> keyed(n);
  auto keys = [&](auto axes_tag, std::size_t b, std::size_t e) {
    constexpr int N = decltype(axes_tag)::value;
    std::uint32_t X[N > 0 ? N : 64];
    for (std::size_t i = b; i < e; ++i) {
      for (int k = 0; k < axes; ++k) X[k] = quantise(k, q[i * D + k]);
      keyed[i] = {hilbert_key<N>(X, bits, axes), static_cast<std::uint32_t>(i)};
    }
  };
  run_chunks(n, threads, [&](std::size_t b, std::size_t e) {
    switch (axes) {
      case 2: keys(std::integral_constant<int, 2>(), b, e); break;
      case 3: keys(std::integral_constant<int, 3>(), b, e); break;
      case 4: keys(std::integral_constant<int, 4>(), b, e); break;
      case 5: keys(std::integral_constant<int, 5>(), b, e); break;
      case 6: keys(std::integral_constant<int, 6>(), b, e); break;
      default: keys(std::integral_constant<int, 0>(), b, e); break;
    }
  });
  // parallel sort: sort T slices, then merge them pairwise
  std::size_t T = threads <= 0 ? static_cast<std::size_t>(default_threads())
                               : static_cast<std::size_t>(threads);
  T = std::max<std::size_t>(1, std::min<std::size_t>(T, n / 4096 + 1));
  std::vector<std::size_t> cut(T + 1);
  for (std::size_t t = 0; t <= T; ++t) cut[t] = n * t / T;
  {
    std::vector<std::thread> pool;
    for (std::size_t t = 1; t < T; ++t)
      pool.emplace_back([&, t]() { std::sort(keyed.begin() + cut[t], keyed.begin() + cut[t + 1]); });
    std::sort(keyed.begin() + cut[0], keyed.begin() + cut[1]);
    for (auto& th : pool) th.join();
  }
  for (std::size_t width = 1; width < T; width *= 2)
    for (std::size_t t = 0; t + width < T; t += 2 * width)
      std::inplace_merge(keyed.begin() + cut[t], keyed.begin() + cut[t + width],
                         keyed.begin() + cut[std::min(T, t + 2 * width)]);
  std::vector<std::uint32_t> order(n);
  for (std::size_t i = 0; i < n; ++i) order[i] = keyed[i].second;
  return order;
}

struct VertexInfo {
  std::int64_t id = -1;
};

// The generation of the cells made on this thread now (an insert's, see
// GenerationScope; 0 otherwise). A cell stamps itself with it when it is
// constructed (or copied), so that the cells an insertion created are told
// apart in one pass over the cell container (Tile & Merge's exchange).
inline thread_local std::uint32_t tls_cell_generation = 0;

struct CellData {
  std::uint32_t index = 0;  // the cell's number (ensure_numbered)
  std::uint32_t gen = tls_cell_generation;
  CellData() = default;
  CellData(const CellData& o) : index(o.index), gen(tls_cell_generation) {}
  CellData& operator=(const CellData&) = default;
};

// Sets this thread's cell generation for its lifetime.
class GenerationScope {
 public:
  explicit GenerationScope(std::uint32_t g) : prev_(tls_cell_generation) {
    tls_cell_generation = g;
  }
  ~GenerationScope() { tls_cell_generation = prev_; }
  GenerationScope(const GenerationScope&) = delete;
  GenerationScope& operator=(const GenerationScope&) = delete;

 private:
  std::uint32_t prev_;
};

template <class DimTag>
struct EigenDim {
  static constexpr int value = Eigen::Dynamic;
};
template <int D>
struct EigenDim<CGAL::Dimension_tag<D>> {
  static constexpr int value = D;
};

template <class DimTag>
class Triangulation final : public TriangulationBase {
 public:
  using K = typename KernelFor<DimTag>::type;  // filtered predicates (fast_predicates.hpp)
  using Vb = CGAL::Triangulation_vertex<K, VertexInfo>;
  using Cb = CGAL::Triangulation_full_cell<K, CellData>;
  using TDS = CGAL::Triangulation_data_structure<DimTag, Vb, Cb>;
  using DT = CGAL::Delaunay_triangulation<K, TDS>;
  using Point = typename K::Point_d;
  using Vertex_handle = typename DT::Vertex_handle;
  using Full_cell_handle = typename DT::Full_cell_handle;
  static constexpr int E = EigenDim<DimTag>::value;
  static constexpr int EM1 = (E == Eigen::Dynamic) ? Eigen::Dynamic : E - 1;
  using Mat = Eigen::Matrix<double, E, E>;
  using Vec = Eigen::Matrix<double, E, 1>;
  using MatF = Eigen::Matrix<double, E, EM1>;       // facet edge vectors
  using MatFF = Eigen::Matrix<double, EM1, EM1>;
  using VecF = Eigen::Matrix<double, EM1, 1>;

  explicit Triangulation(int D) : D_(D), dt_(D) {}

  int dimension() const override { return D_; }
  int current_dimension() const override { return dt_.current_dimension(); }
  std::size_t number_of_vertices() const override { return by_id_.size(); }
  std::size_t number_of_full_cells() const override { return dt_.number_of_full_cells(); }
  std::size_t number_of_finite_cells() const override {
    if (dt_.current_dimension() < D_) return 0;
    ensure_numbered();
    return n_finite_;
  }

  // ------------------------------------------------------------ insertion
  std::uint32_t generation() const override { return gen_; }

  std::size_t insert(const double* pts, std::size_t n, std::int64_t* out_ids,
                     const std::uint8_t* own, std::size_t nown) override {
    GenerationScope stamp(++gen_);  // the cells this insert makes
    const int dim_before = dt_.current_dimension();
    std::vector<Point> P;
    P.reserve(n);
    for (std::size_t i = 0; i < n; ++i) P.emplace_back(pts + i * D_, pts + (i + 1) * D_);
    std::vector<std::size_t> order(n);
    std::iota(order.begin(), order.end(), std::size_t(0));
    using Pmap = typename CGAL::Pointer_property_map<Point>::type;
    using SortTraits = CGAL::Spatial_sort_traits_adapter_d<K, Pmap>;
    if (n > 1)
      CGAL::spatial_sort(order.begin(), order.end(),
                         SortTraits(CGAL::make_property_map(P), dt_.geom_traits()));
    // Insert in spatial order; number the new vertices afterwards in input
    // row order (ids then follow the caller's rows, not CGAL's sort).
    constexpr std::int64_t kNew = -2;
    std::vector<Vertex_handle> row_vertex(n);
    Full_cell_handle hint;
    // own: a point joins only if its conflict zone has a cell with an own
    // vertex (it then becomes a neighbour of one); otherwise it is left out
    // (id -1). A point that is no neighbour of an own vertex in the
    // triangulation of some of the points is none in that of all of them.
    const bool filter = own != nullptr && dt_.current_dimension() == D_ && D_ >= 2;
    const Vertex_handle inf = dt_.infinite_vertex();
    std::vector<Full_cell_handle> zone;
    auto owned = [&](Vertex_handle v) {
      if (v == inf) return false;
      const std::int64_t id = v->data().id;
      return id >= 0 && static_cast<std::size_t>(id) < nown && own[id] != 0;
    };
    for (std::size_t idx : order) {
      Vertex_handle v;
      if (!filter) {
        v = dt_.insert(P[idx], hint);
      } else {
        typename DT::Locate_type lt;
        typename DT::Face f(dt_.maximal_dimension());
        typename DT::Facet ft;
        Full_cell_handle s = dt_.locate(P[idx], lt, f, ft, hint);
        if (lt == DT::ON_VERTEX) {
          v = dt_.insert(P[idx], lt, f, ft, s);
        } else {
          zone.clear();
          ft = dt_.compute_conflict_zone(P[idx], s, std::back_inserter(zone));
          bool near = false;
          for (std::size_t c = 0; c < zone.size() && !near; ++c)
            for (int k = 0; k <= D_ && !near; ++k) near = owned(zone[c]->vertex(k));
          if (!near) {
            row_vertex[idx] = Vertex_handle();
            hint = s;
            continue;
          }
          v = dt_.insert_in_hole(P[idx], zone.begin(), zone.end(), ft);
        }
      }
      if (v->data().id == -1) v->data().id = kNew;
      row_vertex[idx] = v;
      hint = v->full_cell();
    }
    numbered_.store(false);
    // Raising the dimension changes the cells that were there in place (CGAL
    // associates the new vertex with them): they keep their old generation.
    if (dt_.current_dimension() > dim_before) dim_gen_ = gen_;
    std::size_t added = 0, held = 0;
    for (std::size_t idx = 0; idx < n; ++idx) {
      Vertex_handle v = row_vertex[idx];
      if (v == Vertex_handle()) {
        out_ids[idx] = -1;
        continue;
      }
      ++held;
      if (v->data().id == kNew) {
        v->data().id = static_cast<std::int64_t>(by_id_.size());
        by_id_.push_back(v);
        ++added;
      }
      out_ids[idx] = v->data().id;
    }
    // Every row left out: nothing changed, no cell carries this generation, so
    // the triangulation keeps its generation (a snapshot part stays current).
    if (held == 0 && n > 0) --gen_;
    return added;
  }

  // ------------------------------------------------------------ locate
  void locate(const double* q, std::size_t n, bool hilbert, int threads, std::int64_t* ids,
              double* w, std::int8_t* kind, std::int64_t* simplex) const override {
    const int D1 = D_ + 1;
    if (simplex && dt_.current_dimension() == D_) ensure_numbered();
    for_each_query(q, n, hilbert, threads,
                   [&](std::size_t qi, Scratch& s) {
                     std::copy(s.ids.begin(), s.ids.end(), ids + qi * D1);
                     std::copy(s.w.begin(), s.w.end(), w + qi * D1);
                     kind[qi] = s.kind;
                     if (simplex)
                       simplex[qi] = s.kind <= ON_VERTEX ? static_cast<std::int64_t>(s.cell->data().index) : -1;
                   });
  }

  void within(const double* q, std::size_t n, double radius, int threads,
              std::uint8_t* out) const override {
    const int D = D_;
    const double r2 = radius * radius;
    run_chunks(n, threads, [&](std::size_t b, std::size_t e) {
      for (std::size_t i = b; i < e; ++i) {
        const double* qc = q + i * D;
        std::uint8_t hit = 0;
        for (const Vertex_handle& v : by_id_) {
          if (sq_dist(v->point(), qc, D) <= r2) {
            hit = 1;
            break;
          }
        }
        out[i] = hit;
      }
    });
  }

  void interpolate(const double* q, std::size_t n, const double* values, std::size_t nvalues,
                   std::size_t C, bool clamp, bool hilbert, int threads, double* out,
                   std::uint8_t* inside, const std::uint8_t* own,
                   std::int64_t* forward) const override {
    if (nvalues < by_id_.size())
      throw std::invalid_argument("values has fewer rows than the triangulation has vertices");
    const double nan = std::numeric_limits<double>::quiet_NaN();
    const int D1 = D_ + 1;
    for_each_query(q, n, hilbert, threads, [&](std::size_t qi, Scratch& s) {
      double* o = out + qi * C;
      if (forward) forward[qi] = -1;
      if (own && s.kind != OUTSIDE_AFFINE_HULL) {
        bool mine = false;
        for (int k = 0; k < D1 && !mine; ++k) mine = s.ids[k] >= 0 && own[s.ids[k]];
        if (!mine) {
          if (forward) forward[qi] = s.ids[s.perm[0]];
          inside[qi] = 0;
          std::fill(o, o + C, nan);
          return;
        }
      }
      const bool in = s.kind <= ON_VERTEX;
      inside[qi] = in ? 1 : 0;
      if (!(in || (clamp && s.kind == OUTSIDE_CONVEX_HULL))) {
        std::fill(o, o + C, nan);
        return;
      }
      std::fill(o, o + C, 0.0);
      for (int j = 0; j < D1; ++j) {
        const int k = s.perm[j];
        const double wk = s.w[k];
        if (s.ids[k] < 0 || wk == 0.0) continue;
        const double* v = values + static_cast<std::size_t>(s.ids[k]) * C;
        for (std::size_t c = 0; c < C; ++c) o[c] += wk * v[c];
      }
    });
  }

  // ------------------------------------------------------------ access
  void points(double* out) const override {
    for (std::size_t i = 0; i < by_id_.size(); ++i) {
      const Point& p = by_id_[i]->point();
      for (int k = 0; k < D_; ++k) out[i * D_ + k] = p[k];
    }
  }

  // Rows in cell-number order (= find_simplex indices).
  void simplices(std::int64_t* out) const override {
    if (dt_.current_dimension() < D_) return;
    ensure_numbered();
    std::size_t r = 0;
    for (auto it = dt_.full_cells_begin(); it != dt_.full_cells_end(); ++it) {
      if (dt_.is_infinite(it)) continue;
      for (int k = 0; k <= D_; ++k) out[r * (D_ + 1) + k] = it->vertex(k)->data().id;
      ++r;
    }
  }

  // ------------------------------------------------------------ Tile & Merge
  std::size_t count_cells(const std::uint8_t* own) const override {
    if (dt_.current_dimension() < D_) return 0;
    DT& dt = const_cast<DT&>(dt_);
    std::size_t n = 0;
    for (auto it = dt.full_cells_begin(); it != dt.full_cells_end(); ++it) {
      if (dt.is_infinite(it)) continue;
      int first = 0;
      for (int k = 1; k <= D_; ++k)
        if (lex_less(it->vertex(k)->point(), it->vertex(first)->point(), D_)) first = k;
      n += own[it->vertex(first)->data().id] ? 1 : 0;
    }
    return n;
  }

  void conflicts(const std::uint8_t* own, const double* lo, const double* hi,
                 const std::int64_t* start, std::size_t ngroups, std::int64_t skip,
                 const std::int64_t* seeds, std::size_t nseeds, std::int64_t since,
                 std::vector<std::vector<std::int64_t>>& out) const override {
    const int D = D_;
    const std::size_t nv = by_id_.size();
    const std::size_t nbox = ngroups ? static_cast<std::size_t>(start[ngroups]) : 0;
    out.assign(ngroups, {});
    if (ngroups == 0 || nv == 0) return;
    if (dt_.current_dimension() < D) {  // no cells yet: every vertex may matter anywhere
      for (std::size_t g = 0; g < ngroups; ++g)
        if (static_cast<std::int64_t>(g) != skip)
          for (std::size_t i = 0; i < nv; ++i) out[g].push_back(static_cast<std::int64_t>(i));
      return;
    }
    (void)nbox;
    std::vector<std::vector<std::uint8_t>> mark(ngroups);
    for (std::size_t g = 0; g < ngroups; ++g)
      if (static_cast<std::int64_t>(g) != skip) mark[g].assign(nv, 0);
    // group g: its bounding box (the first) first, then its boxes
    auto meets_group = [&](std::size_t g, auto&& meets) {
      const std::size_t b0 = static_cast<std::size_t>(start[g]);
      const std::size_t b1 = static_cast<std::size_t>(start[g + 1]);
      if (b0 >= b1 || !meets(b0)) return false;
      if (b1 - b0 == 1) return true;
      for (std::size_t b = b0 + 1; b < b1; ++b)
        if (meets(b)) return true;
      return false;
    };
    DT& dt = const_cast<DT&>(dt_);
    const Vertex_handle inf = dt.infinite_vertex();
    Mat A(D, D);
    Vec rhs(D), ctr(D);
    Eigen::MatrixXd M(D - 1 > 0 ? D - 1 : 1, D);
    std::vector<double> nrm(D);
    auto send = [&](Full_cell_handle c, std::size_t b) {
      for (int k = 0; k <= D; ++k) {
        Vertex_handle v = c->vertex(k);
        if (v != inf) mark[b][static_cast<std::size_t>(v->data().id)] = 1;
      }
    };
    // the cell's vertices go to every group its ball meets (if one of them is
    // own); true if it meets one (every: tested even without an own vertex)
    auto visit = [&](Full_cell_handle c, bool every) {
      int fi = -1;
      bool mine = false, hit = false;
      for (int k = 0; k <= D; ++k) {
        Vertex_handle v = c->vertex(k);
        if (v == inf) fi = k;
        else mine = mine || own[v->data().id];
      }
      if (!mine && !every) return false;
      if (fi < 0) {
        // circumcentre x of p0..pD: 2 (pi - p0) . (x - p0) = |pi - p0|^2
        const Point& p0 = c->vertex(0)->point();
        for (int i = 1; i <= D; ++i) {
          const Point& pi = c->vertex(i)->point();
          double r2 = 0;
          for (int k = 0; k < D; ++k) {
            const double t = pi[k] - p0[k];
            A(i - 1, k) = 2 * t;
            r2 += t * t;
          }
          rhs(i - 1) = r2;
        }
        ctr = A.partialPivLu().solve(rhs);
        double rr = 0;
        bool finite = true;
        for (int k = 0; k < D; ++k) {
          finite = finite && std::isfinite(ctr(k));
          rr += ctr(k) * ctr(k);
        }
        finite = finite && std::isfinite(rr);
        auto ball_meets = [&](std::size_t b) {
          double d2 = 0;
          for (int k = 0; k < D; ++k) {
            const double x = p0[k] + ctr(k);
            const double y = std::min(std::max(x, lo[b * D + k]), hi[b * D + k]);
            d2 += (x - y) * (x - y);
          }
          return d2 <= rr * (1 + 1e-9);  // conservative: an extra point costs little
        };
        for (std::size_t g = 0; g < ngroups; ++g)
          if (static_cast<std::int64_t>(g) != skip && (!finite || meets_group(g, ball_meets))) {
            hit = true;
            if (mine) send(c, g);
          }
        return hit;
      }
      // infinite cell: the half-space beyond the hull facet (normal n pointing
      // away from the opposite finite vertex)
      int f[64];
      std::vector<int> fdyn;
      int* fv = f;
      if (D > 64) {
        fdyn.resize(D);
        fv = fdyn.data();
      }
      int nf = 0;
      for (int k = 0; k <= D; ++k)
        if (k != fi) fv[nf++] = k;
      const Point& a = c->vertex(fv[0])->point();
      bool finite = true;
      if (D == 1) {
        nrm[0] = 1.0;
      } else {
        for (int j = 1; j < D; ++j) {
          const Point& pj = c->vertex(fv[j])->point();
          for (int k = 0; k < D; ++k) M(j - 1, k) = pj[k] - a[k];
        }
        Eigen::FullPivLU<Eigen::MatrixXd> lu(M);
        Eigen::MatrixXd ker = lu.kernel();
        if (ker.cols() != 1) finite = false;
        for (int k = 0; k < D && finite; ++k) nrm[k] = ker(k, 0);
      }
      const Full_cell_handle in = c->neighbor(fi);
      const Point& pin = in->vertex(c->mirror_index(fi))->point();
      double side = 0, scale = 0, nn = 0;
      for (int k = 0; k < D && finite; ++k) {
        side += nrm[k] * (pin[k] - a[k]);
        nn += std::abs(nrm[k]);
        scale = std::max(scale, std::abs(a[k]));
      }
      finite = finite && std::isfinite(side) && side != 0;
      if (finite && side > 0)
        for (int k = 0; k < D; ++k) nrm[k] = -nrm[k];
      auto half_meets = [&](std::size_t b) {
        double top = 0, sc = scale;
        for (int k = 0; k < D; ++k) {
          const double x = nrm[k] > 0 ? hi[b * D + k] : lo[b * D + k];
          top += nrm[k] * (x - a[k]);
          sc = std::max(sc, std::abs(x));
        }
        return top >= -1e-9 * nn * std::max(sc, 1e-300);
      };
      for (std::size_t g = 0; g < ngroups; ++g)
        if (static_cast<std::int64_t>(g) != skip && (!finite || meets_group(g, half_meets))) {
          hit = true;
          if (mine) send(c, g);
        }
      return hit;
    };
    // cells changed in place by a rise of the dimension after `since` are new too
    if (since >= 0 && since < static_cast<std::int64_t>(dim_gen_)) since = -1;
    // every cell: the search starts from each non-empty box's centre (finite
    // boxes only; the centres are needed for that scan alone)
    const bool every = seeds == nullptr && since < 0;
    bool bounded = every;
    std::vector<double> mids, mid(D);
    for (std::size_t g = 0; every && g < ngroups; ++g) {
      if (static_cast<std::int64_t>(g) == skip) continue;
      for (auto b = static_cast<std::size_t>(start[g]); b < static_cast<std::size_t>(start[g + 1]);
           ++b) {
        bool empty = false, finite = true;
        for (int k = 0; k < D; ++k) {
          const double l = lo[b * D + k], h = hi[b * D + k];
          empty = empty || !(l <= h);
          finite = finite && std::isfinite(l) && std::isfinite(h) && std::isfinite(h - l);
          mid[k] = l + 0.5 * (h - l);
        }
        if (!empty) mids.insert(mids.end(), mid.begin(), mid.end());
        bounded = bounded && (empty || finite);
      }
    }
    if (every && bounded) {
      // every cell: those whose ball meets a box are connected (across facets:
      // the cells whose ball holds a point are, and a box is convex), so a
      // search from the cell holding each box's centre finds them all and
      // tests only them and their neighbours. A search costs about 1.5 times
      // a pass's test a cell (its cells are scattered in memory): past a third
      // of the cells, the cells not reached are passed over instead.
      ensure_numbered();
      const std::size_t ncells = dt.number_of_full_cells();
      std::size_t budget = ncells / 3;
      std::vector<std::uint8_t> seen(ncells, 0);
      std::vector<Full_cell_handle> todo;
      Scratch sc(D);
      for (std::size_t m = 0; m < mids.size(); m += static_cast<std::size_t>(D)) {
        // the cell holding the centre (its ball holds it), or the hull facet's
        // infinite cell beyond which it lies (our walk: no shared state)
        Full_cell_handle c = locate_one(mids.data() + m, Full_cell_handle(), sc);
        if (!seen[c->data().index]) {
          seen[c->data().index] = 1;
          todo.push_back(c);
        }
      }
      while (!todo.empty() && budget) {
        Full_cell_handle c = todo.back();
        todo.pop_back();
        --budget;
        if (!visit(c, true)) continue;
        for (int k = 0; k <= D; ++k) {
          Full_cell_handle n = c->neighbor(k);
          if (!seen[n->data().index]) {
            seen[n->data().index] = 1;
            todo.push_back(n);
          }
        }
      }
      if (!todo.empty()) {  // over budget: the cells found, then those not reached
        for (const Full_cell_handle& c : todo) visit(c, false);
        for (auto it = dt.full_cells_begin(); it != dt.full_cells_end(); ++it)
          if (!seen[it->data().index]) visit(it, false);
      }
    } else if (seeds == nullptr) {
      for (auto it = dt.full_cells_begin(); it != dt.full_cells_end(); ++it)
        if (since < 0 || static_cast<std::int64_t>(it->data().gen) > since) visit(it, false);
    } else {
      std::vector<Full_cell_handle> cells;
      for (std::size_t i = 0; i < nseeds; ++i) {
        const std::int64_t id = seeds[i];
        if (id < 0 || static_cast<std::size_t>(id) >= nv)
          throw std::invalid_argument("seeds: a vertex id out of range");
        dt.tds().incident_full_cells(by_id_[static_cast<std::size_t>(id)],
                                     std::back_inserter(cells));
      }
      std::sort(cells.begin(), cells.end(),
                [](Full_cell_handle x, Full_cell_handle y) { return &*x < &*y; });
      cells.erase(std::unique(cells.begin(), cells.end()), cells.end());
      for (const Full_cell_handle& c : cells) visit(c, false);
    }
    for (std::size_t g = 0; g < ngroups; ++g)
      for (std::size_t i = 0; i < mark[g].size(); ++i)
        if (mark[g][i]) out[g].push_back(static_cast<std::int64_t>(i));
  }

  bool is_valid(bool verbose) const override {
    if (!dt_.is_valid(verbose)) return false;
    // ids: a permutation 0..n-1 matching by_id_.
    if (dt_.number_of_vertices() != by_id_.size()) return false;
    for (std::size_t i = 0; i < by_id_.size(); ++i)
      if (by_id_[i]->data().id != static_cast<std::int64_t>(i)) return false;
    return true;
  }

  // ------------------------------------------------------------ snapshot
  void write_snapshot(Sink& sink, const double* values, std::size_t C) const override {
    DT& dt = const_cast<DT&>(dt_);
    const bool full = dt.current_dimension() == D_;
    SnapshotHeader h;
    h.dim = D_;
    h.current_dim = dt.current_dimension();
    h.n_vertices = by_id_.size();
    h.n_cells = full ? dt.number_of_full_cells() : 0;
    h.n_channels = values ? C : 0;
    if (h.n_cells > 0xffffffffull) throw snapshot_error("too many full cells for format version 1");
    if (!payload_size(h, h.payload_bytes)) throw snapshot_error("snapshot too large");
    unsigned char raw[kHeaderSize];
    encode_header(h, raw);  // placeholder; patched with the checksum below
    sink.write(raw, kHeaderSize);

    PayloadWriter out(sink);
    {
      std::vector<double> row(D_);
      for (const Vertex_handle& v : by_id_) {
        for (int k = 0; k < D_; ++k) row[k] = v->point()[k];
        out.write(row.data(), sizeof(double) * D_);
      }
      for (std::size_t i = 0; i < by_id_.size(); ++i) out.put(static_cast<std::int64_t>(i));
    }
    if (full) {
      // Cells in number order: finite ones (container order), then infinite
      // ones; a loaded snapshot keeps this order, hence the same numbers.
      ensure_numbered();
      const Vertex_handle inf = dt.infinite_vertex();
      std::vector<std::uint32_t> buf;
      buf.reserve(static_cast<std::size_t>(D_ + 1) * 4096);
      auto flush = [&]() {
        out.write(buf.data(), buf.size() * sizeof(std::uint32_t));
        buf.clear();
      };
      auto each_cell = [&](auto&& f) {
        for (int pass = 0; pass < 2; ++pass)
          for (auto it = dt.full_cells_begin(); it != dt.full_cells_end(); ++it)
            if (dt.is_infinite(it) == (pass == 1)) f(it);
      };
      each_cell([&](auto it) {
        for (int k = 0; k <= D_; ++k) {
          Vertex_handle v = it->vertex(k);
          buf.push_back(v == inf ? 0u : static_cast<std::uint32_t>(v->data().id + 1));
        }
        if (buf.size() >= static_cast<std::size_t>(D_ + 1) * 4096) flush();
      });
      flush();
      each_cell([&](auto it) {
        for (int k = 0; k <= D_; ++k) buf.push_back(it->neighbor(k)->data().index);
        if (buf.size() >= static_cast<std::size_t>(D_ + 1) * 4096) flush();
      });
      flush();
      // each vertex's full cell (the infinite vertex first): walks start there,
      // so a loaded triangulation answers exactly like the original
      buf.push_back(inf->full_cell()->data().index);
      for (const Vertex_handle& v : by_id_) {
        buf.push_back(v->full_cell()->data().index);
        if (buf.size() >= 4096) flush();
      }
      flush();
    }
    if (h.n_channels) out.write(values, sizeof(double) * by_id_.size() * C);
    out.flush();
    if (out.bytes() != h.payload_bytes) throw snapshot_error("internal error: payload size");
    h.payload_checksum = out.checksum();
    encode_header(h, raw);
    sink.patch_front(raw, kHeaderSize);
  }

  void read_snapshot(Source& src, const SnapshotHeader& h, std::vector<double>& values) override {
    if (h.dim != D_) throw snapshot_error("internal error: dimension");
    if (!by_id_.empty()) throw snapshot_error("internal error: reading into a non-empty triangulation");
    PayloadReader in(src);
    const std::size_t n = static_cast<std::size_t>(h.n_vertices);
    std::vector<Point> P;
    P.reserve(n);
    {
      constexpr std::size_t kRows = 8192;
      std::vector<double> buf(kRows * D_);
      for (std::size_t i = 0; i < n; i += kRows) {
        std::size_t r = std::min(kRows, n - i);
        in.read(buf.data(), r * D_ * sizeof(double), "points");
        for (std::size_t j = 0; j < r; ++j) {
          for (int k = 0; k < D_; ++k)
            if (!std::isfinite(buf[j * D_ + k])) throw snapshot_error("corrupted snapshot (non-finite point)");
          P.emplace_back(buf.data() + j * D_, buf.data() + (j + 1) * D_);
        }
      }
      std::vector<std::int64_t> ids(kRows);
      for (std::size_t i = 0; i < n; i += kRows) {
        std::size_t r = std::min(kRows, n - i);
        in.read(ids.data(), r * sizeof(std::int64_t), "ids");
        for (std::size_t j = 0; j < r; ++j)
          if (ids[j] != static_cast<std::int64_t>(i + j)) throw snapshot_error("corrupted snapshot (ids)");
      }
    }
    const bool full = h.current_dim == D_;
    numbered_.store(false);
    if (full && (n < static_cast<std::size_t>(D_) + 1 || h.n_cells < static_cast<std::uint64_t>(D_) + 2))
      throw snapshot_error("corrupted snapshot (too few vertices or cells for its dimension)");
    if (full) {
      TDS& tds = dt_.tds();
      dt_.clear();  // infinite vertex + one full cell, dimension -1
      dt_.set_current_dimension(h.current_dim);
      std::vector<Vertex_handle> vh(n + 1);
      vh[0] = dt_.infinite_vertex();
      by_id_.reserve(n);
      for (std::size_t i = 0; i < n; ++i) {
        Vertex_handle v = tds.new_vertex();
        v->set_point(P[i]);
        v->data().id = static_cast<std::int64_t>(i);
        vh[i + 1] = v;
        by_id_.push_back(v);
      }
      std::vector<Point>().swap(P);
      const std::size_t m = static_cast<std::size_t>(h.n_cells);
      const int D1 = D_ + 1;
      std::vector<Full_cell_handle> cells;
      cells.reserve(m);
      constexpr std::size_t kCells = 8192;
      std::vector<std::uint32_t> buf(kCells * D1);
      // Cells in file order = number order (finite ones first); the vertex
      // handles are set from the indices, never by touching the vertices.
      std::size_t n_finite = 0;
      bool seen_infinite = false;
      for (std::size_t i = 0; i < m; i += kCells) {
        std::size_t r = std::min(kCells, m - i);
        in.read(buf.data(), r * D1 * sizeof(std::uint32_t), "cells");
        for (std::size_t j = 0; j < r; ++j) {
          Full_cell_handle s = (i + j == 0) ? dt_.full_cells_begin() : tds.new_full_cell();
          cells.push_back(s);
          s->data().index = static_cast<std::uint32_t>(i + j);
          const std::uint32_t* cv = &buf[j * D1];
          bool infinite = false;
          for (int k = 0; k < D1; ++k) {
            std::uint32_t vi = cv[k];
            if (vi > n) throw snapshot_error("corrupted snapshot (cell vertex index out of range)");
            for (int l = 0; l < k; ++l)
              if (vi == cv[l]) throw snapshot_error("corrupted snapshot (repeated vertex in a cell)");
            infinite |= (vi == 0);
            s->set_vertex(k, vh[vi]);
          }
          if (infinite) {
            seen_infinite = true;
          } else {
            if (seen_infinite) throw snapshot_error("corrupted snapshot (cell order)");
            ++n_finite;
          }
        }
      }
      for (std::size_t i = 0; i < m; i += kCells) {
        std::size_t r = std::min(kCells, m - i);
        in.read(buf.data(), r * D1 * sizeof(std::uint32_t), "neighbours");
        constexpr std::size_t kAhead = 16;  // prefetch distance (cells) for cells[ci]
        for (std::size_t j = 0; j < r; ++j) {
          if (j + kAhead < r)
            for (int k = 0; k < D1; ++k) {
              std::uint32_t cp = buf[(j + kAhead) * D1 + k];
              if (cp < m) __builtin_prefetch(&cells[cp]);
            }
          Full_cell_handle s = cells[i + j];
          for (int k = 0; k < D1; ++k) {
            std::uint32_t ci = buf[j * D1 + k];
            if (ci >= m || ci == i + j)
              throw snapshot_error("corrupted snapshot (neighbour index out of range)");
            s->set_neighbor(k, cells[ci]);
          }
        }
      }
      std::vector<std::uint32_t> vcell(n + 1);
      in.read(vcell.data(), vcell.size() * sizeof(std::uint32_t), "vertex cells");
      for (std::size_t i = 0; i <= n; ++i) {
        if (vcell[i] >= m) throw snapshot_error("corrupted snapshot (vertex cell index out of range)");
        Full_cell_handle c = cells[vcell[i]];
        if (!c->has_vertex(vh[i])) throw snapshot_error("corrupted snapshot (vertex cell)");
        vh[i]->set_full_cell(c);
      }
      n_finite_ = n_finite;
      numbered_.store(true, std::memory_order_release);
    }
    values.resize(static_cast<std::size_t>(h.n_vertices * h.n_channels));
    if (!values.empty()) in.read(values.data(), values.size() * sizeof(double), "values");
    if (in.checksum() != h.payload_checksum)
      throw snapshot_error("corrupted snapshot (payload checksum mismatch)");
    if (!full) {
      // Degenerate (cd < D): few coplanar points; re-insert them in id order.
      Full_cell_handle hint;
      for (std::size_t i = 0; i < n; ++i) {
        Vertex_handle v = dt_.insert(P[i], hint);
        if (v->data().id >= 0) throw snapshot_error("corrupted snapshot (duplicate points)");
        v->data().id = static_cast<std::int64_t>(i);
        by_id_.push_back(v);
        hint = v->full_cell();
      }
      if (dt_.current_dimension() != h.current_dim)
        throw snapshot_error("corrupted snapshot (current dimension)");
    }
  }

 private:
  struct Scratch {
    std::vector<const Point*> pts;
    std::vector<int> ori;
    std::vector<std::int64_t> ids;
    std::vector<double> w;
    // the cell's vertices in lexicographic order of their points (the
    // infinite vertex last): the order weights are computed and summed in
    std::vector<int> perm;
    std::vector<const Point*> cp;
    std::vector<double> wc;
    std::int8_t kind = OUTSIDE_AFFINE_HULL;
    Full_cell_handle cell;
    Mat T;
    Vec rhs;
    MatF F;
    explicit Scratch(int D)
        : pts(D + 1), ori(D + 1), ids(D + 1), w(D + 1), perm(D + 1), cp(D + 1), wc(D + 1),
          T(D, D), rhs(D), F(D, D - 1) {
      std::iota(perm.begin(), perm.end(), 0);
    }
  };

  static bool lex_less(const Point& a, const Point& b, int D) {
    for (int k = 0; k < D; ++k) {
      if (a[k] < b[k]) return true;
      if (b[k] < a[k]) return false;
    }
    return false;
  }

  // Visits every query (in Hilbert or given order, chunked), locating it into
  // a per-chunk Scratch; emit(query_index, scratch) consumes the answer.
  template <class Emit>
  void for_each_query(const double* q, std::size_t n, bool hilbert, int threads,
                      Emit&& emit) const {
    if (n == 0) return;
    const int D = D_;
    if (dt_.current_dimension() < D) {
      Scratch s(D);
      s.kind = OUTSIDE_AFFINE_HULL;
      std::fill(s.ids.begin(), s.ids.end(), -1);
      std::fill(s.w.begin(), s.w.end(), std::numeric_limits<double>::quiet_NaN());
      for (std::size_t i = 0; i < n; ++i) emit(i, s);
      return;
    }
    // Hint samples: every stride-th vertex by id.
    std::vector<Vertex_handle> sample;
    const std::size_t nv = by_id_.size();
    const std::size_t stride = std::max<std::size_t>(1, nv / kHintSamples);
    for (std::size_t i = 0; i < nv; i += stride) sample.push_back(by_id_[i]);

    std::vector<std::uint32_t> order;
    if (hilbert && n > 1 && n <= 0xffffffffull) order = hilbert_order(q, n, D, threads);
    run_chunks(n, threads, [&](std::size_t b, std::size_t e) {
      Scratch s(D);
      Full_cell_handle hint;
      for (std::size_t pos = b; pos < e; ++pos) {
        const std::size_t qi = order.empty() ? pos : order[pos];
        const double* qc = q + qi * D;
        if (pos == b) hint = sample_hint(qc, sample);
        hint = locate_one(qc, hint, s);
        emit(qi, s);
      }
    });
  }

  Full_cell_handle sample_hint(const double* qc, const std::vector<Vertex_handle>& sample) const {
    double best = std::numeric_limits<double>::infinity();
    Vertex_handle bv;
    for (const Vertex_handle& v : sample) {
      const Point& p = v->point();
      double d2 = 0;
      for (int k = 0; k < D_; ++k) {
        double t = p[k] - qc[k];
        d2 += t * t;
      }
      if (d2 < best) {
        best = d2;
        bv = v;
      }
    }
    return bv == Vertex_handle() ? Full_cell_handle() : bv->full_cell();
  }

  // Barycentric coordinates of qc in finite cell c into s.w. False when the
  // cell is too ill-conditioned for their signs to be trusted.
  bool barycentric(Full_cell_handle c, const double* qc, Scratch& s) const {
    for (int k = 0; k <= D_; ++k) s.pts[k] = &c->vertex(k)->point();
    return barycentric_of(s.pts.data(), qc, s.w.data(), s);
  }

  // Barycentric coordinates of qc in the simplex P[0..D] into w[0..D] (the
  // same arithmetic whatever cell the points come from).
  bool barycentric_of(const Point* const* P, const double* qc, double* w, Scratch& s) const {
    const int D = D_;
    const Point& v0 = *P[0];
    for (int k = 1; k <= D; ++k) {
      const Point& vk = *P[k];
      for (int r = 0; r < D; ++r) s.T(r, k - 1) = vk[r] - v0[r];
    }
    for (int r = 0; r < D; ++r) s.rhs(r) = qc[r] - v0[r];
    double dmin = std::numeric_limits<double>::infinity(), dmax = 0;
    double sum = 0;
    if constexpr (E != Eigen::Dynamic) {
      // fixed size: Gaussian elimination with partial pivoting, unrolled
      // (Eigen's PartialPivLU runs its generic blocked loops here)
      double lam[E];
      lu_solve<E>(s.T.data(), s.rhs.data(), lam, dmin, dmax);
      for (int k = 1; k <= D; ++k) {
        w[k] = lam[k - 1];
        sum += lam[k - 1];
      }
    } else {
      Eigen::PartialPivLU<Mat> lu(s.T);
      Vec lam = lu.solve(s.rhs);
      for (int k = 1; k <= D; ++k) {
        w[k] = lam(k - 1);
        sum += lam(k - 1);
      }
      for (int k = 0; k < D; ++k) {
        double u = std::abs(lu.matrixLU()(k, k));
        dmin = std::min(dmin, u);
        dmax = std::max(dmax, u);
      }
    }
    w[0] = 1.0 - sum;
    return dmin > dmax * kPivotRatio && std::isfinite(sum);
  }

  // Solves A x = b for a column-major N x N matrix `a` (overwritten) by Gaussian
  // elimination with partial pivoting; dmin/dmax: extreme |pivots|.
  template <int N>
  static void lu_solve(double* a, double* b, double* x, double& dmin, double& dmax) {
    auto A = [a](int r, int c) -> double& { return a[c * N + r]; };
    for (int k = 0; k < N; ++k) {
      int p = k;
      double best = std::abs(A(k, k));
      for (int i = k + 1; i < N; ++i)
        if (std::abs(A(i, k)) > best) {
          best = std::abs(A(i, k));
          p = i;
        }
      if (p != k) {
        for (int j = k; j < N; ++j) std::swap(A(k, j), A(p, j));
        std::swap(b[k], b[p]);
      }
      dmin = std::min(dmin, best);
      dmax = std::max(dmax, best);
      const double inv = 1.0 / A(k, k);  // inf when singular: caught by dmin/isfinite
      for (int i = k + 1; i < N; ++i) {
        const double f = A(i, k) * inv;
        for (int j = k + 1; j < N; ++j) A(i, j) -= f * A(k, j);
        b[i] -= f * b[k];
      }
    }
    for (int i = N - 1; i >= 0; --i) {
      double t = b[i];
      for (int j = i + 1; j < N; ++j) t -= A(i, j) * x[j];
      x[i] = t / A(i, i);
    }
  }

  // Exact sign of the orientation of cell c with vertex i replaced by p
  // (POSITIVE: p on the same side of facet i as vertex i).
  int exact_side(Full_cell_handle c, int i, const Point& p, Scratch& s) const {
    const int D = D_;
    for (int k = 0; k <= D; ++k) s.pts[k] = &c->vertex(k)->point();
    s.pts[i] = &p;
    auto orient = dt_.geom_traits().orientation_d_object();
    return orient(boost::make_indirect_iterator(s.pts.data()),
                  boost::make_indirect_iterator(s.pts.data() + D + 1));
  }

  // Visibility walk from `start` (full dimension only). Fills s.ids, s.w,
  // s.kind; returns the full cell it ended in (the next hint).
  //
  // Each step computes the query's barycentric coordinates in the current
  // cell (one small LU) and crosses the facet of the most negative one. Signs
  // are trusted in floating point only when clearly away from zero
  // (|lambda| > kLambdaEps * max(1, max|lambda|)) in a well-conditioned cell;
  // every other sign is decided by CGAL's exact Orientation_d, so the final
  // cell and the on-facet/face/vertex kinds are exact. Any choice of a
  // separating facet terminates in a Delaunay triangulation (Edelsbrunner's
  // acyclicity theorem); after kMaxFloatSteps the walk goes exact-only.
  Full_cell_handle locate_one(const double* qc, Full_cell_handle start, Scratch& s) const {
    const int D = D_;
    const Vertex_handle inf = dt_.infinite_vertex();
    auto inf_index = [&](Full_cell_handle c) {
      for (int k = 0; k <= D; ++k)
        if (c->vertex(k) == inf) return k;
      return -1;
    };
    Full_cell_handle c = start;
    if (c == Full_cell_handle()) c = inf->full_cell();
    int fi = inf_index(c);
    if (fi >= 0) c = c->neighbor(fi);
    std::optional<Point> exact_p;  // built only if an exact predicate is needed
    auto P = [&]() -> const Point& {
      if (!exact_p) exact_p.emplace(qc, qc + D);
      return *exact_p;
    };
    bool outside = false;
    std::size_t steps = 0;
    for (;; ++steps) {
      // the walk is bound by memory latency: fetch the cells it may enter next
      // while this one's barycentrics are computed
      for (int k = 0; k <= D; ++k) {
        const char* nb = reinterpret_cast<const char*>(&*c->neighbor(k));
        __builtin_prefetch(nb);
        __builtin_prefetch(nb + 64);
      }
      const bool ok = barycentric(c, qc, s) && steps < kMaxFloatSteps;
      int move = -1;
      if (ok) {
        double big = 1.0;
        for (int k = 0; k <= D; ++k) big = std::max(big, std::abs(s.w[k]));
        const double eps = kLambdaEps * big;
        double most = -eps;
        for (int k = 0; k <= D; ++k)
          if (s.w[k] < most) {
            most = s.w[k];
            move = k;
          }
        if (move < 0) {
          for (int k = 0; k <= D; ++k) {
            if (s.w[k] > eps) {
              s.ori[k] = CGAL::POSITIVE;
              continue;
            }
            s.ori[k] = exact_side(c, k, P(), s);
            if (s.ori[k] == CGAL::NEGATIVE) {
              move = k;
              break;
            }
          }
        }
      } else {
        for (int k = 0; k <= D; ++k) {
          s.ori[k] = exact_side(c, k, P(), s);
          if (s.ori[k] == CGAL::NEGATIVE) {
            move = k;
            break;
          }
        }
      }
      if (move < 0) break;
      c = c->neighbor(move);
      fi = inf_index(c);
      if (fi >= 0) {
        outside = true;
        break;
      }
    }
    for (int k = 0; k <= D; ++k) s.ids[k] = c->vertex(k)->data().id;
    s.cell = c;
    if (outside) {
      s.kind = OUTSIDE_CONVEX_HULL;
      facet_weights(c, fi, qc, s);
      return c;
    }
    // the answer's weights: computed with the vertices in lexicographic order
    // of their points, so they depend on the cell only (not on its vertex
    // order in this triangulation): a tile holding the cell answers the bits
    // of the whole triangulation (Tile & Merge)
    for (int k = 0; k <= D; ++k) s.perm[k] = k;
    std::sort(s.perm.begin(), s.perm.end(), [&](int a, int b) {
      return lex_less(c->vertex(a)->point(), c->vertex(b)->point(), D);
    });
    for (int j = 0; j <= D; ++j) s.cp[j] = &c->vertex(s.perm[j])->point();
    barycentric_of(s.cp.data(), qc, s.wc.data(), s);
    for (int j = 0; j <= D; ++j) s.w[s.perm[j]] = s.wc[j];
    int zeros = 0;
    for (int k = 0; k <= D; ++k) zeros += (s.ori[k] == CGAL::ZERO);
    s.kind = zeros == 0 ? IN_CELL : zeros == D ? ON_VERTEX : zeros == 1 ? ON_FACET : ON_FACE;
    if (zeros)  // exact knowledge from the predicate: these weights are 0
      for (int k = 0; k <= D; ++k)
        if (s.ori[k] == CGAL::ZERO) s.w[k] = 0.0;
    return c;
  }

  // Outside the hull: least-squares barycentrics of the query's projection on
  // the hull facet opposite the infinite vertex (index fi), clamped to >= 0,
  // renormalised; 0 at the infinite vertex.
  void facet_weights(Full_cell_handle c, int fi, const double* qc, Scratch& s) const {
    const int D = D_;
    int fv[64];
    std::vector<int> fv_dyn;
    int* f = fv;
    if (D > 64) {
      fv_dyn.resize(D);
      f = fv_dyn.data();
    }
    int nf = 0;
    for (int k = 0; k <= D; ++k)
      if (k != fi) f[nf++] = k;
    // lexicographic order of the facet's points (see locate_one)
    std::sort(f, f + nf, [&](int x, int y) {
      return lex_less(c->vertex(x)->point(), c->vertex(y)->point(), D);
    });
    for (int j = 0; j < nf; ++j) s.perm[j] = f[j];
    s.perm[D] = fi;
    const Point& a = c->vertex(f[0])->point();
    for (int j = 1; j < D; ++j) {
      const Point& vj = c->vertex(f[j])->point();
      for (int r = 0; r < D; ++r) s.F(r, j - 1) = vj[r] - a[r];
    }
    for (int r = 0; r < D; ++r) s.rhs(r) = qc[r] - a[r];
    VecF mu;
    if (D > 1) {
      MatFF G = s.F.transpose() * s.F;
      VecF g = s.F.transpose() * s.rhs;
      mu = G.ldlt().solve(g);
    }
    std::fill(s.w.begin(), s.w.end(), 0.0);
    double sum = 0;
    for (int j = 1; j < D; ++j) {
      double x = std::max(0.0, mu(j - 1));
      s.w[f[j]] = x;
      sum += mu(j - 1);
    }
    s.w[f[0]] = std::max(0.0, 1.0 - sum);
    double tot = 0;
    for (int j = 0; j < nf; ++j) tot += s.w[f[j]];
    if (tot > 0)
      for (int k = 0; k <= D; ++k) s.w[k] /= tot;
  }

  // Numbers the full cells (the data slot): finite cells 0..F-1 in container
  // order, then the infinite ones (= simplices() rows, find_simplex values,
  // snapshot order). Lazy: the first reader that needs numbers after an
  // insertion pays one pass over the cells (the mutex serialises, the flag
  // publishes; only readers that called this read the slot). A loaded
  // snapshot is numbered already (file order).
  void ensure_numbered() const {
    if (numbered_.load(std::memory_order_acquire)) return;
    std::lock_guard<std::mutex> lk(number_mutex_);
    if (numbered_.load(std::memory_order_relaxed)) return;
    DT& dt = const_cast<DT&>(dt_);
    std::uint32_t idx = 0;
    for (int pass = 0; pass < 2; ++pass) {
      for (auto it = dt.full_cells_begin(); it != dt.full_cells_end(); ++it)
        if (dt.is_infinite(it) == (pass == 1)) it->data().index = idx++;
      if (pass == 0) n_finite_ = idx;
    }
    numbered_.store(true, std::memory_order_release);
  }

  int D_;
  DT dt_;
  std::vector<Vertex_handle> by_id_;
  mutable std::mutex number_mutex_;
  mutable std::atomic<bool> numbered_{false};
  mutable std::size_t n_finite_ = 0;
  std::uint32_t gen_ = 0;      // inserts so far (the cells' generations)
  std::uint32_t dim_gen_ = 0;  // the insert that last raised the dimension
};

}  // namespace flatserve
