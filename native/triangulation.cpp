// Instantiates the triangulation for one dimension. CMake compiles this file
// once per FS_TRI_DIM (2..6: static dimension; 0: dynamic dimension), through
// small generated wrappers, so the CGAL instantiations build in parallel.
#include "triangulation_impl.hpp"

#ifndef FS_TRI_DIM
#error "compile triangulation.cpp with -DFS_TRI_DIM=N (see CMakeLists.txt)"
#endif

namespace flatserve {

#if FS_TRI_DIM > 0
template <int N>
std::unique_ptr<TriangulationBase> make_static() {
  return std::make_unique<Triangulation<CGAL::Dimension_tag<N>>>(N);
}
template std::unique_ptr<TriangulationBase> make_static<FS_TRI_DIM>();
#else
std::unique_ptr<TriangulationBase> make_dynamic(int D) {
  return std::make_unique<Triangulation<CGAL::Dynamic_dimension_tag>>(D);
}
#endif

}  // namespace flatserve
