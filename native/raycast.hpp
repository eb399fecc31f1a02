// Ray casting against a triangle mesh with CGAL's AABB tree.
// Pure C++ (no Python): bindings.cpp converts arrays in its "raycast" block.
//
// A ray is a row: origins (n, 3) and directions (n, 3), row-major doubles.
// cast() writes, for each ray, the parameter t of its first hit
// (hit point = origin + t * direction, t >= 0) or +inf for a miss, and the
// index of the hit triangle or -1.  The tree is immutable after construction,
// so casts from several threads at once are safe.
#pragma once

#include <CGAL/AABB_traits.h>
#include <CGAL/AABB_tree.h>
#include <CGAL/AABB_triangle_primitive.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <thread>
#include <vector>

namespace flatserve {

class RayCaster {
 public:
  using K = CGAL::Exact_predicates_inexact_constructions_kernel;
  using Point = K::Point_3;
  using Vector = K::Vector_3;
  using Ray = K::Ray_3;
  using Segment = K::Segment_3;
  using Triangle = K::Triangle_3;
  using Iterator = std::vector<Triangle>::const_iterator;
  using Primitive = CGAL::AABB_triangle_primitive<K, Iterator>;
  using Traits = CGAL::AABB_traits<K, Primitive>;
  using Tree = CGAL::AABB_tree<Traits>;

  // vertices: (nv, 3) doubles; faces: (nf, 3) vertex indices.
  // Degenerate triangles are skipped (they can never be hit) but keep their
  // index, so face ids returned by cast() index the caller's face array.
  RayCaster(const double* vertices, std::size_t nv, const std::int64_t* faces,
            std::size_t nf) {
    triangles_.reserve(nf);
    face_ids_.reserve(nf);
    for (std::size_t f = 0; f < nf; ++f) {
      Point p[3];
      for (int c = 0; c < 3; ++c) {
        const std::int64_t v = faces[3 * f + c];
        if (v < 0 || static_cast<std::size_t>(v) >= nv)
          throw std::out_of_range("face refers to a vertex that does not exist");
        p[c] = Point(vertices[3 * v], vertices[3 * v + 1], vertices[3 * v + 2]);
      }
      Triangle tri(p[0], p[1], p[2]);
      if (tri.is_degenerate()) continue;
      triangles_.push_back(tri);
      face_ids_.push_back(static_cast<std::int64_t>(f));
    }
    tree_.insert(triangles_.cbegin(), triangles_.cend());
    tree_.build();
  }

  RayCaster(const RayCaster&) = delete;  // the tree holds iterators into triangles_
  RayCaster& operator=(const RayCaster&) = delete;

  std::size_t size() const { return triangles_.size(); }

  // Casts n rays; threads <= 0 means "all hardware threads".
  void cast(const double* origins, const double* directions, std::size_t n,
            double* t_out, std::int64_t* face_out, int threads) const {
    const std::size_t hw = std::max(1u, std::thread::hardware_concurrency());
    std::size_t nt = threads > 0 ? static_cast<std::size_t>(threads) : hw;
    nt = std::max<std::size_t>(1, std::min(nt, (n + kMinRaysPerThread - 1) / kMinRaysPerThread));
    auto work = [&](std::size_t lo, std::size_t hi) {
      for (std::size_t i = lo; i < hi; ++i)
        cast_one(origins + 3 * i, directions + 3 * i, t_out[i], face_out[i]);
    };
    if (nt == 1 || triangles_.empty()) {
      work(0, n);
      return;
    }
    std::vector<std::thread> pool;
    pool.reserve(nt);
    const std::size_t chunk = (n + nt - 1) / nt;
    for (std::size_t k = 0; k < nt; ++k) {
      const std::size_t lo = k * chunk, hi = std::min(n, lo + chunk);
      if (lo >= hi) break;
      pool.emplace_back(work, lo, hi);
    }
    for (auto& th : pool) th.join();
  }

 private:
  static constexpr std::size_t kMinRaysPerThread = 4096;

  void cast_one(const double* o, const double* d, double& t, std::int64_t& face) const {
    t = std::numeric_limits<double>::infinity();
    face = -1;
    const Vector dir(d[0], d[1], d[2]);
    const double dd = dir.squared_length();
    if (!(dd > 0.0) || triangles_.empty()) return;
    const Point orig(o[0], o[1], o[2]);
    const auto hit = tree_.first_intersection(Ray(orig, dir));
    if (!hit) return;
    double best = std::numeric_limits<double>::infinity();
    if (const Point* p = boost::get<Point>(&hit->first)) {
      best = ((*p) - orig) * dir / dd;
    } else if (const Segment* s = boost::get<Segment>(&hit->first)) {
      // Ray lies in the triangle's plane: the nearer end is the first hit.
      best = std::min((s->source() - orig) * dir, (s->target() - orig) * dir) / dd;
    } else {
      return;
    }
    t = std::max(0.0, best);
    face = face_ids_[static_cast<std::size_t>(hit->second - triangles_.cbegin())];
  }

  std::vector<Triangle> triangles_;
  std::vector<std::int64_t> face_ids_;
  Tree tree_;
};

}  // namespace flatserve
