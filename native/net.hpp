// A net of points in arrival order: which candidates lie farther than a radius
// from every point that came before them (flatserve.triangulation.seam_net;
// an atlas chart's thinned seam, flatserve/atlas_field.py).
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "triangulation.hpp"

namespace flatserve {

// cand: m x D, at position cand_at[i] (increasing); base: b x D at base_at[j]
// (increasing); hit[i] != 0: candidate i is known to be near an earlier point
// (the triangulation's: Triangulation::within). keep[i] = 1 iff hit[i] == 0,
// no base point with base_at[j] < cand_at[i] and no kept candidate before i
// lies within radius (sq_dist, as Triangulation::within), else 0.
inline void seam_net(const double* cand, const std::int64_t* cand_at, std::size_t m,
                     const double* base, const std::int64_t* base_at, std::size_t b, int D,
                     double radius, const std::uint8_t* hit, std::uint8_t* keep, int threads) {
  const double r2 = radius * radius;
  auto near = [&](const double* p, const double* q) { return sq_dist(p, q, D) <= r2; };
  // against the base points before each candidate (independent: in parallel)
  run_chunks(m, threads, [&](std::size_t lo, std::size_t hi) {
    for (std::size_t i = lo; i < hi; ++i) {
      if (hit[i]) {
        keep[i] = 0;
        continue;
      }
      const std::size_t upto =
          static_cast<std::size_t>(std::lower_bound(base_at, base_at + b, cand_at[i]) - base_at);
      std::uint8_t k = 1;
      for (std::size_t j = 0; j < upto && k; ++j)
        if (near(base + j * D, cand + i * D)) k = 0;
      keep[i] = k;
    }
  });
  // against the kept candidates before each (in order)
  std::vector<std::size_t> kept;
  for (std::size_t i = 0; i < m; ++i) {
    if (!keep[i]) continue;
    for (std::size_t j : kept)
      if (near(cand + j * D, cand + i * D)) {
        keep[i] = 0;
        break;
      }
    if (keep[i]) kept.push_back(i);
  }
}

}  // namespace flatserve
