// The one file that knows about Python. Everything CGAL lives in headers
// beside it (triangulation.hpp, ...); this file only converts arrays.
#include <nanobind/nanobind.h>
#include <nanobind/stl/string.h>
#include <CGAL/version.h>
#include <Eigen/Core>

namespace nb = nanobind;

NB_MODULE(_core, m) {
  m.doc() = "flatserve private native core (CGAL dD Delaunay). Not a public API.";
  m.attr("cgal_version") = CGAL_VERSION_STR;
  m.attr("eigen_version") = std::to_string(EIGEN_WORLD_VERSION) + "." +
                            std::to_string(EIGEN_MAJOR_VERSION) + "." +
                            std::to_string(EIGEN_MINOR_VERSION);
}
