// flatserve's triangulation core: CGAL's dD Delaunay triangulation over
// Epick_d, one class template for every dimension (static 2..6, dynamic
// beyond), behind a small type-erased interface (TriangulationBase) so the
// bindings dispatch on the dimension at run time. No Python here.
//
// Conventions
// - Every finite vertex carries a sample id (0, 1, 2, ... in insertion order
//   over all batches). The infinite vertex has id -1.
// - Duplicate points: inserting a point that already is a vertex creates no
//   vertex; the row is answered with the existing vertex's id (the caller
//   replaces that sample's value: the later value wins).
// - Locate answers, per query, the D+1 vertex ids of the full cell the walk
//   ends in (-1 for the infinite vertex), barycentric weights and a kind
//   (LocateKind). The walk is our own visibility walk: floating-point
//   barycentrics where their signs are clear, CGAL's exact Orientation_d
//   otherwise (CGAL's locate keeps a shared random generator in the
//   triangulation, a data race across threads). Queries are
//   processed in fixed chunks of kChunk; each chunk starts from a hint that
//   depends only on the triangulation and the chunk's first query, then chains
//   the previous answer's full cell. Hence the answers do not depend on the
//   number of threads.
#pragma once

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <exception>
#include <limits>
#include <memory>
#include <mutex>
#include <numeric>
#include <stdexcept>
#include <thread>
#include <vector>

#include "snapshot.hpp"

namespace flatserve {

// Exported to Python as flatserve._core.LocateKind (bindings.cpp).
enum LocateKind : std::int8_t {
  IN_CELL = 0,               // strictly inside a full cell
  ON_FACET = 1,              // on a facet (one weight exactly 0)
  ON_FACE = 2,               // on a lower-dimensional face (edge, ...)
  ON_VERTEX = 3,             // on a vertex
  OUTSIDE_CONVEX_HULL = 4,   // beyond a hull facet
  OUTSIDE_AFFINE_HULL = 5,   // the triangulation does not span R^D yet
};

constexpr std::size_t kChunk = 2048;  // queries per work unit (fixed: thread-count independent)
constexpr int kHintSamples = 256;     // vertices sampled for a chunk's first hint

inline int default_threads() {
  unsigned h = std::thread::hardware_concurrency();
  return h ? static_cast<int>(h) : 1;
}

// Squared Euclidean distance of a point (anything indexable: a CGAL Point_d or
// a row of doubles) to q, summed in coordinate order: Triangulation::within
// and seam_net (net.hpp) decide alike because they share it.
template <class P>
inline double sq_dist(const P& p, const double* q, int D) {
  double t = 0;
  for (int k = 0; k < D; ++k) {
    const double u = p[k] - q[k];
    t += u * u;
  }
  return t;
}

// Runs body(begin, end) over [0, n) in fixed chunks of kChunk on `threads`
// threads (<= 0: all cores). Exceptions are rethrown in the caller.
template <class F>
void run_chunks(std::size_t n, int threads, F&& body) {
  const std::size_t nchunks = (n + kChunk - 1) / kChunk;
  std::size_t T = threads <= 0 ? static_cast<std::size_t>(default_threads())
                               : static_cast<std::size_t>(threads);
  T = std::min(T, nchunks);
  if (T <= 1) {
    for (std::size_t c = 0; c < nchunks; ++c) body(c * kChunk, std::min(n, (c + 1) * kChunk));
    return;
  }
  std::atomic<std::size_t> next{0};
  std::exception_ptr err;
  std::mutex err_mutex;
  auto worker = [&]() {
    try {
      for (;;) {
        std::size_t c = next.fetch_add(1);
        if (c >= nchunks) break;
        body(c * kChunk, std::min(n, (c + 1) * kChunk));
      }
    } catch (...) {
      std::lock_guard<std::mutex> lk(err_mutex);
      if (!err) err = std::current_exception();
      next.store(nchunks);
    }
  };
  std::vector<std::thread> pool;
  pool.reserve(T - 1);
  for (std::size_t t = 1; t < T; ++t) pool.emplace_back(worker);
  worker();
  for (auto& th : pool) th.join();
  if (err) std::rethrow_exception(err);
}

// The type-erased interface the bindings see.
class TriangulationBase {
 public:
  virtual ~TriangulationBase() = default;
  virtual int dimension() const = 0;
  virtual int current_dimension() const = 0;
  virtual std::size_t number_of_vertices() const = 0;
  virtual std::size_t number_of_full_cells() const = 0;  // infinite ones included
  virtual std::size_t number_of_finite_cells() const = 0;
  // pts: n x D row-major. out_ids[i]: sample id row i landed on. Returns the
  // number of new vertices (n - returned = duplicates and points left out).
  // own (may be null; nown entries, one per sample id, later ids not own):
  // Tile & Merge's halo, a point is inserted only if it becomes a neighbour of
  // a vertex with own[id] != 0 (its conflict zone has a cell with one), else
  // left out with out_ids[i] = -1 (a duplicate of a vertex always lands on it).
  virtual std::size_t insert(const double* pts, std::size_t n, std::int64_t* out_ids,
                             const std::uint8_t* own = nullptr, std::size_t nown = 0) = 0;
  // q: n x D. ids, w: n x (D+1); kind: n. Outside the convex hull the weights
  // are the clamped ones of the hull facet the walk ended at (0 at the
  // infinite vertex); outside the affine hull ids are -1 and weights NaN.
  // simplex (may be null): index of the finite cell (row of simplices()), -1
  // outside.
  virtual void locate(const double* q, std::size_t n, bool hilbert, int threads,
                      std::int64_t* ids, double* w, std::int8_t* kind,
                      std::int64_t* simplex) const = 0;
  // q: n x D. out[i] = 1 if some vertex lies within `radius` of query i
  // (squared Euclidean distance <= radius^2, summed in coordinate order), else
  // 0: every vertex is scanned until one is found (the answer depends on the
  // vertices only, not on the cells or the order they came in).
  virtual void within(const double* q, std::size_t n, double radius, int threads,
                      std::uint8_t* out) const = 0;
  // values: nvalues x C (row = sample id). out: n x C; inside: n. The sum runs
  // over the cell's vertices in lexicographic order of their points (as the
  // weights are computed: locate_one), so any triangulation holding the same
  // cell gives the same bits. own (may be null; one byte per sample id): a
  // query whose cell has no vertex with own[id] != 0 is not answered: out NaN,
  // inside 0 and forward[i] = the id of its cell's lexicographically first
  // finite vertex (-1 for answered queries; forward may be null without own).
  virtual void interpolate(const double* q, std::size_t n, const double* values,
                           std::size_t nvalues, std::size_t C, bool clamp, bool hilbert,
                           int threads, double* out, std::uint8_t* inside,
                           const std::uint8_t* own, std::int64_t* forward) const = 0;
  // Tile & Merge's exchange: for every cell with at least one vertex with
  // own[id] != 0 whose circumscribed ball (for an infinite cell: the open
  // half-space beyond its hull facet) meets a box of group g (lo/hi: nbox x D,
  // closed; group g's boxes are start[g] .. start[g+1]-1, the first of them
  // their bounding box, tested first), the ids of its finite vertices go to
  // out[g] (sorted, unique); group `skip` is not tested (-1: none). Cells
  // scanned: every cell (seeds null and since < 0: a search from the cell
  // holding each box's centre through the cells whose ball meets a box, which
  // are connected, their neighbours tested too; a pass when a box is not
  // finite), those made by the inserts
  // after generation `since` (seeds null; one pass over the cells), or those
  // incident to the seed vertices (the cells an insertion of those vertices
  // created; a walk around each). Conservative: a ball that cannot be
  // computed meets every group (in the search: once reached). Below full dimension every
  // vertex goes to every group.
  // Finite cells whose lexicographically first vertex has own[id] != 0: over
  // tiles that hold every cell around their own vertices, each cell of the
  // whole triangulation is counted once.
  virtual std::size_t count_cells(const std::uint8_t* own) const = 0;
  virtual void conflicts(const std::uint8_t* own, const double* lo, const double* hi,
                         const std::int64_t* start, std::size_t ngroups, std::int64_t skip,
                         const std::int64_t* seeds, std::size_t nseeds, std::int64_t since,
                         std::vector<std::vector<std::int64_t>>& out) const = 0;
  // Inserts so far that held a row (one whose rows were all left out does not
  // count): the cells an insert makes carry its generation (conflicts).
  virtual std::uint32_t generation() const = 0;
  virtual void points(double* out) const = 0;       // n x D, row = sample id
  virtual void simplices(std::int64_t* out) const = 0;  // finite cells x (D+1), numbered order
  virtual bool is_valid(bool verbose) const = 0;
  virtual void write_snapshot(Sink& sink, const double* values, std::size_t C) const = 0;
  // Reads the payload (header already decoded); values receives n x C.
  virtual void read_snapshot(Source& src, const SnapshotHeader& h,
                             std::vector<double>& values) = 0;
};

// Factories, one translation unit per dimension (triangulation.cpp, compiled
// once per FS_TRI_DIM by CMake): N in 2..6 static, make_dynamic beyond.
template <int N>
std::unique_ptr<TriangulationBase> make_static();
extern template std::unique_ptr<TriangulationBase> make_static<2>();
extern template std::unique_ptr<TriangulationBase> make_static<3>();
extern template std::unique_ptr<TriangulationBase> make_static<4>();
extern template std::unique_ptr<TriangulationBase> make_static<5>();
extern template std::unique_ptr<TriangulationBase> make_static<6>();
std::unique_ptr<TriangulationBase> make_dynamic(int D);

inline std::unique_ptr<TriangulationBase> make_triangulation(int D) {
  switch (D) {
    case 2: return make_static<2>();
    case 3: return make_static<3>();
    case 4: return make_static<4>();
    case 5: return make_static<5>();
    case 6: return make_static<6>();
    default:
      if (D < 1) throw std::invalid_argument("dimension must be at least 1");
      return make_dynamic(D);
  }
}

// Snapshot entry points (format in snapshot.hpp).
inline void save_snapshot(const TriangulationBase& t, Sink& sink, const double* values,
                          std::size_t C) {
  t.write_snapshot(sink, values, C);
}

struct LoadedSnapshot {
  std::unique_ptr<TriangulationBase> tri;
  std::vector<double> values;
  std::size_t channels = 0;
};

inline LoadedSnapshot load_snapshot(Source& src) {
  SnapshotHeader h = decode_header(src);
  LoadedSnapshot out;
  out.tri = make_triangulation(h.dim);
  out.tri->read_snapshot(src, h, out.values);
  out.channels = static_cast<std::size_t>(h.n_channels);
  return out;
}

}  // namespace flatserve
