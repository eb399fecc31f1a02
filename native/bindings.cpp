// The one file that knows about Python. Everything CGAL lives in headers
// beside it (triangulation.hpp, ...); this file only converts arrays.
//
// Layout: one delimited block per topic (`// ---- <topic> ----`), each with a
// `bind_<topic>(nb::module_&)` function called from NB_MODULE at the bottom.
// Arrays arrive validated and C-contiguous from the Python wrappers.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>
#include <nanobind/stl/optional.h>
#include <CGAL/version.h>
#include <Eigen/Core>

#include <cstdint>
#include <cstring>
#include <memory>
#include <optional>
#include <string>
#include <vector>

namespace nb = nanobind;

namespace {

// A new NumPy array of the given shape owning a heap buffer.
template <class T>
struct OutArray {
  T* data;
  std::vector<std::size_t> shape;
  explicit OutArray(std::vector<std::size_t> s) : shape(std::move(s)) {
    std::size_t n = 1;
    for (std::size_t d : shape) n *= d;
    data = new T[n ? n : 1];
  }
  // Hands ownership to Python (call with the GIL held).
  nb::ndarray<nb::numpy, T> release() {
    T* p = data;
    data = nullptr;
    nb::capsule owner(p, [](void* q) noexcept { delete[] static_cast<T*>(q); });
    return nb::ndarray<nb::numpy, T>(p, shape.size(), shape.data(), owner);
  }
  ~OutArray() { delete[] data; }
  OutArray(const OutArray&) = delete;
  OutArray& operator=(const OutArray&) = delete;
};

}  // namespace

// ---- triangulation ----
#include "triangulation.hpp"

namespace {

using CArr2 = nb::ndarray<const double, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using U8Arr1 = nb::ndarray<const std::uint8_t, nb::ndim<1>, nb::c_contig, nb::device::cpu>;
using I64Arr1 = nb::ndarray<const std::int64_t, nb::ndim<1>, nb::c_contig, nb::device::cpu>;

struct PyTriangulation {
  std::unique_ptr<flatserve::TriangulationBase> t;
};

void check_cols(const CArr2& a, std::size_t want, const char* name) {
  if (a.shape(1) != want)
    throw std::invalid_argument(std::string(name) + ": expected " + std::to_string(want) +
                                " columns, got " + std::to_string(a.shape(1)));
}

std::optional<nb::ndarray<nb::numpy, double>> values_or_none(std::vector<double>& v,
                                                              std::size_t n, std::size_t C) {
  if (C == 0) return std::nullopt;
  OutArray<double> out({n, C});
  std::memcpy(out.data, v.data(), sizeof(double) * n * C);
  return out.release();
}

void bind_triangulation(nb::module_& m) {
  // A subclass of the library's Python class (which flatserve.errors defines
  // without importing this module): users catch flatserve.errors.SnapshotError.
  nb::exception<flatserve::snapshot_error>(
      m, "SnapshotError", nb::module_::import_("flatserve.errors").attr("SnapshotError"));
  // is_arithmetic: an IntEnum, so members compare with ints and int8 arrays.
  nb::enum_<flatserve::LocateKind>(m, "LocateKind", nb::is_arithmetic(),
                                   "Where a query point lies in the triangulation.")
      .value("IN_CELL", flatserve::IN_CELL, "Strictly inside a full cell.")
      .value("ON_FACET", flatserve::ON_FACET, "On a facet (one weight exactly 0).")
      .value("ON_FACE", flatserve::ON_FACE, "On a lower-dimensional face (edge, ...).")
      .value("ON_VERTEX", flatserve::ON_VERTEX, "On a vertex.")
      .value("OUTSIDE_CONVEX_HULL", flatserve::OUTSIDE_CONVEX_HULL, "Beyond a hull facet.")
      .value("OUTSIDE_AFFINE_HULL", flatserve::OUTSIDE_AFFINE_HULL,
             "The triangulation does not span R^D yet.");
  m.attr("QUERY_CHUNK") = flatserve::kChunk;
  m.def("default_threads", &flatserve::default_threads);

  nb::class_<PyTriangulation>(m, "Triangulation")
      .def("__init__",
           [](PyTriangulation* self, int ndim) {
             new (self) PyTriangulation{flatserve::make_triangulation(ndim)};
           },
           nb::arg("ndim"))
      .def_prop_ro("ndim", [](const PyTriangulation& s) { return s.t->dimension(); })
      .def_prop_ro("current_dimension",
                   [](const PyTriangulation& s) { return s.t->current_dimension(); })
      .def_prop_ro("nvertices",
                   [](const PyTriangulation& s) { return s.t->number_of_vertices(); })
      .def_prop_ro("nfullcells",
                   [](const PyTriangulation& s) { return s.t->number_of_full_cells(); })
      .def_prop_ro("generation", [](const PyTriangulation& s) { return s.t->generation(); },
                   "Inserts so far: the cells an insert makes carry its number "
                   "(conflicts(since=...)).")
      .def("nfinite_cells",
           [](const PyTriangulation& s) {
             nb::gil_scoped_release r;
             return s.t->number_of_finite_cells();
           })
      .def("insert",
           [](PyTriangulation& s, CArr2 pts, std::optional<U8Arr1> own) {
             check_cols(pts, s.t->dimension(), "points");
             const std::size_t n = pts.shape(0);
             if (own && own->shape(0) != s.t->number_of_vertices())
               throw std::invalid_argument("own: one entry per vertex expected");
             OutArray<std::int64_t> ids({n});
             std::size_t added;
             {
               nb::gil_scoped_release r;
               added = s.t->insert(pts.data(), n, ids.data, own ? own->data() : nullptr,
                                   own ? own->shape(0) : 0);
             }
             return std::make_tuple(ids.release(), added);
           },
           nb::arg("points"), nb::arg("own").none() = nb::none(),
           "Inserts the points (n, D); with own (one byte per vertex), only those that "
           "become neighbours of a vertex with own[id] (the others: id -1).")
      .def("locate",
           [](const PyTriangulation& s, CArr2 q, bool hilbert, int threads) {
             const int D = s.t->dimension();
             check_cols(q, D, "xi");
             const std::size_t n = q.shape(0), D1 = D + 1;
             OutArray<std::int64_t> ids({n, D1});
             OutArray<double> w({n, D1});
             OutArray<std::int8_t> kind({n});
             OutArray<std::int64_t> simplex({n});
             {
               nb::gil_scoped_release r;
               s.t->locate(q.data(), n, hilbert, threads, ids.data, w.data, kind.data,
                           simplex.data);
             }
             return std::make_tuple(ids.release(), w.release(), kind.release(),
                                    simplex.release());
           },
           nb::arg("xi"), nb::arg("hilbert") = true, nb::arg("threads") = 0)
      .def("within",
           [](const PyTriangulation& s, CArr2 q, double radius, int threads) {
             check_cols(q, s.t->dimension(), "xi");
             const std::size_t n = q.shape(0);
             OutArray<std::uint8_t> out({n});
             {
               nb::gil_scoped_release r;
               s.t->within(q.data(), n, radius, threads, out.data);
             }
             return out.release();
           },
           nb::arg("xi"), nb::arg("radius"), nb::arg("threads") = 0,
           "Per row of xi, 1 if some vertex lies within radius of it (Euclidean, "
           "inclusive), else 0.")
      .def("interpolate",
           [](const PyTriangulation& s, CArr2 q, CArr2 values, bool clamp, bool hilbert,
              int threads) {
             check_cols(q, s.t->dimension(), "xi");
             const std::size_t n = q.shape(0), C = values.shape(1);
             OutArray<double> out({n, C});
             OutArray<bool> inside({n});
             {
               nb::gil_scoped_release r;
               s.t->interpolate(q.data(), n, values.data(), values.shape(0), C, clamp, hilbert,
                                threads, out.data, reinterpret_cast<std::uint8_t*>(inside.data),
                                nullptr, nullptr);
             }
             return std::make_tuple(out.release(), inside.release());
           },
           nb::arg("xi"), nb::arg("values"), nb::arg("clamp") = false, nb::arg("hilbert") = true,
           nb::arg("threads") = 0)
      .def("interpolate_owned",
           [](const PyTriangulation& s, CArr2 q, CArr2 values, U8Arr1 own, bool clamp,
              bool hilbert, int threads) {
             check_cols(q, s.t->dimension(), "xi");
             if (own.shape(0) < s.t->number_of_vertices())
               throw std::invalid_argument("own: one entry per vertex expected");
             const std::size_t n = q.shape(0), C = values.shape(1);
             OutArray<double> out({n, C});
             OutArray<bool> inside({n});
             OutArray<std::int64_t> forward({n});
             {
               nb::gil_scoped_release r;
               s.t->interpolate(q.data(), n, values.data(), values.shape(0), C, clamp, hilbert,
                                threads, out.data, reinterpret_cast<std::uint8_t*>(inside.data),
                                own.data(), forward.data);
             }
             return std::make_tuple(out.release(), inside.release(), forward.release());
           },
           nb::arg("xi"), nb::arg("values"), nb::arg("own"), nb::arg("clamp") = false,
           nb::arg("hilbert") = true, nb::arg("threads") = 0,
           "interpolate, answering only the queries whose cell has a vertex with own[id]; "
           "the others: NaN, not inside, and forward = the id of their cell's "
           "lexicographically first finite vertex (-1 when answered).")
      .def("count_cells",
           [](const PyTriangulation& s, U8Arr1 own) {
             if (own.shape(0) < s.t->number_of_vertices())
               throw std::invalid_argument("own: one entry per vertex expected");
             nb::gil_scoped_release r;
             return s.t->count_cells(own.data());
           },
           nb::arg("own"),
           "Finite cells whose lexicographically first vertex has own[id] (over Tile & "
           "Merge's tiles: each cell of the whole triangulation once).")
      .def("conflicts",
           [](const PyTriangulation& s, U8Arr1 own, CArr2 lo, CArr2 hi, I64Arr1 start,
              std::int64_t skip, std::optional<I64Arr1> seeds, std::int64_t since) {
             const std::size_t D = s.t->dimension();
             check_cols(lo, D, "lo");
             check_cols(hi, D, "hi");
             if (lo.shape(0) != hi.shape(0))
               throw std::invalid_argument("lo, hi: one row per box each");
             if (own.shape(0) < s.t->number_of_vertices())
               throw std::invalid_argument("own: one entry per vertex expected");
             const std::size_t ng = start.shape(0) ? start.shape(0) - 1 : 0;
             const std::int64_t* st = start.data();
             for (std::size_t g = 0; g < ng; ++g)
               if (st[g] < 0 || st[g] > st[g + 1])
                 throw std::invalid_argument("start: increasing box offsets expected");
             if (ng && static_cast<std::size_t>(st[ng]) != lo.shape(0))
               throw std::invalid_argument("start: its last offset must be the number of boxes");
             std::vector<std::vector<std::int64_t>> got;
             {
               nb::gil_scoped_release r;
               s.t->conflicts(own.data(), lo.data(), hi.data(), st, ng, skip,
                              seeds ? seeds->data() : nullptr, seeds ? seeds->shape(0) : 0,
                              since, got);
             }
             nb::list res;
             for (auto& ids : got) {
               OutArray<std::int64_t> a({ids.size()});
               if (!ids.empty()) std::memcpy(a.data, ids.data(), sizeof(std::int64_t) * ids.size());
               res.append(a.release());
             }
             return res;
           },
           nb::arg("own"), nb::arg("lo"), nb::arg("hi"), nb::arg("start"), nb::arg("skip") = -1,
           nb::arg("seeds").none() = nb::none(), nb::arg("since") = -1,
           "Tile & Merge's exchange: per group of boxes (lo, hi: (nbox, D); group g is "
           "boxes start[g]:start[g+1], its bounding box first), the sorted ids of the "
           "vertices of the cells with a vertex with own[id] whose circumscribed ball "
           "(half-space beyond the hull facet for an infinite cell) meets one of its boxes; "
           "every cell (a search from the boxes' centres), those made by the inserts after "
           "generation since (one pass over "
           "the cells), or those incident to the seed vertices; group skip untested.")
      .def("points",
           [](const PyTriangulation& s) {
             OutArray<double> out({s.t->number_of_vertices(), (std::size_t)s.t->dimension()});
             {
               nb::gil_scoped_release r;
               s.t->points(out.data);
             }
             return out.release();
           })
      .def("simplices",
           [](const PyTriangulation& s) {
             std::size_t m;
             {
               nb::gil_scoped_release r;
               m = s.t->number_of_finite_cells();
             }
             OutArray<std::int64_t> out({m, (std::size_t)s.t->dimension() + 1});
             {
               nb::gil_scoped_release r;
               s.t->simplices(out.data);
             }
             return out.release();
           })
      .def("is_valid",
           [](const PyTriangulation& s, bool verbose) {
             nb::gil_scoped_release r;
             return s.t->is_valid(verbose);
           },
           nb::arg("verbose") = false)
      .def("save",
           [](const PyTriangulation& s, const std::string& path, std::optional<CArr2> values) {
             const double* v = values ? values->data() : nullptr;
             const std::size_t C = values ? values->shape(1) : 0;
             if (values && values->shape(0) != s.t->number_of_vertices())
               throw std::invalid_argument("values: one row per vertex expected");
             nb::gil_scoped_release r;
             flatserve::FileSink sink(path);
             flatserve::save_snapshot(*s.t, sink, v, C);
             sink.close();
           },
           nb::arg("path"), nb::arg("values").none())
      .def("to_bytes",
           [](const PyTriangulation& s, std::optional<CArr2> values) {
             const double* v = values ? values->data() : nullptr;
             const std::size_t C = values ? values->shape(1) : 0;
             if (values && values->shape(0) != s.t->number_of_vertices())
               throw std::invalid_argument("values: one row per vertex expected");
             flatserve::VectorSink sink;
             {
               nb::gil_scoped_release r;
               flatserve::save_snapshot(*s.t, sink, v, C);
             }
             return nb::bytes(sink.buf.data(), sink.buf.size());
           },
           nb::arg("values").none())
      .def_static("load",
                  [](const std::string& path) {
                    flatserve::LoadedSnapshot ls;
                    {
                      nb::gil_scoped_release r;
                      flatserve::FileSource src(path);
                      ls = flatserve::load_snapshot(src);
                    }
                    std::size_t n = ls.tri->number_of_vertices();
                    auto vals = values_or_none(ls.values, n, ls.channels);
                    return std::make_tuple(PyTriangulation{std::move(ls.tri)}, vals);
                  },
                  nb::arg("path"))
      .def_static("from_bytes",
                  [](nb::bytes data) {
                    flatserve::LoadedSnapshot ls;
                    {
                      const char* p = data.c_str();
                      std::size_t len = data.size();
                      nb::gil_scoped_release r;
                      flatserve::MemorySource src(p, len);
                      ls = flatserve::load_snapshot(src);
                    }
                    std::size_t n = ls.tri->number_of_vertices();
                    auto vals = values_or_none(ls.values, n, ls.channels);
                    return std::make_tuple(PyTriangulation{std::move(ls.tri)}, vals);
                  },
                  nb::arg("data"));
}

}  // namespace
// ---- end triangulation ----

// ---- raycast ----
// Ray casting against a triangle mesh (CGAL AABB tree); C++ in raycast.hpp.
// Python face: flatserve.lightfield.scene (LIGHTFIELD helper).
#include "raycast.hpp"

namespace {
using RaycastRows = nb::ndarray<const double, nb::shape<-1, 3>, nb::c_contig, nb::device::cpu>;
using RaycastFaces = nb::ndarray<const std::int64_t, nb::shape<-1, 3>, nb::c_contig, nb::device::cpu>;

void bind_raycast(nb::module_& m) {
  using flatserve::RayCaster;
  nb::class_<RayCaster>(m, "RayCaster")
      .def("__init__",
           [](RayCaster* self, RaycastRows vertices, RaycastFaces faces) {
             nb::gil_scoped_release unlocked;
             new (self) RayCaster(vertices.data(), vertices.shape(0), faces.data(), faces.shape(0));
           },
           nb::arg("vertices"), nb::arg("faces"))
      .def_prop_ro("size", &RayCaster::size)
      .def("cast",
           [](const RayCaster& rc, RaycastRows origins, RaycastRows directions, int threads) {
             if (origins.shape(0) != directions.shape(0))
               throw std::invalid_argument("origins and directions need the same number of rows");
             const std::size_t n = origins.shape(0);
             double* t = new double[n ? n : 1];
             nb::capsule t_owner(t, [](void* p) noexcept { delete[] static_cast<double*>(p); });
             std::int64_t* face = new std::int64_t[n ? n : 1];
             nb::capsule f_owner(face, [](void* p) noexcept { delete[] static_cast<std::int64_t*>(p); });
             {
               nb::gil_scoped_release unlocked;
               rc.cast(origins.data(), directions.data(), n, t, face, threads);
             }
             return std::make_tuple(nb::ndarray<nb::numpy, double, nb::ndim<1>>(t, {n}, t_owner),
                                   nb::ndarray<nb::numpy, std::int64_t, nb::ndim<1>>(face, {n}, f_owner));
           },
           nb::arg("origins"), nb::arg("directions"), nb::arg("threads") = 0);
}
}  // namespace
// ---- /raycast ----

// ---- coordinates ----
// Hot path of flatserve.coordinates.coordinates_rays (k = 1, d = 3, m = 5);
// the math is in coordinates.hpp, the NumPy reference in coordinates.py.
#include "coordinates.hpp"

namespace {
using CoordRows = nb::ndarray<const double, nb::c_contig, nb::device::cpu>;

void bind_coordinates(nb::module_& m) {
  // The reasons shown to users live beside it in flatserve/coordinates.py.
  nb::enum_<flatserve::CoordinateStatus>(m, "CoordinateStatus", nb::is_arithmetic(),
                                         "Status of one coordinate row (see flatserve.coordinates).")
      .value("OK", flatserve::COORD_OK)
      .value("NOT_REPRESENTABLE", flatserve::COORD_NOT_REPRESENTABLE)
      .value("SINGULAR", flatserve::COORD_SINGULAR)
      .value("AMBIGUOUS", flatserve::COORD_AMBIGUOUS)
      .value("NO_SAMPLES", flatserve::COORD_NO_SAMPLES);
  m.def("coordinates_rays3",
        [](CoordRows Qb, CoordRows rb, CoordRows origins, CoordRows directions,
           double roundtrip_tol, double rcond, double gap_tol, double pinv_rcond, int threads) {
          if (Qb.size() != 45 || rb.size() != 15)
            throw std::invalid_argument("Qb, rb: expected 5 flats in R^3 (5x3x3, 5x3)");
          if (origins.ndim() != 2 || origins.shape(1) != 3 || directions.ndim() != 2 ||
              directions.shape(1) != 3 || directions.shape(0) != origins.shape(0))
            throw std::invalid_argument("origins, directions: expected (n, 3) each");
          const std::size_t n = origins.shape(0);
          OutArray<double> w({n, 5});
          OutArray<std::int8_t> status({n});
          OutArray<double> residual({n});
          {
            nb::gil_scoped_release unlocked;
            flatserve::coordinates_rays3_mt(Qb.data(), rb.data(), origins.data(), directions.data(), n,
                                     {roundtrip_tol, rcond, gap_tol, pinv_rcond}, w.data,
                                     status.data, residual.data, threads);
          }
          return std::make_tuple(w.release(), status.release(), residual.release());
        },
        nb::arg("Qb"), nb::arg("rb"), nb::arg("origins"), nb::arg("directions"),
        nb::arg("roundtrip_tol"), nb::arg("rcond"), nb::arg("gap_tol"), nb::arg("pinv_rcond"),
        nb::arg("threads") = 0);
}
}  // namespace
// ---- /coordinates ----

// ---- net ----
// flatserve.triangulation.seam_net; the loop is in net.hpp.
#include "net.hpp"

namespace {
void bind_net(nb::module_& m) {
  m.def("seam_net",
        [](CArr2 cand, I64Arr1 cand_at, CArr2 base, I64Arr1 base_at, double radius,
           U8Arr1 hit, int threads) {
          const std::size_t n = cand.shape(0), b = base.shape(0);
          const int D = static_cast<int>(cand.shape(1));
          if (cand_at.shape(0) != n || hit.shape(0) != n || base_at.shape(0) != b ||
              (b && static_cast<int>(base.shape(1)) != D))
            throw std::invalid_argument("seam_net: mismatched shapes");
          OutArray<std::uint8_t> keep({n});
          {
            nb::gil_scoped_release unlocked;
            flatserve::seam_net(cand.data(), cand_at.data(), n, base.data(), base_at.data(), b,
                                D, radius, hit.data(), keep.data, threads);
          }
          return keep.release();
        },
        nb::arg("cand"), nb::arg("cand_at"), nb::arg("base"), nb::arg("base_at"),
        nb::arg("radius"), nb::arg("hit"), nb::arg("threads") = 0);
}
}  // namespace
// ---- /net ----

NB_MODULE(_core, m) {
  m.doc() =
      "flatserve's private native core (CGAL dD Delaunay, AABB ray casting, coordinates of "
      "lines). Not a public API: use flatserve.Triangulation and friends. Arrays passed in "
      "must be C-contiguous float64, already validated by the Python wrappers.";
  m.attr("cgal_version") = CGAL_VERSION_STR;
  m.attr("eigen_version") = std::to_string(EIGEN_WORLD_VERSION) + "." +
                            std::to_string(EIGEN_MAJOR_VERSION) + "." +
                            std::to_string(EIGEN_MINOR_VERSION);
  bind_triangulation(m);
  bind_raycast(m);
  bind_coordinates(m);
  bind_net(m);
}
